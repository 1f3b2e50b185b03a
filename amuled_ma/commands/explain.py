"""``amuled explain``: one state in the terminal, the panel's beliefs and how they were fused.

Either a state given by hand::

    amuled explain findmilk --obs 2,3,7,7,2,2,1,1 --prompt-var num_crying=4
    amuled explain driving --obs 6,5,-1,-1,-1,-1,0,0,1,0,0 --run-dir runs/driving

or a state of an evaluation episode, replayed as ``amuled view`` replays it::

    amuled explain --state-from runs/findmilk --variant finetune-amuled --step 12

prints each agent's belief, status, fusion weight and reasoning (its raw reply, when the
run's belief store or the replayed recording kept it), then the fusion's intermediate
quantities from :mod:`amuled_ma.fusion` (pairwise BJS divergences, average divergence,
credibility, Deng entropy, information volume, weights, the weighted average evidence and
Dempster's conflict ``K`` of each combination) and the fused belief. Without ``--run-dir``
the shipped scenario of TASK is used (its recording found by name, see
:meth:`~amuled_ma.scenario.Scenario.recording_path`) and nothing is written anywhere.
"""

from __future__ import annotations

import argparse
import textwrap
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.commands import _experiment as common
from amuled_ma.errors import AmuledError, ScenarioError

#: Characters of a raw reply printed without ``--full``.
REPLY_CHARS = 1200


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled explain``."""
    parser = subparsers.add_parser(
        "explain",
        help="explain one state: each agent's belief, weight and reasoning, and the fusion's "
        "intermediate quantities",
        description=(
            "Ask the moral panel about one state and print each agent's belief, status, "
            "fusion weight and reasoning, the fusion's intermediate quantities (BJS "
            "divergences, credibility, Deng entropy, information volume, weights, Dempster's "
            "conflict K of each combination) and the fused belief. The state is given with "
            "--obs (and --prompt-var), or taken from an evaluation episode with --state-from "
            "RUN --variant V --step N. Without --run-dir, TASK's shipped scenario is used "
            "and nothing is written."
        ),
    )
    parser.add_argument(
        "scenario",
        metavar="TASK",
        nargs="?",
        default=None,
        help="a shipped scenario (findmilk, driving, ...) or a scenario TOML file; not "
        "needed with --state-from",
    )
    parser.add_argument(
        "--obs",
        default=None,
        metavar="V1,V2,...",
        help="the observation, comma-separated (FindMilk: x,y,milk_x,milk_y,cry_x,cry_y,"
        "sleep_x,sleep_y)",
    )
    parser.add_argument(
        "--prompt-var",
        dest="prompt_vars",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a prompt variable the observation lacks (repeatable), e.g. num_crying=4",
    )
    parser.add_argument(
        "--run-dir",
        type=Path,
        default=None,
        help="a run directory: its scenario and its belief store (read-only)",
    )
    parser.add_argument(
        "--feedback",
        default=None,
        help="feedback variant: amuled (default), cluster:<name>, agg:mean|max|vote, moral, "
        "human, human:rules; with --state-from: the variant's own",
    )
    parser.add_argument(
        "--state-from",
        type=Path,
        default=None,
        metavar="RUN",
        help="take the state from an evaluation episode of this run (with --variant, --step)",
    )
    parser.add_argument("--variant", default=None, help="with --state-from: the variant folder")
    parser.add_argument(
        "--step", type=common.bounded_int(0), default=None, help="with --state-from: the step"
    )
    parser.add_argument(
        "--episode",
        type=common.bounded_int(0),
        default=0,
        metavar="K",
        help="with --state-from: evaluation episode K (default 0)",
    )
    parser.add_argument(
        "--mode",
        choices=("greedy", "sampled"),
        default="greedy",
        help="with --state-from: how the episode's actions were chosen (default greedy)",
    )
    parser.add_argument(
        "--full", action="store_true", help=f"print whole replies (default: {REPLY_CHARS} chars)"
    )
    parser.add_argument("--prompt", action="store_true", help="print the state prompt too")
    common.add_overrides_argument(parser)
    parser.set_defaults(handler=explain_command)


# ---------------------------------------------------------------------------------------
# Text tables


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


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float | np.floating):
        return f"{float(value):.4f}"
    return str(value)


# ---------------------------------------------------------------------------------------
# The command


def parse_obs(text: str, task_cls: Any) -> np.ndarray:
    """``"1,2,3"`` -> float array, checked against the task's observation length.

    Raises:
        ScenarioError: Not numbers, or the wrong count (the message lists the entries).

    """
    try:
        values = [float(x) for x in text.replace(" ", "").split(",") if x != ""]
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
    return np.asarray(values, dtype=np.float32)


def parse_prompt_vars(items: Sequence[str]) -> dict[str, Any]:
    """``["num_crying=4", ...]`` -> ``{"num_crying": 4}`` (values in TOML syntax)."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, raw = item.partition("=")
        if not sep or not name.strip():
            raise ScenarioError(f"--prompt-var {item!r}: expected NAME=VALUE, e.g. num_crying=4")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw.strip()
        out[name.strip()] = value
    return out


