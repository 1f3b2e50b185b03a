"""The settings that decide what a variant learns, and their comparison before a resume."""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.files.hashing import sha256_file
from amuled_ma.learn.config import planned_iterations
from amuled_ma.scenario import Scenario

if TYPE_CHECKING:
    from amuled_ma.deliberation.plan import PanelPlan
    from amuled_ma.experiments.run_folder import TrainJob

#: Scenario keys left out of `training_config`: paths, logging and service keys, the
#: seed (the job's own seed is kept) and the run's length (kept as ``"iterations"``: a
#: resume may lengthen a run).
NOT_LEARNED = {
    "task": ("seed",),
    "base": ("save_interval", "total_steps"),
    "finetune": ("save_interval", "iterations"),
    "feedback": ("host", "hosts", "concurrency", "timeout_s", "store", "max_abstention", "name"),
}


def training_config(job: TrainJob, panel: PanelPlan | None = None) -> dict[str, Any]:
    """The settings that decide what a variant learns, as JSON data; a resume compares them.

    Left out: `NOT_LEARNED`, the folders of files (their names stay), ``[feedback.distill]``
    when off, and ``[feedback]`` for a job that asks no panel. ``inputs`` holds the SHA-256 of
    the recordings replayed, of each cluster file of ``panel`` and of ``amuled``'s weights file.

    Raises:
        ValueError: A fine-tune that asks a panel, without its plan.
    """
    scenario, variant, seed, iterations = job.scenario, job.variant, job.seed, job.iterations
    if variant.asks_panel and (panel is None or not panel.asks_panel):
        raise ValueError(f"the settings of {variant} need its panel plan")
    data = scenario.settings()
    sections: tuple[str, ...] = ("task", "ppo", "finetune" if variant.finetuning else "base")
    if variant.asks_panel:
        sections += ("feedback",)
    total = planned_iterations(scenario.finetune if variant.finetuning else scenario.base)
    out: dict[str, Any] = {
        "variant": str(variant),
        "seed": scenario.task.seed if seed is None else seed,
        "iterations": total if iterations is None else iterations,
    }
    for section in sections:
        skip = NOT_LEARNED.get(section, ())
        out[section] = {k: v for k, v in data[section].items() if k not in skip}
    distill = out.get("feedback", {}).get("distill")
    if distill is not None and not distill.get("enabled"):
        del out["feedback"]["distill"]  # off: its other keys change nothing
    weights = out.get("feedback", {}).pop("weights", "")
    if weights and variant.feedback_kind[0] == "amuled":  # the prior of its bjs-dst fusion
        out["feedback"]["weights"] = Path(weights).name
        out["inputs"] = {"weights_sha256": file_sha256(scenario.resolve(weights))}
    if out.get("feedback", {}).get("recording"):
        out["feedback"]["recording"] = Path(out["feedback"]["recording"]).name
        if out["feedback"].get("source") == "replay":
            digest = file_sha256(scenario.recording_path())
            out.setdefault("inputs", {})["recording_sha256"] = digest
    for agent, spec in sorted((out.get("feedback", {}).get("agents") or {}).items()):
        if spec.get("source") == "replay" and spec.get("recording"):
            path = scenario.replace("feedback", recording=spec["recording"]).recording_path()
            out.setdefault("inputs", {})[f"recording_sha256[{agent}]"] = file_sha256(path)
    if panel is not None and panel.asks_panel:  # the files the panel's prompts are made of
        hashes: dict[str, str | None] = {}
        described = panel.registry.panel() if panel.registry is not None else []
        for cluster in [*panel.clusters, *described]:
            if cluster.path is not None and cluster.name not in hashes:
                hashes[cluster.name] = file_sha256(Path(cluster.path))
        for name, digest in sorted(hashes.items()):
            out.setdefault("inputs", {})[f"cluster_sha256[{name}]"] = digest
    return json.loads(json.dumps(out, default=str))


@functools.lru_cache(maxsize=64)
def _sha256_of(path: str, size: int, mtime_ns: int) -> str:
    return sha256_file(path)  # cached by (path, size, mtime): a changed file is hashed again


def file_sha256(path: Path) -> str | None:
    """SHA-256 of a file's content (memoised while its size and mtime stay), None if absent."""
    try:
        info = path.stat()
    except OSError:
        return None
    return _sha256_of(str(path), info.st_size, info.st_mtime_ns)


def differences(saved: object, current: object, prefix: str = "") -> list[str]:
    """``key: saved -> current`` for every leaf that differs between two JSON values."""
    if isinstance(saved, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(saved) | set(current), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            out += differences(saved.get(key), current.get(key), name)
        return out
    return [] if saved == current else [f"{prefix}: {saved!r} -> {current!r}"]


def learned_only(saved: dict[str, Any]) -> dict[str, Any]:
    """A saved training config without the keys `NOT_LEARNED` now leaves out."""
    out = dict(saved)
    for section, keys in NOT_LEARNED.items():
        if isinstance(out.get(section), dict):
            out[section] = {k: v for k, v in out[section].items() if k not in keys}
    return out


def without_keys_added_since(saved: dict[str, Any], training: dict[str, Any]) -> dict[str, Any]:
    """Drop from ``training`` what a folder saved by an older version could not record.

    The input hashes it lacks, and keys added since that hold their default; a key added since
    but set otherwise stays, so the difference is reported.
    """
    defaults = Scenario().to_dict()
    out = {k: v for k, v in training.items() if k != "inputs" or "inputs" in saved}
    saved_inputs = saved.get("inputs")
    if not isinstance(saved_inputs, dict):
        saved_inputs = {}
    if isinstance(out.get("inputs"), dict) and not any(
        str(k).startswith("cluster_sha256[") for k in saved_inputs
    ):  # saved before cluster files were hashed
        out["inputs"] = {
            k: v for k, v in out["inputs"].items() if not k.startswith("cluster_sha256[")
        }
        if not out["inputs"] and "inputs" not in saved:
            del out["inputs"]
    for section, values in training.items():
        if section == "inputs":
            continue  # hashes, not settings with defaults: dealt with above
        if isinstance(values, dict) and isinstance(saved.get(section), dict):
            out[section] = {
                k: v
                for k, v in values.items()
                if k in saved[section] or v != defaults.get(section, {}).get(k, object())
            }
    return out
