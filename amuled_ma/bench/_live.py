"""Live belief throughput against a real Ollama server (``amuled bench beliefs --live``).

Per concurrency level the same distinct requests (the paper's Driving prompts) are answered
twice through a `CachedSource`: first on an empty store, then by a new source on the same
file (every cacheable answer a hit). Requests/s = requests / wall seconds; the server's
``OLLAMA_NUM_PARALLEL`` bounds the work done at once.
"""

from __future__ import annotations

import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from amuled_ma.beliefs.sources.ollama import OllamaSource
from amuled_ma.beliefs.store.cached import CachedSource
from amuled_ma.beliefs.store.database import BeliefStore
from amuled_ma.beliefs.types import BeliefRequest

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
    """Measure live belief throughput at each concurrency, first run and cached second run.

    ``num_ctx`` must hold the paper's ~3k-token prompt; ``workdir`` holds the stores (default:
    a temporary folder); ``echo`` gets each output line.

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