def with_overrides(scenario: Any, overrides: Sequence[str]) -> Any:
    """A run's scenario with ``--set SECTION.KEY=VALUE`` applied (as for a shipped one).

    Raises:
        ScenarioError: A malformed override or an unknown section or key.

    """
    for text in overrides:
        section, name, value = common.parse_override(text)
        if not hasattr(scenario, section) or section in ("name", "path"):
            raise ScenarioError(f"--set {text!r}: unknown section [{section}]")
        scenario = scenario.replace(section, **{name: value})
    return scenario


def explain_command(args: argparse.Namespace) -> int:
    """Run ``amuled explain``."""
    from amuled_ma.evaluate import episode_trace as trace
    from amuled_ma.tasks import get_task

    context: list[str] = []
    if args.state_from is not None:
        if args.variant is None or args.step is None:
            raise ScenarioError(
                "--state-from needs --variant V (a variant folder of the run) and --step N"
            )
        run_dir = Path(args.state_from)
        common.scenario_of_run(run_dir)  # a clear error when it is no run
        variant_dir = run_dir / args.variant
        if not (variant_dir / trace.LAST).is_file():
            raise AmuledError(
                f"{run_dir}: no trained variant {args.variant!r} (no "
                f"{variant_dir / trace.LAST}); variants are the folders with a checkpoint"
            )
        scenario = with_overrides(trace.variant_scenario(run_dir, variant_dir), args.overrides)
        feedback_name = args.feedback or trace.feedback_variant(variant_dir) or "amuled"
        task_cls = get_task(scenario.task.name)
        feedback, store = trace.open_feedback(feedback_name, scenario, run_dir)
        try:
            actor = trace.load_actor(variant_dir / trace.LAST, scenario)
            base_path = trace.base_checkpoint_of(run_dir, variant_dir)
            base = trace.load_actor(base_path, scenario) if base_path is not None else None
            live = feedback if getattr(feedback, "panel", None) is None else None
            ep = trace.replay_episode(
                actor,
                scenario,
                episode=args.episode,
                mode=args.mode,
                base_actor=base,
                live_feedback=live,
            )
            if args.step >= ep.length:
                raise ScenarioError(
                    f"--step {args.step}: episode {args.episode} of {args.variant} has "
                    f"{ep.length} steps (0..{ep.length - 1})"
                )
            t = args.step
            obs, prompt_vars = ep.obs[t], ep.prompt_vars[t]
            names = ep.action_names
            line = (
                f"state of step {t} of evaluation episode {args.episode} (seed {ep.seed}, "
                f"{args.mode}) of {run_dir}/{args.variant}: the fine-tuned policy took "
                f"{names[ep.actions[t]]} (p={ep.probs[t][ep.actions[t]]:.3f})"
            )
            if ep.base_actions is not None:
                b = int(ep.base_actions[t])
                differs = "DIFFERENT from" if b != int(ep.actions[t]) else "the same as"
                line += f"; the base policy would take {names[b]} ({differs} the fine-tune)"
            context.append(line)
            _explain(args, scenario, task_cls, feedback, store, feedback_name, obs, prompt_vars,
                     context, live_belief=None if live is None else ep.live_beliefs[t])  # fmt: skip
        finally:
            feedback.close()
            store.close()
        return 0

    if args.obs is None:
        raise ScenarioError(
            "give a state: TASK --obs V1,V2,... (and --prompt-var NAME=VALUE), or "
            "--state-from RUN --variant V --step N"
        )
    if args.run_dir is not None:
        scenario = with_overrides(common.scenario_of_run(Path(args.run_dir)), args.overrides)
        if args.scenario and args.scenario not in (scenario.task.name, scenario.name):
            raise ScenarioError(
                f"TASK {args.scenario!r} does not match the run {args.run_dir} (task "
                f"{scenario.task.name}, scenario {scenario.name}); leave TASK out or match it"
            )
    elif args.scenario is None:
        raise ScenarioError("name TASK (findmilk, driving, ...) or give --run-dir RUN")
    else:
        scenario = common.load(args)
    task_cls = get_task(scenario.task.name)
    obs = parse_obs(args.obs, task_cls)
    extras = parse_prompt_vars(args.prompt_vars)
    feedback_name = args.feedback or "amuled"
    feedback, store = trace.open_feedback(feedback_name, scenario, args.run_dir)
    try:
        prompt_vars = None
        needs = bool(getattr(getattr(feedback, "panel", None), "with_messages", False))
        try:
            prompt_vars = task_cls.prompt_variables_from_obs(obs, **extras)
        except (ValueError, TypeError) as error:
            if needs:
                raise ScenarioError(
                    f"{scenario.task.name} state prompt: {error}; give the missing variable "
                    "with --prompt-var NAME=VALUE"
                ) from None
        where = f"run {args.run_dir}" if args.run_dir else f"scenario {scenario.name} (shipped)"
        context.append(f"state given by hand, {where}")
        live_belief = None
        if getattr(feedback, "panel", None) is None:
            import torch

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
        _explain(args, scenario, task_cls, feedback, store, feedback_name, obs, prompt_vars,
                 context, live_belief=live_belief)  # fmt: skip
    finally:
        feedback.close()
        store.close()
    return 0


