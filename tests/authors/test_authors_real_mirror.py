"""The authors' real FindMilk gpt-4o-mini cache converts to the shared recording, unchanged.

Needs the git mirror of ``temetski/moral_agent`` named by ``$AMULED_AUTHORS_MIRROR`` (no
default: no test names a path of one machine) and ``../shared/amuled-recordings``; skips
with the reason otherwise. The pickle is read with ``git cat-file`` (the mirror is not touched).
"""

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from amuled_ma.authors.caches import convert_cache, model_slug

MIRROR_ENV = "AMULED_AUTHORS_MIRROR"
MIRROR = Path(os.environ[MIRROR_ENV]) if os.environ.get(MIRROR_ENV) else None
CACHE = "models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle"


def test_real_findmilk_cache_equals_the_shared_recording(tmp_path, recordings_dir):
    if MIRROR is None:
        pytest.skip(f"set {MIRROR_ENV} to a git mirror of temetski/moral_agent to run this test")
    if not (MIRROR / "HEAD").is_file() or shutil.which("git") is None:
        pytest.skip(f"no git mirror of temetski/moral_agent at {MIRROR} (or no git)")
    target = tmp_path / "FindMilk-v4_42" / "gpt-4o-mini_llm_cache.pickle"
    target.parent.mkdir()
    with target.open("wb") as out:
        done = subprocess.run(
            ["git", f"--git-dir={MIRROR}", "cat-file", "blob", f"HEAD:{CACHE}"],
            stdout=out,
            stderr=subprocess.PIPE,
            check=False,
        )
    if done.returncode != 0:
        pytest.skip(f"{CACHE} not in the mirror: {done.stderr.decode().strip()}")
    converted = convert_cache(target)
    name = f"{converted.task}-{model_slug(converted.model)}.json"
    assert name == "findmilk-gpt-4o-mini.json"
    shared = (recordings_dir / name).read_text()
    ours = json.loads(converted.to_json())
    theirs = json.loads(shared)
    assert len(ours["states"]) == len(theirs["states"]) == 524
    assert sum(s["error"] for s in ours["states"]) == 55
    for i in (0, 1, 100, 523):
        assert ours["states"][i] == theirs["states"][i], i
    first_flagged = next(i for i, s in enumerate(theirs["states"]) if s["error"])
    assert (
        ours["states"][first_flagged]["exchanges"] == theirs["states"][first_flagged]["exchanges"]
    )
    assert converted.to_json() == shared  # byte for byte, so the SHA-256 is the same


def published_caches() -> dict[str, bytes]:
    """Every ``*_llm_cache.pickle`` of the mirror's HEAD that it holds (a mirror may lack
    its largest files); skips the test without a mirror."""
    if MIRROR is None or not (MIRROR / "HEAD").is_file() or shutil.which("git") is None:
        pytest.skip(f"set {MIRROR_ENV} to a git mirror of temetski/moral_agent to run this test")
    listing = subprocess.run(
        ["git", f"--git-dir={MIRROR}", "ls-tree", "-r", "--name-only", "HEAD"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    caches = {}
    for name in (n for n in listing if n.endswith("_llm_cache.pickle")):
        blob = subprocess.run(
            ["git", f"--git-dir={MIRROR}", "cat-file", "blob", f"HEAD:{name}"],
            capture_output=True,
            check=False,
        )
        if blob.returncode == 0:
            caches[name] = blob.stdout
    assert caches, "no LLM cache in the mirror"
    return caches


def test_every_published_cache_fits_the_opcode_budget_with_room():
    """The budget (MAX_OPCODES) is 2.3 times the most opcodes of a published cache."""
    from amuled_ma.authors.unpickle import MAX_OPCODES, scan_pickle

    counts = {name: scan_pickle(data).opcodes for name, data in published_caches().items()}
    assert max(counts.values()) == 896_093, counts  # the figure docs/authors.md gives
    assert max(counts.values()) * 2 < MAX_OPCODES


def test_every_published_cache_fits_the_key_work_budget_with_room():
    """The key work budget (MAX_KEY_WORK) is 7.1 times the most a published cache needs."""
    from amuled_ma.authors.unpickle import MAX_KEY_WORK, BoundedReader

    spent = {}
    for name, data in published_caches().items():
        reader = BoundedReader(data, max_array_bytes=len(data), max_memory=None)
        reader.read()
        spent[name] = MAX_KEY_WORK - reader.key_work_left
    assert max(spent.values()) == 147_488, spent  # the figure the reader gives
    assert max(spent.values()) * 7 < MAX_KEY_WORK
