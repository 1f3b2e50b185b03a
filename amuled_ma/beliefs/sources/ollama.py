"""``ollama``: cluster beliefs from Ollama servers (``docs/beliefs.md``, ``docs/ollama.md``)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any

import httpx
import ollama

from amuled_ma.beliefs.replies.parsing import belief_schema, parse_belief, uniform
from amuled_ma.beliefs.replies.validate import (
    ANSWER_STATUSES,
    check_belief,
    checked_result,
    show_values,
)
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, in_order, indices_by
from amuled_ma.errors import AmuledError, BackendUnavailable, ModelNotFound, ScenarioError
from amuled_ma.servers.hosts import (
    ServerCheck,
    model_missing_error,
    preflight,
    resolve_host,
    unreachable_error,
    up_command,
)
from amuled_ma.servers.pool import HostPool
from amuled_ma.servers.timing import RequestTiming, publish_timing
from amuled_ma.servers.urls import normalize_hosts

log = logging.getLogger(__name__)

#: HTTP statuses worth retrying.
RETRY_STATUSES = frozenset({408, 429, 500, 502, 503, 504})


@dataclass
class OllamaStats:
    """Counters of an `OllamaSource` (their meanings: ``docs/beliefs.md``, `ollama`)."""

    requests: int = 0
    sent: int = 0
    deduplicated: int = 0
    attempts: int = 0
    retries: int = 0
    parse_retries: int = 0
    timeouts: int = 0
    errors: int = 0
    fallbacks: int = 0
    failovers: int = 0
    ok: int = 0
    repaired: int = 0
    abstained: int = 0
    prompt_tokens: int = 0
    completion_tokens: int = 0


class _FailureError(Exception):
    def __init__(self, status: str, message: str, host: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.host = host


#: The pool's failure kind of each :class:`_FailureError` status.
_FAILURE_KINDS = {"timeout": "timeout", "unreachable": "connection", "error": "server_error"}


class OllamaSource(BeliefSource):
    """Beliefs from an Ollama server or a pool of them; the options are in ``docs/beliefs.md``.

    ``transport``: an ``httpx`` transport for every host (tests use ``httpx.MockTransport``).
    """

    name = "ollama"
    needs_messages = True

    def __init__(
        self,
        model: str = "amuled-tiny",
        *,
        host: str | None = None,
        hosts: Sequence[str] | None = None,
        structured: bool = True,
        reasoning: bool = True,
        reasoning_max_chars: int = 400,
        temperature: float = 0.0,
        seed: int = 42,
        num_ctx: int = 8192,
        num_predict: int = 1024,
        options: Mapping[str, Any] | None = None,
        concurrency: int = 2,
        timeout_s: float = 120.0,
        retries: int = 2,
        retry_timeouts: bool = False,
        backoff_s: float = 0.5,
        backoff_max_s: float = 8.0,
        parse_retries: int = 1,
        fallback: BeliefSource | None = None,
        keep_alive: str | float | None = None,
        check_timeout_s: float = 4.5,
        down_for_s: float = 5.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        if concurrency < 1:
            raise ScenarioError(f"ollama concurrency: expected >= 1, found {concurrency}")
        if retries < 0 or parse_retries < 0:
            raise ScenarioError("ollama retries and parse_retries must be >= 0")
        if not (float(down_for_s) >= 0 and float(down_for_s) < float("inf")):
            raise ScenarioError(f"ollama down_for_s: expected a number >= 0, found {down_for_s}")
        if host and hosts is not None:
            raise ScenarioError(
                f"ollama: host {host!r} and hosts {list(hosts)!r} are both given; give one "
                "server with host, or a pool with hosts = [...] (list the host there too)"
            )
        self.model = model
        #: The server URLs: ``hosts`` (a pool), else ``host`` resolved.
        self.hosts = (
            (resolve_host(host),) if hosts is None else normalize_hosts(hosts, where="ollama hosts")
        )
        #: The first server (the only one without a pool).
        self.host = self.hosts[0]
        self.structured = structured
        self.reasoning = reasoning
        self.reasoning_max_chars = reasoning_max_chars
        self.options: dict[str, Any] = {
            "temperature": float(temperature),
            "seed": int(seed),
            "num_ctx": int(num_ctx),
            "num_predict": int(num_predict),
            **dict(options or {}),
        }
        self.concurrency = int(concurrency)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.retry_timeouts = retry_timeouts
        self.backoff_s = float(backoff_s)
        self.backoff_max_s = float(backoff_max_s)
        self.parse_retries = int(parse_retries)
        self.fallback = fallback
        self.keep_alive = keep_alive
        self.check_timeout_s = float(check_timeout_s)
        self._transport = transport
        self._clients = {
            url: ollama.Client(
                host=url,
                timeout=httpx.Timeout(
                    self.timeout_s, connect=min(self.check_timeout_s, self.timeout_s)
                ),
                transport=transport,
            )
            for url in self.hosts
        }
        self.down_for_s = float(down_for_s)
        #: Which host takes each call, and each host's figures (:meth:`server_stats`).
        self.host_pool = HostPool(
            self.hosts,
            down_for_s=self.down_for_s,
            fix=(
                "start the servers again, or remove the dead ones from the pool "
                "([feedback].hosts, or the agent's hosts); 'amuled ollama status' shows a "
                "private server"
            ),
        )
        self._digest: str | None = None  # the model's, once checked
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self.stats = OllamaStats()

    def check(self) -> str:
        """Preflight every host once; return the model's digest.

        `BackendUnavailable`: a host does not answer within ``check_timeout_s``;
        `ModelNotFound`: a host lacks the model, or two hosts hold different digests of it.
        """
        if self._digest is not None:
            return self._digest
        found: dict[str, ServerCheck] = {}
        problems: list[tuple[str, AmuledError]] = []
        for url in self.hosts:
            try:
                found[url] = preflight(
                    url, self.model, self.check_timeout_s, transport=self._transport
                )
            except (BackendUnavailable, ModelNotFound) as error:
                problems.append((url, error))
        if problems and len(self.hosts) == 1:
            raise problems[0][1]
        if problems:
            lines = "; ".join(str(error) for _, error in problems)
            urls = ", ".join(url for url, _ in problems)
            kind = (
                BackendUnavailable
                if any(isinstance(e, BackendUnavailable) for _, e in problems)
                else ModelNotFound
            )
            raise kind(
                f"{len(problems)} of the {len(self.hosts)} Ollama servers of the pool cannot "
                f"serve model {self.model!r}: {lines}; or remove {urls} from the pool "
                "([feedback].hosts, or the agent's hosts)"
            ) from problems[0][1]
        digests = {url: check.digest or "" for url, check in found.items()}
        first = self.hosts[0]
        for url, digest in digests.items():
            if digest != digests[first]:
                raise ModelNotFound(
                    f"model {self.model!r} differs between the Ollama servers of the pool: "
                    f"{first} has digest {digests[first] or '(none)'!r}, {url} has "
                    f"{digest or '(none)'!r}; the servers of one pool must hold the same "
                    f"weights (their answers share store keys): make them equal with "
                    f"'ollama pull {self.model}' (or the same 'ollama create') on each, or "
                    f"remove {url} from the pool"
                )
        self._digest = digests[first]
        return self._digest

    def server_stats(self) -> dict[str, dict[str, Any]]:
        """Each host's figures (sent, answered, failed by kind, latencies): `HostPool.as_dict`."""
        return self.host_pool.as_dict()

    def identity(self) -> dict[str, Any]:
        """The model, its digest, options and output format; never the host (raises as `check`)."""
        digest = self.check()
        return {
            "source": self.name,
            "model": self.model,
            "digest": digest,
            "options": dict(sorted(self.options.items())),
            "format": {
                "structured": self.structured,
                "reasoning": self.reasoning,
                "reasoning_max_chars": self.reasoning_max_chars if self.reasoning else None,
            },
            "parse_retries": self.parse_retries,
        }

    def schema(self, action_names: Sequence[str]) -> dict[str, Any] | None:
        """Return the ``format`` sent for a task (``None`` without structured output)."""
        if not self.structured:
            return None
        return belief_schema(
            action_names, reasoning=self.reasoning, reasoning_max_chars=self.reasoning_max_chars
        )

    def _count(self, **increments: int) -> None:
        with self._lock:
            for key, value in increments.items():
                setattr(self.stats, key, getattr(self.stats, key) + value)

    def _chat(self, request: BeliefRequest, seed: int) -> tuple[Any, str]:
        """One chat call with retries; return ``(reply, host)`` or raise `_FailureError`.

        In a pool of several hosts a connection failure or a timeout is retried at once on
        another host (at most ``len(hosts)`` times); otherwise a transient failure is retried
        ``retries`` times with exponential backoff. `ModelNotFound`: a host lacks the model;
        `BackendUnavailable`: every host of the pool is down.
        """
        messages = [{"role": role, "content": content} for role, content in request.messages]
        options = {**self.options, "seed": seed}
        pool = self.host_pool
        several = len(self.hosts) > 1
        failed_on: list[str] = []
        retries = failovers = 0
        while True:
            with pool.acquire(avoid=failed_on) as lease:
                host = lease.host
                where = f" at {host}" if several else ""
                self._count(attempts=1)
                try:
                    reply = self._clients[host].chat(
                        model=self.model,
                        messages=messages,
                        format=self.schema(request.action_names),
                        options=options,
                        keep_alive=self.keep_alive,
                    )
                except httpx.TimeoutException as error:
                    self._count(timeouts=1)
                    failure = _FailureError(
                        "timeout", f"timed out after {self.timeout_s} s{where}: {error!r}", host
                    )
                    transient = self.retry_timeouts
                except ollama.ResponseError as error:
                    if error.status_code == 404 and "not found" in str(error.error).lower():
                        lease.fail("model_missing", str(error))
                        raise model_missing_error(self.model, host) from error
                    failure = _FailureError("error", f"server error{where}: {error}", host)
                    transient = error.status_code in RETRY_STATUSES
                except (ConnectionError, httpx.TransportError) as error:
                    failure = _FailureError("unreachable", f"{type(error).__name__}: {error}", host)
                    transient = True
                else:
                    return reply, host
                lease.fail(_FAILURE_KINDS[failure.status], str(failure))
            if several and failure.status in ("timeout", "unreachable"):
                if failovers >= len(self.hosts):
                    raise failure
                failovers += 1
                failed_on.append(host)
                pool.retried(host)
                self._count(failovers=1)
                log.warning(
                    "ollama %s at %s for cluster %s: retried on another host (%s)",
                    failure.status, host, request.cluster, pool.describe(),
                )  # fmt: skip
                continue
            if not transient or retries >= self.retries:
                raise failure
            self._count(retries=1)
            time.sleep(min(self.backoff_max_s, self.backoff_s * 2**retries))
            retries += 1

    def _answer(self, request: BeliefRequest) -> BeliefResult:
        """Ask, parse, re-ask on abstention; never raises except for a dead server."""
        n = request.num_actions
        if not request.messages:
            self._count(errors=1)
            return BeliefResult.failed(n, "error", self.name, "request has no messages")
        start = time.perf_counter()
        base_seed = int(self.options["seed"])
        reply = None
        parsed = None
        host = self.host
        timing = RequestTiming()
        for attempt in range(self.parse_retries + 1):
            if attempt:
                self._count(parse_retries=1)
            asked = time.perf_counter()
            try:
                reply, host = self._chat(request, base_seed + attempt)
            except _FailureError as failure:
                if failure.status == "unreachable":
                    raise self._unreachable(failure) from failure
                if failure.status != "timeout":
                    self._count(errors=1)
                log.warning(
                    "ollama %s for cluster %s: %s", failure.status, request.cluster, failure
                )
                return self._failed(request, failure, time.perf_counter() - start)
            timing += RequestTiming.from_reply(reply, time.perf_counter() - asked)
            content = reply.message.content if reply.message is not None else None
            self._count(
                prompt_tokens=int(reply.prompt_eval_count or 0),
                completion_tokens=int(reply.eval_count or 0),
            )
            parsed = parse_belief(content, request.action_names, structured=self.structured)
            status, invalid = parsed.status, None
            belief, reason = check_belief(parsed.belief, n)
            if belief is None:
                if status in ANSWER_STATUSES:  # the parser let an invalid belief through
                    invalid = f"the reply gave an invalid belief: it {reason}"
                    status = "abstained"
                belief = uniform(n)
            if status != "abstained":
                break
        assert reply is not None and parsed is not None and belief is not None
        self._count(**{status: 1})  # ok, repaired or abstained
        error = "; ".join(e for e in (invalid, parsed.error) if e) or None
        if status == "abstained":
            log.warning("ollama reply abstained for cluster %s: %s", request.cluster, error)
        publish_timing(timing, start, time.perf_counter())
        optional = {
            "host": host if len(self.hosts) > 1 else None,  # not part of the store key
            "repairs": list(parsed.repairs),
            "reasoning": parsed.reasoning,
            "error": error,
            "invalid_belief": show_values(parsed.belief) if invalid else None,
        }
        extra = {"attempts": attempt + 1, "model": self.model, "timing": timing.as_dict()}
        extra.update((key, value) for key, value in optional.items() if value)
        return BeliefResult(
            belief=belief,
            status=status,
            source=self.name,
            raw=content,
            latency_s=time.perf_counter() - start,
            prompt_tokens=reply.prompt_eval_count,
            completion_tokens=reply.eval_count,
            extra=extra,
        )

    def _unreachable(self, failure: _FailureError) -> BackendUnavailable:
        """The error of a call no host answered: the host (or every host of the pool)."""
        if len(self.hosts) == 1:
            return unreachable_error(self.host, failure, self.model)
        return BackendUnavailable(
            f"no Ollama server of the pool answers (last at {failure.host}: {failure}); the "
            f"hosts: {self.host_pool.describe()}; start them again or remove the dead ones "
            "from the pool ([feedback].hosts, or the agent's hosts); "
            f"'{up_command(self.model)}' starts a private server"
        )

    def _failed(
        self, request: BeliefRequest, failure: _FailureError, latency: float
    ) -> BeliefResult:
        self._count(fallbacks=1)
        if self.fallback is not None:
            result = checked_result(self.fallback.beliefs([request])[0], request.num_actions)
            result.extra = {**result.extra, "ollama_failure": failure.status, "error": str(failure)}
            return result
        n = request.num_actions
        return BeliefResult.failed(n, failure.status, self.name, str(failure), latency_s=latency)

    def iter_beliefs(self, requests: Sequence[BeliefRequest]) -> Iterator[tuple[int, BeliefResult]]:
        """Yield ``(index, result)`` as answers complete; identical requests sent once; `check`s."""
        self.check()
        groups = indices_by(requests, lambda r: (r.messages, r.action_names))
        self._count(requests=len(requests), deduplicated=len(requests) - len(groups))
        if not groups:
            return
        # Submit grouped by system prompt (then by the rest), so shared prefixes are adjacent.
        order = sorted(groups, key=lambda k: (k[0][0][1] if k[0] else "", k[0][1:], k[1]))
        self._count(sent=len(order))
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.concurrency, thread_name_prefix="amuled-ollama")
        pool = self._pool
        pending: dict[Future[BeliefResult], tuple[Any, ...]] = {}
        queue = list(reversed(order))
        try:
            while queue or pending:
                while queue and len(pending) < 2 * self.concurrency:
                    key = queue.pop()
                    pending[pool.submit(self._answer, requests[groups[key][0]])] = key
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    key = pending.pop(future)
                    result = future.result()
                    for j, index in enumerate(groups[key]):
                        yield index, result if j == 0 else result.copy()
        finally:
            for future in pending:
                future.cancel()

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """Answer every request (concurrently, deduplicated), in order."""
        return in_order(self.iter_beliefs(requests), len(requests), self.name)

    def close(self) -> None:
        """Stop the worker threads and close the HTTP clients."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        for client in self._clients.values():
            client.close()
        if self.fallback is not None:
            self.fallback.close()
