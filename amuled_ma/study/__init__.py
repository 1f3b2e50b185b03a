"""People judge the agents: a study built from runs, served and analysed (docs/study.md)."""
