"""People judge the agents: a study built from runs, served, its answers analysed.

``build`` (a study folder from runs), ``model`` (the folder's format), ``drawing`` (a state
as SVG), ``server`` (the participant page and answer API), ``answers`` (the SQLite answer
store), ``analysis`` (win rates, Bradley-Terry, reliability, agreement), ``report`` (the
report). See ``docs/study.md``.
"""
