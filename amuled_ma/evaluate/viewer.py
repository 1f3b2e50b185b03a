"""``amuled view``: one self-contained HTML page showing why a fine-tuned agent acts.

CSS, script and data are inline under a strict Content-Security-Policy (hash-allowed inline
script and style), so the page loads and sends nothing and works from ``file://`` offline.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.deliberation.plan import plan_panel
from amuled_ma.evaluate import episode_trace as trace
from amuled_ma.evaluate.panel_answers import ask_panel, state_prompt
from amuled_ma.evaluate.readonly_feedback import describe_feedback, open_feedback
from amuled_ma.files.safe import check_write_target, write_text_atomic
from amuled_ma.tasks.colors import COLORS, css_variables

if TYPE_CHECKING:
    from amuled_ma.scenario import EvaluationConfig

#: Decimals kept for probabilities, weights and conflicts in the page.
DECIMALS = 4
#: Longest raw reply or prompt kept in the page, in characters (the rest is cut, said so).
MAX_TEXT = 6000
#: Characters of text (replies, prompts) a page keeps in all: past it every text is cut
#: to an equal share, so that a long live-LLM episode stays a few MB.
TEXT_BUDGET = 2_000_000
#: The shortest a text is cut to by `TEXT_BUDGET`.
MIN_TEXT = 400
#: The page's assets, shipped beside this module.
ASSETS = Path(__file__).resolve().parent


@dataclass
class ViewResult:
    """What `write_view` wrote: file, bytes, ``(name, steps, states)`` per variant, seconds."""

    path: Path
    size: int
    variants: list[tuple[str, int, int]]
    seconds: float


class TextTable:
    """Texts stored once; a step or an agent points at its text by index."""

    def __init__(self, limit: int = MAX_TEXT) -> None:
        self.limit = limit
        self.texts: list[str] = []
        self._index: dict[str, int] = {}

    def add(self, text: str | None) -> int:
        """Index of ``text`` in the table (added once), -1 for no text."""
        if not text:
            return -1
        text = _cut(text, self.limit)
        found = self._index.get(text)
        if found is None:
            found = self._index[text] = len(self.texts)
            self.texts.append(text)
        return found

    def fit(self, budget: int = TEXT_BUDGET) -> bool:
        """Cut every text to an equal share of ``budget`` characters when over it; True if cut."""
        total = sum(len(t) for t in self.texts)
        if total <= budget or not self.texts:
            return False
        share = max(MIN_TEXT, budget // len(self.texts))
        self.texts = [_cut(t, share) for t in self.texts]
        return True


def _cut(text: str, limit: int) -> str:
    cut = f"{text[:limit]}\n[... {len(text) - limit} more characters, cut for the page]"
    return text if len(text) <= limit else cut


def _round(values: object, decimals: int = DECIMALS) -> Any:
    """Nested lists of floats rounded (``-0.0`` as ``0.0``) for JSON."""
    array = np.round(np.asarray(values, dtype=np.float64), decimals) + 0.0
    return array.tolist()


def _compact_number(value: float) -> int | float:
    return int(value) if float(value).is_integer() else round(float(value), DECIMALS)


#: The legend under a task's picture of a state.
PICTURE_NOTES = {
    "driving": "Vermillion: cars, green circles: grandmas, black: the agent's car at distance 0; "
    "red ✕: a collision, green ★: a rescue on this step.",
    "findmilk": "M milk, C crying baby (solid green ✓ once pacified), z sleeping baby (solid red "
    "! once woken); the purple line is the path so far.",
}


def variant_view(
    run_dir: Path,
    trained: trace.TrainedVariant,
    texts: TextTable,
    *,
    episode: int = 0,
    mode: str = "greedy",
    episodes: int | None = None,
) -> dict[str, Any]:
    """Replay one variant's evaluation episode: its entry of the page's data."""
    run_dir = Path(run_dir)
    base_path = trained.base_checkpoint
    feedback_name = trained.feedback
    feedback = store = None
    if feedback_name is not None:
        plan = plan_panel(feedback_name, trained.scenario)
        feedback, store = open_feedback(plan, trained.scenario.feedback.store, run_dir)
    try:
        panel = getattr(feedback, "panel", None)
        live = feedback if feedback is not None and panel is None else None
        ep = trace.replay_variant(
            trained, episode=episode, mode=mode, episodes=episodes, live_feedback=live
        )
        first, index = ep.unique_states()
        picture: dict[str, Any] = {"kind": ep.task if ep.layout is not None else "text"}
        entry: dict[str, Any] = {
            "name": trained.name,
            "mode": ep.mode,
            "T": ep.length,
            "terminated": ep.terminated,
            "metrics": {k: _compact_number(v) for k, v in ep.metrics.items()},
            "picture": {**picture, **(ep.layout or {})},
            "picture_note": PICTURE_NOTES.get(ep.task, ""),
            "frames": ep.frames,
            "a": ep.actions.tolist(),
            "b": ep.base_actions.tolist() if ep.base_actions is not None else None,
            "p": _round(ep.probs, 3),
            "bp": _round(ep.base_probs, 3) if ep.base_probs is not None else None,
            "ev": {
                k: [_compact_number(x) for x in v.tolist()] for k, v in ep.events.items() if v.any()
            },
            "r": _round(ep.rewards, 2),
        }
        entry.update(
            feedback=feedback_name,
            policy=str(trained.checkpoint),
            base=str(base_path) if base_path is not None else None,
            explain=(
                f"amuled explain --state-from {run_dir} --variant {trained.name} "
                f"--episode {episode} --mode {mode} --step {{step}}"
            ),
            distinct_states=len(first),
        )
        if base_path is None:
            entry["note_base"] = "no base policy found for this variant"
        if panel is not None:
            answers = ask_panel(panel, ep.obs[first], [ep.prompt_vars[t] for t in first], store)
            entry.update(
                _states_entry(
                    answers.agents,
                    answers.rule,
                    answers.statuses.tolist(),
                    b=_round(answers.beliefs),
                    w=_round(answers.weights),
                    k=_round(answers.conflicts),
                    f=_round(answers.fused),
                    x=[[texts.add(r) for r in row] for row in answers.raws],
                    why=[[texts.add(r) for r in row] for row in answers.reasons],
                    q=[texts.add(p) for p in answers.prompts],
                )
            )
            entry.update(
                kind="panel",
                s=index.tolist(),
                source=describe_feedback(feedback),
                raw_note=(
                    "Neither the run's belief store nor the recording kept a reply text for "
                    "this answer (the authors' recordings keep the exchanges of the states "
                    "their parser had to repair only)."
                ),
            )
        elif live is not None and ep.live_beliefs is not None:
            agent = str(getattr(live, "agent", getattr(live, "name", "feedback")))
            beliefs = ep.live_beliefs[first]
            assert ep.live_statuses is not None
            entry.update(
                _states_entry(
                    [agent],
                    None,
                    [[pairs[0][1] if (pairs := ep.live_statuses[t]) else "ok"] for t in first],
                    b=_round(beliefs[:, None, :]),
                    w=None,
                    k=None,
                    f=_round(beliefs),
                    x=None,
                    why=None,
                    q=[texts.add(state_prompt(ep.task, ep.prompt_vars[t])) for t in first],
                )
            )
            entry.update(kind="belief", s=index.tolist(), source=describe_feedback(live))
            entry["note"] = (
                f"The feedback '{feedback_name}' of this variant is not a panel of agents "
                f"({type(live).__name__}): shown is the feedback belief itself, the reward "
                "the fine-tune was given, with no per-agent beliefs, weights or reasoning."
            )
        else:
            entry.update(kind="none", st=None, s=None, agents=[])
            entry["note"] = (
                "This variant was not fine-tuned on feedback (a base policy): only its "
                "actions are shown."
            )
        if base_path is None:
            entry["note"] = (entry.get("note", "") + " No base policy was found: base "
                             "actions are not shown.").strip()  # fmt: skip
        return entry
    finally:
        if feedback is not None:
            feedback.close()
        if store is not None:
            store.close()


def _states_entry(
    agents: list[str],
    rule: str | None,
    statuses: list[list[str]],
    b: object,
    w: object,
    **st: object,
) -> dict[str, Any]:
    """The page's per-distinct-state data: statuses coded by their index in ``statuses``."""
    names = sorted({s for row in statuses for s in row})
    code = {name: i for i, name in enumerate(names)}
    coded = [[code[s] for s in row] for row in statuses]
    return {
        "agents": agents,
        "rule": rule,
        "statuses": names,
        "st": {"b": b, "w": w, "s": coded, **st},
    }


