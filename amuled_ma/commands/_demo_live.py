"""The demo's live leg: a few requests to a local Ollama model, its report section and timing."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.files.safe import checked_read_path, write_text_atomic

if TYPE_CHECKING:
    from amuled_ma.scenario import FeedbackConfig, Scenario
    from amuled_ma.servers.timing import CacheReuse, RequestTiming, TimingLog


def say(message: str) -> None:
    """Print one ``[demo]`` line on stderr."""
    print(f"[demo] {message}", file=sys.stderr, flush=True)


#: The live leg: the first distinct states of the AMULED fine-tune's greedy evaluation
#: episode asked of the live model, and the clusters asked about each: 2 x 2 = 4 requests
#: (15-25 s each for the tiny model on a loaded 2-core machine, docs/ollama.md).
LIVE_STATES = 2
LIVE_CLUSTERS: tuple[str, ...] = ("care", "virtue")
#: The live leg's folder in the run folder (its belief store and ``live.json``).
LIVE_DIR = "live"
#: How the report's live-leg section starts.
LIVE_HEADING = "## Live leg: a few requests to a local model (its judgement is not meaningful)"


def live_section(leg: dict[str, Any]) -> list[str]:
    """The report's live-leg section (`LIVE_HEADING`), from ``live/live.json``'s data."""
    actions = leg["actions"]
    lines = [
        LIVE_HEADING,
        "",
        f"**The model `{leg['model']}` was asked live; its moral judgement is not meaningful"
        + (" (SmolLM2-135M, 135M parameters)" if leg["model"] == "amuled-tiny" else "")
        + ": this leg only shows the live path** (the paper's prompts -> Ollama -> parsing -> "
        "the belief store -> fusion). Nothing here trained a policy: every figure above "
        "comes from the replayed recording.",
        "",
        f"{leg['requests']} requests to `{leg['model']}` at `{leg['host']}` in "
        f"{leg['wall_s']:.1f} s, stored in `{LIVE_DIR}/{Path(leg['store']).name}` (belief "
        f"source: `ollama`, model `{leg['model']}`); the states are the first distinct states "
        "of `finetune-amuled`'s greedy evaluation episode 0; fusion "
        f"`{leg['fusion']}`. Beliefs over {' / '.join(actions)}:",
        "",
        "| step | agent | source | status | belief | fusion weight |",
        "|---|---|---|---|---|---|",
    ]
    for state in leg["states"]:
        for k, agent in enumerate(leg["agents"]):
            belief = " / ".join(f"{p:.2f}" for p in state["beliefs"][k])
            lines.append(
                f"| {state['step']} | {agent} | ollama `{leg['model']}` | "
                f"{state['statuses'][k]} | {belief} | {state['weights'][k]:.3f} |"
            )
        fused = " / ".join(f"{p:.2f}" for p in state["fused"])
        conflict = ", ".join(f"{c:.3f}" for c in state["conflicts"]) or "-"
        lines.append(f"| {state['step']} | **fused** | - | Dempster's K {conflict} | {fused} | |")
    return [*lines, ""]


def write_live_leg(run_dir: Path, scenario: Scenario, *, model: str, host: str) -> bool:
    """Ask a live model about a few states of the AMULED fine-tune's episode; report it.

    The first `LIVE_STATES` distinct states of ``finetune-amuled``'s greedy evaluation episode
    0 are asked of the scenario's panel with ``[feedback].source = "ollama"``, ``model`` at
    ``host`` and the clusters `LIVE_CLUSTERS`, through the store ``RUN_DIR/live/<store>``, and
    fused as in training; ``live/live.json`` keeps the answers and ``report.md`` gets their
    section. True when the leg ran (a failure is printed and the report says so).
    """
    import json

    import numpy as np

    from amuled_ma.beliefs.store.cached import requests_sent
    from amuled_ma.deliberation.build import build_feedback, run_store
    from amuled_ma.deliberation.panel_feedback import PanelFeedback
    from amuled_ma.deliberation.plan import plan_panel
    from amuled_ma.errors import AmuledError
    from amuled_ma.evaluate.episode_trace import replay_variant
    from amuled_ma.evaluate.panel_answers import ask_panel
    from amuled_ma.experiments.trained_variants import evaluated_episodes, trained_variant
    from amuled_ma.monitor.progress import Progress
    from amuled_ma.tasks import get_task

    say(
        f"live leg: {LIVE_STATES} states x {len(LIVE_CLUSTERS)} clusters asked of {model} "
        "(its judgement is not meaningful: it shows the live path)"
    )
    try:
        with Progress("live leg", None, bar=False, unit="batch"):  # never silent while asking
            live = scenario.replace(
                "feedback", source="ollama", model=model, host=host, clusters=list(LIVE_CLUSTERS)
            )
            plan, store = plan_panel("amuled", live), live.feedback.store
            episodes = evaluated_episodes(run_dir, scenario.evaluation.episodes)
            trained = trained_variant(run_dir, run_dir / "finetune-amuled")
            episode = replay_variant(trained, episode=0, mode="greedy", episodes=episodes)
            steps = np.asarray(episode.obs[: episode.length], dtype=np.float64)
            steps = steps.reshape(episode.length, -1)
            # each distinct state's first step
            _, first = np.unique(steps, axis=0, return_index=True)
            picked = sorted(first.tolist())[:LIVE_STATES]
            obs = steps[picked]
            prompt_vars = [dict(episode.prompt_vars[i]) for i in picked]
            out = run_dir / LIVE_DIR
            out.mkdir(parents=True, exist_ok=True)
            feedback = build_feedback(plan, run_store(out / store), cache_dir=out)
            if not isinstance(feedback, PanelFeedback):  # ollama: always asked as a panel
                feedback.close()
                raise TypeError(f"the live panel's feedback is a {type(feedback).__name__}")
            began = time.perf_counter()
            try:
                answers = ask_panel(feedback.panel, obs, prompt_vars)
                sent = requests_sent(feedback.source) or 0  # the store answers the others
            finally:
                feedback.close()
            wall = time.perf_counter() - began
            actions = list(get_task(plan.task).action_names)
            leg: dict[str, Any] = {
                "model": model,
                "host": host,
                "store": str(out / Path(store).name),
                "source": "ollama",
                "meaningful": False,
                "wall_s": wall,
                "asked": len(picked) * len(answers.agents),
                "requests": sent,
                "actions": actions,
                "agents": list(answers.agents),
                "fusion": answers.rule,
                "states": [
                    {
                        "step": int(step),
                        "obs": obs[u].tolist(),
                        "prompt_vars": {  # numpy numbers as Python's
                            k: v.item() if hasattr(v, "item") else v
                            for k, v in prompt_vars[u].items()
                        },
                        "beliefs": answers.beliefs[u].tolist(),
                        "statuses": answers.statuses[u].tolist(),
                        "weights": answers.weights[u].tolist(),
                        "fused": answers.fused[u].tolist(),
                        "conflicts": answers.conflicts[u].tolist(),
                    }
                    for u, step in enumerate(picked)
                ],
            }
    except (AmuledError, OSError, ValueError) as error:
        say(f"live leg failed: {error}")
        put_live_section(run_dir, [LIVE_HEADING, "", f"The live leg failed: {error}", ""])
        return False
    write_text_atomic(run_dir / LIVE_DIR / "live.json", json.dumps(leg, indent=1))
    put_live_section(run_dir, live_section(leg))
    stored = leg["asked"] - leg["requests"]
    from_store = f", {stored} answered from {LIVE_DIR}/ without a request" if stored else ""
    say(f"live leg: {leg['requests']} requests in {leg['wall_s']:.1f} s{from_store}")
    return True


def read_report(run_dir: Path, name: str = "report.md") -> str | None:
    """The text of ``run_dir/name`` (None when it is missing), bounded as a report.

    Raises:
        AmuledError: It is a link, not a regular file, over `MAX_REPORT_BYTES`, or unreadable.
        UnicodeDecodeError: It is not UTF-8 text.
    """
    from amuled_ma.evaluate.report.writing import MAX_REPORT_BYTES
    from amuled_ma.files.limits import read_bounded_bytes

    path = checked_read_path(run_dir, name)
    if not path.is_file():
        return None
    fix = f"is it the right folder? Write the report again with 'amuled evaluate {run_dir}'"
    noun = name.partition(".")[0]  # "report", "results"
    return read_bounded_bytes(path, MAX_REPORT_BYTES, noun, fix=fix).decode("utf-8")


def put_live_section(run_dir: Path, lines: list[str]) -> None:
    """End ``report.md`` with the live leg's section, in place of an earlier one (`read_report`)."""
    text = read_report(run_dir)
    if text is None:
        return
    if LIVE_HEADING in text:  # a re-run: replace the old section
        text = text[: text.index(LIVE_HEADING)]
    write_text_atomic(run_dir / "report.md", text.rstrip("\n") + "\n\n" + "\n".join(lines))


