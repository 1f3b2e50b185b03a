"""HostPool: least-busy choice, down and back with a fake clock, all down, the figures.

Every expected number is worked out by hand in the comments.
"""

from __future__ import annotations

import threading
import time

import pytest

from amuled_ma.errors import BackendUnavailable
from amuled_ma.servers.pool import HostPool, host_lines, merge_host_stats, percentile

A, B, C = "http://a:1", "http://b:2", "http://c:3"


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_least_busy_then_fewest_sent_then_list_order() -> None:
    pool = HostPool([A, B, C], down_for_s=10, clock=Clock())
    # all idle, none sent: list order
    first, second, third = pool.take(), pool.take(), pool.take()
    assert [first.host, second.host, third.host] == [A, B, C]
    pool.release(A, True, 1.0)
    # in flight a 0, b 1, c 1: a
    assert pool.take().host == A
    # in flight 1, 1, 1; sent a 2, b 1, c 1: fewest sent, then list order: b
    assert pool.take().host == B
    # in flight 1, 2, 1; sent 2, 2, 1: c (one in flight, one sent)
    assert pool.take().host == C
    assert [pool.in_flight(h) for h in (A, B, C)] == [1, 2, 2]
    assert [pool.stats(h).sent for h in (A, B, C)] == [2, 2, 2]


def test_a_failed_host_is_out_for_down_for_s_then_probed_and_back() -> None:
    clock = Clock()
    pool = HostPool([A, B], down_for_s=10, wait_s=0, clock=clock)
    lease = pool.take()
    assert lease.host == A
    clock.now = 1.0
    pool.release(A, False, 1.0, "connection", detail="ConnectError: refused")
    assert pool.live() == [B]  # a out until t = 1 + 10 = 11
    clock.now = 5.0
    assert pool.take().host == B and pool.take().host == B  # only b, however busy
    clock.now = 11.0
    probe = pool.take()
    assert probe.host == A and probe.probe  # due: the next request probes it
    assert pool.take().host == B  # one probe at a time: the others go to b
    clock.now = 12.0
    pool.release(A, True, 1.0)  # answered: a is back
    assert pool.live() == [A, B]
    stats = pool.stats(A)
    assert (stats.went_down, stats.came_back, stats.failures) == (1, 1, {"connection": 1})
    # a failed probe takes it out again, for another down_for_s
    assert pool.take().host == A  # in flight a 0, b 3
    clock.now = 13.0
    pool.release(A, False, 0.1, "timeout")
    assert pool.live() == [B]
    clock.now = 22.9
    assert pool.take().host == B  # a due at 13 + 10 = 23
    clock.now = 23.0
    assert pool.take().host == A
    assert pool.stats(A).went_down == 2 and pool.stats(A).failures == {
        "connection": 1,
        "timeout": 1,
    }


def test_a_request_avoids_the_host_it_failed_on_only_when_there_is_another() -> None:
    pool = HostPool([A, B], down_for_s=10, clock=Clock())
    assert pool.take(avoid=[A]).host == B
    assert pool.take(avoid=[A, B]).host == A  # nothing else: a host it failed on
    pool.release(A, False, 0.0, "server_error")  # an HTTP error: a stays in the pool
    assert pool.live() == [A, B] and pool.stats(A).failures == {"server_error": 1}


def test_every_host_down_is_one_error_naming_each_and_the_fix() -> None:
    clock = Clock()
    pool = HostPool([A, B], down_for_s=30, wait_s=0, fix="start them", clock=clock)
    for host in (A, B):
        assert pool.take().host == host
    pool.release(A, False, 0.0, "connection", detail="ConnectError: refused")
    pool.release(B, False, 0.0, "timeout")
    clock.now = 10.0
    with pytest.raises(BackendUnavailable) as info:
        pool.take()
    message = str(info.value)
    assert "http://a:1 (connection: ConnectError: refused; probed again in 20.0 s)" in message
    assert "http://b:2 (timeout; probed again in 20.0 s)" in message
    assert message.endswith("; start them")


def test_all_down_waits_for_the_first_probe_then_raises_after_wait_s() -> None:
    pool = HostPool([A, B], down_for_s=0.2, wait_s=1.0)
    for host in (A, B):
        pool.take()
        pool.release(host, False, 0.0, "connection")
    start = time.monotonic()
    probe = pool.take()  # nothing live: waits until a is due (0.2 s)
    waited = time.monotonic() - start
    assert probe.host == A and probe.probe and 0.1 < waited < 0.9
    # b is due too; with a and b being probed, a third request waits for one of them
    assert pool.take().host == B
    released = threading.Timer(0.2, pool.release, args=(B, True, 0.2))
    released.start()
    assert pool.take().host == B  # b answered its probe: back, and free
    released.join()
    # a probe that keeps failing: the waiting request gives up after wait_s
    pool.release(A, False, 0.0, "connection")
    pool.release(B, False, 0.0, "connection")
    pool.take(), pool.take()  # both probes taken (after 0.2 s)
    start = time.monotonic()
    with pytest.raises(BackendUnavailable, match="being probed"):
        pool.take()
    assert 0.9 < time.monotonic() - start < 3.0


