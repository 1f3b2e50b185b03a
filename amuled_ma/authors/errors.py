"""Errors of the importer of the AMULED authors' artefacts (:mod:`amuled_ma.authors`)."""

from __future__ import annotations

from amuled_ma.errors import AmuledError


class AuthorsImportError(AmuledError, ValueError):
    """A file of the authors' checkout is missing, malformed, or would overwrite other data."""


class UnsafePickleError(AuthorsImportError):
    """A pickle needs a global outside the allow-list; nothing from it was run."""
