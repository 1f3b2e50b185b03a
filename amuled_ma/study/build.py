"""``amuled study build``: a study folder of the states variants met in replayed evaluations.

A pair shows two variants' differing actions as ``A``/``B`` in random order; an expert item all
the task's actions; panels come from the run's belief store, read-only. Same inputs, same bytes.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from amuled_ma.beliefs.replies.parsing import parse_belief
from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.deliberation.state_key import freeze
from amuled_ma.evaluate import episode_trace as trace
from amuled_ma.evaluate.evaluator import variant_dirs
from amuled_ma.evaluate.panel_answers import ask_panel, state_prompt
from amuled_ma.evaluate.readonly_feedback import open_feedback
from amuled_ma.experiments.run_folder import read_record, split_replica
from amuled_ma.experiments.trained_variants import evaluated_episodes, trained_variant
from amuled_ma.files.safe import (
    check_own_folder,
    check_write_targets,
    write_bytes_atomic,
    write_text_atomic,
)
from amuled_ma.learn.policies import action_log_probs
from amuled_ma.study.drawing import state_svg
from amuled_ma.study.model import (
    CONSENT_FILE,
    STUDY_FILE,
    Item,
    Option,
    PanelView,
    Study,
    StudyError,
    write_study,
)

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

#: Evaluation episodes replayed per variant (states met) unless asked otherwise.
EPISODES = 3
#: Decimals kept of a belief (stable bytes across machines).
DECIMALS = 6
TEMPLATES = Path(__file__).parent / "templates"
#: The consent page written into a new study folder, per mode.
CONSENT_TEMPLATES = {
    "pairs": TEMPLATES / "consent.html",
    "expert": TEMPLATES / "consent_expert.html",
}
#: Longest reason kept, in characters (the rest is cut, and the cut is said).
MAX_REASON_CHARS = 3000


def stated_reason(raw: str | None, action_names: Sequence[str]) -> str | None:
    """A JSON reply's ``reasoning``, or its text if not only JSON, cut at `MAX_REASON_CHARS`."""
    if not isinstance(raw, str) or not raw.strip():
        return None
    parsed = parse_belief(raw, action_names)
    text: str | None = parsed.reasoning if isinstance(parsed.reasoning, str) else None
    if not text:
        try:
            whole = json.loads(raw)
        except (ValueError, RecursionError):
            whole = None
        text = None if isinstance(whole, dict | list | int | float) else raw
    if text is None or not text.strip():
        return None
    text = text.strip()
    if len(text) > MAX_REASON_CHARS:
        text = text[:MAX_REASON_CHARS] + f" [... cut at {MAX_REASON_CHARS} characters]"
    return text


@dataclass
class _State:
    run: int
    task: str
    met_by: str
    episode: int
    step: int
    obs: np.ndarray
    prompt_vars: dict[str, Any]
    svg: str


def resolve_variant(run_dir: Path, name: str) -> Path:
    """The variant folder ``name`` means (folder, ``finetune-<name>``, feedback; no seed replica).

    StudyError: no variant, or several, fit; the message lists the run's variants.
    """
    run_dir = Path(run_dir)
    found = variant_dirs(run_dir)
    listing = ", ".join(d.name for d in found) or "none"
    for folder in (run_dir / name, run_dir / f"finetune-{name}"):
        if folder in found:
            return folder
    matches = []
    for folder in found:
        if split_replica(folder.name)[1] is not None:
            continue
        record = read_record(folder, checkpoint=False)
        variant = record.variant if record is not None else None
        feedback = variant.feedback if variant is not None else None
        if feedback and (feedback == name or feedback.split(":")[0] == name):
            matches.append(folder)
    if len(matches) == 1:
        return matches[0]
    what = "several variants" if matches else "no variant"
    raise StudyError(
        f"--variants: {what} of {run_dir} fit {name!r}; variants found: {listing}; "
        "name a folder instead"
    )


def _round(values: ArrayLike) -> list[Any]:
    return np.round(np.asarray(values, dtype=np.float64), DECIMALS).tolist()


