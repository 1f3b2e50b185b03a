"""Every state of the AMULED authors' real LLM recordings (../shared/amuled-recordings).

``fused_by_reference`` is the authors' BJS + DST fusion of the five cluster beliefs. We
reproduce it to 1e-9 on every state whose five beliefs are not all identical. Where they
are identical, the authors' code returned the raw belief; we check that it did, and that
we return the documented limit ``m^k / sum(m^k)`` instead.

Three states of the gpt-4o-mini recording are anomalies of the recording itself: there the
authors' code fused *six* sources, the five clusters plus the unprompted ``moral_agent``
belief (found by search: no rule that uses only the five clusters can produce them, e.g.
state 172, where every cluster gives 0.1 to action 2). We pin them to that six-source
fusion, to 1e-9, and check that no other state needs an exception.
"""

from __future__ import annotations

import numpy as np
import pytest

from amuled_ma.fusion import fuse
from amuled_ma.fusion.reference import fuse_beliefs

FILES = [
    "findmilk-gpt-4o-mini.json",
    "findmilk-llama-3_1-70b.json",
    "findmilk-llama-3_1-8b.json",
    "findmilk-mistral-nemo.json",
    "driving-llama-3_1-70b.json",
]


def _arrays(recording: dict) -> tuple[np.ndarray, np.ndarray]:
    clusters = recording["clusters"]
    beliefs = np.array([[s["beliefs"][c] for c in clusters] for s in recording["states"]])
    reference = np.array([s["fused_by_reference"] for s in recording["states"]])
    return beliefs, reference


SIX_SOURCE_STATES = {"findmilk-gpt-4o-mini.json": [11, 172, 397]}


def _identical(beliefs: np.ndarray) -> np.ndarray:
    return np.all(beliefs == beliefs[:, :1, :], axis=(1, 2))


@pytest.mark.parametrize("name", FILES)
def test_reproduces_reference_fusion(load_recording, name):
    beliefs, reference = _arrays(load_recording(name))
    assert beliefs.shape[1] == 5
    fused = fuse(beliefs, "bjs-dst")  # the whole recording in one batched call
    same = _identical(beliefs)
    anomalies = np.zeros(len(beliefs), dtype=bool)
    anomalies[SIX_SOURCE_STATES.get(name, [])] = True
    checked = ~same & ~anomalies
    assert checked.sum() > 50
    np.testing.assert_allclose(fused[checked], reference[checked], rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(SIX_SOURCE_STATES))
def test_anomalous_states_are_six_source_fusions(load_recording, name):
    recording = load_recording(name)
    beliefs, reference = _arrays(recording)
    indices = SIX_SOURCE_STATES[name]
    moral_agent = np.array([recording["states"][i]["moral_agent"] for i in indices])
    six = np.concatenate([beliefs[indices], moral_agent[:, None, :]], axis=1)
    np.testing.assert_allclose(fuse(six), reference[indices], rtol=0, atol=1e-9)
    # ... and the five-cluster fusion really differs there (so the exception is needed).
    assert np.all(np.abs(fuse(beliefs[indices]) - reference[indices]).max(axis=1) > 1e-6)


@pytest.mark.parametrize("name", FILES)
def test_identical_beliefs_use_documented_limit(load_recording, name):
    beliefs, reference = _arrays(load_recording(name))
    same = _identical(beliefs)
    assert same.any(), "every recording has states where all five clusters agree"
    raw = beliefs[same, 0, :]
    # The authors' code returned the raw belief there ...
    np.testing.assert_allclose(reference[same], raw, rtol=0, atol=1e-12)
    # ... we return the limit of the formula, m^k / sum(m^k) with k = 5.
    limit = raw**5 / (raw**5).sum(axis=-1, keepdims=True)
    fused = fuse(beliefs[same])
    np.testing.assert_allclose(fused, limit, rtol=0, atol=1e-12)
    diag = fuse(beliefs[same], return_diagnostics=True)
    np.testing.assert_allclose(diag.credibility, 0.2, atol=1e-15)
    np.testing.assert_allclose(diag.weights, 0.2, atol=1e-15)


@pytest.mark.parametrize("name", FILES)
def test_diagnostics_path_gives_same_fusion(load_recording, name):
    beliefs, _ = _arrays(load_recording(name))
    result = fuse(beliefs, return_diagnostics=True)
    np.testing.assert_allclose(result.fused, fuse(beliefs), rtol=0, atol=1e-15)
    assert result.conflicts.shape == (len(beliefs), 4)
    assert np.all(np.isfinite(result.conflicts))


@pytest.mark.parametrize("name", FILES)
def test_pure_python_reference_agrees_on_a_sample(load_recording, name):
    beliefs, reference = _arrays(load_recording(name))
    same = _identical(beliefs)
    usable = ~same
    usable[SIX_SOURCE_STATES.get(name, [])] = False
    for index in np.flatnonzero(usable)[:40]:
        got = fuse_beliefs(beliefs[index].tolist())
        np.testing.assert_allclose(got, reference[index], rtol=0, atol=1e-9)
