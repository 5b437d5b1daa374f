"""Import EPyMARL agents (MARBLER's paper models) as marbler-jax numpy policies, without torch.

MARBLER's models are EPyMARL agent state dicts saved by ``torch.save``: a zip holding ``<root>/data.pkl``
(a pickle of an ``OrderedDict`` whose tensors point at raw storages by key) and the storages as
``<root>/data/<key>``. :func:`read_state_dict` reads one with a restricted unpickler that knows only the
few globals such a file names (``OrderedDict``, torch's tensor rebuild function and storage types), so a
crafted file cannot run code, and numpy (torch is not needed).

:func:`convert` maps the agent to the numpy policy format (:mod:`marbler_jax.numpy_policy`), kind
``q_agent`` with a GRU cell, whose equations are torch's ``GRUCell`` exactly (its hidden biases
``b_hr``, ``b_hz``, ``b_hn`` are kept as ``gru.hr.bias``, ``gru.hz.bias``, ``gru.hn.bias``):

* ``agent: rnn`` -- one network shared by the robots, fed the one-hot agent ID when ``obs_agent_id``
  (VDN, QMIX; MAPPO's actor is the same network, its outputs logits);
* ``agent: rnn_ns`` -- one network per robot (QMIX_NS), parameters stacked on a leading agent axis.

Greedy actions are the argmax of the outputs, as MARBLER's ``main.py`` picks them; the hidden state
starts at zero each episode.
"""
from __future__ import annotations

import json
import pickle
import re
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np

from marbler_jax.numpy_policy import FORMAT, NumpyPolicy

AGENTS = ("rnn", "rnn_ns")
"""EPyMARL agent types the importer converts (``agent`` in the model's config)."""

_STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16,
    "CharStorage": np.int8, "ByteStorage": np.uint8, "BoolStorage": np.bool_,
}


class _StorageType:
    def __init__(self, name: str):
        self.dtype = np.dtype(_STORAGE_DTYPES[name]).newbyteorder("<")


def _rebuild_tensor(storage, offset, size, stride, *_):
    """torch's ``_rebuild_tensor_v2`` in numpy: a view of ``storage`` with element ``offset`` and strides."""
    item = storage.itemsize
    view = np.lib.stride_tricks.as_strided(storage[offset:], shape=tuple(size),
                                           strides=tuple(s * item for s in stride))
    return np.array(view)          # owns its memory, C order


class _Unpickler(pickle.Unpickler):
    """Unpickles a torch state dict; refuses every global that such a file does not need."""

    def __init__(self, file, load_storage):
        super().__init__(file)
        self._load_storage = load_storage

    def find_class(self, module, name):
        if (module, name) == ("collections", "OrderedDict"):
            return OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in a model state dict")

    def persistent_load(self, pid):
        kind, storage_type, key, _location, numel = pid[:5]
        if kind != "storage" or not isinstance(storage_type, _StorageType):
            raise pickle.UnpicklingError(f"unsupported persistent id {pid!r}")
        return self._load_storage(str(key), storage_type.dtype, int(numel))


def read_state_dict(path) -> dict[str, np.ndarray]:
    """The tensors of a ``torch.save`` state dict file (zip format) as numpy arrays, by name."""
    path = Path(path)
    try:
        archive = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as err:
        raise ValueError(f"{path} is not a PyTorch state dict (zip format): {err}") from None
    with archive:
        pickles = [n for n in archive.namelist() if n.endswith("/data.pkl") or n == "data.pkl"]
        if len(pickles) != 1:
            raise ValueError(f"{path} is not a PyTorch state dict: expected one data.pkl, found {pickles}")
        root = pickles[0][:-len("data.pkl")]

        def load_storage(key, dtype, numel):
            try:
                raw = archive.read(f"{root}data/{key}")
            except KeyError:
                raise ValueError(f"{path}: storage {key!r} is missing") from None
            if len(raw) < numel * dtype.itemsize:
                raise ValueError(f"{path}: storage {key!r} holds {len(raw)} bytes, expected {numel * dtype.itemsize}")
            return np.frombuffer(raw, dtype, numel)

        with archive.open(pickles[0]) as f:
            try:
                state = _Unpickler(f, load_storage).load()
            except (pickle.UnpicklingError, EOFError, TypeError, AttributeError) as err:
                raise ValueError(f"cannot read {path}: {err}") from None
    if not isinstance(state, dict) or not all(isinstance(v, np.ndarray) for v in state.values()):
        raise ValueError(f"{path} holds no state dict of tensors")
    return dict(state)


def _linear(tensors: dict, prefix: str, name: str) -> dict[str, np.ndarray]:
    """torch ``Linear`` (``weight [out, in]``) as a numpy policy dense layer (``kernel [in, out]``)."""
    return {f"{name}.kernel": tensors[f"{prefix}{name}.weight"].T, f"{name}.bias": tensors[f"{prefix}{name}.bias"]}


def _gru(tensors: dict, prefix: str) -> dict[str, np.ndarray]:
    """torch ``GRUCell`` (gates stacked r, z, n in ``weight_ih [3H, in]``, ``weight_hh [3H, H]``) as
    the numpy policy's ``gru.{i,h}{r,z,n}`` dense layers, every bias kept where torch adds it."""
    out = {}
    for side in ("i", "h"):
        weight, bias = tensors[f"{prefix}rnn.weight_{side}h"], tensors[f"{prefix}rnn.bias_{side}h"]
        for gate, w, b in zip("rzn", np.split(weight, 3), np.split(bias, 3)):
            out[f"gru.{side}{gate}.kernel"] = w.T
            out[f"gru.{side}{gate}.bias"] = b
    return out