def _states_of_run(
    r: int, run_dir: Path, names: Sequence[str], folders: list[Path], episodes: int
) -> tuple[list[_State], dict[str, np.ndarray], Any, list[str]]:
    """Distinct states the variants met, each variant's greedy action in them, the panel."""
    trained = [trained_variant(run_dir, folder) for folder in folders]
    scenario = trained[0].scenario
    n = evaluated_episodes(run_dir, scenario.evaluation.episodes)
    actors = [trace.load_actor(t.checkpoint, t.scenario.ppo) for t in trained]
    states: list[_State] = []
    seen: set[bytes] = set()
    action_names: list[str] = []
    for name, actor, tv in zip(names, actors, trained, strict=True):
        for k in range(min(episodes, n)):
            ep = trace.replay_episode(
                actor, tv.scenario.task, tv.scenario.evaluation, episode=k, episodes=n
            )
            action_names = list(ep.action_names)
            for t in range(ep.length):
                obs = np.asarray(ep.obs[t], dtype=np.float64)
                key = obs.tobytes() + freeze(ep.prompt_vars[t])
                if key in seen:
                    continue
                seen.add(key)
                svg = state_svg(ep.task, ep.layout, ep.frames, t, obs.tolist())
                states.append(_State(r, ep.task, name, k, t, obs, ep.prompt_vars[t], svg))
    rows = torch.as_tensor(np.stack([s.obs for s in states]), dtype=torch.float32)
    with torch.no_grad():
        actions = {
            name: action_log_probs(actor, rows).argmax(dim=1).numpy()
            for name, actor in zip(names, actors, strict=True)
        }
    panel = None
    for tv in trained:
        if tv.variant is not None and tv.variant.asks_panel and tv.feedback is not None:
            plan = plan_panel(tv.feedback, tv.scenario)
            feedback, store = open_feedback(plan, tv.scenario.feedback.store, run_dir)
            try:
                if (asked := getattr(feedback, "panel", None)) is not None:
                    answers = ask_panel(
                        asked,
                        np.stack([s.obs for s in states]),
                        [s.prompt_vars for s in states],
                        store,
                    )
                    panel = (tv.feedback, answers)
                    break
            finally:
                feedback.close()
                store.close()
    return states, actions, panel, action_names


def build_study(
    runs: Sequence[Path],
    variants: Sequence[str],
    out: Path,
    *,
    items: int,
    seed: int,
    attention: int | None = None,
    episodes: int = EPISODES,
    force: bool = False,
    mode: Literal["pairs", "expert"] = "pairs",
) -> Study:
    """Build a study folder ``out`` of ``items`` pairs (expert mode: states) of ``runs``.

    ``attention`` checks default to one per ten pairs; ``force`` replaces a study (an edited
    ``consent.html`` is kept either way). StudyError: a run folder or variant missing, too few
    variants, no state where two differ, attention checks in expert mode, or ``out`` holds a
    study without ``force``.
    """
    from amuled_ma.clusters.loader import default_registry

    names = list(dict.fromkeys(variants))
    least = 2 if mode == "pairs" else 1
    if len(names) < least:
        raise StudyError(
            f"--variants: expected at least {('one variant', 'two variants')[least - 1]} to "
            f"compare, found {names}; e.g. --variants amuled,base"
        )
    if mode == "expert" and attention:
        raise StudyError(
            f"--attention: expert mode asks no attention checks, found {attention}; "
            "leave --attention out with --mode expert"
        )
    out = Path(out)
    if (out / STUDY_FILE).exists() and not force:
        raise StudyError(f"{out}: holds a study already ({STUDY_FILE}); pass --force to rebuild")
    _check_outputs(out)
    torch.set_num_threads(1)
    states: list[_State] = []
    actions: list[dict[str, int]] = []
    panels: list[tuple[str, Any, int] | None] = []
    folders: list[dict[str, str]] = []
    action_names: dict[str, list[str]] = {}
    for r, run in enumerate(runs):
        chosen = [resolve_variant(Path(run), name) for name in names]
        folders.append({name: f.name for name, f in zip(names, chosen, strict=True)})
        run_states, run_actions, panel, names_of_actions = _states_of_run(
            r, Path(run), names, chosen, episodes
        )
        action_names[run_states[0].task] = names_of_actions
        for u, state in enumerate(run_states):
            states.append(state)
            actions.append({name: int(run_actions[name][u]) for name in names})
            panels.append((panel[0], panel[1], u) if panel is not None else None)
    rng = np.random.default_rng(seed)
    if mode == "expert":
        slots: list[_Slot] = [
            ("expert", s, (), None) for s in rng.permutation(len(states))[:items].tolist()
        ]
        candidates = len(states)
    else:
        slots, candidates = _pair_slots(states, actions, action_names, names, rng, items, attention)
    built: list[Item] = []
    pictures: dict[str, str] = {}
    for position, (kind, s, options, expected) in enumerate(slots):
        item_id = f"q{position + 1:03d}"
        state = states[s]
        view = None
        if kind != "attention" and (found := panels[s]) is not None:
            feedback, answers, u = found
            view = PanelView(
                feedback=feedback,
                agents=list(answers.agents),
                rule=answers.rule,
                beliefs=_round(answers.beliefs[u]),
                statuses=[str(x) for x in answers.statuses[u]],
                fused=_round(answers.fused[u]),
                reasons=[stated_reason(raw, action_names[state.task]) for raw in answers.raws[u]],
            )
        built.append(
            Item(
                id=item_id,
                kind=kind,
                run=state.run,
                task=state.task,
                episode=state.episode,
                step=state.step,
                met_by=state.met_by,
                obs=_round(state.obs),
                prompt=state_prompt(state.task, state.prompt_vars),
                picture=f"states/{item_id}.svg",
                options=options,
                expected=expected,
                instruction=None if expected is None else INSTRUCTION.format(expected),
                policies=dict(actions[s]),
                panel=view,
            )
        )
        pictures[item_id] = state.svg
    study = Study(
        mode=mode,
        seed=int(seed),
        runs=[str(r) for r in runs],
        variants=names,
        folders=folders,
        action_names=action_names,
        # the moral frameworks an expert may cite: the clusters of the shipped registry
        frameworks=[(c.name, c.title) for c in default_registry().panel()]
        if mode == "expert"
        else [],
        items=built,
        candidates=candidates,
    )
    return _write(out, study, pictures)