def _explain(
    args: argparse.Namespace,
    scenario: Any,
    task_cls: Any,
    feedback: Any,
    store: Any,
    feedback_name: str,
    obs: np.ndarray,
    prompt_vars: dict[str, Any] | None,
    context: list[str],
    *,
    live_belief: np.ndarray | None,
) -> None:
    from amuled_ma.evaluate import episode_trace as trace
    from amuled_ma.tasks.prompts import render_state_prompt

    say = common.say
    actions = list(task_cls.action_names)
    shown = ", ".join(f"{n}={_num(v)}" for n, v in zip(task_cls.obs_names, obs, strict=True))
    say(f"explain {scenario.task.name}: {shown}")
    if prompt_vars is not None:
        extra = {k: v for k, v in prompt_vars.items() if k not in task_cls.obs_names}
        if extra:
            say("  prompt variables: " + ", ".join(f"{k}={v}" for k, v in extra.items()))
    for line in context:
        say("  " + line)
    panel = getattr(feedback, "panel", None)
    say(f"feedback {feedback_name}: {trace.describe_feedback(feedback)}")
    if panel is None:
        assert live_belief is not None
        say(
            f"  this feedback is not a panel of agents ({type(feedback).__name__}): its belief "
            "is the reward, with no agents, weights or reasoning to show"
        )
        if getattr(feedback, "recording", None) is not None and scenario.feedback.cluster_recording:
            say(
                "  for the clusters' own beliefs, replay the recording with them: --set "
                f'feedback.recording="{scenario.feedback.cluster_recording}"'
            )
        say("")
        say(table(["", *actions], [["feedback belief", *live_belief.tolist()]]))
        return
    answers = trace.ask_panel(
        panel, obs[None].astype(np.float64), [prompt_vars] if prompt_vars else None, store
    )
    agents, rule = answers.agents, answers.rule
    beliefs, weights = answers.beliefs[0], answers.weights[0]
    statuses = answers.statuses[0].tolist()
    say(f"  {len(agents)} agents, fusion rule {rule}; an agent that did not answer abstains")
    say("")
    say("beliefs:")
    rows = [
        [agent, statuses[c], *beliefs[c].tolist(), float(weights[c])]
        for c, agent in enumerate(agents)
    ]
    rows.append([f"fused ({rule})", "", *answers.fused[0].tolist(), ""])
    say(table(["agent", "status", *actions, "weight"], rows))
    breakdown = trace.fusion_breakdown(agents, beliefs, statuses, rule)
    say("")
    if breakdown is None:
        say("no agent answered: the fused belief is the uniform fallback")
    else:
        _print_breakdown(breakdown, actions, answers.fused[0], answers.conflicts[0])
    say("")
    say("reasoning (raw replies):")
    for c, agent in enumerate(agents):
        raw = answers.raws[0][c]
        reason = answers.reasons[0][c]
        if not raw:
            why = f" ({reason})" if reason else ""
            say(f"  {agent} [{statuses[c]}]: no reply text kept{why}")
            continue
        text = raw if args.full or len(raw) <= REPLY_CHARS else raw[:REPLY_CHARS]
        say(f"  {agent} [{statuses[c]}]:")
        for paragraph in text.splitlines() or [""]:
            wrapped = textwrap.wrap(paragraph, 96) or [""]
            for piece in wrapped:
                say("    | " + piece)
        if text is not raw:
            say(f"    | [... {len(raw) - REPLY_CHARS} more characters; --full prints them]")
    if args.prompt and prompt_vars is not None:
        say("")
        say("state prompt:")
        for line in render_state_prompt(scenario.task.name, prompt_vars).splitlines():
            say("    " + line)


