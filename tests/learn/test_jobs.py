"""The job graph: planning, seed replicas, parallel workers, a real Ctrl-C to the group.

Every test that starts Ray runs it in a network namespace it makes (``unshare -n``,
loopback only; ``tests/netns.py``): skipped with the reason where that is not permitted,
a failure under ``CI=true``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from netns import require_netns, run_sealed

from amuled_ma.errors import AmuledError
from amuled_ma.experiments.jobs import check_order, resolve_workers, run_jobs
from amuled_ma.experiments.plans import plan_ablation, plan_run, training_seeds
from amuled_ma.experiments.run_folder import TrainJob, replica_folder, split_replica
from amuled_ma.learn.checkpoints import checkpoint_infos
from amuled_ma.records.variants import Variant
from amuled_ma.scenario import load_scenario

TINY = {
    "base": {"total_steps": 1024, "num_envs": 16, "num_steps_per_env": 16},
    "finetune": {"iterations": 3, "num_envs": 4, "num_steps_per_env": 8},
    "output": {"tensorboard": False},
    "feedback": {"source": "rules"},
}


def tiny_scenario():
    scenario = load_scenario("findmilk")
    for section, values in TINY.items():
        scenario = scenario.replace(section, **values)
    return scenario


def test_seed_replica_names_round_trip():
    assert replica_folder("finetune-amuled", 1, 1) == "finetune-amuled"
    assert replica_folder("finetune-amuled", 3, 1) == "finetune-amuled.seed3"
    assert split_replica("finetune-amuled.seed3") == ("finetune-amuled", 3)
    assert split_replica("finetune-amuled-kl2.5") == ("finetune-amuled-kl2.5", None)
    assert training_seeds(1, 3) == [1, 2, 3]
    assert training_seeds(7, 2) == [7, 8]
    with pytest.raises(AmuledError, match="--seeds"):
        training_seeds(1, 0)


def test_plan_run_anchors_each_seed_to_its_own_base(tmp_path):
    jobs = plan_run(tiny_scenario(), tmp_path, [1, 2])
    assert [j.name for j in jobs] == [
        "base", "shaped", "finetune-human", "finetune-amuled",
        "base.seed2", "shaped.seed2", "finetune-human.seed2", "finetune-amuled.seed2",
    ]  # fmt: skip
    by_name = {j.name: j for j in jobs}
    assert by_name["finetune-amuled.seed2"].needs == ("base.seed2",)
    assert by_name["finetune-amuled.seed2"].base_variant == "base.seed2"
    assert by_name["finetune-amuled.seed2"].seed == 2
    assert by_name["shaped.seed2"].needs == ()
    assert by_name["finetune-human"].out_dir == tmp_path / "finetune-human"


def test_plan_ablation_reuses_bases_and_writes_under_ablate_dir(tmp_path):
    jobs = plan_ablation("aggregation", tiny_scenario(), tmp_path, [1, 2], resume=False)
    bases = [j for j in jobs if str(j.variant) == "base"]
    assert [j.name for j in bases] == ["base", "base.seed2"]
    assert all(j.resume for j in bases)  # a finished base from `amuled run` is reused
    tunes = [j for j in jobs if str(j.variant) != "base"]
    assert len(tunes) == 16  # mean, max, vote, mec, nash-vote, variance-vote, borda, bjs-dst x 2
    assert {j.out_dir.parent for j in tunes} == {tmp_path / "ablate-aggregation"}
    assert {j.needs for j in tunes} == {("base",), ("base.seed2",)}


def test_check_order_and_workers():
    sc = tiny_scenario()
    a = TrainJob("a", sc, Path("r"), Variant("base"), Path("r/a"))
    b = TrainJob("b", sc, Path("r"), Variant.finetune("amuled"), Path("r/b"), needs=("a",))
    check_order([a, b])
    with pytest.raises(AmuledError, match="needs"):
        check_order([b, a])
    with pytest.raises(AmuledError, match="duplicate"):
        check_order([a, a])
    assert resolve_workers(5, [a, b]) == 2  # never more workers than jobs
    assert resolve_workers(1, [a, b]) == 1
    live = TrainJob(
        "c",
        sc.replace("feedback", source="ollama"),
        Path("r"),
        Variant.finetune("amuled"),
        Path("c"),
    )
    assert resolve_workers(0, [a, live]) == 1  # a live Ollama server: one at a time
    assert resolve_workers(0, [a, b]) == min(2, len(os.sched_getaffinity(0)))
    with pytest.raises(AmuledError, match="--jobs"):
        resolve_workers(-1, [a])


def test_workers_auto_is_one_when_a_single_agent_asks_a_live_server():
    sc = tiny_scenario()
    base = TrainJob("a", sc, Path("r"), Variant("base"), Path("r/a"))
    one_live = sc.replace("feedback", agents={"care": {"source": "ollama", "model": "tiny"}})
    tune = TrainJob("b", one_live, Path("r"), Variant.finetune("amuled"), Path("r/b"), needs=("a",))
    assert resolve_workers(0, [base, tune]) == 1


def _learned(row: dict) -> dict:
    """A curve row without its wall-clock figures."""
    return {k: v for k, v in row.items() if k != "wall_s" and not k.startswith("time/")}


PARALLEL_SCRIPT = """
import json, sys
from pathlib import Path
sys.path[:0] = [sys.argv[2], str(Path(sys.argv[2]).parent)]  # tests/learn, tests
from test_jobs import tiny_scenario
from amuled_ma.experiments.jobs import job_groups, run_jobs
from amuled_ma.experiments.plans import plan_jobs, plan_run
from amuled_ma.records.variants import Variant
runs, workers_used, groups = {}, {}, {}
CONFIGS = (("1", 1, False), ("2", 2, False), ("p1", 1, True), ("p2", 2, True))
for label, workers, population in CONFIGS:
    run_dir = Path(sys.argv[1]) / label
    jobs = plan_jobs(plan_run(tiny_scenario(), run_dir, [1, 2]))
    grouped = job_groups(jobs, workers=workers, population=population)
    groups[label] = [[j.name for j in g] for g in grouped]
    outcome = run_jobs(
        jobs, workers=workers, describe=lambda r: str(r.variant), population=population
    )
    workers_used[label] = [outcome.workers, len(outcome.results)]
    runs[label] = {j.name: json.loads((j.out_dir / "curve.json").read_text()) for j in jobs}
