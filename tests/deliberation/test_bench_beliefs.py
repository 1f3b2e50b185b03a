"""``amuled bench beliefs`` (replay): runs end to end and meets its second-run target."""

from __future__ import annotations

from amuled_ma.cli import main


def test_bench_beliefs_replay_small(recordings_dir, capsys, tmp_path):
    store = tmp_path / "bench.sqlite"
    rc = main(["bench", "beliefs", "--task", "findmilk", "--copies", "96", "--repeats", "2",
                 "--store", str(store)])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "96 env copies x 5 clusters = 480 lookups per call" in out
    assert "100% store hits, 0 requests sent (target met)" in out
    second = next(line for line in out.splitlines() if "2 second run" in line)
    assert second.split("|")[-1].strip() == "0"  # requests sent
    assert store.is_file()  # the last trial's store is kept
