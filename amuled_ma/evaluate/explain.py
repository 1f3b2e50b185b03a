"""One state explained: each agent's belief, weight and reasoning, and the fusion's workings."""

from __future__ import annotations

import math
import re
import textwrap
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from amuled_ma.beliefs.types import FUSED_STATUSES
from amuled_ma.errors import ScenarioError
from amuled_ma.evaluate.numbers import format_number
from amuled_ma.evaluate.panel_answers import ask_panel
from amuled_ma.evaluate.readonly_feedback import describe_feedback

if TYPE_CHECKING:
    from amuled_ma.deliberation.feedback_base import Feedback
    from amuled_ma.evaluate.episode_trace import Episode
    from amuled_ma.evaluate.readonly_feedback import ReadOnlyStore
    from amuled_ma.tasks.base import BatchedTask


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], indent: str = "  ") -> str:
    """Aligned columns: the first left-aligned, the others right-aligned."""
    cells = [[str(h) for h in headers]] + [[_cell(x) for x in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    for n, row in enumerate(cells):
        parts = [row[0].ljust(widths[0])]
        parts += [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        lines.append(indent + "  ".join(parts).rstrip())
        if n == 0:
            lines.append(indent + "  ".join("-" * w for w in widths))
    return "\n".join(lines)


#: Characters a terminal would act on rather than show: C0 controls but tab and newline (ESC
#: starts escape sequences), DEL, the C1 controls (U+009B is a one-character CSI), the
#: bidirectional overrides, and lone surrogates (not text: printing one would fail).
_UNPRINTABLE = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069\ud800-\udfff]")


def printable(text: str) -> str:
    r"""Outside text safe to print on a terminal: control characters as ``\xNN``/``\uNNNN``."""
    return _UNPRINTABLE.sub(_escape, text)


def _escape(match: re.Match[str]) -> str:
    code = ord(match.group())
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def _cell(value: object) -> str:
    return "-" if value is None else format_number(value, 4)  # -0.0000 printed as 0.0000


def _num(value: float) -> str:
    value = float(value)
    return str(int(value)) if value.is_integer() else f"{value:g}"


def parse_obs(text: str, task_cls: type[BatchedTask]) -> np.ndarray:
    """``"1,2,3"`` -> float array; ScenarioError: not finite float32 numbers, or the wrong count."""
    tokens = [x for x in text.replace(" ", "").split(",") if x != ""]
    try:
        values = [float(x) for x in tokens]
    except ValueError:
        raise ScenarioError(
            f"--obs {text!r}: expected numbers separated by commas, e.g. 2,3,7,7,2,2,1,1"
        ) from None
    names = list(task_cls.obs_names)
    if len(values) != len(names):
        raise ScenarioError(
            f"--obs: {task_cls.name} observations have {len(names)} entries "
            f"({', '.join(names)}), found {len(values)}"
        )
    with np.errstate(over="ignore"):
        obs = np.asarray(values, dtype=np.float32)
    bad = ~np.isfinite(obs)
    if bad.any():
        i = int(np.argmax(bad))
        raise ScenarioError(
            f"--obs: entry {i + 1} ({names[i]}) is {tokens[i][:40]!r}, expected a "
            f"finite number (within +-{float(np.finfo(np.float32).max):.3g}, a 32-bit float)"
        )
    return obs


#: Largest integer a prompt variable may be (exact as a float: the tasks count with them).
MAX_PROMPT_INT = 2**53


def parse_prompt_vars(items: Sequence[str]) -> dict[str, Any]:
    """``["num_crying=4", ...]`` -> ``{"num_crying": 4}`` (TOML values); ScenarioError if bad.

    Bad: not ``NAME=VALUE``, nested too deep, or a number not finite or beyond `MAX_PROMPT_INT`.
    """
    out: dict[str, Any] = {}
    for item in items:
        name, sep, raw = item.partition("=")
        if not sep or not name.strip():
            raise ScenarioError(f"--prompt-var {item!r}: expected NAME=VALUE, e.g. num_crying=4")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw.strip()
        except RecursionError:
            raise ScenarioError(
                f"--prompt-var {name.strip()}: the value is nested deeper than Python can read"
            ) from None
        for number in value if isinstance(value, list) else [value]:
            if isinstance(number, bool) or not isinstance(number, int | float):
                continue
            if isinstance(number, float) and not math.isfinite(number):
                raise ScenarioError(
                    f"--prompt-var {name.strip()}: expected a finite number, found {number!r}; "
                    "e.g. num_crying=4"
                )
            if abs(number) > MAX_PROMPT_INT:
                raise ScenarioError(
                    f"--prompt-var {name.strip()}: expected a number within +-{MAX_PROMPT_INT:,} "
                    f"(2^53), found {number:.3g}; e.g. num_crying=4"
                )
        out[name.strip()] = value
    return out


@dataclass
class State:
    """The state to explain; ``live_belief`` is a non-panel feedback's belief (None for a panel)."""

    obs: np.ndarray
    prompt_vars: dict[str, Any] | None
    context: list[str]
    live_belief: np.ndarray | None = None


def state_of_step(ep: Episode, step: int, where: str) -> State:
    """State ``step`` of a replayed episode and what both policies did; ScenarioError if none."""
    if not 0 <= step < ep.length:
        raise ScenarioError(
            f"--step {step}: episode {ep.episode} of {where} has {ep.length} steps "
            f"(0..{ep.length - 1})"
        )
    names = ep.action_names
    taken = int(ep.actions[step])
    line = (
        f"state of step {step} of evaluation episode {ep.episode} (seed {ep.seed}, "
        f"{ep.mode}) of {where}: the fine-tuned policy took {names[taken]} "
        f"(p={ep.probs[step][taken]:.3f})"
    )
    if ep.base_actions is not None:
        b = int(ep.base_actions[step])
        differs = "DIFFERENT from" if b != taken else "the same as"
        line += f"; the base policy would take {names[b]} ({differs} the fine-tune)"
    live = None if ep.live_beliefs is None else ep.live_beliefs[step]
    return State(ep.obs[step], ep.prompt_vars[step], [line], live)


def state_by_hand(
    task_cls: type[BatchedTask],
    feedback: Feedback,
    feedback_name: str,
    obs: np.ndarray,
    extras: dict[str, Any],
    where: str,
) -> State:
    """A state given by hand: its prompt variables and, for a non-panel feedback, its belief.

    ScenarioError: the panel reads prompts and a variable is missing, or the feedback needs the
    live task.
    """
    import torch

    prompt_vars = None
    needs = bool(getattr(getattr(feedback, "panel", None), "with_messages", False))
    try:
        prompt_vars = task_cls.prompt_variables_from_obs(obs, **extras)
    except (ValueError, TypeError, OverflowError) as error:
        if needs:
            raise ScenarioError(
                f"{task_cls.name} state prompt: {error}; give the missing variable "
                "with --prompt-var NAME=VALUE"
            ) from None
    live_belief = None
    if getattr(feedback, "panel", None) is None:
        try:
            live_belief = np.asarray(
                feedback(torch.as_tensor(obs[None]), None, [0])[0], dtype=np.float64
            )
        except (AttributeError, TypeError):
            raise ScenarioError(
                f"feedback {feedback_name!r} needs the task's full state, not only the "
                "observation: take the state from an episode with --state-from RUN "
                "--variant V --step N"
            ) from None
    return State(obs, prompt_vars, [f"state given by hand, {where}"], live_belief)


def breakdown_lines(
    agents: Sequence[str],
    beliefs: np.ndarray,
    statuses: Sequence[str],
    rule: str,
    prior: Sequence[float] | None,
    actions: list[str],
    panel_fused: np.ndarray,
) -> list[str]:
    """One state's fusion recomputed as the panel fuses (non-answers left out), as lines.

    Per agent: mean BJS, Xiao's credibility, Deng's entropy (bits), ``exp(E_d)`` normalised, weight;
    then pairwise BJS, WAE (``bjs-dst``), Dempster's ``K`` per combination, and the fused belief.
    """
    from amuled_ma.fusion import bjs_divergence, fuse

    beliefs = np.asarray(beliefs, dtype=np.float64)
    answered = [i for i, s in enumerate(statuses) if str(s) in FUSED_STATUSES]
    if not answered:
        return ["no agent answered: the fused belief is the uniform fallback"]
    names = [agents[i] for i in answered]
    sub = beliefs[answered]
    k = len(answered)
    rho = None if prior is None else np.asarray(prior, dtype=np.float64)[answered]
    if rho is not None and not rho.sum() > 0:
        rho = None  # as the panel: only agents without weight answered
    diag = fuse(sub[None], rule, prior=rho, return_diagnostics=True)
    pairwise = bjs_divergence(sub[:, None, :], sub[None, :, :])
    entropy = np.asarray(diag.entropy, dtype=np.float64)[0]
    volume = np.exp(entropy - entropy.max())
    conflicts = np.asarray(diag.conflicts, dtype=np.float64).reshape(-1)
    fused = np.asarray(diag.fused, dtype=np.float64)[0]
    out = [f"fusion ({rule}) over the {k} agents that answered:"]
    say = out.append
    left_out = [f"{agents[i]} ({statuses[i]})" for i in range(len(agents)) if i not in answered]
    if left_out:
        say("  left out (weight 0): " + ", ".join(left_out))
    columns = np.column_stack([
        pairwise.sum(axis=1) / max(k - 1, 1),
        np.asarray(diag.credibility, dtype=np.float64)[0],
        entropy,
        volume / volume.sum(),
        np.asarray(diag.weights, dtype=np.float64)[0],
    ])  # fmt: skip
    rows = [[name, *values] for name, values in zip(names, columns.tolist(), strict=True)]
    head = ["agent", "avg BJS", "credibility", "Deng H (bits)", "info volume", "weight"]
    say(table(head, rows))
    if k > 1:
        rows = [[names[i], *pairwise[i].tolist()] for i in range(k)]
        out += ["", "pairwise BJS divergence:", table(["", *names], rows)]
    say("")
    if diag.wae is not None:
        wae = np.asarray(diag.wae, dtype=np.float64)[0].tolist()
        say(table(["", *actions], [["WAE (weighted average evidence)", *wae]]))
    if conflicts.size:
        parts = "  ".join(f"K{t + 1}={c:.4f}" for t, c in enumerate(conflicts.tolist()))
        say(f"Dempster's conflict at each of the {conflicts.size} combinations: {parts}")
    else:
        say("Dempster's conflict: none (this rule does not combine)")
    agree = np.allclose(fused, panel_fused, atol=1e-9)
    say(
        table(["", *actions], [["fused (recomputed)", *fused.tolist()]])
        + ("" if agree else "\n  note: the panel's fused belief differs from this recomputation")
    )
    return out


def explain_lines(
    task_name: str,
    cluster_recording: str,
    task_cls: type[BatchedTask],
    feedback: Feedback,
    store: ReadOnlyStore,
    feedback_name: str,
    state: State,
    *,
    reply_chars: int | None = None,
    show_prompt: bool = False,
) -> list[str]:
    """The lines explaining one state: the panel's answers, the fusion, the raw replies.

    ``cluster_recording`` (``[feedback].cluster_recording``) is named as the fix when the feedback
    replays fused beliefs only; ``store`` is the run's store, read-only (the raw replies of
    non-answers); ``reply_chars`` cuts each raw reply (None: whole); ``show_prompt`` adds the
    state prompt.
    """
    from amuled_ma.tasks.prompts import render_state_prompt

    out: list[str] = []
    say = out.append
    obs, prompt_vars = state.obs, state.prompt_vars
    actions = list(task_cls.action_names)
    shown = ", ".join(f"{n}={_num(v)}" for n, v in zip(task_cls.obs_names, obs, strict=True))
    say(f"explain {task_name}: {shown}")
    if prompt_vars is not None:
        extra = {k: v for k, v in prompt_vars.items() if k not in task_cls.obs_names}
        if extra:
            say("  prompt variables: " + ", ".join(f"{k}={v}" for k, v in extra.items()))
    for line in state.context:
        say("  " + line)
    panel = getattr(feedback, "panel", None)
    say(f"feedback {feedback_name}: {describe_feedback(feedback)}")
    if panel is None:
        if state.live_belief is None:
            raise ScenarioError(
                f"feedback {feedback_name!r} is not a panel and gave no belief for this state"
            )
        say(
            f"  this feedback is not a panel of agents ({type(feedback).__name__}): its belief "
            "is the reward, with no agents, weights or reasoning to show"
        )
        if getattr(feedback, "recording", None) is not None and cluster_recording:
            say(
                "  for the clusters' own beliefs, replay the recording with them: --set "
                f'feedback.recording="{cluster_recording}"'
            )
        out += ["", table(["", *actions], [["feedback belief", *state.live_belief.tolist()]])]
        return [printable(line) for line in out]
    answers = ask_panel(
        panel, obs[None].astype(np.float64), [prompt_vars] if prompt_vars else None, store
    )
    agents, rule = answers.agents, answers.rule
    beliefs, weights = answers.beliefs[0], answers.weights[0]
    statuses = answers.statuses[0].tolist()
    say(f"  {len(agents)} agents, fusion rule {rule}; an agent that did not answer abstains")
    out += ["", "beliefs:"]
    rows = [
        [agent, statuses[c], *beliefs[c].tolist(), float(weights[c])]
        for c, agent in enumerate(agents)
    ]
    rows.append([f"fused ({rule})", "", *answers.fused[0].tolist(), ""])
    say(table(["agent", "status", *actions, "weight"], rows))
    out.append("")
    prior = getattr(panel, "prior", None)
    out += breakdown_lines(agents, beliefs, statuses, rule, prior, actions, answers.fused[0])
    out += ["", "reasoning (raw replies):"]
    for c, agent in enumerate(agents):
        raw = answers.raws[0][c]
        reason = answers.reasons[0][c]
        if not raw:
            why = f" ({reason})" if reason else ""
            say(f"  {agent} [{statuses[c]}]: no reply text kept{why}")
            continue
        text = raw if reply_chars is None or len(raw) <= reply_chars else raw[:reply_chars]
        say(f"  {agent} [{statuses[c]}]:")
        for paragraph in text.splitlines() or [""]:
            for piece in textwrap.wrap(paragraph, 96) or [""]:
                say("    | " + piece)
        if text is not raw:
            say(f"    | [... {len(raw) - len(text)} more characters; --full prints them]")
    if show_prompt and prompt_vars is not None:
        out += ["", "state prompt:"]
        out += ["    " + line for line in render_state_prompt(task_name, prompt_vars).splitlines()]
    # replies, reasons and names come from outside: no terminal control sequence is printed
    return [printable(line) for line in out]