class PrefixWarmup(threading.Thread):
    """Evaluate the prompt prefix every request shares, on the private server, in the background.

    The shared system prompt and few-shot turns (~3,300 of 3,600 tokens) take ~40 s on one
    thread; warming them while the policies train lets the first belief request find them in
    the server's prefix cache. The thread never raises.

    Attributes:
        timing: Ollama's account of the warm-up (None until done, or on failure).
        error: Why it failed, if it did.
        cut: The demo stopped its server while the warm-up was still running.
    """

    def __init__(self, host: str, model: str, messages: Sequence[tuple[str, str]], options: dict):
        self.host, self.model = host, model
        self.messages = [{"role": role, "content": text} for role, text in messages]
        self.options = options
        self.timing: RequestTiming | None = None
        self.error: str | None = None
        self.cut = False
        super().__init__(name="amuled-warmup", daemon=True)

    def run(self) -> None:
        """Send the warm-up request; keep its timing, or why it failed (never raises)."""
        import ollama

        began = time.perf_counter()
        try:
            with ollama.Client(host=self.host, timeout=600.0) as client:
                reply = client.chat(model=self.model, messages=self.messages, options=self.options)
        except Exception as error:  # a warm-up failure only costs time
            self.error = f"{type(error).__name__}: {error}"
            return
        from amuled_ma.servers.timing import RequestTiming

        self.timing = RequestTiming.from_reply(reply, time.perf_counter() - began)

    def describe(self) -> str:
        """One line on what the warm-up did."""
        if self.cut:
            return (
                "prefix warm-up: still running when the demo stopped its server, so cut short "
                "(it only saves the first live request time; nothing depends on it)"
            )
        if self.timing is None:
            return f"prefix warm-up: {self.error or 'not finished'}"
        return (
            f"prefix warm-up while the policies trained: {self.timing.prompt_tokens:,} shared "
            f"prompt tokens (system prompt + few-shot turns) evaluated in "
            f"{self.timing.prefill_s:.1f} s (not a belief; its chat call is in the prefix "
            f"cache figures below)"
        )


