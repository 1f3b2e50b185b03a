"""A mixed panel for tests: paper clusters replayed, a user cluster answered elsewhere."""

from __future__ import annotations

from pathlib import Path
from typing import Any

PERSON = """\
name = "person"
kind = "cluster"
order = 6
title = "A Person"
credence_label = "A Person"
focus = "What a person at the terminal judges right"
key_principle = "Ask the person"

[[theories]]
name = "Common sense"
key_concepts = ["Judgement"]
decision_factors = ["The situation"]
"""

TINY = [
    "--set", "base.total_steps=512", "--set", "base.num_envs=16",
    "--set", "base.num_steps_per_env=16", "--set", "output.tensorboard=false",
]  # fmt: skip


def mixed_scenario(
    tmp_path: Path,
    recordings_dir: Path,
    *,
    person: str,
    agents: dict[str, dict[str, Any]] | None = None,
) -> Path:
    """FindMilk: consequentialist, deontological, virtue, care replayed; ``person`` = its source.

    ``agents`` adds more ``[feedback.agents.<name>]`` tables (e.g. social_justice on Ollama).
    """
    clusters = tmp_path / "clusters"
    clusters.mkdir()
    (clusters / "person.toml").write_text(PERSON)
    recording = recordings_dir / "findmilk-gpt-4o-mini.json"
    text = (Path(__file__).parents[1] / "scenarios" / "findmilk.toml").read_text()
    text = text.replace(
        'recording = "../../shared/amuled-recordings/findmilk-gpt-4o-mini.json"',
        f'recording = "{recording}"',
    ).replace(
        'clusters = ["consequentialist", "deontological", "virtue", "care", "social_justice"]',
        'clusters = ["consequentialist", "deontological", "virtue", "care", "social_justice", '
        '"person"]\n'
        f'clusters_dirs = ["{clusters}"]',
    )
    text += f'\n[feedback.agents.person]\nsource = "{person}"\n'
    for name, table in (agents or {}).items():
        text += f"\n[feedback.agents.{name}]\n"
        text += "".join(f"{key} = {value!r}\n".replace("'", '"') for key, value in table.items())
    path = tmp_path / "mixed.toml"
    path.write_text(text)
    return path
