"""A cluster file nested deeper, or longer, than a cluster can be is refused with one line.

Before, a cluster file nested 10,000 levels deep reached Python's TOML reader, which
recursed until ``RecursionError`` (a traceback); the scenario file already had this check.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from sparse_files import sparse

from amuled_ma.clusters.loader import MAX_CLUSTER_BYTES, MAX_CLUSTER_CHARS, load_cluster
from amuled_ma.errors import ClusterDefinitionError
from amuled_ma.scenario.loading import MAX_TOML_DEPTH

SHIPPED = Path(__file__).resolve().parents[2] / "prompts" / "clusters" / "care.toml"


def test_a_deeply_nested_cluster_file_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "deep.toml"
    path.write_text(SHIPPED.read_text() + "x = " + "[" * 10_000 + "]" * 10_000 + "\n")
    with pytest.raises(ClusterDefinitionError) as caught:
        load_cluster(path)
    text = str(caught.value)
    assert "\n" not in text
    assert str(path) in text and "10000 levels" in text and f"at most {MAX_TOML_DEPTH}" in text


def test_nesting_at_the_limit_is_read(tmp_path: Path) -> None:
    # 31 levels of array inside the file's own top level: a value a TOML reader accepts
    path = tmp_path / "care.toml"
    deep = "[" * (MAX_TOML_DEPTH - 1) + "]" * (MAX_TOML_DEPTH - 1)
    path.write_text(SHIPPED.read_text() + f"\n[extra]\nx = {deep}\n")
    with pytest.raises(ClusterDefinitionError) as caught:  # an unknown table, not a depth
        load_cluster(path)
    assert "levels" not in str(caught.value)


def test_an_oversized_cluster_file_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "big.toml"
    path.write_text(SHIPPED.read_text() + "# " + "x" * MAX_CLUSTER_CHARS + "\n")
    with pytest.raises(ClusterDefinitionError) as caught:
        load_cluster(path)
    assert "\n" not in str(caught.value) and "characters long" in str(caught.value)


def test_the_shipped_cluster_still_loads() -> None:
    assert load_cluster(SHIPPED).name == "care"


def test_a_2_gb_cluster_file_is_refused_from_its_size_unread(tmp_path: Path) -> None:
    path = tmp_path / "big.toml"
    sparse(path, 2 * 10**9)
    with pytest.raises(ClusterDefinitionError) as caught:
        load_cluster(path)
    text = str(caught.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: the cluster file is 2,000,000,000 bytes, more than the ")
    assert f"{MAX_CLUSTER_BYTES:,} a cluster file may be" in text and "it is not read" in text


def test_a_cluster_file_of_the_most_characters_is_not_refused_by_its_size(tmp_path: Path) -> None:
    # 4-byte characters up to the character cap: within the byte cap, refused for length
    path = tmp_path / "wide.toml"
    path.write_text("# " + "\U0001f600" * (MAX_CLUSTER_CHARS - 2), encoding="utf-8")
    assert path.stat().st_size <= MAX_CLUSTER_BYTES
    with pytest.raises(ClusterDefinitionError) as caught:
        load_cluster(path)
    assert "characters" not in str(caught.value) and "bytes" not in str(caught.value)
