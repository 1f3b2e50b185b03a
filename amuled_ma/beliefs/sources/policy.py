"""``policy``: a saved torch policy's softmax over its logits (``docs/beliefs.md``, "policy")."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from amuled_ma.beliefs.replies.validate import check_belief, show_values
from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource, in_order, indices_by
from amuled_ma.errors import CheckpointError, ScenarioError
from amuled_ma.files.hashing import sha256_file
from amuled_ma.files.torch_load import load_weights_only

#: Activations of an inferred MLP (``torch.nn`` class names).
ACTIVATIONS = {
    "tanh": "Tanh",
    "relu": "ReLU",
    "elu": "ELU",
    "selu": "SELU",
    "lrelu": "LeakyReLU",
    "sigmoid": "Sigmoid",
    "identity": "Identity",
}

_LAYER = re.compile(r"^(?P<prefix>.*?)(?P<index>\d+)\.(?P<kind>weight|bias)$")
_FIX = (
    "save the weights only, e.g. torch.save(model.state_dict(), path), and name the "
    "network with module = 'pkg.module:Class' unless it is a plain MLP"
)


def load_weights(path: str | Path, key: str = "") -> dict[str, Any]:
    """The state dict at dotted ``key`` (``""``: the top) of a file, read ``weights_only=True``.

    `ScenarioError` naming the file and the fix: missing, needs Python objects (refused, nothing
    ran), not a dict of tensors, or no ``key``.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise ScenarioError(
            f"policy file {path} not found; fix the path (relative to the scenario file)"
        )
    try:
        data = load_weights_only(path, "policy file")
    except CheckpointError as error:
        raise ScenarioError(f"{error}; {_FIX}") from None
    where = "the file"
    for part in [p for p in key.split(".") if p] if key else []:
        if not isinstance(data, Mapping) or part not in data:
            keys = ", ".join(map(str, data)) if isinstance(data, Mapping) else type(data).__name__
            raise ScenarioError(
                f"policy file {path}: key {key!r}: {where} has no {part!r} (it has: {keys}); "
                "fix key"
            )
        data, where = data[part], f"{where}[{part!r}]"
    if not isinstance(data, Mapping) or not data:
        raise ScenarioError(
            f"policy file {path}: {where} is not a state dict (found "
            f"{type(data).__name__}); expected {{name: tensor}}; {_FIX}"
        )
    tensors = {str(k): v for k, v in data.items() if isinstance(v, torch.Tensor)}
    if not tensors:
        nested = [str(k) for k, v in data.items() if isinstance(v, Mapping)]
        hint = f"; name the state dict with key = {nested[0]!r}" if nested else ""
        raise ScenarioError(
            f"policy file {path}: {where} holds no tensors (keys: "
            f"{', '.join(map(str, data))}){hint}"
        )
    return tensors


def infer_mlp(
    weights: Mapping[str, Any], activation: str = "tanh", *, where: str = "policy"
) -> Any:
    """The eval-mode ``Sequential`` MLP ``weights`` describe, loaded, ``activation`` between layers.

    ``weights`` is ``{"<prefix><i>.weight": (out, in), "<prefix><i>.bias": (out,), ...}``;
    anything else raises `ScenarioError` naming ``where``.
    """
    import torch

    if activation not in ACTIVATIONS:
        raise ScenarioError(
            f"{where}: activation expects one of {', '.join(ACTIVATIONS)}, found {activation!r}"
        )
    groups: dict[str, dict[int, dict[str, Any]]] = {}
    for name, tensor in weights.items():
        match = _LAYER.match(name)
        if match:
            layer = groups.setdefault(match["prefix"], {}).setdefault(int(match["index"]), {})
            layer[match["kind"]] = tensor
    fix = "or name the network's class with module = 'pkg.module:Class'"
    if len(groups) != 1:
        raise ScenarioError(
            f"{where}: cannot infer an MLP: expected the linear layers of one network "
            f"('<prefix><i>.weight' / '.bias'), found {sorted(weights)[:8]}; name the state "
            f"dict with key = '...' {fix}"
        )
    ((prefix, layers),) = groups.items()
    modules: list[Any] = []
    previous_out = None
    for position, index in enumerate(sorted(layers)):
        parts = layers[index]
        weight, bias = parts.get("weight"), parts.get("bias")
        bad_bias = bias is not None and weight is not None and bias.shape != weight.shape[:1]
        if weight is None or weight.ndim != 2 or bad_bias:
            raise ScenarioError(
                f"{where}: cannot infer an MLP: layer {prefix}{index} is not linear (weight "
                f"{None if weight is None else tuple(weight.shape)}, bias "
                f"{None if bias is None else tuple(bias.shape)}) {fix}"
            )
        if previous_out is not None and weight.shape[1] != previous_out:
            raise ScenarioError(
                f"{where}: cannot infer an MLP: layer {prefix}{index} takes {weight.shape[1]} "
                f"inputs, the layer before gives {previous_out} {fix}"
            )
        if position:
            modules.append(getattr(torch.nn, ACTIVATIONS[activation])())
        linear = torch.nn.Linear(weight.shape[1], weight.shape[0], bias=bias is not None)
        with torch.no_grad():
            linear.weight.copy_(weight)
            if bias is not None:
                linear.bias.copy_(bias)
        modules.append(linear)
        previous_out = weight.shape[0]
    return torch.nn.Sequential(*modules).eval()


