"""Exported numpy policies act like the JAX policies: values within 1e-5, identical greedy actions,
on random observations and along whole episodes (hidden state carried and reset)."""
from __future__ import annotations

import ast
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl import ippo, mappo, qmix, vdn
from marbler_jax_rl.export import export_params
from marbler_jax_rl.networks import apply_agents
from marbler_jax_rl.q_learning import agent_inputs, agent_module
from marbler_jax.numpy_policy import NumpyPolicy, load_policy
from tests.helpers import initial_params

CASES = {
    "vdn-gru-shared": (vdn, vdn.VDNConfig(hidden=32)),
    "qmix-ff-shared": (qmix, qmix.QMIXConfig(hidden=32, recurrent=False)),
    "qmix_ns-gru": (qmix, qmix.QMIXNSConfig(hidden=32)),
    "vdn-mingru-shared": (vdn, vdn.VDNConfig(hidden=32, cell="mingru")),
    "qmix_ns-mingru": (qmix, qmix.QMIXNSConfig(hidden=32, cell="mingru")),
    "vdn-mingru-layernorm": (vdn, vdn.VDNConfig(hidden=32, cell="mingru", layer_norm=True)),
    "qmix_ns-gru-layernorm": (qmix, qmix.QMIXNSConfig(hidden=32, layer_norm=True)),
    "qmix-ff-layernorm": (qmix, qmix.QMIXConfig(hidden=32, recurrent=False, layer_norm=True)),
    "vdn-gru-last-action": (vdn, vdn.VDNConfig(hidden=32, last_action=True)),
    "qmix_ns-mingru-last-action": (qmix, qmix.QMIXNSConfig(hidden=32, cell="mingru", last_action=True)),
    "qmix-ff-last-action": (qmix, qmix.QMIXConfig(hidden=32, recurrent=False, last_action=True)),
    "ippo-shared": (ippo, ippo.IPPOConfig(hidden=32)),
    "mappo-per-agent": (mappo, mappo.MAPPOConfig(hidden=32, shared=False, activation="relu")),
}
ALGO = {"vdn-gru-shared": "vdn", "qmix-ff-shared": "qmix", "qmix_ns-gru": "qmix_ns", "ippo-shared": "ippo",
        "mappo-per-agent": "mappo", "vdn-mingru-shared": "vdn", "qmix_ns-mingru": "qmix_ns",
        "vdn-mingru-layernorm": "vdn", "qmix_ns-gru-layernorm": "qmix_ns", "qmix-ff-layernorm": "qmix",
        "vdn-gru-last-action": "vdn", "qmix_ns-mingru-last-action": "qmix_ns", "qmix-ff-last-action": "qmix"}


def _params(module, cfg, env, seed=0):
    """Initial parameters, every one perturbed (LayerNorm's scale 1 / bias 0 would hide a misuse)."""
    params = initial_params(module, env, cfg, seed)
    leaves, tree = jax.tree_util.tree_flatten(params)
    keys = jax.random.split(jax.random.PRNGKey(seed + 100), len(leaves))
    return jax.tree_util.tree_unflatten(
        tree, [x + 0.1 * jax.random.normal(k, x.shape, x.dtype) for x, k in zip(leaves, keys)])


@pytest.mark.parametrize("case", sorted(CASES))
def test_numpy_policy_matches_jax_on_random_observations(case, tmp_path):
    module, cfg = CASES[case]
    env = marbler_jax.make("predator_capture_prey")
    params = _params(module, cfg, env)
    export_params(ALGO[case], cfg, params, env, tmp_path / "policy")
    policy = load_policy(tmp_path / "policy")
    assert all(p.suffix == ".npy" for p in (tmp_path / "policy").iterdir())
    obs = np.random.default_rng(0).uniform(-1.5, 1.5, (10, 64, env.num_agents, env.obs_dim)).astype(np.float32)
    if ALGO[case] in ("ippo", "mappo"):
        jax_logits = apply_agents(ippo.ActorCritic(env.num_actions, cfg.hidden, cfg.layers, cfg.activation), params,
                                  ippo.policy_inputs(cfg, jnp.asarray(obs)), ippo.critic_inputs(cfg, jnp.asarray(obs)),
                                  shared=cfg.shared)[0]
        np_logits, _ = policy.values(obs)
        np.testing.assert_allclose(np_logits, jax_logits, atol=1e-5, rtol=1e-5)
        np.testing.assert_array_equal(policy.act(obs)[0], np.argmax(np.asarray(jax_logits), -1))
        return
    agent = agent_module(env, cfg)
    h_jax = agent.initial_hidden((64, env.num_agents))
    h_np = policy.initial_hidden()[None].repeat(64, 0)
    no_reset = jnp.zeros((64, env.num_agents, 1), bool)
    last = jnp.zeros((64, env.num_agents, env.num_actions))   # no previous action at the first step
    assert policy.initial_hidden().shape[-1] == h_jax.shape[-1] + (env.num_actions if cfg.last_action else 0)
    for t in range(10):                                   # hidden state (and last action) carried over 10 steps
        h_jax, q_jax = apply_agents(agent, params["agent"], h_jax, agent_inputs(cfg, jnp.asarray(obs[t]), last),
                                    no_reset, shared=cfg.shared)
        actions, h_np, q_np = policy.act(obs[t], h_np)
        np.testing.assert_allclose(q_np, q_jax, atol=1e-5, rtol=1e-5)
        np.testing.assert_array_equal(actions, np.argmax(np.asarray(q_jax), -1))
        last = jax.nn.one_hot(jnp.argmax(q_jax, -1), env.num_actions)
        memory = jnp.concatenate([h_jax, last], -1) if cfg.last_action else h_jax
        np.testing.assert_allclose(h_np, memory, atol=1e-5, rtol=1e-5)