def _csp_hash(text: str) -> str:
    digest = hashlib.sha256(text.encode("utf-8")).digest()
    return "'sha256-" + base64.b64encode(digest).decode("ascii") + "'"


def render_html(data: dict[str, Any]) -> str:
    """The page: data, script and style inline under a strict CSP.

    ``<``, ``>``, ``&`` and the line separators are escaped in the JSON, so no text in it can
    end the script element.
    """
    script = (ASSETS / "viewer.js").read_text(encoding="utf-8")
    # the colour table of the figures as CSS variables (--c-good, ...), then the style sheet
    style = css_variables(data.get("colors") or COLORS) + (ASSETS / "viewer.css").read_text(
        encoding="utf-8"
    )
    payload = json.dumps(data, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    payload = payload.translate({ord(c): f"\\u{ord(c):04x}" for c in "<>&\u2028\u2029"})
    csp = (
        f"default-src 'none'; script-src {_csp_hash(script)}; style-src {_csp_hash(style)}; "
        "img-src data:; base-uri 'none'; form-action 'none'"
    )
    title = html.escape(str(data.get("title", "AMULED viewer")))
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f'<meta http-equiv="Content-Security-Policy" content="{csp}">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{title}</title>\n"
        f"<style>{style}</style>\n"
        "</head>\n<body>\n"
        '<div id="app"><noscript>This page needs JavaScript (inline, nothing is '
        "downloaded).</noscript></div>\n"
        f'<script type="application/json" id="amuled-data">{payload}</script>\n'
        f"<script>{script}</script>\n"
        "</body>\n</html>\n"
    )


