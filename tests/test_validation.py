"""Bad training input gets one clear error naming the setting, the value and what is allowed -- before
anything is created."""
from __future__ import annotations

import pytest

from marbler_jax_rl.driver import build_config, train_run
from marbler_jax_rl.cli import main


@pytest.mark.parametrize("algo, overrides, message", [
    ("vdn", {"lr": -1.0}, "lr must be > 0, got -1.0"),
    ("vdn", {"lr": float("inf")}, "lr=inf is not valid: expected a finite number"),
    ("vdn", {"lr": "abc"}, "lr='abc' is not valid: expected a finite number"),
    ("qmix", {"gamma": 1.5}, r"gamma must be in \(0, 1\], got 1.5"),
    ("qmix_ns", {"eps_start": 5}, r"eps_start must be in \[0, 1\], got 5"),
    ("vdn", {"max_grad_norm": -1}, "max_grad_norm must be > 0, got -1"),
    ("vdn", {"hidden": 32.5}, "hidden=32.5 is not valid: expected an integer"),
    ("vdn", {"shared": 1}, "shared=1 is not valid: expected true or false"),
    ("ippo", {"lr": 0}, "lr must be > 0, got 0"),
    ("mappo", {"gae_lambda": 2.0}, r"gae_lambda must be in \[0, 1\], got 2.0"),
    ("ippo", {"ent_coef": float("nan")}, "ent_coef=nan is not valid"),
])
def test_training_settings_are_checked_when_the_config_is_built(algo, overrides, message):
    with pytest.raises(ValueError, match=message):
        build_config(algo, overrides)


def test_cli_rejects_bad_input_with_exit_2_and_creates_nothing(tmp_path, capsys):
    out = tmp_path / "run"
    for args in (["--hp", "lr=Infinity"], ["--hp", "lr=abc"], ["--hp", "gamma=1.5"], ["--checkpoint-every", "-3"],
                 ["--checkpoint-every", "0"]):
        assert main(["train", "--algo", "ippo", "--out", str(out), "--no-progress", *args]) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("marbler-jax: error: ") and err.count("\n") == 1, err
    assert not out.exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    assert main(["train", "--algo", "ippo", "--out", str(notes), "--no-progress"]) == 2
    assert "is a file" in capsys.readouterr().err and notes.read_text() == "mine"
    missing = tmp_path / "runs" / "never-trained"
    assert main(["train", "--algo", "ippo", "--resume", "--out", str(missing), "--no-progress"]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_driver_checks_checkpoint_every(tmp_path):
    with pytest.raises(ValueError, match="checkpoint_every must be an integer >= 1"):
        train_run("simple_navigation", "ippo", 1000, 1, tmp_path / "x", checkpoint_every=0, progress=False)
    assert not (tmp_path / "x").exists()


def test_scenario_config_values_are_checked_with_the_key_named():
    import marbler_jax

    with pytest.raises(ValueError, match="n_agents must be an integer, got 'four'"):
        marbler_jax.make("simple_navigation", n_agents="four")
    for bad in (0.0, -0.2):
        with pytest.raises(ValueError, match=r"step_dist must be a distance > 0 \[m\]"):
            marbler_jax.make("simple_navigation", step_dist=bad)
    with pytest.raises(ValueError, match="levels must hold finite numbers"):
        marbler_jax.make("foraging", levels=(float("nan"), 1.0))
    with pytest.raises(ValueError, match="max_episode_steps must be an integer"):
        marbler_jax.make("warehouse", max_episode_steps=float("inf"))


@pytest.mark.parametrize("scenario, key, value", [
    ("predator_capture_prey", "capture_radius", -0.1), ("predator_capture_prey", "predator_radius", 0.0),
    ("rware", "pickup_radius", -1.0), ("material_transport", "zone1_radius", -0.2),
    ("arctic_transport", "fast_step", -0.3), ("discovery", "agent_spacing", 0.0),
    ("discovery", "landmark_spacing", 0.0), ("foraging", "spawn_spacing", 0.0), ("discovery", "sensing_radius", -1.0),
])
def test_radii_spacings_and_steps_must_be_positive(scenario, key, value):
    """Every length a scenario takes (radii, spawn spacings, step lengths) is > 0, the error naming key and
    value: a negative radius trained silently, a zero spacing divided by zero."""
    import marbler_jax

    with pytest.raises(ValueError, match=rf"^{key} must be a distance > 0 \[m\], got {value}$"):
        marbler_jax.make(scenario, **{key: value})


def test_barrier_parameters_must_be_finite():
    from marbler_jax import cbf

    for kw in (dict(projection_distance=float("inf")), dict(barrier_gain=float("inf")),
               dict(safety_radius=float("nan")), dict(boundary_points=(-1.6, float("inf"), -1, 1))):
        kind = "uni_boundary"
        with pytest.raises(ValueError, match="must be"):
            cbf.make_barrier(kind, **kw)


def test_a_non_finite_pose_is_a_violation():
    import numpy as np

    from marbler_jax import physics

    params = physics.PRESETS["robotarium"]
    poses = np.array([[np.nan, 0.0, 0.0], [0.5, 0.0, np.inf], [0.0, 0.5, 0.0]])
    np.testing.assert_array_equal(physics.out_of_bounds(params, poses), [True, True, False])


def test_out_of_range_actions_raise_eagerly_and_in_the_checked_mode_under_jit():
    """Outside jit an out-of-range action raises; a jitted step clips it (documented), and the same step
    run through ``marbler_jax.env.checked`` raises naming the actions."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.experimental import checkify

    import marbler_jax
    from marbler_jax.env import checked

    env = marbler_jax.make("warehouse")
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    _, state = jax.jit(jax.vmap(env.reset))(keys)
    bad = jnp.array([[0, 1, 2, 3, 4, 0], [0, 1, 2, 7, 4, 0]])
    with pytest.raises(ValueError, match=r"actions must be in \[0, 5\), got \[0, 1, 2, 7, 4, 0\]"):
        env.step(keys[1], jax.tree_util.tree_map(lambda x: x[1], state), bad[1])
    clipped = jax.jit(jax.vmap(env.step))(keys, state, bad)                      # silently clipped to 4
    same = jax.jit(jax.vmap(env.step))(keys, state, bad.at[1, 3].set(4))
    jax.tree_util.tree_map(np.testing.assert_array_equal, clipped, same)
    with pytest.raises(checkify.JaxRuntimeError, match=r"warehouse: actions must be in \[0, 5\), got \[0 1 2 7 4 0\]"):
        checked(jax.vmap(env.step))(keys, state, bad)
    good = checked(jax.vmap(env.step))(keys, state, bad.at[1, 3].set(4))
    jax.tree_util.tree_map(np.testing.assert_array_equal, good, same)
