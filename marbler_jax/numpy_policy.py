"""Trained policies in plain numpy: load an exported policy folder and act greedily.

This module imports numpy only (no JAX), so it runs where JAX is not installed (the Robotarium
server). A policy folder, written by ``marbler-jax export`` (:mod:`marbler_jax_rl.export`), is flat:

* ``policy_spec.npy`` -- a 0-d unicode array holding JSON: ``format``, ``kind`` (``"q_agent"`` for
  VDN/QMIX/QMIX_NS, ``"actor"`` for IPPO/MAPPO), ``recurrent``, ``cell`` (``"gru"``, ``"mingru"``
  or ``"none"``; absent from specs written before it existed, where it is ``"gru"`` if ``recurrent``), ``shared``, ``agent_ids``,
  ``layer_norm`` (Q-agents; absent from earlier specs: false), ``last_action`` (Q-agents
  that also see the one-hot of their previous action; absent from earlier specs: false), ``num_agents``, ``obs_dim``,
  ``num_actions``, ``hidden``, ``activation``, ``layers`` (actor MLP layer names in order),
  ``tensors`` (parameter name -> file name) and ``sha256`` (file name -> SHA-256 of its bytes, checked
  at load; absent from earlier specs: unchecked).
* one ``.npy`` per parameter tensor (``float32``; with a leading agent axis when not shared).

Everything loads with ``np.load(path, allow_pickle=False)``. Network equations (the same as the
flax modules in ``algorithms/networks.py``):

* ``q_agent``: the input is the observation, then with ``last_action`` the one-hot of the agent's
  previous action (zeros at the first step), then with ``shared`` and ``agent_ids`` the agent-ID
  one-hot; ``x = relu(input W_fc1 + b)`` (with ``layer_norm``, every ``relu(y)`` of a hidden
  layer is ``relu(LN(y))``, ``LN(y) = (y - mean(y)) / sqrt(var(y) + 1e-6) * scale + bias`` over the
  last axis, parameters ``ln1`` after ``fc1`` and ``ln_out`` after ``fc_out`` / ``fc_hidden``); recurrent: a GRU cell --
  ``r = s(x W_ir + b_ir + h W_hr [+ b_hr])``, ``z = s(x W_iz + b_iz + h W_hz [+ b_hz])``,
  ``n = tanh(x W_in + b_in + r * (h W_hn + b_hn))``, ``h' = (1 - z) n + z h``, ``x = h'`` (flax's
  ``GRUCell`` has no ``b_hr`` / ``b_hz``; torch's, in imported EPyMARL agents, has them);
  minimal GRU: ``[g_z, g_c] = x W_mingru + b``, ``z = s(g_z)``, ``h' = (1 - z) h + z g_c``,
  ``x = relu(h' W_fc_out + b)``; feed-forward: ``x = relu(x W_fc_hidden + b)``; ``q = x W_fc2 + b``.
* ``actor``: ``Dense -> act -> ... -> Dense`` (logits).

Greedy action = argmax over the last axis (first maximum on ties, as ``jnp.argmax``). The memory a
Q-agent carries from step to step is ``[N, M]``: its hidden state (width ``hidden``; 1 for
feed-forward agents), followed with ``last_action`` by the one-hot of the action it took.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from marbler_jax.xp import namespace

FORMAT = "marbler-jax-policy/1"
SPEC_FILE = "policy_spec.npy"
CELLS = ("gru", "mingru", "none")      # a Q-agent's memory (marbler_jax_rl.networks.QAgent uses the same names)


def _sigmoid(x, xp=np):
    """The logistic function, as ``(1 + tanh(x / 2)) / 2``: no overflow for large negative ``x``."""
    return 0.5 * (1.0 + xp.tanh(0.5 * x))


class NumpyPolicy:
    """A greedy multi-agent policy: ``act(obs [N, D], hidden) -> (actions [N], hidden, values)``."""

    def __init__(self, spec: dict, tensors: dict[str, np.ndarray]):
        if spec.get("format") != FORMAT:
            raise ValueError(f"unsupported policy format {spec.get('format')!r}; expected {FORMAT!r}")
        self.spec = spec
        self.t = tensors
        self.num_agents = int(spec["num_agents"])
        self.obs_dim = int(spec["obs_dim"])
        self.recurrent = bool(spec["kind"] == "q_agent" and spec["recurrent"])
        self.cell = spec.get("cell", "gru") if self.recurrent else "none"
        self.layer_norm = bool(spec.get("layer_norm", False))
        self.last_action = bool(spec["kind"] == "q_agent" and spec.get("last_action", False))
        self.num_actions = spec.get("num_actions")
        if self.last_action and not isinstance(self.num_actions, int):
            raise ValueError(f"a policy with last_action needs num_actions in its spec, got {self.num_actions!r}")
        if self.cell not in CELLS:
            raise ValueError(f"unsupported recurrent cell {self.cell!r} in the policy spec; "
                             f"expected one of {list(CELLS)}")
        self._check_tensors()

    def _check_tensors(self) -> None:
        """Every tensor finite, the first layer's input and the last layer's output the widths the spec
        implies, and one forward pass through all of them; each error names the tensor."""
        for name, tensor in self.t.items():
            if not np.issubdtype(tensor.dtype, np.floating):
                raise ValueError(f"policy tensor {name!r} has dtype {tensor.dtype}, expected floating point")
            if not np.all(np.isfinite(tensor)):
                raise ValueError(f"policy tensor {name!r} holds non-finite values (NaN or inf)")
        actor = self.spec["kind"] == "actor"
        first, last = (self.spec["layers"][0], self.spec["layers"][-1]) if actor else ("fc1", "fc2")
        for layer in (first, last):
            if f"{layer}.kernel" not in self.t:
                raise ValueError(f"policy tensor {layer + '.kernel'!r} is missing (tensors: {sorted(self.t)})")
        width = self.obs_dim + (self.num_actions if self.last_action else 0)
        width += self.num_agents if self.spec["agent_ids"] and self.spec["shared"] else 0
        kernel_in, kernel_out = self.t[f"{first}.kernel"], self.t[f"{last}.kernel"]
        if kernel_in.shape[-2] != width:
            raise ValueError(f"policy tensor {first + '.kernel'!r} takes {kernel_in.shape[-2]} inputs, but the spec "
                             f"gives {width} (observation, previous action, agent ID)")
        if isinstance(self.num_actions, int) and kernel_out.shape[-1] != self.num_actions:
            raise ValueError(f"policy tensor {last + '.kernel'!r} has {kernel_out.shape[-1]} outputs for "
                             f"{self.num_actions} actions")
        if not self.spec["shared"] and any(t.shape[0] != self.num_agents for t in self.t.values()):
            odd = sorted(name for name, t in self.t.items() if t.shape[0] != self.num_agents)
            raise ValueError(f"per-agent policy tensors {odd} lack the leading axis of {self.num_agents} agents")
        try:
            self.values(np.zeros((self.num_agents, self.obs_dim), np.float32))
        except (ValueError, KeyError) as err:
            raise ValueError(f"the policy's tensors do not fit together: {err}") from None

    @property
    def hidden_width(self) -> int:
        """Width of the hidden state in the memory (1 for memoryless policies)."""
        return int(self.spec["hidden"]) if self.recurrent else 1

    def initial_hidden(self) -> np.ndarray:
        """Zero memory ``[N, M]``: ``M = H`` (1 for memoryless policies), plus the number of actions
        with ``last_action`` (no previous action yet)."""
        width = self.hidden_width + (self.num_actions if self.last_action else 0)
        return np.zeros((self.num_agents, width), np.float32)

    def _dense(self, name, x):
        kernel, bias = self.t[f"{name}.kernel"], self.t.get(f"{name}.bias")
        if self.spec["shared"]:
            y = x @ kernel
        else:                      # per-agent parameters: agent i's kernel on agent i's row
            y = namespace(x).einsum("...ni,nio->...no", x, kernel)
        return y if bias is None else y + bias

    def _relu_layer(self, name, norm, x):
        """``relu(x W + b)``, layer-normalised first (flax ``LayerNorm``: epsilon 1e-6) with ``layer_norm``."""
        xp = namespace(x)
        y = self._dense(name, x)
        if self.layer_norm:
            mean = y.mean(-1, keepdims=True)
            var = xp.square(y - mean).mean(-1, keepdims=True)
            y = (y - mean) / xp.sqrt(var + 1e-6) * self.t[f"{norm}.scale"] + self.t[f"{norm}.bias"]
        return xp.maximum(y, 0)

    def inputs(self, obs, last=None) -> np.ndarray:
        """Network inputs of ``obs [..., N, D]`` (``last [..., N, A]``: the previous actions' one-hot,
        used with ``last_action``)."""
        xp = namespace(obs, last)
        obs = xp.asarray(obs, xp.float32)
        if obs.shape[-2:] != (self.num_agents, self.obs_dim):
            raise ValueError(f"observations must be [..., {self.num_agents}, {self.obs_dim}], got {obs.shape}")
        if self.last_action:
            obs = xp.concatenate([obs, xp.broadcast_to(last, obs.shape[:-1] + (self.num_actions,))], axis=-1)
        if self.spec["agent_ids"] and self.spec["shared"]:
            ids = xp.broadcast_to(xp.eye(self.num_agents, dtype=xp.float32), obs.shape[:-1] + (self.num_agents,))
            obs = xp.concatenate([obs, ids], axis=-1)
        return obs

    def values(self, obs, hidden=None):
        """``(Q-values or logits [..., N, A], new memory [..., N, M])`` for ``obs [..., N, D]`` and the
        memory ``hidden`` (``None``: the initial one); with ``last_action`` the new memory holds the
        greedy action's one-hot. numpy in, numpy out; JAX arrays in (e.g. under ``jax.jit``), JAX out."""
        xp = namespace(obs, hidden)
        if hidden is not None:
            hidden = xp.asarray(hidden, xp.float32)
        last = None
        if self.last_action:
            memory = self.initial_hidden() if hidden is None else hidden
            hidden, last = memory[..., :self.hidden_width], memory[..., self.hidden_width:]
        x = self.inputs(obs, last)
        if self.spec["kind"] == "actor":
            act = {"tanh": xp.tanh, "relu": lambda v: xp.maximum(v, 0)}[self.spec["activation"]]
            layers = self.spec["layers"]
            for name in layers[:-1]:
                x = act(self._dense(name, x))
            return self._dense(layers[-1], x), hidden
        x = self._relu_layer("fc1", "ln1", x)
        if self.recurrent:
            h = self.initial_hidden() if hidden is None else hidden
        if self.cell == "gru":
            r = _sigmoid(self._dense("gru.ir", x) + self._dense("gru.hr", h), xp)
            z = _sigmoid(self._dense("gru.iz", x) + self._dense("gru.hz", h), xp)
            n = xp.tanh(self._dense("gru.in", x) + r * self._dense("gru.hn", h))
            hidden = (1.0 - z) * n + z * h
            x = hidden
        elif self.cell == "mingru":
            gates = self._dense("mingru", x)
            width = h.shape[-1]
            z = _sigmoid(gates[..., :width], xp)
            hidden = (1.0 - z) * h + z * gates[..., width:]
            x = self._relu_layer("fc_out", "ln_out", hidden)
        else:
            x = self._relu_layer("fc_hidden", "ln_out", x)
        values = self._dense("fc2", x)
        if self.last_action:
            greedy = xp.eye(self.num_actions, dtype=xp.float32)[xp.argmax(values, axis=-1)]
            hidden = xp.concatenate([xp.broadcast_to(hidden, greedy.shape[:-1] + hidden.shape[-1:]), greedy], -1)
        return values, hidden

    def act(self, obs, hidden=None):
        """Greedy actions ``[..., N]`` (int32), the new hidden state and the values."""
        values, hidden = self.values(obs, hidden)
        xp = namespace(values)
        return xp.argmax(values, axis=-1).astype(xp.int32), hidden, values


def load_policy(folder) -> NumpyPolicy:
    """Load a policy folder written by ``marbler-jax export``; clear errors for missing/corrupt files."""
    folder = Path(folder)
    spec_path = folder / SPEC_FILE
    if not spec_path.exists():
        raise ValueError(f"{folder} holds no {SPEC_FILE}; export a run with `marbler-jax export RUN --out {folder}`")
    try:
        spec = json.loads(str(np.load(spec_path, allow_pickle=False)))
        for file, digest in spec.get("sha256", {}).items():
            if file_sha256(folder / file) != digest:
                raise ValueError(f"{folder / file} changed after export (checksum mismatch with {SPEC_FILE})")
        tensors = {name: np.load(folder / file, allow_pickle=False) for name, file in spec["tensors"].items()}
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"cannot load the policy in {folder}: {err}") from err
    return NumpyPolicy(spec, tensors)


def file_sha256(path) -> str:
    """Hex SHA-256 of a file's bytes (what a spec's ``sha256`` entries hold), read in 1 MiB blocks."""
    sha = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            sha.update(block)
    return sha.hexdigest()


__all__ = ["NumpyPolicy", "load_policy", "file_sha256", "FORMAT", "SPEC_FILE", "CELLS"]
