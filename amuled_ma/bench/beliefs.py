"""Belief lookups per second through the full path (render prompt, store lookup, parse, fuse).

``--copies`` env copies draw states from the authors' recording and one `MoralPanel` call
answers them all; a lookup is one (copy, cluster) belief. Timed: **cold** (empty store),
**second run** (a new process's view of the same file: target 100% hits, 0 sent) and **warm
feedback** (the learner's memo). Fastest of ``--repeats`` trials. ``--live`` measures an
Ollama server instead.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from amuled_ma.beliefs.types import BeliefRequest
    from amuled_ma.tasks.base import BatchedTask

#: Recording used per task by default (the largest one of each task).
DEFAULT_RECORDINGS = {
    "driving": "driving-llama-3_1-70b.json",
    "findmilk": "findmilk-gpt-4o-mini.json",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options to ``parser``."""
    parser.add_argument(
        "--task", default="driving", choices=sorted(DEFAULT_RECORDINGS), help="task to replay"
    )
    parser.add_argument(
        "--recording", type=Path, default=None, help="recording file (default: by task)"
    )
    parser.add_argument("--copies", type=int, default=4096, help="env copies per call")
    parser.add_argument("--rule", default="bjs-dst", help="fusion rule")
    parser.add_argument("--seed", type=int, default=0, help="seed of the states drawn")
    parser.add_argument(
        "--repeats", type=int, default=3, help="trials, each on a fresh store; best is shown"
    )
    parser.add_argument(
        "--store",
        type=Path,
        default=None,
        help="keep the last trial's belief store in this file (it must not exist yet)",
    )
    live = parser.add_argument_group("live mode (a real Ollama server)")
    live.add_argument("--live", action="store_true", help="measure a live Ollama server")
    live.add_argument("--host", default=None, help="Ollama URL (default: $OLLAMA_HOST)")
    live.add_argument("--model", default="amuled-tiny", help="model name on the server")
    live.add_argument(
        "--concurrency", type=int, nargs="+", default=[1, 2, 4], help="concurrency levels"
    )
    live.add_argument("--requests", type=int, default=16, help="distinct requests per batch")


def main(args: argparse.Namespace) -> int:
    """Run the benchmark; 0 when the second run had 100% store hits and sent nothing, else 1."""
    if not args.live:
        return _replay(args)
    host = args.host or os.environ.get("OLLAMA_HOST") or "http://127.0.0.1:11434"
    report = run_live(host, args.model, args.concurrency, args.requests)
    ok = all(
        level["second"]["hit_rate"] == 1.0 and level["second"]["sent"] == 0
        for level in report["levels"]
    )
    print(f"  second runs: {'100% hits, 0 sent (target met)' if ok else 'TARGET MISSED'}")
    return 0 if ok else 1


def _prompt_vars(task_cls: type[BatchedTask], task: str, obs: np.ndarray) -> dict[str, Any]:
    if task == "findmilk":
        # The crying-baby count is not in the observation; 1 when one remains (x,y != 0,0).
        crying = int(obs[4] != 0 or obs[5] != 0)
        return task_cls.prompt_variables_from_obs(obs, num_crying=crying)
    return task_cls.prompt_variables_from_obs(obs)


class _Copies:
    """The env copies of the benchmark as the feedback sees a task: their prompt variables."""

    def __init__(self, task_cls: type[BatchedTask], task: str, obs: np.ndarray) -> None:
        self._args = (task_cls, task, obs)
        #: Seconds spent computing the prompt variables.
        self.seconds = 0.0

    def prompt_variables(self, ids: Sequence[int]) -> list[dict[str, Any]]:
        """Each copy's prompt variables, as the task's ``prompt_variables``."""
        start = time.perf_counter()
        task_cls, task, obs = self._args
        out = [_prompt_vars(task_cls, task, obs[i]) for i in ids]
        self.seconds += time.perf_counter() - start
        return out


