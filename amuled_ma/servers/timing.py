"""Where an Ollama request's time goes: the server's metrics per request (`RequestTiming`), summed.

Prefix-cache reuse is read from an ``OLLAMA_DEBUG=1`` server's log: the response lacks it.
"""

from __future__ import annotations

import contextlib
import re
import statistics
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class RequestTiming:
    """Where one request's time went, by Ollama's own account (its response metrics).

    ``prompt_eval_count`` counts the whole prompt, cached part included; ``prompt_eval_duration``
    only the part evaluated; sampling under the JSON grammar is only in ``total_duration``.
    """

    calls: int = 0  # chat calls answered (more than 1 when an abstention was re-asked)
    load_s: float = 0.0  # ``load_duration``
    prompt_tokens: int = 0  # ``prompt_eval_count``
    prefill_s: float = 0.0  # ``prompt_eval_duration``
    decode_tokens: int = 0  # ``eval_count``
    decode_s: float = 0.0  # ``eval_duration``
    total_s: float = 0.0  # the server's seconds (``total_duration``)
    wall_s: float = 0.0  # the client's seconds (HTTP and queueing included)

    @classmethod
    def from_reply(cls, reply: object, wall_s: float) -> RequestTiming:
        """Read the metrics of one ``ollama.ChatResponse`` waited ``wall_s`` for (absent: 0)."""

        def seconds(name: str) -> float:
            return float(getattr(reply, name, None) or 0) / 1e9

        return cls(
            calls=1,
            load_s=seconds("load_duration"),
            prompt_tokens=int(getattr(reply, "prompt_eval_count", None) or 0),
            prefill_s=seconds("prompt_eval_duration"),
            decode_tokens=int(getattr(reply, "eval_count", None) or 0),
            decode_s=seconds("eval_duration"),
            total_s=seconds("total_duration"),
            wall_s=float(wall_s),
        )

    def __add__(self, other: RequestTiming) -> RequestTiming:
        """Sum two accounts field by field (the calls of one request)."""
        return RequestTiming(
            **{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)}
        )

    def as_dict(self) -> dict[str, float | int]:
        """Return the fields as a plain dict (seconds rounded to microseconds)."""
        return {k: round(v, 6) if isinstance(v, float) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RequestTiming:
        """Inverse of `as_dict` (unknown keys are ignored, missing ones count 0)."""
        kinds = {k: type(v) for k, v in asdict(cls()).items()}
        return cls(**{k: kinds[k](v) for k, v in data.items() if k in kinds})


@dataclass
class TimingLog:
    """The timings collected by `record_timings` (in order of completion), and when they ran."""

    timings: list[RequestTiming] = field(default_factory=list)
    first_start: float | None = None  # perf_counter() of the first asked (None: none)
    last_end: float | None = None  # perf_counter() of the last answered

    @property
    def span_s(self) -> float:
        """Seconds from the first request asked to the last answered (0 without any)."""
        if self.first_start is None or self.last_end is None:
            return 0.0
        return self.last_end - self.first_start

    def add(self, timing: RequestTiming, start: float, end: float) -> None:
        """Record one request asked at ``start`` and answered at ``end`` (perf_counter)."""
        self.timings.append(timing)
        self.first_start = start if self.first_start is None else min(self.first_start, start)
        self.last_end = end if self.last_end is None else max(self.last_end, end)


_logs: list[TimingLog] = []
_logs_lock = threading.Lock()


@contextlib.contextmanager
def record_timings() -> Iterator[TimingLog]:
    """Collect in the yielded `TimingLog` each request an `OllamaSource` of this process answers.

    One entry a request (a re-asked abstention's calls summed); failed ones have no metrics.
    """
    log = TimingLog()
    with _logs_lock:
        _logs.append(log)
    try:
        yield log
    finally:
        with _logs_lock:
            _logs.remove(log)


def publish_timing(timing: RequestTiming, start: float, end: float) -> None:
    """Add one request's timing (asked, answered at ``start``, ``end``) to every open log."""
    with _logs_lock:
        for log in _logs:
            log.add(timing, start, end)


#: Ollama's debug log line of a prompt's prefix-cache lookup (one per chat call).
_CACHE_SLOT = re.compile(r'msg="loading cache slot".*?\bprompt=(\d+)\b.*?\bused=(\d+)\b')


@dataclass(frozen=True)
class CacheReuse:
    """Prefix-cache reuse of a server's chat calls, from its debug log."""

    calls: int = 0  # ``loading cache slot`` lines read (one per chat call)
    prompt_tokens: int = 0
    reused_tokens: int = 0  # found in the prefix cache (not evaluated)

    @property
    def evaluated_tokens(self) -> int:
        """Prompt tokens the server evaluated (sent minus reused)."""
        return self.prompt_tokens - self.reused_tokens


def cache_reuse(log: str | Path, offset: int = 0) -> CacheReuse | None:
    """Sum the prefix-cache lookups of an ``OLLAMA_DEBUG=1`` log past ``offset`` (None: none)."""
    try:
        with open(log, "rb") as handle:
            handle.seek(offset)
            text = handle.read().decode("utf-8", errors="replace")
    except OSError:
        return None
    found = [(int(m[1]), int(m[2])) for m in _CACHE_SLOT.finditer(text)]
    if not found:
        return None
    return CacheReuse(
        calls=len(found),
        prompt_tokens=sum(p for p, _ in found),
        reused_tokens=sum(u for _, u in found),
    )


def _stats(values: Sequence[float], unit: str, digits: int) -> str:
    mean, median = statistics.fmean(values), statistics.median(values)
    return f"mean {mean:.{digits}f}{unit}, median {median:.{digits}f}{unit}"


def timing_breakdown(
    timings: Sequence[RequestTiming],
    wall_s: float | None = None,
    reuse: CacheReuse | None = None,
) -> list[str]:
    """Summarise where the requests' time went, one line per figure.

    ``wall_s``: wall-clock seconds from the first asked to the last answered (None: not
    shown); ``reuse``: the server's prefix-cache reuse over the same calls (None: not known).
    """
    if not timings:
        return ["no live requests (every belief came from the belief store)"]
    total = sum(timings, RequestTiming())
    lines = [f"requests {len(timings)} ({total.calls} chat calls, re-asks included)"]
    lines.append(
        "prompt tokens per request: "
        + _stats([t.prompt_tokens for t in timings], "", 0)
        + "; prefill (prompt eval) "
        + _stats([t.prefill_s for t in timings], " s", 2)
    )
    rates = [t.decode_tokens / t.decode_s for t in timings if t.decode_s > 0]
    lines.append(
        "tokens generated per request: "
        + _stats([t.decode_tokens for t in timings], "", 0)
        + "; decode (JSON schema) "
        + _stats([t.decode_s for t in timings], " s", 2)
        + (f"; {statistics.fmean(rates):.1f} tokens/s" if rates else "")
    )
    if reuse is not None and reuse.prompt_tokens:
        lines.append(
            f"prefix cache: {reuse.prompt_tokens:,} prompt tokens sent in {reuse.calls} calls, "
            f"{reuse.reused_tokens:,} reused ({reuse.reused_tokens / reuse.prompt_tokens:.0%}), "
            f"{reuse.evaluated_tokens:,} evaluated"
        )
    else:
        lines.append("prefix cache: not known (the server's debug log is not ours to read)")
    load, server, client = total.load_s, total.total_s, total.wall_s
    prefill, decode = total.prefill_s, total.decode_s
    lines.append(
        f"request seconds summed: {client:.1f} s at the client, {server:.1f} s at the server "
        f"= prefill {prefill:.1f} + decode {decode:.1f} + model load {load:.1f} "
        f"+ other {server - prefill - decode - load:.1f} (sampling under the grammar, "
        f"waiting for a slot); mean {client / len(timings):.2f} s per request"
    )
    if wall_s is not None and wall_s > 0:
        lines.append(
            f"wall time while requests ran {wall_s:.1f} s; summed request seconds / wall "
            f"= {client / wall_s:.2f} requests in flight on average"
        )
    return lines
