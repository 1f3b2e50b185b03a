"""``amuled explain``: one state, the panel's beliefs and how they were fused."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from amuled_ma.commands import _experiment as common
from amuled_ma.errors import ScenarioError

if TYPE_CHECKING:
    from collections.abc import Callable

    from amuled_ma.deliberation.feedback_base import Feedback

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
        help="feedback variant: amuled (default), cluster:<name>, agg:<rule> (mean, max, vote, "
        "mec, nash-vote, variance-vote, borda), moral, "
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
    common.add_episode_args(parser, "with --state-from: ")
    parser.add_argument(
        "--full", action="store_true", help=f"print whole replies (default: {REPLY_CHARS} chars)"
    )
    parser.add_argument("--prompt", action="store_true", help="print the state prompt too")
    common.add_clusters_dir_argument(parser)
    common.add_overrides_argument(parser)
    parser.set_defaults(handler=explain_command)


def explain_command(args: argparse.Namespace) -> int:
    """Run ``amuled explain``."""
    from amuled_ma.deliberation.plan import plan_panel
    from amuled_ma.evaluate import explain
    from amuled_ma.evaluate.explain import explain_lines
    from amuled_ma.evaluate.readonly_feedback import open_feedback
    from amuled_ma.experiments.run_folder import scenario_of_run
    from amuled_ma.tasks import get_task

    state_of: Callable[[Feedback], explain.State]
    if args.state_from is not None:
        if args.variant is None or args.step is None:
            raise ScenarioError(
                "--state-from needs --variant V (a variant folder of the run) and --step N"
            )
        store_dir = Path(args.state_from)
        run_scenario = scenario_of_run(store_dir)  # a clear error when it is no run
        # here: the episode's replay imports torch, after the checks that need none
        from amuled_ma.evaluate.episode_trace import replay_variant
        from amuled_ma.experiments.trained_variants import evaluated_episodes, trained_variant

        trained = trained_variant(store_dir, store_dir / args.variant)
        scenario = common.customise(
            trained.scenario, clusters_dirs=args.clusters_dir, overrides=args.overrides
        )
        trained = dataclasses.replace(trained, scenario=scenario)
        feedback_name = args.feedback or trained.feedback or "amuled"
        plan = plan_panel(feedback_name, scenario)  # an unknown cluster: one line, nothing opened
        episodes = args.episodes or evaluated_episodes(store_dir, run_scenario.evaluation.episodes)

        def state_of(feedback: Feedback) -> explain.State:
            live = feedback if getattr(feedback, "panel", None) is None else None
            ep = replay_variant(
                trained, episode=args.episode, mode=args.mode, episodes=episodes, live_feedback=live
            )
            return explain.state_of_step(ep, args.step, f"{store_dir}/{args.variant}")

    else:
        if args.obs is None:
            raise ScenarioError(
                "give a state: TASK --obs V1,V2,... (and --prompt-var NAME=VALUE), or "
                "--state-from RUN --variant V --step N"
            )
        store_dir = args.run_dir
        if args.run_dir is not None:
            scenario = common.customise(
                scenario_of_run(Path(args.run_dir)),
                clusters_dirs=args.clusters_dir,
                overrides=args.overrides,
            )
            if args.scenario and args.scenario not in (scenario.task.name, scenario.name):
                raise ScenarioError(
                    f"TASK {args.scenario!r} does not match the run {args.run_dir} (task "
                    f"{scenario.task.name}, scenario {scenario.name}); leave TASK out or match it"
                )
        elif args.scenario is None:
            raise ScenarioError("name TASK (findmilk, driving, ...) or give --run-dir RUN")
        else:
            scenario = common.load(args)
        feedback_name = args.feedback or "amuled"
        plan = plan_panel(feedback_name, scenario)  # an unknown cluster: one line, before torch
        task_cls = get_task(scenario.task.name)
        obs = explain.parse_obs(args.obs, task_cls)
        extras = explain.parse_prompt_vars(args.prompt_vars)
        where = f"run {args.run_dir}" if args.run_dir else f"scenario {scenario.name} (shipped)"

        def state_of(feedback: Feedback) -> explain.State:
            return explain.state_by_hand(task_cls, feedback, feedback_name, obs, extras, where)

    feedback, store = open_feedback(plan, scenario.feedback.store, store_dir)
    try:
        lines = explain_lines(
            scenario.task.name,
            scenario.feedback.cluster_recording,
            get_task(scenario.task.name),
            feedback,
            store,
            feedback_name,
            state_of(feedback),
            reply_chars=None if args.full else REPLY_CHARS,
            show_prompt=args.prompt,
        )
        for line in lines:
            common.say(line)
    finally:
        feedback.close()
        store.close()
    return 0