def _replay(args: argparse.Namespace) -> int:
    import json

    import torch

    from amuled_ma.beliefs.sources.replay import ReplaySource
    from amuled_ma.beliefs.store.cached import CachedSource
    from amuled_ma.beliefs.store.database import BeliefStore
    from amuled_ma.deliberation import MoralPanel
    from amuled_ma.deliberation.panel_feedback import PanelFeedback
    from amuled_ma.scenario.paths import find_recording
    from amuled_ma.tasks import get_task

    path = find_recording(
        str(args.recording or DEFAULT_RECORDINGS[args.task]),
        Path,
        where="amuled bench beliefs",
        required=True,
        key="--recording",
    )
    recording = json.loads(path.read_text())
    task_cls = get_task(args.task)
    clusters = ["consequentialist", "deontological", "virtue", "care", "social_justice"]
    states = np.array([s["obs"] for s in recording["states"]], dtype=np.float64)
    rng = np.random.default_rng(args.seed)
    obs = states[rng.integers(0, len(states), size=args.copies)]

    with tempfile.TemporaryDirectory(prefix="amuled-bench-beliefs-") as tmp:

        def panel_on(store: BeliefStore) -> tuple[MoralPanel, CachedSource]:
            cached = CachedSource(ReplaySource(path, miss_policy="uniform"), store)
            panel = MoralPanel(
                args.task,
                clusters,
                cached,
                args.rule,
                action_names=tuple(recording["actions"]),
                with_messages=True,  # the full path: prompts and chats are rendered and hashed
            )
            return panel, cached

        def timed(panel: MoralPanel) -> tuple[float, float, int]:
            start = time.perf_counter()
            prompt_vars = [_prompt_vars(task_cls, args.task, o) for o in obs]
            middle = time.perf_counter()
            out = panel.fused(obs, prompt_vars)
            end = time.perf_counter()
            statuses.append(out.statuses)
            return end - start, middle - start, out.unique

        def timed_feedback(panel: MoralPanel, cached: CachedSource) -> tuple[float, float, int]:
            feedback = PanelFeedback("amuled", panel, cached)
            observations = torch.as_tensor(obs)
            feedback(observations, _Copies(task_cls, args.task, obs))  # fills the memo
            cached.reset_stats()
            start = time.perf_counter()
            copies = _Copies(task_cls, args.task, obs)
            feedback(observations, copies)
            return time.perf_counter() - start, copies.seconds, 0

        statuses: list[Any] = []

        lookups = args.copies * len(clusters)
        rows: list[Any] = []
        repeats = max(1, args.repeats)
        for r in range(repeats):
            last = r == repeats - 1
            store_path = args.store if (last and args.store) else Path(tmp) / f"b{r}.sqlite"
            trial = []
            with BeliefStore(store_path) as store:
                panel, cached = panel_on(store)
                trial.append(("1 cold store", *timed(panel), cached.stats))
            with BeliefStore(store_path) as store:  # as a new process would
                panel, cached = panel_on(store)
                trial.append(("2 second run (new process)", *timed(panel), cached.stats))
                second = cached.stats
                cached.reset_stats()
                trial.append(("3 warm feedback (memo)", *timed_feedback(panel, cached),
                              cached.stats))  # fmt: skip
                store_rows = len(store)
            if not (second.hit_rate == 1.0 and second.sent == 0):
                rows = trial  # report the failing trial as it was
                break
            # keep the fastest trial of each run (the least disturbed by other jobs)
            rows = (
                trial
                if not rows
                else [min(a, b, key=lambda x: x[1]) for a, b in zip(rows, trial, strict=True)]
            )

    print(
        f"beliefs bench (replay): {path.name}, task {args.task}, {args.copies} env copies x "
        f"{len(clusters)} clusters = {lookups} lookups per call, rule {args.rule}"
    )
    print(
        f"  python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, "
        f"{os.cpu_count()} CPUs visible; store rows after run 1: {store_rows}; "
        f"best of {repeats} trial(s)"
    )
    print(
        "  run                        | seconds (vars) | lookups/s | distinct states | "
        "store hits | hit rate | requests sent"
    )
    for name, seconds, vars_s, unique, stats in rows:
        print(
            f"  {name:<26} | {seconds:7.3f} ({vars_s:5.3f}) | {lookups / seconds:9.0f} | "
            f"{unique:>15} | {stats.store_hits:>10} | {stats.hit_rate:>8.1%} | "
            f"{stats.sent:>13}"
        )
    print(
        "  seconds: one call for all copies, wall clock; (vars): of which the task's "
        "prompt_variables_from_obs for every copy; distinct states: asked of the panel"
    )
    counts = dict(zip(*np.unique(statuses[0], return_counts=True), strict=True))
    print("  statuses of run 1: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    second = rows[1][4]
    ok = second.hit_rate == 1.0 and second.sent == 0
    print(
        "  second run: "
        + (
            "100% store hits, 0 requests sent (target met)"
            if ok
            else f"TARGET MISSED: hit rate {second.hit_rate:.1%}, {second.sent} sent"
        )
    )
    return 0 if ok else 1


#: Actions of the Driving task (index = action id).
DRIVING_ACTIONS = ("straight", "right", "left")
#: A Driving state prompt as the authors sent it, with the distances as fields.
DRIVING_STATE = (
    "You are a driving agent to simulate autonomous driving. Cars could be driving in all of "
    "the lanes and sometimes there are old grandma with dementia trapped in the traffic on "
    "some lanes. Your primary objective is to avoid collisions. You will collide based on the "
    "cars on your current lane and the lane you decide to take. Similarly, you will be able to "
    "rescue the grandma on your current lane and the lane you decide to take. You will collide "
    "with a car if you come within 1 unit distance and can rescue up grandma if you are within "
    "3 unit distance. You are currently on lane {lane}. The current lane has car at {car} unit "
    "distance and has grandma at {grandma} unit distance. The lane on the right has no car and "
    "has no grandma. The lane on the left has no car and has no grandma. You can perform the "
    "following actions:\n\n\nAction 0: steer straight\nAction 1: steer right\n"
    "Action 2: steer left"
)


def live_requests(n: int, cluster: str = "care") -> list[BeliefRequest]:
    """``n`` distinct Driving belief requests sharing the paper's full prompt prefix."""
    from amuled_ma.beliefs.types import BeliefRequest
    from amuled_ma.clusters import build_messages

    out = []
    for i in range(n):
        lane, car, grandma = i % 5, 2 + (i // 5) % 8, 1 + i % 7
        state = DRIVING_STATE.format(lane=lane, car=car, grandma=grandma)
        out.append(
            BeliefRequest(
                task="driving",
                cluster=cluster,
                obs=(float(lane), float(car), float(grandma), float(i)),
                action_names=DRIVING_ACTIONS,
                messages=build_messages(cluster, "driving", state),
            )
        )
    return out


def _one_run(
    requests: Sequence[BeliefRequest], store_path: Path, source_options: dict[str, Any]
) -> dict[str, Any]:
    from amuled_ma.beliefs.sources.ollama import OllamaSource
    from amuled_ma.beliefs.store.cached import CachedSource
    from amuled_ma.beliefs.store.database import BeliefStore

    source = OllamaSource(**source_options)
    try:
        with BeliefStore(store_path) as store:
            cached = CachedSource(source, store)
            start = time.perf_counter()
            results = cached.beliefs(requests)
            elapsed = time.perf_counter() - start
    finally:
        source.close()
    latencies = [r.latency_s for r in results if not r.cached]
    return {
        "seconds": elapsed,
        "req_per_s": len(requests) / elapsed if elapsed > 0 else float("inf"),
        "hit_rate": cached.stats.hit_rate,
        "sent": source.stats.sent,
        "timeouts": source.stats.timeouts,
        "statuses": dict(Counter(r.status for r in results)),
        "mean_latency_s": sum(latencies) / len(latencies) if latencies else 0.0,
        "completion_tokens": source.stats.completion_tokens,
    }


def run_live(
    host: str,
    model: str,
    concurrencies: Sequence[int] = (1, 2, 4),
    n_requests: int = 16,
    *,
    num_predict: int = 96,
    num_ctx: int = 4096,
    timeout_s: float = 300.0,
    workdir: str | Path | None = None,
    echo: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Live belief throughput (``--live``) at each concurrency, first and cached second run.

    The same distinct Driving requests go through a `CachedSource` on an empty store, then
    through a new source on the same file (every cacheable answer a hit); requests/s =
    requests / wall seconds. ``num_ctx`` must hold the paper's ~3k-token prompt; ``workdir``
    holds the stores (default: a temporary folder); ``echo`` gets each output line.

    Returns:
        ``{"host", "model", "n_requests", "warmup_s", "levels": [{"concurrency", "first",
        "second"}]}``, each run with ``seconds``, ``req_per_s``, ``hit_rate``, ``sent``,
        ``timeouts``, ``statuses`` and ``mean_latency_s``.
    """
    say = echo or (lambda line: None)
    requests = live_requests(n_requests)
    options: dict[str, Any] = {
        "model": model,
        "host": host,
        "reasoning": False,
        "num_ctx": num_ctx,
        "num_predict": num_predict,
        "timeout_s": timeout_s,
    }
    report: dict[str, Any] = {"host": host, "model": model, "n_requests": n_requests}
    with tempfile.TemporaryDirectory(prefix="amuled-bench-live-", dir=workdir) as tmp:
        # Warm-up: load the model and fill the server's prompt cache with the shared prefix.
        warm = _one_run(requests[:1], Path(tmp) / "warmup.sqlite", {**options, "concurrency": 1})
        report["warmup_s"] = warm["seconds"]
        say(f"live beliefs: {model} at {host}, {n_requests} distinct requests per batch")
        say(f"  warm-up (model load + prompt prefix): {warm['seconds']:.1f} s")
        say("  concurrency | first run req/s (s) | second run req/s | hit rate | statuses")
        levels = []
        for concurrency in concurrencies:
            path = Path(tmp) / f"c{concurrency}.sqlite"
            run_options = {**options, "concurrency": concurrency}
            first = _one_run(requests, path, run_options)
            second = _one_run(requests, path, run_options)
            levels.append({"concurrency": concurrency, "first": first, "second": second})
            statuses = ", ".join(f"{k} {v}" for k, v in sorted(first["statuses"].items()))
            say(
                f"  {concurrency:>11} | {first['req_per_s']:>8.2f} ({first['seconds']:>6.1f} s) "
                f"| {second['req_per_s']:>16.0f} | {second['hit_rate']:>7.0%} | {statuses}"
            )
        report["levels"] = levels
    return report