REPLAYS = {"vdn": ("vdn", vdn, vdn.VDNConfig(hidden=32)),
           "vdn-last-action": ("vdn", vdn, vdn.VDNConfig(hidden=32, last_action=True)),
           "mappo-gru": ("mappo", mappo, mappo.MAPPOConfig(hidden=32, cell="gru")),
           "ippo-mingru-per-agent": ("ippo", ippo, ippo.IPPOConfig(hidden=32, cell="mingru", shared=False))}


@pytest.mark.parametrize("case", sorted(REPLAYS))
def test_numpy_policy_replays_whole_episodes_like_the_jax_policy(tmp_path, case):
    """Recurrent agents, value-based and PPO actors: exported, the numpy policy takes the JAX policy's actions
    and carries the same memory along several episodes."""
    algo, module, cfg = REPLAYS[case]
    env = marbler_jax.make("material_transport", control_period=15)
    params = _params(module, cfg, env, seed=3)
    export_params(algo, cfg, params, env, tmp_path / "p")
    policy = load_policy(tmp_path / "p")
    greedy = module.greedy_policy(env, cfg, params)
    step = jax.jit(env.step)
    act = jax.jit(greedy.step)
    obs, state = env.reset(jax.random.PRNGKey(0))
    h_jax, h_np, reset = greedy.initial_carry(()), None, True
    finished, steps = 0, 0
    while finished < 2 or steps < 100:                   # several episodes: the memory must reset between them
        a_jax, h_jax = act(None, obs, h_jax, jnp.bool_(reset))
        if reset:
            h_np = policy.initial_hidden()
        a_np, h_np, _ = policy.act(np.asarray(obs), h_np)
        np.testing.assert_array_equal(a_np, np.asarray(a_jax), err_msg=f"step {steps}")
        np.testing.assert_allclose(h_np, h_jax, atol=1e-4)     # the same memory layout (rounding builds up)
        obs, state, _, done, _ = step(jax.random.PRNGKey(steps), state, a_jax)
        reset, steps = bool(done), steps + 1
        finished += int(reset)
    assert finished >= 2


def _imports(module: str) -> set[str]:
    source = Path(__file__).resolve().parents[1] / (module.replace(".", "/") + ".py")
    return {alias.name for node in ast.walk(ast.parse(source.read_text()))
            if isinstance(node, (ast.Import, ast.ImportFrom))
            for alias in (node.names if isinstance(node, ast.Import) else [ast.alias(node.module or "")])}


def test_numpy_policy_module_needs_no_jax():
    # stdlib + numpy, and marbler_jax.xp (the array namespace that lets JAX arrays through without importing JAX)
    assert _imports("marbler_jax.numpy_policy") <= {"__future__", "hashlib", "json", "pathlib", "numpy",
                                                     "marbler_jax.xp"}
    assert _imports("marbler_jax.xp") <= {"__future__", "dataclasses", "sys", "typing", "numpy"}


