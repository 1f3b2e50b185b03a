"""Files: bounded, link-safe reads and writes; hashes; weights-only torch loads; run lock; data."""