print("RESULT " + json.dumps({"runs": runs, "workers": workers_used, "groups": groups}))
"""


@pytest.mark.slow
def test_parallel_training_is_bit_identical_to_sequential(tmp_path):
    """Worker processes change where a job runs, not what it learns; populations neither.

    Without populations, Ray's two workers give bit-identical curves; as populations (one
    population of each shape in this process, or one per worker on Ray) every job's curve
    equals its lone run's within float rounding (batched matmuls sum in another order).
    """
    require_netns()
    script = tmp_path / "parallel.py"
    script.write_text(PARALLEL_SCRIPT)
    here = str(Path(__file__).resolve().parent)
    result, _ = run_sealed(script, [str(tmp_path), here], timeout=900, env=ENV)
    assert result["workers"] == {"1": [1, 8], "2": [2, 8], "p1": [1, 8], "p2": [2, 8]}
    # bases first, then the fine-tunes (human and AMULED share a shape); with two workers
    # a level fills both: its two shapes (base, shaped), or its one shape cut in two
    assert result["groups"]["p1"] == [
        ["base", "base.seed2"], ["shaped", "shaped.seed2"],
        ["finetune-human", "finetune-amuled", "finetune-human.seed2", "finetune-amuled.seed2"],
    ]  # fmt: skip
    assert result["groups"]["p2"] == [
        ["base", "base.seed2"], ["shaped", "shaped.seed2"],
        ["finetune-human", "finetune-amuled"], ["finetune-human.seed2", "finetune-amuled.seed2"],
    ]  # fmt: skip
    assert len(result["groups"]["1"]) == 8
    runs = result["runs"]
    for name, curve in runs["1"].items():
        other = runs["2"][name]
        assert [_learned(row) for row in curve] == [_learned(row) for row in other], name
        for label in ("p1", "p2"):
            together = [_learned(row) for row in runs[label][name]]
            alone = [_learned(row) for row in curve]
            assert len(together) == len(alone), (label, name)
            for a, b in zip(alone, together, strict=True):
                assert set(a) == set(b)
                for key, value in a.items():
                    if isinstance(value, float):
                        assert b[key] == pytest.approx(value, rel=1e-5, abs=1e-6), (
                            label,
                            name,
                            key,
                        )
                    else:
                        assert b[key] == value, (label, name, key)
    # the two seeds really differ
    assert runs["1"]["finetune-amuled"] != runs["1"]["finetune-amuled.seed2"]


AMULED = [sys.executable, "-m", "amuled_ma"]
ENV = {**os.environ, "GIT_PYTHON_REFRESH": "quiet"}


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _ablate_args(run_dir: Path, iterations: int) -> list[str]:
    """``amuled ablate findmilk --what aggregation`` on TINY, in 2 workers."""
    args = ["ablate", "findmilk", "--what", "aggregation", "--run-dir", str(run_dir)]
    args += ["--jobs", "2", "--episodes", "2", "--no-progress"]
    tiny = {**TINY, "finetune": {**TINY["finetune"], "iterations": iterations}}
    for section, values in tiny.items():
        for key, value in values.items():
            text = json.dumps(value) if isinstance(value, str) else str(value).lower()
            args += ["--set", f"{section}.{key}={text}"]
    return args


def _sealed(command: list[str]) -> list[str]:
    """``command`` in a new network namespace with loopback only (Ray's ports stay here)."""
    return ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$0" "$@"', *command]


def _start(args: list[str]) -> subprocess.Popen:
    require_netns()
    return subprocess.Popen(
        _sealed([*AMULED, *args]),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=ENV,
        # a terminal's foreground job takes Ctrl-C; a job started in the background of a
        # non-interactive shell (as CI runners may start pytest) inherits SIGINT ignored
        preexec_fn=_default_sigint,
    )


def _wait_for(paths: list[Path], proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not all(p.exists() for p in paths):
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    assert all(p.exists() for p in paths), [p for p in paths if not p.exists()]


def _ctrl_c(proc: subprocess.Popen) -> str:
    """SIGINT to the whole process group, as a terminal's Ctrl-C; returns stderr."""
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert "resume with: amuled ablate findmilk --what aggregation" in err
    assert err.count("resume with:") == 1  # once, from the parent
    assert "Traceback" not in err, err
    return err


def _tunes(run_dir: Path, *names: str) -> list[Path]:
    return [run_dir / "ablate-aggregation" / f"finetune-agg-{n}" for n in names]


def _resume_to(run_dir: Path, iterations: int, tunes: list[Path]) -> None:
    """``--resume`` the ablation to ``iterations``; each of ``tunes`` then has every one."""
    resume = [*_ablate_args(run_dir, iterations), "--resume"]
    done = subprocess.run(
        _sealed([*AMULED, *resume]), capture_output=True, text=True, env=ENV, timeout=300
    )
    assert done.returncode == 0, done.stderr
    _check_curves(iterations, tunes)


def _check_curves(iterations: int, tunes: list[Path]) -> None:
    """Each of ``tunes`` has a learning-curve row for every iteration up to ``iterations``."""
    for tune in tunes:
        curve = json.loads((tune / "curve.json").read_text())
        assert [row["iteration"] for row in curve] == list(range(1, iterations + 1))


@pytest.mark.slow
@pytest.mark.parametrize("population", [False, True], ids=["alone", "populations"])
def test_parallel_stops_on_ctrl_c_with_checkpoints_then_resumes(tmp_path, population):
    """A real SIGINT to the whole process group, as a terminal's Ctrl-C sends it.

    Alone, two of the four fine-tunes run on the two workers and the others wait; as
    populations, the four train as two populations of two, every member stops with its
    checkpoint, and the resume continues each population from its own iteration.
    """
    run_dir = tmp_path / "run"
    args = _ablate_args(run_dir, 4000) + ([] if population else ["--no-population"])
    proc = _start(args)
    tunes = _tunes(run_dir, "mean", "max", *(["vote"] if population else []))
    # the fine-tunes are iterating: each has written its first periodic checkpoint
    # (a variant folder exists earlier, from config.json, while its worker still sets up)
    _wait_for([t / "model_last.pt" for t in tunes], proc)
    time.sleep(1.0)
    _ctrl_c(proc)
    stopped = [checkpoint_infos(t / "model_last.pt") for t in tunes]
    assert all(s is not None and not s["completed"] for s in stopped), stopped
    assert all(0 < s["iteration"] < 4000 for s in stopped)
    if not population:  # queued behind the two running ones: never started
        assert not (_tunes(run_dir, "vote")[0] / "model_last.pt").exists()

    # resume, shortened to 3 iterations past the furthest stop
    last = max(s["iteration"] for s in stopped)
    _resume_to(run_dir, last + 3, tunes)
    for tune in tunes:
        assert checkpoint_infos(tune / "model_last.pt")["iteration"] == last + 3


@pytest.mark.slow
def test_ctrl_c_while_the_workers_start_the_finetunes_then_resume(tmp_path):
    """Ctrl-C as soon as the fine-tunes' folders appear, before either has iterated much."""
    run_dir = tmp_path / "run"
    proc = _start(_ablate_args(run_dir, 4000))
    tunes = _tunes(run_dir, "mean", "max")
    _wait_for([t / "config.json" for t in tunes], proc)
    _ctrl_c(proc)
    # whatever a job had reached is kept (a checkpoint of an unfinished run, or nothing yet)
    stopped = [checkpoint_infos(t / "model_last.pt") for t in tunes]
    assert all(s is None or not s["completed"] for s in stopped), stopped
    assert checkpoint_infos(run_dir / "base" / "model_last.pt")["completed"]

    target = 3 + max((s["iteration"] for s in stopped if s), default=0)
    _resume_to(run_dir, target, _tunes(run_dir, "mean", "max", "vote"))


def _children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _started(pid: int) -> str | None:
    """When ``pid`` started (``/proc`` field 22, in clock ticks; None: gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except OSError:
        return None


def _running(pid: int, started: str | None) -> bool:
    """Whether the process ``pid`` that started at ``started`` still runs.

    A zombie waiting to be reaped does not; nor does another process given the same pid.
    """
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z" and fields[19] == started


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return "?"


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (Ray's GCS, raylet and workers, for a driver)."""
    found, todo = [], [pid]
    while todo:
        children = _children(todo.pop())
        found += children
        todo += children
    return found


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_a_killed_driver_leaves_no_process_and_resumes_from_its_checkpoints(tmp_path):
    """A real ``kill -9`` of the driver: its local Ray (GCS, raylet, workers) goes with it.

    The training tasks end at once; Ray's dashboard and runtime-env agents follow about a
    minute later, when they notice their raylet is gone.

    The jobs cannot write a last checkpoint (Ray kills the tasks of a dead driver); each
    keeps its last periodic one (every ``save_interval`` = 100 iterations), and
    ``--resume`` continues from there.
    """
    run_dir = tmp_path / "run"
    proc = _start(_ablate_args(run_dir, 4000))
    tunes = _tunes(run_dir, "mean", "max")
    _wait_for([t / "model_last.pt" for t in tunes], proc)
    below = {pid: _started(pid) for pid in _descendants(proc.pid)}
    names = " ".join(_cmdline(pid) for pid in below)
    assert "raylet" in names and "gcs_server" in names, names  # a local Ray under the driver
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGKILL
    stopped = [checkpoint_infos(t / "model_last.pt") for t in tunes]
    assert all(not s["completed"] and 100 <= s["iteration"] < 4000 for s in stopped), stopped
    assert all(s["iteration"] % 100 == 0 for s in stopped), stopped  # periodic checkpoints

    # the resume (its own namespace and Ray) runs while the killed Ray's processes end
    target = max(s["iteration"] for s in stopped) + 3
    resume = subprocess.Popen(
        _sealed([*AMULED, *_ablate_args(run_dir, target), "--resume"]),
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    try:
        # the tasks end at once; Ray's two node agents notice the raylet is gone after ~60 s
        deadline = time.monotonic() + 150
        while any(_running(*p) for p in below.items()) and time.monotonic() < deadline:
            time.sleep(0.5)
        lingering = {pid: _cmdline(pid) for pid in below if _running(pid, below[pid])}
        assert not lingering
        _, err = resume.communicate(timeout=300)
    finally:
        if resume.poll() is None:
            resume.kill()
            resume.wait()
    assert resume.returncode == 0, err
    _check_curves(target, tunes)


def test_plan_ablation_reuses_the_runs_amuled_finetune_only_with_same_settings(tmp_path):
    run_dir = tmp_path / "run"
    run_jobs(plan_run(tiny_scenario(), run_dir, [1, 2]), describe=str)
    checkpoint = (run_dir / "finetune-amuled" / "model_last.pt").read_bytes()

    jobs = plan_ablation("aggregation", tiny_scenario(), run_dir, [1, 2])
    where = {j.name: j.out_dir for j in jobs if str(j.variant) == "finetune:amuled"}
    assert where == {
        "finetune-amuled": run_dir / "finetune-amuled",
        "finetune-amuled.seed2": run_dir / "finetune-amuled.seed2",
    }
    others = [j.out_dir.parent for j in jobs if str(j.variant).startswith("finetune:agg")]
    assert len(others) == 14 and set(others) == {run_dir / "ablate-aggregation"}  # 7 x 2
    outcome = run_jobs(jobs, describe=str)
    skipped = {Path(r.out_dir).name for r in outcome.results if r.skipped}
    assert skipped == {"base", "base.seed2", "finetune-amuled", "finetune-amuled.seed2"}
    assert (run_dir / "finetune-amuled" / "model_last.pt").read_bytes() == checkpoint
    assert not (run_dir / "ablate-aggregation" / "finetune-amuled").exists()

    # other settings or another length: the ablation trains its own
    for scenario in (
        tiny_scenario().replace("finetune", lambda_kl=0.5),
        tiny_scenario().replace("finetune", iterations=4),
    ):
        jobs = plan_ablation("aggregation", scenario, run_dir, [1], resume=True)
        (amuled,) = [j for j in jobs if str(j.variant) == "finetune:amuled"]
        assert amuled.out_dir == run_dir / "ablate-aggregation" / "finetune-amuled"


def test_a_ray_address_where_nothing_listens_fails_at_once_naming_the_fix(tmp_path, capsys):
    """``--ray HOST:PORT`` with no Ray head there: one line, no minutes of Ray retries."""
    import socket

    from amuled_ma.cli import main

    with socket.socket() as probe:  # a port nothing listens on: bound, then released
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    argv = ["run", "findmilk", "--run-dir", str(tmp_path / "run"), "--no-progress"]
    argv += ["--ray", f"127.0.0.1:{port}", "--set", 'feedback.source="rules"']
    started = time.monotonic()
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert f"--ray 127.0.0.1:{port}: no Ray head answers there" in err, err
    assert f"ray start --head --port={port}" in err
    assert time.monotonic() - started < 60
    assert not list((tmp_path / "run").glob("*/model_last.pt"))  # nothing trained
    assert main([*argv[:-4], "--ray", "nohost", "--set", 'feedback.source="rules"']) == 1
    assert "expected HOST:PORT of a Ray head" in capsys.readouterr().err
