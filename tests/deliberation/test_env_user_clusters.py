"""The PettingZoo deliberation env with a user cluster folder: one more agent, same API."""

from pettingzoo.test import parallel_api_test

from amuled_ma.deliberation.env import DeliberationEnv

WELFARE = """\
name = "animal_welfare"
kind = "cluster"
order = 6
title = "Animal Welfare Ethics"
credence_label = "Animal Welfare Ethics"
focus = "Focus on the wellbeing of every sentient creature"
key_principle = "Suffering matters, whoever feels it"

[[theories]]
name = "Sentientism"
key_concepts = ["Sentience", "Suffering"]
decision_factors = ["Who can feel pain here"]
"""


def test_user_cluster_folder_adds_an_agent(tmp_path):
    (tmp_path / "animal_welfare.toml").write_text(WELFARE)
    env = DeliberationEnv("findmilk", clusters_dirs=[tmp_path], seed=0)
    assert env.possible_agents == [
        "actor", "consequentialist", "deontological", "virtue", "care", "social_justice",
        "animal_welfare",
    ]  # fmt: skip
    parallel_api_test(env, num_cycles=20)
    default = DeliberationEnv("findmilk", seed=0)
    assert "animal_welfare" not in default.possible_agents
