"""Import the AMULED authors' published artefacts (``temetski/moral_agent``) on any machine.

``amuled import authors PATH`` (:mod:`amuled_ma.commands.importer`) reads a checkout of the
authors' repository and writes our formats; see ``docs/authors.md``. Modules:

- :mod:`amuled_ma.authors.unpickle`: the allow-list unpickler (numpy arrays and scalars in
  builtin containers, nothing else; a file naming another global is refused before
  anything from it runs);
- :mod:`amuled_ma.authors.caches`: LLM-cache pickle -> recording JSON
  (:func:`~amuled_ma.authors.caches.convert_cache`);
- :mod:`amuled_ma.authors.policies`: CleanRL policy (weights only) -> our checkpoint and
  variant folder (:func:`~amuled_ma.authors.policies.build_checkpoint`);
- :mod:`amuled_ma.authors.checkout`: finds the files of a checkout and imports them all
  (:func:`~amuled_ma.authors.checkout.import_authors`).

Errors: :class:`~amuled_ma.errors.AuthorsImportError` and
:class:`~amuled_ma.errors.UnsafePickleError` (the package's one hierarchy).
"""
