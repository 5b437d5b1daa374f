"""Gymnasium and PettingZoo adapters pass the upstream API checkers and agree with the core."""
from __future__ import annotations

import warnings

import gymnasium
import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import marbler_jax.adapters  # noqa: F401  (registers the gymnasium ids)
from marbler_jax.adapters import GYM_IDS, GymnasiumEnv


@pytest.mark.parametrize("suffix", sorted(GYM_IDS))
def test_gymnasium_checker_and_registration(suffix):
    env = gymnasium.make(f"marbler_jax/{suffix}-v0", render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings count as failures
        check_env(env.unwrapped, skip_render_check=False)
    obs, _ = env.reset(seed=5)
    core = env.unwrapped.core
    assert obs.shape == (core.num_agents, core.obs_dim) and obs.dtype == np.float32
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.std() > 0


def test_gymnasium_episode_matches_core_and_seeding():
    env = GymnasiumEnv("predator_capture_prey", barrier_certificate="none", penalize_violations=False)
    obs_a, _ = env.reset(seed=11)
    obs_b, _ = env.reset(seed=11)
    np.testing.assert_array_equal(obs_a, obs_b)
    total, steps = 0.0, 0
    terminated = truncated = False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(np.full(4, 4))
        total += reward
        steps += 1
        assert reward == pytest.approx(float(info["rewards"][0]))  # PCP: shared team reward
    assert truncated and not terminated and steps == 81
    assert total == pytest.approx(float(info["episode_return"]), abs=1e-4)
    with pytest.raises(ValueError, match=r"expected 4 integer actions in \[0, 5\)"):
        env.step(np.array([0, 1, 2]))


def test_pettingzoo_parallel_api():
    pettingzoo_test = pytest.importorskip("pettingzoo.test")
    from marbler_jax.adapters import PettingZooEnv

    for name in ("material_transport", "warehouse"):
        pettingzoo_test.parallel_api_test(PettingZooEnv(name), num_cycles=150)
    env = PettingZooEnv("simple_navigation")
    obs, infos = env.reset(seed=3)
    assert set(obs) == set(env.possible_agents) == {f"agent_{i}" for i in range(4)}
    obs, rewards, term, trunc, infos = env.step({a: 1 for a in env.agents})
    assert all(isinstance(r, float) for r in rewards.values())
    assert env.state().shape == (4 * 10,)
    with pytest.raises(ValueError, match=r"missing actions for \['agent_3'\]"):
        env.step({a: 1 for a in env.agents[:3]})
    with pytest.raises(ValueError, match=r"actions for unknown agent\(s\) \['robot_9'\]"):
        env.step(dict({a: 1 for a in env.agents}, robot_9=1))
    jax.clear_caches()


def test_importing_the_package_has_no_gymnasium_side_effect_and_the_numpy_policy_needs_no_jax():
    """``import marbler_jax`` defines things only (the adapters register the gymnasium ids), and
    ``marbler_jax.numpy_policy`` -- what the Robotarium bundle runs -- imports with JAX unimportable."""
    import subprocess
    import sys

    code = ("import sys, marbler_jax; assert 'gymnasium' not in sys.modules, 'gymnasium imported'; "
            "import marbler_jax.adapters, gymnasium; assert 'marbler_jax/Warehouse-v0' in gymnasium.registry")
    subprocess.run([sys.executable, "-c", code], check=True)
    code = ("import sys; sys.modules['jax'] = None; sys.modules['flax'] = None; "
            "from marbler_jax.numpy_policy import load_policy; assert sys.modules['jax'] is None")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_simulator_never_imports_the_learners_and_algorithms_is_no_import_name(tmp_path):
    """``marbler_jax`` (simulator, scenarios, adapters, deploy, numpy policy, render) stands alone; the learners
    install as ``marbler_jax_rl``, so no top-level ``algorithms`` package shadows another project's."""
    import subprocess
    import sys

    code = ("import sys, marbler_jax, marbler_jax.adapters, marbler_jax.deploy.bundle, marbler_jax.numpy_policy, "
            "marbler_jax.render, marbler_jax.rollout, marbler_jax.scenarios; "
            "assert not [m for m in sys.modules if m.startswith(('marbler_jax_rl', 'algorithms'))], 'learners imported'; "
            "import importlib.util; assert importlib.util.find_spec('algorithms') is None, 'algorithms is importable'; "
            "import marbler_jax_rl.cli")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=tmp_path)   # not the repository root