Kind = Literal["pair", "attention", "expert"]
#: An item drawn: its kind, the state's index, its options and the attention check's answer.
_Slot = tuple[Kind, int, tuple[Option, Option] | tuple[()], Literal["A", "B"] | None]
#: What an attention check asks, given the option to choose.
INSTRUCTION = (
    "This question checks that you are reading: whatever the situation, please choose option {}."
)


def _pair_slots(
    states: list[_State],
    actions: list[dict[str, int]],
    action_names: dict[str, list[str]],
    names: list[str],
    rng: np.random.Generator,
    items: int,
    attention: int | None,
) -> tuple[list[_Slot], int]:
    """Pairs where two variants' actions differ and attention checks, drawn; and the candidates.

    StudyError: the variants take the same action in every state.
    """
    candidates = [
        (s, a, b)
        for s in range(len(states))
        for a, b in itertools.combinations(names, 2)
        if actions[s][a] != actions[s][b]
    ]
    if not candidates:
        raise StudyError(
            f"the variants {', '.join(names)} take the same action in every state they met "
            f"({len(states)} states): nothing to compare; train them longer or compare others"
        )
    picks = rng.permutation(len(candidates))[: min(items, len(candidates))]
    n_att = max(1, len(picks) // 10) if attention is None else int(attention)
    kinds: list[Kind] = ["pair"] * len(picks)
    kinds += ["attention"] * n_att
    pairs = iter(picks.tolist())
    slots: list[_Slot] = []
    for slot in rng.permutation(len(kinds)).tolist():
        expected: Literal["A", "B"] | None = None
        if kinds[slot] == "pair":
            s, a, b = candidates[next(pairs)]
            shown = (a, b) if rng.random() < 0.5 else (b, a)
            (va, xa), (vb, xb) = ((v, actions[s][v]) for v in shown)
        else:
            s = int(rng.integers(len(states)))
            va = vb = None
            xa, xb = rng.choice(len(action_names[states[s].task]), size=2, replace=False).tolist()
            expected = "A" if rng.random() < 0.5 else "B"
        names_of = action_names[states[s].task]
        options = (
            Option(label="A", variant=va, action=xa, action_name=names_of[xa]),
            Option(label="B", variant=vb, action=xb, action_name=names_of[xb]),
        )
        slots.append((kinds[slot], s, options, expected))
    return slots, len(candidates)


def _check_outputs(out: Path) -> None:
    """Refuse (UnsafePathError) outputs that are links or not regular files, ``states/`` a link."""
    check_write_targets([out / STUDY_FILE, out / CONSENT_FILE])
    check_own_folder(
        out / "states",
        "the build empties and refills the study's own states/ folder and never writes "
        "through a link; nothing was written; remove it, or build the study into another "
        "folder",
    )


def _write(out: Path, study: Study, pictures: dict[str, str]) -> Study:
    """Write ``study.json``, the pictures, and the consent page if absent (the researcher's)."""
    out.mkdir(parents=True, exist_ok=True)
    _check_outputs(out)
    states = out / "states"
    if states.exists():
        shutil.rmtree(states)
    states.mkdir()
    for item_id, svg in pictures.items():
        write_text_atomic(states / f"{item_id}.svg", svg)
    write_study(out, study)
    if not os.path.lexists(out / CONSENT_FILE):
        write_bytes_atomic(out / CONSENT_FILE, CONSENT_TEMPLATES[study.mode].read_bytes())
    return study
