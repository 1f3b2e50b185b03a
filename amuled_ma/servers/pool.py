"""`HostPool`: the live server with the fewest requests in flight takes the next; per-host figures.

The rules: ``docs/ollama.md``, "A pool of servers".
"""

from __future__ import annotations

import contextlib
import copy
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from amuled_ma.errors import BackendUnavailable

#: Failure kinds that take a host out of the pool until it is probed again.
DOWN_FAILURES = frozenset({"connection", "timeout"})

#: Counters of a host in :meth:`HostPool.as_dict`, summed by :func:`merge_host_stats`.
COUNTS = ("sent", "answered", "failed", "retried_from", "went_down", "came_back")


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile, ``q`` in (0, 100], of ``values`` by nearest rank (None if empty)."""
    if not values:
        return None
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100 * len(ordered)))  # ceil(q / 100 * n)
    return float(ordered[rank - 1])


@dataclass
class HostStats:
    """What happened at one host of a pool."""

    host: str
    sent: int = 0  # every attempt, a retry or a probe included
    answered: int = 0
    failures: dict[str, int] = field(default_factory=dict)  # by kind (``connection``, ...)
    retried_from: int = 0  # failed here and retried on another host
    went_down: int = 0  # times taken out of the pool
    came_back: int = 0  # times put back
    latencies: list[float] = field(default_factory=list)  # seconds, chosen to answer

    @property
    def failed(self) -> int:
        """Failed requests of every kind."""
        return sum(self.failures.values())

    def as_dict(self) -> dict[str, Any]:
        """The figures as plain JSON data (latencies as mean and 95th percentile)."""
        n = len(self.latencies)
        return {
            "sent": self.sent,
            "answered": self.answered,
            "failed": self.failed,
            "failures": dict(sorted(self.failures.items())),
            "retried_from": self.retried_from,
            "went_down": self.went_down,
            "came_back": self.came_back,
            "mean_latency_s": sum(self.latencies) / n if n else None,
            "p95_latency_s": percentile(self.latencies, 95),
        }


@dataclass(eq=False)
class Lease:
    """One request's use of a host, from :meth:`HostPool.acquire`."""

    host: str
    started: float  # the pool's clock when ``host`` was chosen
    probe: bool  # the host was down
    failure: str | None = None  # as given to :meth:`fail` (None: the request went well)
    detail: str = ""

    def fail(self, kind: str, detail: str = "") -> None:
        """Mark the request failed: ``kind`` of :data:`DOWN_FAILURES` takes the host out."""
        self.failure = kind
        self.detail = detail