def write_view(
    run_dir: Path,
    variants: Sequence[trace.TrainedVariant],
    output: Path | None = None,
    *,
    scenario_name: str,
    task_name: str,
    evaluation: EvaluationConfig,
    episode: int = 0,
    mode: str = "greedy",
    episodes: int | None = None,
    say: Callable[[str], None] | None = None,
) -> ViewResult:
    """Write the page of evaluation episode ``episode`` of ``episodes`` (`replay_episode`).

    ``output`` defaults to ``<run>/view-episode<K>.html``; ``say`` gets a line per variant.
    UnsafePathError (before any replay): the output is not a regular file; FileWriteError.
    """
    from amuled_ma import __version__
    from amuled_ma.tasks import get_task

    start = time.perf_counter()
    path = check_write_target(output or Path(run_dir) / f"view-episode{episode}.html")
    episodes = int(evaluation.episodes if episodes is None else episodes)
    texts = TextTable()
    entries = []
    for trained in variants:
        began = time.perf_counter()
        entry = variant_view(run_dir, trained, texts, episode=episode, mode=mode, episodes=episodes)
        entries.append(entry)
        if say is not None:
            say(
                f"  {trained.name}: {entry['T']} steps, {entry['distinct_states']} distinct "
                f"states, {entry.get('kind')} feedback ({time.perf_counter() - began:.1f} s)"
            )
    if texts.fit(TEXT_BUDGET) and say is not None:
        say(
            f"  texts cut to fit {TEXT_BUDGET:,} characters in all "
            "(amuled explain --full prints them whole)"
        )
    seed = evaluation.seed + episode
    how = (
        "greedy: each step the policy's most probable action (as amuled evaluate's greedy mode)"
        if mode == "greedy"
        else "sampled: actions drawn from the policy with amuled evaluate's own draws (the "
        f"episode {episode} of its {episodes})"
    )
    data = {
        "version": 1,
        "title": f"AMULED viewer: {scenario_name}, evaluation episode {episode}",
        "subtitle": (
            f"run {run_dir} · task {task_name} · episode {episode} (seed {seed} = "
            f"[evaluation].seed {evaluation.seed} + {episode}) · {how}"
        ),
        "footer": (
            f"Written by amuled-ma {__version__} (amuled view). Beliefs from the run's belief "
            "store (read-only) or the variant's source; probabilities rounded to "
            f"{DECIMALS} decimals. This page loads nothing from the network."
        ),
        "run": str(run_dir),
        "scenario": scenario_name,
        "task": task_name,
        "episode": episode,
        "seed": seed,
        "mode": mode,
        "episodes": episodes,
        "actions": list(get_task(task_name).action_names),
        "colors": dict(COLORS),
        "texts": texts.texts,
        "variants": entries,
    }
    page = render_html(data)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, page)
    shown = [(v["name"], int(v["T"]), int(v.get("distinct_states", 0))) for v in entries]
    return ViewResult(path, path.stat().st_size, shown, time.perf_counter() - start)