def test_a_pool_of_one_never_takes_its_host_out() -> None:
    pool = HostPool([A], down_for_s=60, wait_s=0, clock=Clock())
    pool.take()
    pool.release(A, False, 0.0, "connection")
    assert pool.live() == [A] and pool.take().host == A
    assert pool.stats(A).failures == {"connection": 1} and pool.stats(A).went_down == 0


def test_acquire_releases_however_the_block_ends() -> None:
    clock = Clock()
    pool = HostPool([A, B], down_for_s=5, clock=clock)
    with pool.acquire() as lease:
        clock.now = 2.5
    assert lease.host == A and pool.stats(A).latencies == [2.5]
    with pool.acquire() as lease:  # a has sent 1: b
        lease.fail("timeout", "read timed out")
    assert lease.host == B and pool.live() == [A]
    with pytest.raises(RuntimeError), pool.acquire():
        raise RuntimeError("boom")
    assert pool.stats(A).failures == {"error": 1}
    assert [pool.in_flight(h) for h in (A, B)] == [0, 0]
    pool.retried(B)
    figures = pool.as_dict()
    assert list(figures) == [A, B]
    assert figures[A] == {
        "sent": 2, "answered": 1, "failed": 1, "failures": {"error": 1}, "retried_from": 0,
        "went_down": 0, "came_back": 0, "mean_latency_s": 2.5, "p95_latency_s": 2.5,
        "live": True,
    }  # fmt: skip
    assert figures[B]["failures"] == {"timeout": 1} and figures[B]["retried_from"] == 1
    assert figures[B]["live"] is False and figures[B]["mean_latency_s"] is None


def test_bad_pools_are_refused() -> None:
    with pytest.raises(ValueError, match="at least one host"):
        HostPool([])
    with pytest.raises(ValueError, match="http://a:1 more than once"):
        HostPool([A, B, A])
    with pytest.raises(ValueError, match="down_for_s"):
        HostPool([A], down_for_s=-1)


def test_latency_figures_by_hand() -> None:
    # nearest rank: 95% of 20 values = rank 19 of 1..20
    assert percentile([float(i) for i in range(20, 0, -1)], 95) == 19.0
    assert percentile([0.2, 0.4, 0.1], 95) == 0.4  # rank ceil(2.85) = 3
    assert percentile([0.2, 0.4, 0.1], 50) == 0.2  # rank ceil(1.5) = 2
    assert percentile([], 95) is None
    clock = Clock()
    pool = HostPool([A], clock=clock)
    for seconds in (1.0, 2.0, 6.0):
        lease = pool.take()
        clock.now += seconds
        pool.release(A, True, clock.now - lease.started)
    row = pool.as_dict()[A]
    assert row["mean_latency_s"] == 3.0 and row["p95_latency_s"] == 6.0  # (1+2+6)/3


def test_merge_adds_counts_and_weights_the_mean_by_answers() -> None:
    one = {A: {"sent": 3, "answered": 2, "failed": 1, "failures": {"connection": 1},
               "retried_from": 1, "went_down": 1, "came_back": 0, "mean_latency_s": 1.0,
               "p95_latency_s": 1.5, "live": False}}  # fmt: skip
    two = {A: {"sent": 3, "answered": 3, "failed": 0, "failures": {}, "retried_from": 0,
               "went_down": 0, "came_back": 0, "mean_latency_s": 2.0, "p95_latency_s": 2.5,
               "live": True},
           B: {"sent": 1, "answered": 0, "failed": 1, "failures": {"timeout": 1},
               "retried_from": 1, "went_down": 1, "came_back": 1, "mean_latency_s": None,
               "p95_latency_s": None, "live": True}}  # fmt: skip
    merged = merge_host_stats([one, two])
    assert list(merged) == [A, B]
    a = merged[A]
    assert (a["sent"], a["answered"], a["failed"], a["retried_from"]) == (6, 5, 1, 1)
    assert a["mean_latency_s"] == pytest.approx((2 * 1.0 + 3 * 2.0) / 5)  # 1.6
    assert a["p95_latency_s"] == 2.5 and a["live"] is False
    assert a["failures"] == {"connection": 1}
    assert merged[B]["mean_latency_s"] is None and merged[B]["failures"] == {"timeout": 1}
    lines = host_lines(merged)
    assert lines[0] == (
        "http://a:1: sent 6, answered 5, failed 1 (connection 1), retried from 1, latency "
        "mean 1.60 s, p95 2.50 s, down 1x, back 0x"
    )
    assert lines[1].startswith("http://b:2: sent 1, answered 0, failed 1 (timeout 1)")
    assert "latency mean - , p95 -" not in lines[1] and "mean -, p95 -" in lines[1]