class HostPool:
    """Choose a live, least-busy host for each request and keep each host's figures.

    ``hosts`` in order of preference on ties; ``down_for_s``: seconds a failed host stays out
    before a request probes it; ``wait_s``: seconds :meth:`acquire` waits for a live host
    (None: ``2 * down_for_s``, each host probed once); ``fix`` ends the all-down error.
    `ValueError`: no host, a repeated host, or a negative or non-finite time.
    """

    def __init__(
        self,
        hosts: Sequence[str],
        *,
        down_for_s: float = 5.0,
        wait_s: float | None = None,
        fix: str = "",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        hosts = tuple(hosts)
        if not hosts:
            raise ValueError("a host pool needs at least one host")
        repeated = sorted({h for h in hosts if hosts.count(h) > 1})
        if repeated:
            raise ValueError(f"a host pool lists {', '.join(repeated)} more than once")
        wait = 2 * float(down_for_s) if wait_s is None else float(wait_s)
        for name, value in (("down_for_s", float(down_for_s)), ("wait_s", wait)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"host pool {name}: expected a finite number >= 0, found {value}")
        self.hosts = hosts
        self.down_for_s = float(down_for_s)
        self.wait_s = wait
        self.fix = fix
        self._clock = clock
        self._cond = threading.Condition()
        self._in_flight = dict.fromkeys(hosts, 0)
        self._down_until: dict[str, float] = {}
        self._down_why: dict[str, str] = {}
        self._probing: set[str] = set()
        self._stats = {h: HostStats(h) for h in hosts}

    def live(self) -> list[str]:
        """The hosts in the pool now (not taken out), in list order."""
        with self._cond:
            return [h for h in self.hosts if h not in self._down_until]

    def in_flight(self, host: str) -> int:
        """Requests in flight at ``host`` now."""
        with self._cond:
            return self._in_flight[host]

    def stats(self, host: str) -> HostStats:
        """A copy of ``host``'s figures."""
        with self._cond:
            return copy.deepcopy(self._stats[host])

    def _choose(self, avoid: Iterable[str], now: float) -> tuple[str, bool] | None:
        """``(host, is a probe)`` by the rules of the module, or None; holds the lock."""
        avoided = set(avoid)
        for skip in (avoided, set()):  # a host failed before only when there is no other
            due = [
                h
                for h in self.hosts
                if h in self._down_until
                and self._down_until[h] <= now
                and h not in self._probing
                and h not in skip
            ]
            if due:
                return min(due, key=lambda h: (self._down_until[h], self.hosts.index(h))), True
            live = [h for h in self.hosts if h not in self._down_until and h not in skip]
            if live:
                return min(live, key=lambda h: (self._in_flight[h], self._stats[h].sent,
                                                 self.hosts.index(h))), False  # fmt: skip
        return None

    def take(self, avoid: Iterable[str] = ()) -> Lease:
        """Choose a host for one request, counted as sent and in flight (prefer :meth:`acquire`).

        ``avoid``: hosts this request failed on, used only when no other is live or due a probe.
        `BackendUnavailable`: none is within ``wait_s`` (each host named, why down, ``fix``).
        """
        avoid = tuple(avoid)
        with self._cond:
            now = self._clock()
            deadline = now + self.wait_s
            while True:
                chosen = self._choose(avoid, now)
                if chosen is not None:
                    host, probe = chosen
                    if probe:
                        self._probing.add(host)
                    self._in_flight[host] += 1
                    self._stats[host].sent += 1
                    return Lease(host, now, probe)
                left = deadline - now
                if left <= 0:
                    raise self._all_down_error()
                waiting = [u - now for h, u in self._down_until.items() if h not in self._probing]
                step = min([left, *(w for w in waiting if w > 0)])
                self._cond.wait(timeout=max(step, 0.001))
                now = self._clock()

    @contextlib.contextmanager
    def acquire(self, avoid: Iterable[str] = ()) -> Iterator[Lease]:
        """Use a host for one request: ``with pool.acquire() as lease: ... lease.host``.

        Released as answered at the block's end, as failed after ``lease.fail(kind)`` or a raise
        (kind ``"error"``); ``avoid`` and errors as :meth:`take`.
        """
        lease = self.take(avoid)
        raised = True
        try:
            yield lease
            raised = False
        finally:
            ok = not raised and lease.failure is None
            latency = self._clock() - lease.started
            self.release(lease.host, ok, latency, lease.failure, detail=lease.detail)

    def release(
        self,
        host: str,
        ok: bool,
        latency_s: float,
        failure: str | None = None,
        *,
        detail: str = "",
    ) -> None:
        """Record how a request at ``host`` ended (``latency_s`` kept when ``ok``).

        ``failure`` (default ``"error"``) of :data:`DOWN_FAILURES` takes the host out for
        ``down_for_s`` (not in a pool of one); any other outcome puts it back.
        """
        with self._cond:
            self._in_flight[host] -= 1
            self._probing.discard(host)
            stats = self._stats[host]
            kind = None if ok else (failure or "error")
            if kind is None:
                stats.answered += 1
                stats.latencies.append(float(latency_s))
            else:
                stats.failures[kind] = stats.failures.get(kind, 0) + 1
            if kind in DOWN_FAILURES and len(self.hosts) > 1:
                if host not in self._down_until:
                    stats.went_down += 1
                self._down_until[host] = self._clock() + self.down_for_s
                self._down_why[host] = f"{kind}{': ' + detail if detail else ''}"
            elif host in self._down_until:
                del self._down_until[host]
                self._down_why.pop(host, None)
                stats.came_back += 1
            self._cond.notify_all()

    def retried(self, host: str) -> None:
        """Count a request that failed at ``host`` and is retried on another host."""
        with self._cond:
            self._stats[host].retried_from += 1

    def _all_down_error(self) -> BackendUnavailable:
        now = self._clock()
        parts = []
        for host in self.hosts:
            if host in self._probing:
                parts.append(f"{host} (being probed)")
            elif host in self._down_until:
                back = max(0.0, self._down_until[host] - now)
                parts.append(f"{host} ({self._down_why.get(host, 'down')}; probed again in "
                             f"{back:.1f} s)")  # fmt: skip
            else:
                parts.append(f"{host} (live)")
        fix = f"; {self.fix}" if self.fix else ""
        return BackendUnavailable(
            f"no LLM server of the pool answers: every one of the {len(self.hosts)} hosts is "
            f"down after waiting {self.wait_s:g} s for one to come back: "
            f"{', '.join(parts)}{fix}"
        )

    def describe(self) -> str:
        """Each host and its state, e.g. ``http://a:1 (live), http://b:2 (down: ...)``."""
        with self._cond:
            states = {h: f"down: {self._down_why.get(h, '')}" for h in self._down_until}
            return ", ".join(f"{h} ({states.get(h, 'live')})" for h in self.hosts)

    def as_dict(self) -> dict[str, dict[str, Any]]:
        """Every host's figures in list order: :meth:`HostStats.as_dict` plus ``"live"``."""
        with self._cond:
            return {
                h: {**self._stats[h].as_dict(), "live": h not in self._down_until}
                for h in self.hosts
            }


def merge_host_stats(reports: Iterable[Mapping[str, Mapping[str, Any]]]) -> dict[str, Any]:
    """Add up several :meth:`HostPool.as_dict` reports, host by host, in order of appearance.

    Counts summed; mean latency weighted by ``answered``; p95 the largest (an upper bound);
    ``live`` when live in every report.
    """
    out: dict[str, dict[str, Any]] = {}
    weights: dict[str, float] = {}
    for report in reports:
        for host, row in report.items():
            merged = out.setdefault(
                host,
                {**dict.fromkeys(COUNTS, 0), "failures": {}, "mean_latency_s": None,
                 "p95_latency_s": None, "live": True},
            )  # fmt: skip
            for key in COUNTS:
                merged[key] += int(row.get(key, 0) or 0)
            for kind, n in (row.get("failures") or {}).items():
                merged["failures"][kind] = merged["failures"].get(kind, 0) + int(n)
            answered = float(row.get("answered", 0) or 0)
            mean = row.get("mean_latency_s")
            if mean is not None and answered:
                total = weights.get(host, 0.0) + answered
                previous = merged["mean_latency_s"] or 0.0
                merged["mean_latency_s"] = previous + (float(mean) - previous) * answered / total
                weights[host] = total
            p95 = row.get("p95_latency_s")
            if p95 is not None:
                merged["p95_latency_s"] = max(float(p95), merged["p95_latency_s"] or 0.0)
            merged["live"] = bool(merged["live"] and row.get("live", True))
    for row in out.values():
        row["failures"] = dict(sorted(row["failures"].items()))
    return out


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{float(value):.2f} s"


def host_lines(stats: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """A pool's figures (:meth:`HostPool.as_dict`, :func:`merge_host_stats`), a line a host."""
    lines = []
    for host, row in stats.items():
        kinds = ", ".join(f"{k} {n:,}" for k, n in (row.get("failures") or {}).items())
        failed = f"failed {int(row.get('failed', 0)):,}" + (f" ({kinds})" if kinds else "")
        lines.append(
            f"{host}: sent {int(row.get('sent', 0)):,}, answered {int(row.get('answered', 0)):,}, "
            f"{failed}, retried from {int(row.get('retried_from', 0)):,}, latency mean "
            f"{_seconds(row.get('mean_latency_s'))}, p95 {_seconds(row.get('p95_latency_s'))}, "
            f"down {int(row.get('went_down', 0))}x, back {int(row.get('came_back', 0))}x"
        )
    return lines
