"""``ollama``: cluster beliefs from a local Ollama server, through the official client.

Each :class:`~amuled_ma.beliefs.types.BeliefRequest` carries the full chat (system prompt,
few-shot examples, state prompt; see :func:`amuled_ma.clusters.build_messages`). The
source sends it with ``ollama.Client.chat`` and parses the reply with
:func:`~amuled_ma.beliefs.parsing.parse_belief`.

- **Host**: the ``host`` argument, else ``$OLLAMA_HOST``, else ``http://127.0.0.1:11434``.
- **Determinism**: ``temperature`` 0, a fixed ``seed`` and ``num_ctx`` (Ollama
  ``options``), so the same request gives the same answer and can be cached.
- **Structured output** (``structured=True``, default): ``format`` is the JSON schema of
  :func:`~amuled_ma.beliefs.parsing.belief_schema`: an optional short ``reasoning``
  string, then one probability per action key ``"0"``, ``"1"``, ... The parser still
  accepts free text, should a model ignore the schema.
- **Batching**: identical requests of a batch (same messages and actions) are sent once;
  distinct ones run concurrently on ``concurrency`` threads (across clusters and env
  copies), submitted grouped by system prompt so that requests sharing a prompt prefix
  follow each other (the server can reuse its KV cache).
- **Faults**: each request has a ``timeout_s``; transient failures (timeouts when
  ``retry_timeouts``, HTTP 5xx/429, dropped connections) are retried up to ``retries``
  times with exponential backoff (``backoff_s * 2**attempt``, capped at
  ``backoff_max_s``); an abstained parse is re-asked up to ``parse_retries`` times with
  ``seed + attempt``. A request that still fails is answered by the ``fallback`` source
  if one is given, else with a uniform belief and status ``"timeout"`` or ``"error"``;
  all of it is counted in :attr:`OllamaSource.stats` and logged. A server that stops
  answering altogether raises :class:`~amuled_ma.errors.BackendUnavailable`.
- **Timings**: every answered request keeps Ollama's own account of its chat calls in
  ``extra["timing"]`` (:class:`~amuled_ma.beliefs.timing.RequestTiming`: model load,
  prompt tokens and prefill seconds, tokens generated and decode seconds, server and
  client seconds; summed over the calls when an abstention was re-asked), and adds it
  to the log of every open :func:`~amuled_ma.beliefs.timing.record_timings` block
  (``amuled demo`` prints their breakdown).
- **Checked answers**: a parsed belief must be a valid probability vector over the
  request's actions (:mod:`amuled_ma.beliefs.validate`). A reply that parses to anything
  else (NaN, inf, negative, all zero, the wrong length) counts as an abstention: it is
  re-asked like one, and if it stays invalid the answer has status ``"abstained"``, a
  uniform belief, the reason in ``extra["error"]`` and the values in
  ``extra["invalid_belief"]``; never ``"ok"``.
- **Bad setup**: an unreachable server raises ``BackendUnavailable`` within
  ``check_timeout_s`` (5 s) naming the host and how to start a server; a model the
  server lacks raises :class:`~amuled_ma.errors.ModelNotFound` naming the model and the
  ``ollama pull`` / ``ollama create`` command. Both are checked on first use
  (:meth:`OllamaSource.check`, also called by :meth:`~OllamaSource.identity`) by the
  package's one Ollama preflight, :func:`amuled_ma.beliefs.hosts.preflight`.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass
from typing import Any

import httpx
import ollama

from amuled_ma.beliefs.hosts import (
    DEFAULT_HOST,
    model_missing_error,
    normalize_host,
    preflight,
    unreachable_error,
)
from amuled_ma.beliefs.parsing import belief_schema, parse_belief, uniform
from amuled_ma.beliefs.timing import RequestTiming, publish_timing
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.beliefs.validate import (
    ANSWER_STATUSES,
    check_belief,
    checked_result,
    show_values,
)
from amuled_ma.errors import ScenarioError

log = logging.getLogger(__name__)

#: HTTP statuses worth retrying.
RETRY_STATUSES = frozenset({408, 429, 500, 502, 503, 504})


def resolve_host(host: str | None = None) -> str:
    """Return the server URL: ``host``, else ``$OLLAMA_HOST``, else the default.

    ``HOST`` and ``HOST:PORT`` forms get a scheme and the default port 11434.

    Raises:
        ScenarioError: The address is malformed (:func:`~amuled_ma.beliefs.hosts.normalize_host`).
    """
    if host:
        return normalize_host(host)
    if os.environ.get("OLLAMA_HOST"):
        return normalize_host(os.environ["OLLAMA_HOST"], where="$OLLAMA_HOST")
    return DEFAULT_HOST


@dataclass
class OllamaStats:
    """Counters of an :class:`OllamaSource` (``stats.as_dict()`` for logging).

    Attributes:
        requests: Requests received (duplicates included).
        sent: Distinct requests sent (first attempts).
        deduplicated: Requests answered by an identical request of the same batch.
        attempts: HTTP chat calls made (retries included).
        retries: Retries after a transient failure.
        parse_retries: Re-asks after an abstained parse.
        timeouts: Requests that timed out (every attempt counted).
        errors: Requests that failed with a non-timeout error in the end.
        fallbacks: Requests answered by the fallback source or a uniform belief.
        ok: Answers parsed as is.
        repaired: Answers parsed after repairs.
        abstained: Answers the parser gave up on (uniform).
        prompt_tokens: Prompt tokens reported by the server.
        completion_tokens: Completion tokens reported by the server.

    """

    requests: int = 0
    sent: int = 0
    deduplicated: int = 0
    attempts: int = 0
    retries: int = 0
    parse_retries: int = 0
    timeouts: int = 0
    errors: int = 0
    fallbacks: int = 0
    ok: int = 0
    repaired: int = 0
    abstained: int = 0
    prompt_tokens: int = 0
    completion_tokens: int = 0

    def as_dict(self) -> dict[str, int]:
        """Return the counters as a plain dict."""
        return asdict(self)


class _FailureError(Exception):
    def __init__(self, status: str, message: str) -> None:
        super().__init__(message)
        self.status = status


class OllamaSource(BeliefSource):
    """Beliefs from a local Ollama server.

    Args:
        model: Model name on the server (``"amuled-tiny"`` is the test model).
        host: Server URL (default ``$OLLAMA_HOST``, then ``http://127.0.0.1:11434``).
        structured: Ask for the JSON schema of :func:`belief_schema` via ``format``.
        reasoning: Include the short ``reasoning`` string in the schema.
        reasoning_max_chars: Maximum length of that string.
        temperature: Sampling temperature (0: greedy).
        seed: Sampling seed.
        num_ctx: Context window in tokens (must hold the system prompt, few-shot
            examples, state prompt and reply: about 4k tokens for the paper's prompts).
        num_predict: Maximum reply tokens (the authors used 1024).
        options: Extra Ollama ``options`` (merged over the above).
        concurrency: Requests in flight at once (across clusters and env copies).
        timeout_s: Seconds allowed per request.
        retries: Retries of a transient failure.
        retry_timeouts: Whether a timeout counts as transient (it is retried).
        backoff_s: First retry delay; doubled each retry.
        backoff_max_s: Longest retry delay.
        parse_retries: Re-asks (with ``seed + attempt``) after an abstained parse.
        fallback: Source asked for requests that fail in the end (else uniform).
        keep_alive: Ollama ``keep_alive`` (how long the model stays loaded).
        check_timeout_s: Seconds allowed for the server/model check.
        transport: An ``httpx`` transport (tests use ``httpx.MockTransport``).

    """

    name = "ollama"
    needs_messages = True

    def __init__(
        self,
        model: str = "amuled-tiny",
        *,
        host: str | None = None,
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
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        if concurrency < 1:
            raise ScenarioError(f"ollama concurrency: expected >= 1, found {concurrency}")
        if retries < 0 or parse_retries < 0:
            raise ScenarioError("ollama retries and parse_retries must be >= 0")
        self.model = model
        self.host = resolve_host(host)
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
        self._client = ollama.Client(
            host=self.host,
            timeout=httpx.Timeout(
                self.timeout_s, connect=min(self.check_timeout_s, self.timeout_s)
            ),
            transport=transport,
        )
        self._digest: str | None = None
        self._checked = False
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self.stats = OllamaStats()

    # -- setup -------------------------------------------------------------------------
    def check(self) -> str:
        """Check that the server answers and has the model; return the model's digest.

        Runs :func:`~amuled_ma.beliefs.hosts.preflight` once (later calls return the digest).

        Raises:
            BackendUnavailable: No server answers at the host (within ``check_timeout_s``).
            ModelNotFound: The server lacks the model.

        """
        if self._checked:
            return self._digest or ""
        found = preflight(self.host, self.model, self.check_timeout_s, transport=self._transport)
        self._digest = found.digest or ""
        self._checked = True
        return self._digest

    def identity(self) -> dict[str, Any]:
        """Return the model name and digest, the options and the output format.

        Raises:
            BackendUnavailable: As :meth:`check`.
            ModelNotFound: As :meth:`check`.

        """
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

    # -- one request -------------------------------------------------------------------
    def _count(self, **increments: int) -> None:
        with self._lock:
            for key, value in increments.items():
                setattr(self.stats, key, getattr(self.stats, key) + value)

    def _chat(self, request: BeliefRequest, seed: int) -> Any:
        """One chat call with transient-failure retries; raises :class:`_FailureError`."""
        messages = [{"role": role, "content": content} for role, content in request.messages]
        options = {**self.options, "seed": seed}
        last: _FailureError | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                self._count(retries=1)
                time.sleep(min(self.backoff_max_s, self.backoff_s * 2 ** (attempt - 1)))
            self._count(attempts=1)
            try:
                return self._client.chat(
                    model=self.model,
                    messages=messages,
                    format=self.schema(request.action_names),
                    options=options,
                    keep_alive=self.keep_alive,
                )
            except httpx.TimeoutException as error:
                self._count(timeouts=1)
                last = _FailureError("timeout", f"timed out after {self.timeout_s} s: {error!r}")
                if not self.retry_timeouts:
                    break
            except ollama.ResponseError as error:
                if error.status_code == 404 and "not found" in str(error.error).lower():
                    raise model_missing_error(self.model, self.host) from error
                last = _FailureError("error", f"server error: {error}")
                if error.status_code not in RETRY_STATUSES:
                    break
            except (ConnectionError, httpx.TransportError) as error:
                last = _FailureError("unreachable", f"{type(error).__name__}: {error}")
        assert last is not None
        raise last

    def _answer(self, request: BeliefRequest) -> BeliefResult:
        """Ask, parse, re-ask on abstention; never raises except for a dead server."""
        n = request.num_actions
        if not request.messages:
            self._count(errors=1)
            return BeliefResult(
                uniform(n), "error", self.name, extra={"error": "request has no messages"}
            )
        start = time.perf_counter()
        base_seed = int(self.options["seed"])
        reply = None
        parsed = None
        status, belief, invalid = "abstained", uniform(n), None
        timing = RequestTiming()
        for attempt in range(self.parse_retries + 1):
            if attempt:
                self._count(parse_retries=1)
            asked = time.perf_counter()
            try:
                reply = self._chat(request, base_seed + attempt)
            except _FailureError as failure:
                if failure.status == "unreachable":
                    raise unreachable_error(self.host, failure) from failure
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
            status, belief, invalid = parsed.status, parsed.belief, None
            checked, reason = check_belief(parsed.belief, n)
            if checked is not None:
                belief = checked
            elif status in ANSWER_STATUSES:  # the parser let an invalid belief through
                invalid = f"the reply gave an invalid belief: it {reason}"
                status, belief = "abstained", uniform(n)
            else:
                belief = uniform(n)
            if status != "abstained":
                break
        assert reply is not None and parsed is not None
        self._count(**{status if status in ("ok", "repaired") else "abstained": 1})
        error = "; ".join(e for e in (invalid, parsed.error) if e) or None
        if status == "abstained":
            log.warning("ollama reply abstained for cluster %s: %s", request.cluster, error)
        extra: dict[str, Any] = {
            "attempts": attempt + 1,
            "model": self.model,
            "timing": timing.as_dict(),
        }
        publish_timing(timing, start, time.perf_counter())
        if parsed.repairs:
            extra["repairs"] = list(parsed.repairs)
        if parsed.reasoning:
            extra["reasoning"] = parsed.reasoning
        if error:
            extra["error"] = error
        if invalid:
            extra["invalid_belief"] = show_values(parsed.belief)
        return BeliefResult(
            belief=belief,
            status=status,
            source=self.name,
            raw=reply.message.content if reply.message is not None else None,
            latency_s=time.perf_counter() - start,
            prompt_tokens=reply.prompt_eval_count,
            completion_tokens=reply.eval_count,
            extra=extra,
        )

    def _failed(
        self, request: BeliefRequest, failure: _FailureError, latency: float
    ) -> BeliefResult:
        self._count(fallbacks=1)
        if self.fallback is not None:
            result = checked_result(self.fallback.beliefs([request])[0], request.num_actions)
            result.extra = {**result.extra, "ollama_failure": failure.status, "error": str(failure)}
            return result
        return BeliefResult(
            belief=uniform(request.num_actions),
            status=failure.status,
            source=self.name,
            latency_s=latency,
            extra={"error": str(failure)},
        )

    # -- batches -----------------------------------------------------------------------
    def _executor(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.concurrency, thread_name_prefix="amuled-ollama")
        return self._pool

    def iter_beliefs(self, requests: Sequence[BeliefRequest]) -> Iterator[tuple[int, BeliefResult]]:
        """Yield ``(index, result)`` for every request as answers complete.

        Identical requests are sent once and their answer yielded for each index.

        Raises:
            BackendUnavailable: The server is not reachable (checked first).
            ModelNotFound: The server lacks the model.

        """
        self.check()
        groups: dict[tuple[Any, ...], list[int]] = {}
        for i, request in enumerate(requests):
            groups.setdefault((request.messages, request.action_names), []).append(i)
        self._count(requests=len(requests), deduplicated=len(requests) - len(groups))
        if not groups:
            return
        # Submit grouped by system prompt (then by the rest), so shared prefixes are adjacent.
        order = sorted(groups, key=lambda k: (k[0][0][1] if k[0] else "", k[0][1:], k[1]))
        self._count(sent=len(order))
        pool = self._executor()
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
        out: list[BeliefResult | None] = [None] * len(requests)
        for index, result in self.iter_beliefs(requests):
            out[index] = result
        return out  # type: ignore[return-value]

    def close(self) -> None:
        """Stop the worker threads and close the HTTP client."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._client.close()
        if self.fallback is not None:
            self.fallback.close()
