"""The belief store: SQLite file, row checks, key recipe, cached front, stand-ins, JSON Lines."""