def test_bad_policy_folders_are_reported(tmp_path):
    with pytest.raises(ValueError, match="holds no policy_spec.npy"):
        load_policy(tmp_path)
    env = marbler_jax.make("simple_navigation")
    cfg = ippo.IPPOConfig(hidden=8)
    good = export_params("ippo", cfg, _params(ippo, cfg, env), env, tmp_path / "p")
    with pytest.raises(ValueError, match=r"observations must be \[..., 4, 10\]"):
        good.inputs(np.zeros((3, 10)))
    last = good.spec["layers"][-1] + ".kernel"

    def broken(name, value):
        return dict(good.t, **{name: value})

    # tensors that would reach the robots wrong: each error names the tensor
    with pytest.raises(ValueError, match=f"policy tensor '{last}' has 6 outputs for 5 actions"):
        NumpyPolicy(good.spec, broken(last, np.zeros(good.t[last].shape[:-1] + (6,), np.float32)))
    nan = good.t["actor.Dense_0.kernel"].copy()
    nan[0, 0] = np.nan
    with pytest.raises(ValueError, match="policy tensor 'actor.Dense_0.kernel' holds non-finite values"):
        NumpyPolicy(good.spec, broken("actor.Dense_0.kernel", nan))
    with pytest.raises(ValueError, match="policy tensor 'actor.Dense_0.kernel' takes 10 inputs, but the spec gives 14"):
        NumpyPolicy(good.spec, broken("actor.Dense_0.kernel", good.t["actor.Dense_0.kernel"][:10]))
    with pytest.raises(ValueError, match="do not fit together"):
        NumpyPolicy(good.spec, broken("actor.Dense_1.kernel", np.zeros((3, 8), np.float32)))
    with pytest.raises(ValueError, match="policy tensor 'fc1.kernel' is missing"):
        NumpyPolicy({"format": "marbler-jax-policy/1", "kind": "q_agent", "recurrent": False, "num_agents": 4,
                     "obs_dim": 10, "hidden": 8, "shared": True, "agent_ids": True}, {})
    q_agent = {"format": "marbler-jax-policy/1", "kind": "q_agent", "recurrent": True, "num_agents": 4,
               "obs_dim": 10, "hidden": 8, "shared": True, "agent_ids": True}
    with pytest.raises(ValueError, match="unsupported recurrent cell 'lstm'"):
        NumpyPolicy(dict(q_agent, cell="lstm"), {})
    with pytest.raises(ValueError, match="a policy with last_action needs num_actions"):
        NumpyPolicy(dict(q_agent, last_action=True), {})
    # a flipped byte in a weight file still loads as a valid .npy: the spec's checksums catch it
    kernel_file = tmp_path / "p" / "actor_Dense_0_kernel.npy"
    data = bytearray(kernel_file.read_bytes())
    data[-3] ^= 0x40
    kernel_file.write_bytes(bytes(data))
    assert np.load(kernel_file).shape == good.t["actor.Dense_0.kernel"].shape
    with pytest.raises(ValueError, match=r"actor_Dense_0_kernel.npy changed after export \(checksum mismatch"):
        load_policy(tmp_path / "p")
    kernel_file.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="cannot load the policy"):
        load_policy(tmp_path / "p")

def test_exports_never_touch_a_users_folders_beside_the_target(tmp_path):
    """The policy folder and the bundle are built beside their target under names no user picks and swapped
    in: folders the user named ``<target>.tmp`` / ``.old`` / ``.new`` stay as they were; a failed export
    leaves the target as it was and no staging folder behind."""
    env = marbler_jax.make("predator_capture_prey")
    module, cfg = CASES["vdn-gru-shared"]
    params = _params(module, cfg, env)
    mine = {}
    for suffix in (".tmp", ".old", ".new"):
        for name in ("pol", "bundle"):
            folder = tmp_path / f"{name}{suffix}"
            folder.mkdir()
            (folder / "notes.txt").write_text("mine")
            mine[folder] = "mine"
    export_params("vdn", cfg, params, env, tmp_path / "pol")
    export_params("vdn", cfg, params, env, tmp_path / "pol")            # replacing an earlier export
    from marbler_jax.deploy.bundle import write_bundle

    write_bundle(env, tmp_path / "pol", tmp_path / "bundle", "vdn", episodes=1)
    write_bundle(env, tmp_path / "pol", tmp_path / "bundle", "vdn", episodes=1)
    assert all((folder / "notes.txt").read_text() == text for folder, text in mine.items())
    before = sorted(p.name for p in tmp_path.iterdir())
    nan = jax.tree_util.tree_map(lambda x: x * np.nan, params)
    with pytest.raises(ValueError, match="non-finite"):
        export_params("vdn", cfg, nan, env, tmp_path / "pol")
    assert sorted(p.name for p in tmp_path.iterdir()) == before          # nothing half-written, nothing left
    assert load_policy(tmp_path / "pol").spec["algo"] == "vdn"
