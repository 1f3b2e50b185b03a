"""A two-node Ray cluster on loopback trains small ablations: a node killed; a node apart.

``ray_cluster_netns.py`` runs inside network and PID namespaces this test makes
(``unshare -n -p -f --mount-proc``, loopback only): a head and a second ``ray start`` on
127.0.0.1, each offering one unit of the custom resource ``amuled_job``
(``--ray-resource``), so the fine-tunes land on both nodes. Once two fine-tunes have
written a periodic checkpoint (every 25 iterations), the second node's raylet gets
``kill -9``. Checked: the run finishes; jobs started on both nodes; the lost job was run
again and resumed from its checkpoint (not from iteration 0); every fine-tune's learning
curve equals that of the same ablation with ``--jobs 1`` (an exact resume: the checkpoint
keeps the episodes in flight).

The script ends with ``ray stop --force``; in the script's own PID namespace that stops
this cluster alone, not another Ray of the machine, and every process left dies with the
namespace.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from netns import require_netns, run_sealed

from amuled_ma.records.variants import AGGREGATIONS

SCRIPT = Path(__file__).resolve().parent / "ray_cluster_netns.py"
#: The aggregation ablation's fine-tunes: each other rule, and bjs-dst (``amuled``).
FINE_TUNES = len(AGGREGATIONS) + 1


@pytest.mark.slow
def test_two_node_cluster_loses_a_node_and_finishes_equal_to_one_process(tmp_path: Path):
    require_netns(own_pids=True)
    result, _output = run_sealed(
        SCRIPT, ["kill", str(tmp_path)], timeout=840, env=os.environ, own_pids=True
    )
    context = f"{ {k: v for k, v in result.items() if k != 'tail'} }\n{result['tail']}"
    assert result["code"] == 0, context
    assert len(result["nodes"]) == 2, context  # jobs started on both nodes
    assert result["fine_tunes"] == FINE_TUNES, context
    # the lost job resumed from a periodic checkpoint (every 25 of 150 iterations)
    assert result["resumed_from"], context
    assert all(0 < it < 150 and it % 25 == 0 for it in result["resumed_from"]), context
    assert result["equal_to_jobs_1"], context


@pytest.mark.slow
def test_a_node_without_the_driver_files_shares_the_sweep_belief_store(
    tmp_path: Path, recordings_dir: Path
):
    """The second node sees an empty tmpfs where the run folder is (its own mount namespace).

    Its jobs get their inputs and return their folders through Ray, and ask the driver's
    belief store through the store actor. The shipped replay feedback counts every
    request as if live: the sweep sends no more requests than the same sweep on one
    machine (``--jobs 2``, one SQLite store; the issue's target: at most 5% more), and
    learns the same policies.
    """
    require_netns(own_pids=True)
    result, _output = run_sealed(
        SCRIPT, ["store", str(tmp_path)], timeout=840, env=os.environ, own_pids=True
    )
    context = f"{ {k: v for k, v in result.items() if k != 'tail'} }\n{result['tail']}"
    assert result["code"] == 0, context
    assert len(result["nodes"]) == 2 and result["fine_tunes"] == FINE_TUNES, context
    # the other node used the store actor: keys looked up, rows written
    (looked_up, _calls, written), *_ = result["served"]
    assert looked_up > 0 and written > 0, context
    assert result["reference_asked"] > 0, context
    assert result["ray_asked"] <= 1.05 * result["reference_asked"], context
    assert result["equal_to_one_machine"], context
