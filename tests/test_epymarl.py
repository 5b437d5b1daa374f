"""``marbler-jax import``: MARBLER's paper models (EPyMARL GRU agents) read without torch act as MARBLER's
own torch agents do, in numpy and in JAX.

``tests/data/epymarl_forward.npz`` holds, for each of the 16 models, MARBLER's torch forward pass on an
observation sequence that MARBLER's code recorded (``scripts/make_epymarl_fixture.py``). The models
themselves are read from ``../shared/marbler``; those tests skip where it is absent."""
from __future__ import annotations

import io
import json
import pickle
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax.numpy_policy import load_policy
from marbler_jax.rollout import numpy_policy_greedy
from marbler_jax_rl.cli import main as cli
from marbler_jax_rl.epymarl import algorithm_name, convert, import_model, read_state_dict

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO.parent / "shared" / "marbler" / "robotarium_gym" / "scenarios"
FIXTURE = np.load(REPO / "tests" / "data" / "epymarl_forward.npz")
SCENARIOS = {"PredatorCapturePrey": "predator_capture_prey", "Warehouse": "warehouse",
             "MaterialTransport": "material_transport", "ArcticTransport": "arctic_transport"}
ALGOS = ("mappo", "qmix", "qmix_ns", "vdn")
MODEL_CASES = [(s, a) for s in SCENARIOS for a in ALGOS]


def _model(scenario, algo):
    if not MODELS.is_dir():
        pytest.skip(f"MARBLER's models are not at {MODELS}")
    return MODELS / scenario / "models" / f"{algo}.th", MODELS / scenario / "models" / f"{algo}.json"


@pytest.mark.parametrize("scenario,algo", MODEL_CASES)
def test_imported_model_acts_as_marblers_torch_agent(scenario, algo, tmp_path):
    model, config = _model(scenario, algo)
    spec = import_model(model, config, SCENARIOS[scenario], tmp_path / "policy")
    assert spec["algo"] == algo and spec["env"] == {"protocol": "marbler"}
    policy = load_policy(tmp_path / "policy")
    obs = FIXTURE[f"{scenario}/obs"]
    expected_values, expected_actions = FIXTURE[f"{scenario}/{algo}/values"], FIXTURE[f"{scenario}/{algo}/actions"]
    hidden = None
    for t in range(len(obs)):                  # MARBLER's loop: hidden state carried from step to step
        actions, hidden, values = policy.act(obs[t], hidden)
        np.testing.assert_allclose(values, expected_values[t], atol=2e-5, rtol=1e-5, err_msg=f"step {t}")
        np.testing.assert_array_equal(actions, expected_actions[t], err_msg=f"step {t}")

    # the same forward pass on JAX arrays (how `evaluate` runs it), jitted and scanned over the sequence
    def scan_step(carry, step_obs):
        actions, carry, values = policy.act(step_obs, carry)
        return carry, (actions, values)

    _, (actions, values) = jax.jit(lambda o: jax.lax.scan(scan_step, jnp.zeros(policy.initial_hidden().shape), o))(
        jnp.asarray(obs))
    np.testing.assert_allclose(np.asarray(values), expected_values, atol=2e-5, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(actions), expected_actions)


def test_a_first_step_clears_the_memory_in_batched_rollouts():
    """``numpy_policy_greedy`` zeroes the hidden state of the envs whose episode starts, only theirs."""
    model, config = _model("PredatorCapturePrey", "vdn")
    from marbler_jax_rl.epymarl import load_model

    policy = load_model(model, config, 4, 16, 5)
    greedy = numpy_policy_greedy(policy)
    obs = jnp.asarray(FIXTURE["PredatorCapturePrey/obs"][3:5])             # two envs
    carry = jnp.ones((2,) + policy.initial_hidden().shape)
    actions, new = greedy.step(None, obs, carry, jnp.array([True, False]))
    fresh_actions, fresh, _ = policy.act(np.asarray(obs[0]), None)
    carried_actions, carried, _ = policy.act(np.asarray(obs[1]), np.ones(policy.initial_hidden().shape))
    np.testing.assert_allclose(np.asarray(new), np.stack([fresh, carried]), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(actions), np.stack([fresh_actions, carried_actions]))