class PolicySource(BeliefSource):
    """Beliefs from a saved torch policy; `ScenarioError` as `load_weights` and `infer_mlp`."""

    name = "policy"
    needs_messages = False

    def __init__(
        self,
        path: str | Path,
        *,
        key: str = "",
        module: str = "",
        kwargs: Mapping[str, Any] | None = None,
        activation: str = "tanh",
    ) -> None:
        import torch

        self.path = Path(path)
        self.key = key
        self.module_name = module
        self.kwargs = dict(kwargs or {})
        self.activation = activation
        weights = load_weights(self.path, key)
        self.sha256 = sha256_file(self.path)  # in 1 MiB blocks, not the file at once
        where = f"policy file {self.path}"
        if module:
            from amuled_ma.beliefs.sources.rules import resolve_callable

            cls = resolve_callable(module, f"{where}: module")
            try:
                net = cls(**self.kwargs)
            except Exception as error:
                raise ScenarioError(
                    f"{where}: module {module!r}({show_values(self.kwargs)}) failed: {error}; "
                    "fix kwargs"
                ) from error
            if not isinstance(net, torch.nn.Module):
                raise ScenarioError(
                    f"{where}: module {module!r} built {type(net).__name__}, expected a "
                    "torch.nn.Module"
                )
            try:
                net.load_state_dict(weights)
            except Exception as error:
                first = str(error).strip().splitlines()[0]
                raise ScenarioError(
                    f"{where}: the weights do not fit {module!r}: {first}; fix key or the "
                    "module's kwargs"
                ) from None
            self.net = net.eval()
        else:
            self.net = infer_mlp(weights, activation, where=where)

    def identity(self) -> dict[str, Any]:
        """Return the file's name and content hash and how the network is built."""
        return {
            "source": self.name,
            "file": self.path.name,
            "sha256": self.sha256,
            "key": self.key,
            "module": self.module_name,
            "kwargs": dict(sorted(self.kwargs.items())),
            "activation": self.activation if not self.module_name else None,
        }

    def beliefs(self, requests: Sequence[BeliefRequest]) -> list[BeliefResult]:
        """One forward pass per (observation length, action count); softmax of the logits."""
        pairs: list[tuple[int, BeliefResult]] = []
        for (_, n), indices in indices_by(requests, lambda r: (len(r.obs), r.num_actions)).items():
            probs, error = self._forward([requests[i].obs for i in indices], n)
            for j, i in enumerate(indices):
                if probs is None:
                    pairs.append((i, self._error(n, error or "no output")))
                    continue
                belief, reason = check_belief(probs[j], n, scores=True)
                pairs.append(
                    (i, BeliefResult(belief=belief, status="ok", source=self.name))
                    if belief is not None
                    else (i, self._error(n, f"the policy's belief {reason}"))
                )
        return in_order(pairs, len(requests), self.name)

    def _forward(
        self, rows: list[tuple[float, ...]], n: int
    ) -> tuple[np.ndarray | None, str | None]:
        import torch

        try:
            with torch.no_grad():
                obs = torch.as_tensor(np.asarray(rows, dtype=np.float32))
                logits = self.net(obs)
                is_tensor = isinstance(logits, torch.Tensor)
                if not is_tensor or tuple(logits.shape) != (len(rows), n):
                    shape = tuple(logits.shape) if is_tensor else type(logits).__name__
                    return None, (
                        f"the policy gave output {shape} for {len(rows)} observation(s) of "
                        f"{len(rows[0])} values, expected ({len(rows)}, {n}): one logit per action"
                    )
                probs = torch.softmax(logits.to(torch.float64), dim=-1)
        except Exception as error:  # a shape mismatch inside the network, say
            first = str(error).strip().splitlines()
            return None, (
                f"the policy failed on observations of {len(rows[0])} values: "
                f"{first[0] if first else type(error).__name__}"
            )
        return probs.numpy(), None

    def _error(self, n: int, reason: str) -> BeliefResult:
        return BeliefResult.failed(
            n, "error", self.name, f"{reason} (policy file {self.path.name})"
        )
