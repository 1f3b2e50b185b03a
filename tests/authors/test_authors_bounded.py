"""Hostile caches end in seconds with one line, in bounded memory; SIGTERM is honoured.

Each attack runs ``amuled import authors`` in a child process on a checkout holding only
the hostile cache, with a timeout: before the unpickler was bounded, the 2 MB collision
cache took over 13 minutes and ignored SIGTERM, and the void-dtype cache 18 s and 1 GB;
before the opcode budget, 16 MiB of one-byte opcodes took 25-39 s to read or refuse.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pickle_attacks as attacks
import pytest

from amuled_ma.authors.unpickle import (
    MAX_KEY_WORK,
    MAX_OPCODES,
    MAX_PICKLE_BYTES,
    MEMORY_CHECK_EVERY,
    BoundedReader,
    PickleUnbounded,
    load_pickle,
)
from amuled_ma.errors import AuthorsImportError, UnsafePickleError

CACHE = "models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle"
#: What the child prints: its exit status, its stderr, its wall time and peak memory.
CHILD = """
import resource, sys, time
import amuled_ma.authors.checkout, amuled_ma.tasks  # torch: before the clock and memory
from amuled_ma.cli import build_parser, main
build_parser()  # every command module imported
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start, cpu = time.monotonic(), time.process_time()
print("child: ready", file=sys.stderr, flush=True)
code = main(sys.argv[1:])
grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024
used = time.process_time() - cpu
print(f"child: {code} {time.monotonic() - start:.2f} {grown} {used:.2f}", file=sys.stderr)
sys.exit(code)
"""


def checkout_with(tmp_path: Path, data: bytes) -> Path:
    root = tmp_path / "moral_agent"
    path = root / CACHE
    path.parent.mkdir(parents=True)
    path.write_bytes(data)
    return root


def import_command(tmp_path: Path, root: Path) -> list[str]:
    return [sys.executable, "-c", CHILD, "import", "authors", str(root),
            "--runs", str(tmp_path / "runs"), "--to", str(tmp_path / "rec")]  # fmt: skip


def run_import(tmp_path: Path, data: bytes, timeout: float = 60.0, *, cpu: bool = False):
    """``amuled import authors`` of ``data``: exit status, stderr lines, seconds, MiB grown.

    With ``cpu``, the seconds are the child's CPU time (not its wall time: on a loaded
    machine that is several times longer).
    """
    root = checkout_with(tmp_path, data)
    env = {**os.environ, "AMULED_DATA": str(tmp_path / "data")}
    done = subprocess.run(
        import_command(tmp_path, root),
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=tmp_path,
    )
    lines = [line for line in done.stderr.splitlines() if not line.startswith("child:")]
    (stats,) = [
        line
        for line in done.stderr.splitlines()
        if line.startswith("child: ") and "ready" not in line
    ]
    _, _code, seconds, grown_mib, cpu_s = stats.split()
    return done.returncode, lines, float(cpu_s if cpu else seconds), int(grown_mib)


@pytest.mark.parametrize(
    ("name", "data", "expected"),
    [
        ("int keys", attacks.colliding_int_keys(2 * 2**20), "multiples of 2**61 - 1"),
        ("tuple keys", attacks.colliding_tuple_keys(2 * 2**20), "multiples of 2**61 - 1"),
        ("void dtype", attacks.void_array(), "void dtype"),
        ("void BUILD", attacks.huge_void_build(), "void dtype"),
    ],
)
def test_hostile_cache_ends_in_seconds_with_one_line(tmp_path, name, data, expected):
    code, lines, cpu_s, grown_mib = run_import(tmp_path, data, cpu=True)
    assert cpu_s < 5, f"{name}: {cpu_s:.1f} s of CPU"  # the unbounded reader: 13 min, 18 s
    assert grown_mib < 100, f"{name}: grew {grown_mib} MiB"  # the void array: 1 GB and more
    assert code == 1, lines
    assert len(lines) == 1, lines
    assert lines[0].startswith("amuled: error: ") and CACHE in lines[0], lines
    assert expected in lines[0]
    assert "refusing to unpickle" in lines[0]


#: Just under 16 MiB, the largest file read: the opcode budget, not the size, bounds it.
NEAR_CAP = 16 * 2**20 - 64


def one_byte_opcodes(kind: str, count: int) -> bytes:
    """A pickle of ``count`` one-byte opcodes: marks, empty sets or ``None`` in a list."""
    if kind == "marks":
        return attacks.PROTO4 + b"(" * count + b"N."
    if kind == "sets":
        return attacks.many_sets(count)
    return attacks.PROTO4 + b"](" + b"N" * count + b"e."


@pytest.mark.parametrize(
    ("name", "data"),
    [
        ("16 MiB of MARK", one_byte_opcodes("marks", NEAR_CAP)),
        ("16 MiB of empty sets", one_byte_opcodes("sets", NEAR_CAP)),
        ("16 MiB of None", one_byte_opcodes("nones", NEAR_CAP)),
        ("16 MiB of colliding int keys", attacks.colliding_int_keys(NEAR_CAP)),
    ],
)
def test_a_16_mib_file_of_small_opcodes_is_refused_in_seconds(tmp_path, name, data):
    # before: read opcode by opcode to its end, 25-39 s (the marks and None files loaded)
    assert len(data) <= MAX_PICKLE_BYTES
    code, lines, cpu_s, _grown = run_import(tmp_path, data, timeout=120, cpu=True)
    assert cpu_s < 5, f"{name}: {cpu_s:.1f} s of CPU"
    assert code == 1 and len(lines) == 1, lines
    assert f"more than {MAX_OPCODES:,} opcodes" in lines[0] and CACHE in lines[0], lines
    assert "refusing to unpickle" in lines[0]


def test_the_slowest_file_within_the_opcode_budget_ends_in_seconds(tmp_path):
    # empty sets, the costliest opcode to build: read until the memory bound refuses it
    data = one_byte_opcodes("sets", MAX_OPCODES - 8)
    code, lines, cpu_s, _grown = run_import(tmp_path, data, timeout=120, cpu=True)
    assert cpu_s < 8, f"{cpu_s:.1f} s of CPU"
    assert code == 1 and len(lines) == 1 and "MiB of memory" in lines[0], lines


def test_a_file_of_costly_keys_is_refused_by_its_key_work_in_a_second(tmp_path):
    # 16 MiB of set() calls on a memoized list of 64-value tuples: 2 million opcodes, 400,000
    # calls hashing 390 values each; counted by opcodes only it took 23-31 s of CPU here
    # (and 187 s in another form); the key work stops it at 1,048,576 units
    data = attacks.memoized_key_sets(2_000_000 // 5 - 200)
    assert len(data) <= MAX_PICKLE_BYTES
    code, lines, cpu_s, _grown = run_import(tmp_path, data, timeout=120, cpu=True)
    assert cpu_s < 5, f"{cpu_s:.1f} s of CPU"
    assert code == 1 and len(lines) == 1, lines
    assert f"more than {MAX_KEY_WORK:,} units of work hashing dict keys" in lines[0], lines
    assert "refusing to unpickle" in lines[0] and CACHE in lines[0]


def test_the_key_work_counts_values_of_tuple_keys():
    # 2,688 calls of 6 keys of 65 units: 1,048,320 units, within the budget; one more is not
    ok = attacks.memoized_key_sets(MAX_KEY_WORK // 390)
    assert BoundedReader(ok, max_array_bytes=len(ok), max_memory=None).read() is None
    over = attacks.memoized_key_sets(MAX_KEY_WORK // 390 + 1)
    with pytest.raises(PickleUnbounded, match="units of work hashing"):
        BoundedReader(over, max_array_bytes=len(over), max_memory=None).read()


def test_the_reader_keeps_its_own_opcode_budget():
    # the second guard: the reader counts too, should a caller skip the scan
    data = one_byte_opcodes("nones", 3 * MEMORY_CHECK_EVERY)
    reader = BoundedReader(
        data, max_array_bytes=len(data), max_memory=None, max_opcodes=MEMORY_CHECK_EVERY
    )
    with pytest.raises(PickleUnbounded, match=f"more than {MEMORY_CHECK_EVERY:,} opcodes"):
        reader.read()
    assert len(BoundedReader(data, max_array_bytes=len(data), max_memory=None).read()) == (
        3 * MEMORY_CHECK_EVERY
    )


def test_colliding_float_keys_refused_by_the_hash_count(tmp_path):
    # 17 floats 2.0 ** (61 j) share the hash 1 (no integer involved)
    assert len({hash(2.0 ** (61 * j)) for j in range(17)}) == 1
    path = tmp_path / "floats.pickle"
    path.write_bytes(attacks.colliding_float_keys())
    with pytest.raises(AuthorsImportError, match="more than 8 keys of one dict") as info:
        load_pickle(path)
    assert not isinstance(info.value, UnsafePickleError)


def test_memory_bounded_per_byte_of_file(tmp_path):
    # 2 million empty sets (the opcode budget): 2 MB in the file, about 450 MB in memory
    path = tmp_path / "sets.pickle"
    path.write_bytes(attacks.many_sets(MAX_OPCODES - 8))
    started = time.monotonic()
    with pytest.raises(AuthorsImportError, match="MiB of memory"):
        load_pickle(path)
    assert time.monotonic() - started < 60


def test_arrays_hold_no_more_bytes_than_the_file(tmp_path):
    # a legal float64 array (1, 2**20 items) declared through _reconstruct of a tiny file
    data = (
        attacks.PROTO4
        + attacks._global("numpy.core.multiarray", "_reconstruct")
        + attacks._global("numpy", "ndarray")
        + b"J" + (2**20).to_bytes(4, "little") + b"\x85"
        + attacks._dtype("f8")
        + b"\x87R."
    )  # fmt: skip
    path = tmp_path / "big.pickle"
    path.write_bytes(data)
    with pytest.raises(AuthorsImportError, match="more than the file's size allows"):
        load_pickle(path)


def test_real_sized_values_still_load(tmp_path):
    # what a cache holds: float32 key tuples, float64 arrays, frozenset keys
    cache = {
        tuple(np.float32(i + j) for j in range(8)): {
            "care": np.arange(4, dtype=np.float64) / 6,
            "rewards": {frozenset({str(a)}): np.float64(a / 6) for a in range(4)},
        }
        for i in range(300)
    }
    import pickle

    path = tmp_path / "ok.pickle"
    path.write_bytes(pickle.dumps(cache, protocol=4))
    loaded = load_pickle(path)
    assert list(loaded) == list(cache)
    np.testing.assert_array_equal(loaded[next(iter(cache))]["care"], [0, 1 / 6, 2 / 6, 3 / 6])


def start_import(tmp_path: Path, data: bytes) -> subprocess.Popen:
    """The import in a child process, returned once its imports are done and main() runs."""
    root = checkout_with(tmp_path, data)
    env = {**os.environ, "AMULED_DATA": str(tmp_path / "data")}
    child = subprocess.Popen(
        import_command(tmp_path, root), stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path
    )
    assert child.stderr is not None
    assert child.stderr.readline().strip() == "child: ready"
    return child


def terminate(child: subprocess.Popen) -> tuple[float, str]:
    """SIGTERM (if still running); seconds until it ended (at most 10) and its stderr."""
    sent = time.monotonic()
    if child.poll() is None:
        child.send_signal(signal.SIGTERM)
    try:
        _, err = child.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        err = "still running 10 s after SIGTERM"
    finally:
        child.kill()
    return time.monotonic() - sent, err


def test_sigterm_during_a_long_import_ends_it_at_once(tmp_path):
    # a legal-looking cache that takes seconds to read: 10 MB of float keys in one dict,
    # just within the opcode budget (two opcodes a key)
    body = bytearray()
    for x in range(MAX_OPCODES // 2 - 8):
        body += b"G" + np.float64(x).byteswap().tobytes() + b"N"
    child = start_import(tmp_path, attacks.PROTO4 + b"}(" + bytes(body) + b"u.")
    time.sleep(1.5)  # inside the scan or the reading (both take several seconds)
    assert child.poll() is None, "the import ended before SIGTERM: make the file larger"
    seconds, err = terminate(child)
    assert seconds < 5, err
    assert child.returncode == 143, err
    assert "amuled: terminated (SIGTERM)" in err


def test_sigterm_not_blocked_by_the_collision_cache(tmp_path):
    # the unbounded reader spent minutes inside one C call here, SIGTERM waiting behind it
    child = start_import(tmp_path, attacks.colliding_int_keys(2 * 2**20))
    time.sleep(4.0)
    seconds, err = terminate(child)
    assert seconds < 5, err
    lines = [line for line in err.splitlines() if not line.startswith("child: ")]
    assert child.returncode in (1, 143), err  # refused by now, or stopped by SIGTERM
    assert len(lines) == 1, lines