def _torch_zip(path: Path, pickled: bytes, storages: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("agent/data.pkl", pickled)
        for key, raw in storages.items():
            archive.writestr(f"agent/data/{key}", raw)
        archive.writestr("agent/version", "3\n")
    return path


def _state_dict_bytes(tensors: dict[str, tuple[str, tuple, tuple, int]]) -> bytes:
    """A torch-format ``data.pkl`` for ``name -> (storage key, size, stride, offset)`` float tensors,
    written with the same pickle opcodes torch uses (a reduce of ``torch._utils._rebuild_tensor_v2`` on a
    persistent storage id)."""
    class Pickler(pickle.Pickler):
        def persistent_id(self, obj):
            return obj if isinstance(obj, tuple) and obj and obj[0] == "storage" else None

    class Rebuild:
        def __init__(self, storage, offset, size, stride):
            self.args = (storage, offset, size, stride, False, {})

        def __reduce__(self):
            return _rebuild, self.args

    import collections
    import sys
    import types

    fake_torch_utils = types.ModuleType("torch._utils")
    fake_torch = types.ModuleType("torch")

    def _rebuild(*args):
        raise AssertionError("never called while pickling")

    _rebuild.__module__, _rebuild.__qualname__ = "torch._utils", "_rebuild_tensor_v2"
    fake_torch_utils._rebuild_tensor_v2 = _rebuild

    class FloatStorage:
        pass

    FloatStorage.__module__, FloatStorage.__qualname__ = "torch", "FloatStorage"
    fake_torch.FloatStorage = FloatStorage
    saved = {k: sys.modules.get(k) for k in ("torch", "torch._utils")}
    sys.modules.update({"torch": fake_torch, "torch._utils": fake_torch_utils})
    try:
        state = collections.OrderedDict(
            (name, Rebuild(("storage", FloatStorage, key, "cpu", 64), offset, size, stride))
            for name, (key, size, stride, offset) in tensors.items())
        buffer = io.BytesIO()
        Pickler(buffer, protocol=2).dump(state)
        return buffer.getvalue()
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def test_reader_follows_offsets_and_strides(tmp_path):
    """A transposed view (stride (1, 3)) and an offset slice of one storage read as torch lays them out."""
    storage = np.arange(64, dtype="<f4")
    pickled = _state_dict_bytes({"w": ("0", (3, 2), (1, 3), 0), "b": ("0", (4,), (1,), 10)})
    tensors = read_state_dict(_torch_zip(tmp_path / "m.th", pickled, {"0": storage.tobytes()}))
    np.testing.assert_array_equal(tensors["w"], storage[:6].reshape(2, 3).T)
    np.testing.assert_array_equal(tensors["b"], storage[10:14])


def test_reader_refuses_code_in_the_pickle(tmp_path):
    class Evil:
        def __reduce__(self):
            import os
            return os.system, ("echo pwned > /dev/null",)

    path = _torch_zip(tmp_path / "evil.th", pickle.dumps({"w": Evil()}, protocol=2), {})
    with pytest.raises(ValueError, match="posix.system is not allowed|os.system is not allowed"):
        read_state_dict(path)


def test_reader_errors_name_the_file(tmp_path):
    (tmp_path / "not.th").write_text("hello")
    with pytest.raises(ValueError, match="not.th is not a PyTorch state dict"):
        read_state_dict(tmp_path / "not.th")
    storage = np.zeros(4, "<f4").tobytes()            # 4 floats where the pickle says 64
    path = _torch_zip(tmp_path / "short.th", _state_dict_bytes({"w": ("0", (2,), (1,), 0)}), {"0": storage})
    with pytest.raises(ValueError, match="storage '0' holds 16 bytes, expected 256"):
        read_state_dict(path)


def test_a_model_for_another_scenario_is_refused(tmp_path):
    model, config = _model("PredatorCapturePrey", "vdn")
    with pytest.raises(ValueError, match=r"takes 20 inputs .* needs 24 inputs \(18 observation features \+ 6 agent"):
        import_model(model, config, "warehouse", tmp_path / "policy")
    assert not (tmp_path / "policy").exists()


def test_unsupported_configs_are_named():
    with pytest.raises(ValueError, match="EPyMARL agent 'mlp' is not supported"):
        convert({}, {"agent": "mlp", "hidden_dim": 8}, 4, 16, 5)
    with pytest.raises(ValueError, match="obs_last_action=true"):
        convert({}, {"agent": "rnn", "hidden_dim": 8, "obs_last_action": True}, 4, 16, 5)
    assert [algorithm_name(c) for c in (
        {"agent": "rnn", "agent_output_type": "pi_logits"}, {"agent": "rnn", "mixer": "vdn"},
        {"agent": "rnn_ns", "mixer": "qmix"}, {"agent": "rnn", "mixer": "qmix"})] == ["mappo", "vdn", "qmix_ns", "qmix"]


def test_import_cli_then_evaluate_in_both_protocols(tmp_path, capsys):
    model, config = _model("PredatorCapturePrey", "qmix_ns")
    out = tmp_path / "pcp-qmix_ns"
    assert cli(["import", str(model), "--config", str(config), "--scenario", "pcp", "--out", str(out),
                "--bundle", str(tmp_path / "bundle")]) == 0
    assert (tmp_path / "bundle" / "main.py").exists() and (tmp_path / "bundle" / "gru_hr_bias.npy").exists()
    files = sorted(p.name for p in out.iterdir())
    for protocol in ([], ["--protocol", "robots"]):
        assert cli(["evaluate", str(out), "--episodes", "8", "--json", str(tmp_path / "e.json"), *protocol]) == 0
        result = json.loads((tmp_path / "e.json").read_text())
        assert result["control_period"] == (1 if protocol else 15)
        assert result["algo"] == "qmix_ns" and result["paper"]["reward"] == [31.76, 2.7]
    assert sorted(p.name for p in out.iterdir()) == files        # evaluate never writes into a policy folder
    assert "protocol marbler" in capsys.readouterr().out
    # export and render take the policy folder like a run
    assert cli(["export", str(out), "--bundle", str(tmp_path / "bundle2"), "--episodes", "1"]) == 0
    assert (tmp_path / "bundle2" / "policy_spec.npy").exists()
    assert cli(["export", str(out), "--out", str(tmp_path / "x")]) == 2         # one clear line, no traceback
    assert "already a policy folder: give --bundle B" in capsys.readouterr().err
    assert cli(["render", str(out), "--out", str(tmp_path / "pcp.gif"), "--no-progress"]) == 0
    assert (tmp_path / "pcp.gif").stat().st_size > 0


def test_marbler_protocol_sets_what_marbler_ships():
    env = marbler_jax.make("warehouse", protocol="marbler")
    config = env.config
    assert (config.control_period, config.physics, config.zero_reset_obs, config.barrier_certificate) == (
        15, "marbler", True, "safe")
    obs, _ = env.reset(jax.random.PRNGKey(0))
    assert not np.asarray(obs).any()
    with pytest.raises(ValueError, match="protocol='marbler' uses control_period=15, but control_period=1"):
        marbler_jax.make("warehouse", protocol="marbler", control_period=1)
    with pytest.raises(ValueError, match=r"protocol='paper' is not one of \['marbler', 'robots'\]"):
        marbler_jax.make("warehouse", protocol="paper")
