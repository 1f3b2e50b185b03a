"""A pool of two real Ollama servers serves one fine-tune; one is killed with ``kill -9``.

The test runs ``host_pool_netns.py`` inside a network namespace it makes itself
(``unshare -n``, then ``ip link set lo up``: loopback only), so no traffic can leave the
machine. There, two private servers with the tiny model on two loopback ports serve
``amuled finetune findmilk --feedback amuled`` with ``[feedback] hosts = [A, B]``; the first
server to answer is killed (``SIGKILL``) while it has a request in flight. Checked: every
belief answered exactly once (no request lost as ``error``/``timeout``, every store row
written once, one row per distinct request), both servers got requests, the killed
server's failures recorded and its requests retried on the other, the per-host counts
adding up to the requests sent, and the figures in the run's output, ``feedback.json``,
``results.json`` and ``report.md``.

Needs root (or ``CAP_SYS_ADMIN``) for ``unshare -n``, ``ip``, and the Ollama build with the
tiny model (``.ci/setup-ollama``); without them it skips with the reason, except under
``CI=true``, where it fails: CI runs it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from netns import require_netns, run_sealed, unavailable

from amuled_ma.errors import AmuledError
from amuled_ma.servers import local_server as llm_server

SCRIPT = Path(__file__).resolve().parent / "host_pool_netns.py"
#: Seconds allowed for the whole run in the namespace (the script stops itself at 480).
TIMEOUT_S = 540
ANSWERS = {"ok", "repaired", "abstained"}


def _check_prerequisites() -> None:
    try:
        llm_server.find_binary()
        llm_server.find_tiny_gguf()
    except AmuledError as error:
        unavailable(f"no Ollama build with the tiny model: {error}")
    require_netns()


def _run_sealed(workdir: Path) -> tuple[dict, str]:
    """Run the script in a new network namespace; return its RESULT and its output."""
    env = {k: v for k, v in os.environ.items() if k != "OLLAMA_HOST"}
    return run_sealed(SCRIPT, [str(workdir)], timeout=TIMEOUT_S, env=env)


@pytest.mark.slow
def test_two_servers_one_killed_mid_finetune_every_belief_answered_once(tmp_path: Path) -> None:
    _check_prerequisites()
    result, output = _run_sealed(tmp_path)
    context = json.dumps({k: v for k, v in result.items() if k != "written"}, indent=1)[-8000:]

    # sealed: the namespace has the loopback interface only
    assert result["interfaces"] == ["lo"], result["interfaces"]
    assert result["base_exit"] == 0, context
    assert result["finetune_exit"] == 0, result["finetune_output"] + output[-4000:]
    first, second = result["hosts"]
    kill = result["kill"]
    assert kill, f"no server was killed: {context}"
    victim = kill["host"]
    survivor = second if victim == first else first
    assert kill["in_flight"] >= 1 and kill["before"][victim]["answered"] >= 1

    figures, stats = result["figures"], result["stats"]
    # one pool for the whole fine-tune, after the preflight's probe pool of two requests
    assert result["pool_sources"] == 2 and result["probe_attempts"] == [2], context
    dead, alive = figures[victim], figures[survivor]
    # both servers got requests; the killed one's failures are recorded, every one of them
    # retried on the other server, which never failed
    assert dead["sent"] >= 2 and alive["sent"] >= 1 and alive["answered"] >= 1, context
    assert dead["failed"] >= 1 and set(dead["failures"]) == {"connection"}, context
    assert dead["retried_from"] == dead["failed"] == stats["failovers"], context
    assert dead["went_down"] >= 1 and dead["live"] is False and dead["came_back"] == 0
    assert alive["failed"] == 0 and alive["retried_from"] == 0, context
    # nothing answered by the dead server after the kill (but what was about to arrive)
    assert dead["answered"] <= kill["before"][victim]["answered"] + kill["in_flight"]
    # the per-host counts add up to the chat calls sent
    assert dead["sent"] + alive["sent"] == stats["attempts"], context
    for row in (dead, alive):
        assert row["answered"] + row["failed"] == row["sent"], context

    # every request answered exactly once: one result each, none lost as error/timeout
    assert stats["fallbacks"] == stats["timeouts"] == stats["errors"] == 0, context
    assert stats["ok"] + stats["repaired"] + stats["abstained"] == stats["sent"], context
    store = result["store"]
    assert set(store["statuses"]) <= ANSWERS, store
    # ... and written once into the store: one row per distinct request, no key twice
    written = result["written"]
    assert len(written) == len(set(written)) == stats["sent"], (len(written), stats)
    assert store["rows"] == store["distinct_keys"] == store["sum_attempts"] == stats["sent"]
    assert sum(store["hosts"].values()) == store["rows"]
    assert set(store["hosts"]) <= {first, second} and store["hosts"].get(survivor, 0) >= 1

    # the figures are in the run's output, feedback.json, results.json and the report
    said = result["finetune_output"]
    assert "LLM servers (2):" in said, said
    assert f"{victim}: sent {dead['sent']}, answered {dead['answered']}" in said, said
    summary = result["feedback_json"]
    assert summary["llm_servers"] == figures
    for agent, row in summary["agents_per_state"].items():
        assert row["timeout"] == row["error"] == 0, (agent, row)
    assert result["results_servers"] == figures
    report = result["report"]
    assert "## LLM servers" in report
    assert f"| finetune-amuled | `{victim}` | {dead['sent']} | {dead['answered']} |" in report
    assert f"| finetune-amuled | `{survivor}` | {alive['sent']} | {alive['answered']} |" in report
    print(
        f"\nsealed pool run: {result['wall_s']} s in all, fine-tune {result['finetune_s']} s; "
        f"killed {victim} at {kill['at_s']} s with {kill['in_flight']} in flight; "
        f"{json.dumps(figures)}; source {json.dumps(stats)}"
    )
