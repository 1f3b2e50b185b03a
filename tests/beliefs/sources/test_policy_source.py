"""The policy source: a saved torch policy, loaded weights-only, softmax over its logits."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from amuled_ma.beliefs import BeliefRequest, make_source
from amuled_ma.beliefs.sources.policy import PolicySource
from amuled_ma.errors import ScenarioError

MILK = ("up", "down", "left", "right")
HERE = Path(__file__).resolve().parent
OBS = [
    (0.0, 0.0, 3.0, 3.0, 1.0, 0.0, 0.0, 1.0),
    (1.0, 2.0, 3.0, 3.0, 0.0, 1.0, 1.0, 0.0),
    (4.0, 4.0, 3.0, 3.0, 1.0, 1.0, 0.0, 0.0),
]


def req(obs, actions=MILK) -> BeliefRequest:
    return BeliefRequest("findmilk", "virtue", tuple(obs), actions)


@pytest.fixture
def mlp() -> torch.nn.Sequential:
    torch.manual_seed(0)
    return torch.nn.Sequential(
        torch.nn.Linear(8, 16), torch.nn.Tanh(), torch.nn.Linear(16, 16), torch.nn.Tanh(),
        torch.nn.Linear(16, 4),
    )  # fmt: skip


def expected(model: torch.nn.Module, rows) -> np.ndarray:
    with torch.no_grad():
        logits = model(torch.tensor(rows, dtype=torch.float32)).double()
    return torch.softmax(logits, dim=-1).numpy()


def test_a_saved_state_dict_gives_the_softmax_of_the_policys_logits(tmp_path, mlp):
    path = tmp_path / "virtue.pt"
    torch.save(mlp.state_dict(), path)
    source = PolicySource(path)
    results = source.beliefs([req(o) for o in OBS])
    assert [r.status for r in results] == ["ok"] * 3
    assert np.allclose([r.belief for r in results], expected(mlp, OBS), atol=1e-6)
    ident = source.identity()
    assert ident["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert ident["file"] == "virtue.pt" and ident["activation"] == "tanh"
    assert source.needs_messages is False


def test_a_trainer_checkpoint_serves_its_actor_by_key(tmp_path, mlp):
    path = tmp_path / "model_last.pt"
    actor = {f"mlp.{k}": v for k, v in mlp.state_dict().items()}
    torch.save({"actor_state_dict": actor, "iter": 7, "infos": {"x": 1}}, path)
    with pytest.raises(ScenarioError, match=r"holds no tensors .*key = 'actor_state_dict'"):
        PolicySource(path)
    source = make_source("policy", path=str(path), key="actor_state_dict")
    beliefs = [r.belief for r in source.beliefs([req(o) for o in OBS])]
    assert np.allclose(beliefs, expected(mlp, OBS), atol=1e-6)
    with pytest.raises(ScenarioError, match=r"key 'critic': the file has no 'critic'"):
        PolicySource(path, key="critic")


def test_a_named_module_class_takes_the_weights(tmp_path, monkeypatch):
    from amuled_ma.clusters import plugins

    monkeypatch.syspath_prepend(str(HERE))
    monkeypatch.setattr(plugins, "_ALLOWED", frozenset({"amuled_agent_helper:TinyNet"}))
    from amuled_agent_helper import TinyNet

    torch.manual_seed(1)
    net = TinyNet(scale=2.0)
    path = tmp_path / "tiny.pt"
    torch.save(net.state_dict(), path)
    with pytest.raises(ScenarioError, match="cannot infer an MLP"):
        PolicySource(path)  # body/head: no <i>.weight layers to infer
    source = PolicySource(path, module="amuled_agent_helper:TinyNet", kwargs={"scale": 2.0})
    beliefs = [r.belief for r in source.beliefs([req(o) for o in OBS])]
    assert np.allclose(beliefs, expected(net, OBS), atol=1e-6)
    with pytest.raises(ScenarioError, match="the weights do not fit"):
        PolicySource(path, module="amuled_agent_helper:TinyNet", kwargs={"actions": 3})


def test_a_pickled_module_is_refused_unloaded(tmp_path, mlp):
    path = tmp_path / "whole.pt"
    torch.save(mlp, path)  # the whole nn.Module: a pickle that needs torch classes
    with pytest.raises(ScenarioError) as info:
        PolicySource(path)
    assert "needs torch.nn.modules.container.Sequential to load" in str(info.value)
    assert "(refused as not weights-only; nothing was run)" in str(info.value)
    assert "torch.save(model.state_dict(), path)" in str(info.value)


class Payload:
    """Unpickling this runs ``exec`` (it writes a file): the attack weights_only stops."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({str(self.marker)!r}, 'w').close()",))


def test_a_malicious_pickle_payload_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pt"
    torch.save({"0.weight": torch.zeros(4, 8), "trap": Payload(marker)}, path)
    with pytest.raises(ScenarioError, match=r"needs exec to load.*nothing was run"):
        PolicySource(path)
    assert not marker.exists()


def test_wrong_shapes_and_non_finite_outputs_are_errors_not_crashes(tmp_path, mlp):
    path = tmp_path / "virtue.pt"
    torch.save(mlp.state_dict(), path)
    source = PolicySource(path)
    short, three, good = source.beliefs(
        [req((1.0, 2.0)), req(OBS[0], ("left", "right", "straight")), req(OBS[1])]
    )
    assert short.status == "error" and "observations of 2 values" in short.extra["error"]
    assert three.status == "error" and "expected (1, 3)" in three.extra["error"]
    assert np.allclose(short.belief, 0.25) and np.allclose(three.belief, 1 / 3)
    assert good.status == "ok"

    broken = {k: torch.full_like(v, float("nan")) for k, v in mlp.state_dict().items()}
    torch.save(broken, tmp_path / "nan.pt")
    (result,) = PolicySource(tmp_path / "nan.pt").beliefs([req(OBS[0])])
    assert result.status == "error" and "nan" in result.extra["error"]


def test_missing_file_and_bad_activation_name_the_fix(tmp_path, mlp):
    with pytest.raises(ScenarioError, match=r"policy file .*nope\.pt not found; fix the path"):
        PolicySource(tmp_path / "nope.pt")
    torch.save(mlp.state_dict(), tmp_path / "v.pt")
    with pytest.raises(ScenarioError, match="activation expects one of tanh, relu"):
        PolicySource(tmp_path / "v.pt", activation="swish")