def _num(value: float) -> str:
    value = float(value)
    return str(int(value)) if value.is_integer() else f"{value:g}"


def _print_breakdown(
    b: Any, actions: list[str], panel_fused: np.ndarray, panel_conflicts: np.ndarray
) -> None:
    say = common.say
    answered = len(b.agents)
    say(f"fusion ({b.rule}) over the {answered} agents that answered:")
    if b.left_out:
        say(
            "  left out (weight 0): "
            + ", ".join(f"{name} ({status})" for name, status in b.left_out)
        )
    rows = [
        [
            name,
            float(b.bjs_mean[i]),
            float(b.credibility[i]),
            float(b.entropy[i]),
            float(b.volume[i]),
            float(b.weights[i]),
        ]
        for i, name in enumerate(b.agents)
    ]
    say(
        table(
            ["agent", "avg BJS", "credibility", "Deng H (bits)", "info volume", "weight"],
            rows,
        )
    )
    if answered > 1:
        say("")
        say("pairwise BJS divergence:")
        say(table(["", *b.agents], [[b.agents[i], *b.bjs[i].tolist()] for i in range(answered)]))
    say("")
    if b.wae is not None:
        say(table(["", *actions], [["WAE (weighted average evidence)", *b.wae.tolist()]]))
    if b.conflicts.size:
        parts = "  ".join(f"K{t + 1}={k:.4f}" for t, k in enumerate(b.conflicts.tolist()))
        say(f"Dempster's conflict at each of the {b.conflicts.size} combinations: {parts}")
    else:
        say("Dempster's conflict: none (this rule does not combine)")
    agree = np.allclose(b.fused, panel_fused, atol=1e-9)
    say(
        table(["", *actions], [["fused (recomputed)", *b.fused.tolist()]])
        + ("" if agree else "\n  note: the panel's fused belief differs from this recomputation")
    )
    del panel_conflicts