def _agent_tensors(tensors: dict, prefix: str) -> dict[str, np.ndarray]:
    try:
        return {**_linear(tensors, prefix, "fc1"), **_gru(tensors, prefix), **_linear(tensors, prefix, "fc2")}
    except KeyError as err:
        raise ValueError(f"the state dict lacks {err.args[0]!r} (keys: {sorted(tensors)})") from None


def convert(tensors: dict[str, np.ndarray], config: dict, num_agents: int, obs_dim: int,
            num_actions: int) -> tuple[dict, dict[str, np.ndarray]]:
    """``(spec, tensors)`` of the numpy policy for an EPyMARL agent's state dict and its config (the
    model's ``.json``), for a team of ``num_agents`` robots seeing ``obs_dim`` features with
    ``num_actions`` actions each. Raises ``ValueError`` naming what does not fit."""
    agent = config.get("agent")
    if agent not in AGENTS:
        raise ValueError(f"EPyMARL agent {agent!r} is not supported; supported: {list(AGENTS)}")
    if not config.get("use_rnn", True):
        raise ValueError("use_rnn=false agents (a Linear layer in place of the GRU) are not supported")
    if config.get("obs_last_action"):
        raise ValueError("obs_last_action=true agents are not supported (MARBLER's models do not use it)")
    hidden = int(config["hidden_dim"])
    shared = agent == "rnn"
    if not shared and config.get("obs_agent_id"):
        raise ValueError("rnn_ns agents with obs_agent_id=true are not supported (MARBLER's models do not use it)")
    agent_ids = bool(config.get("obs_agent_id")) and shared
    if shared:
        params = _agent_tensors(tensors, "")
    else:
        indices = sorted({int(m.group(1)) for k in tensors if (m := re.match(r"agents\.(\d+)\.", k))})
        if indices != list(range(num_agents)):
            raise ValueError(f"rnn_ns state dict holds agents {indices}, but the scenario has {num_agents} robots")
        per_agent = [_agent_tensors(tensors, f"agents.{i}.") for i in indices]
        params = {name: np.stack([p[name] for p in per_agent]) for name in per_agent[0]}
    params = {name: np.ascontiguousarray(value, np.float32) for name, value in params.items()}
    width = obs_dim + (num_agents if agent_ids else 0)
    if params["fc1.kernel"].shape[-2:] != (width, hidden) or params["fc2.kernel"].shape[-1] != num_actions:
        raise ValueError(f"the model takes {params['fc1.kernel'].shape[-2]} inputs and gives "
                         f"{params['fc2.kernel'].shape[-1]} outputs; the scenario needs {width} inputs "
                         f"({obs_dim} observation features{f' + {num_agents} agent IDs' if agent_ids else ''}) "
                         f"and {num_actions} actions")
    spec = dict(format=FORMAT, kind="q_agent", recurrent=True, cell="gru", shared=shared, agent_ids=agent_ids,
                layer_norm=False, last_action=False, num_agents=num_agents, obs_dim=obs_dim,
                num_actions=num_actions, hidden=hidden, activation="relu", layers=[],
                origin=dict(source="epymarl", agent=agent, name=config.get("name"), mixer=config.get("mixer"),
                            outputs=config.get("agent_output_type")))
    return spec, params


def algorithm_name(config: dict) -> str:
    """marbler-jax's name for the algorithm an EPyMARL config trained (``mappo``, ``vdn``, ``qmix``,
    ``qmix_ns``, or the config's own ``name``)."""
    if config.get("agent_output_type") == "pi_logits":
        return "mappo" if config.get("agent") == "rnn" else "ippo_ns"
    mixer = config.get("mixer")
    if mixer in ("vdn", "qmix"):
        return mixer + ("_ns" if config.get("agent") == "rnn_ns" else "")
    return str(config.get("name", "epymarl"))


def _read_config(config_path) -> dict:
    try:
        config = json.loads(Path(config_path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"cannot read the model config {config_path}: {err}") from None
    if not isinstance(config, dict):
        raise ValueError(f"{config_path} holds no EPyMARL config object")
    return config


def load_model(model_path, config_path, num_agents: int, obs_dim: int, num_actions: int) -> NumpyPolicy:
    """The numpy policy of an EPyMARL model file and its ``.json`` config (in memory)."""
    spec, tensors = convert(read_state_dict(model_path), _read_config(config_path), num_agents, obs_dim, num_actions)
    return NumpyPolicy(spec, tensors)


def import_model(model_path, config_path, scenario: str, out, env_overrides: dict | None = None,
                 force: bool = False) -> dict:
    """Convert an EPyMARL model for ``scenario`` into the numpy policy folder ``out``; returns its spec.

    The spec records the scenario and ``env_overrides`` (default: MARBLER's protocol, where MARBLER's
    models trained), so ``marbler-jax evaluate OUT`` runs the policy where it was trained. ``out`` is
    replaced only when empty or an earlier policy folder (or ``force``)."""
    import marbler_jax

    from .export import write_policy

    env_overrides = {"protocol": "marbler"} if env_overrides is None else dict(env_overrides)
    env = marbler_jax.make(scenario, **env_overrides)
    config = _read_config(config_path)
    spec, tensors = convert(read_state_dict(model_path), config, env.num_agents, env.obs_dim, env.num_actions)
    spec = dict(spec, algo=algorithm_name(config), scenario=env.name, env=env_overrides,
                origin=dict(spec["origin"], model=Path(model_path).name))
    return write_policy(spec, tensors, out, force).spec


__all__ = ["read_state_dict", "convert", "load_model", "import_model", "algorithm_name", "AGENTS"]
