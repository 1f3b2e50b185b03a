"""People judge the agents: a study built from runs, served, its answers analysed.

``build`` (a study folder from runs, pairs or expert mode), ``model`` (the folder's format),
``drawing`` (a state as SVG), ``reasons`` (a panel member's stated reason), ``requests`` (the
request bodies' models), ``server`` (the participant page and answer API), ``answers`` (the
SQLite answer store), ``analysis`` (win rates, Bradley-Terry, acceptability, reliability,
agreement), ``expert`` (the expert mode's numbers), ``report`` and ``figures`` (the report
and its figure). See ``docs/study.md``.
"""