def start_warmup(
    host: str, model: str, task: str, feedback: FeedbackConfig, resolve: Callable[[str], Path]
) -> PrefixWarmup | None:
    """Start the warm-up for the run the demo is about to make (None: not).

    ``resolve`` resolves a path of ``feedback`` against the scenario file's folder.
    """
    from amuled_ma.beliefs.sources.ollama import OllamaSource
    from amuled_ma.clusters import build_messages
    from amuled_ma.deliberation.plan import cluster_registry, panel_of
    from amuled_ma.errors import AmuledError

    try:  # the run reports any error itself
        registry = cluster_registry(feedback, resolve)
        clusters, _ = panel_of("amuled", feedback, registry)
        messages = build_messages(clusters[0], task, "", registry=registry)
        source = OllamaSource(model, host=host, **dict(feedback.ollama))
        source.close()
    except (AmuledError, ValueError, TypeError, IndexError) as error:
        say(f"no prefix warm-up: {error}")
        return None
    options = {**source.options, "num_predict": 1}
    warmup = PrefixWarmup(host, model, [*messages[:-1], ("user", "")], options)
    warmup.start()
    return warmup


def print_breakdown(
    model: str, phases: list[tuple[str, TimingLog]], reuse: CacheReuse | None
) -> None:
    """Print where the demo's live requests spent their time (Ollama's own metrics), per phase."""
    from amuled_ma.servers.timing import timing_breakdown

    timings = [t for _, log in phases for t in log.timings]
    parts = [
        f"{name} {len(log.timings)} in {log.span_s:.1f} s" for name, log in phases if log.timings
    ]
    say(f"live requests to {model}" + (f" ({', '.join(parts)})" if parts else "") + ":")
    wall = sum(log.span_s for _, log in phases)
    for line in timing_breakdown(timings, wall or None, reuse):
        say(f"  {line}")
