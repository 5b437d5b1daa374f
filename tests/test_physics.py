"""Physics against rps traces (golden uni_step*.npz) and invariants."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from marbler_jax import physics
from tests.conftest import angle_diff, robot_major

STEP_FILES = {
    "uni_step.npz": "marbler",
    "uni_step_rpsv1last.npz": "rps2024",
    "uni_step_rpsv2.npz": "robotarium",
}
NS = [1, 4, 8, 20]


def _pose_err(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return max(np.abs(a[..., :2] - b[..., :2]).max(), angle_diff(a[..., 2], b[..., 2]).max())


@pytest.mark.parametrize("fname", sorted(STEP_FILES))
@pytest.mark.parametrize("n", NS)
def test_step_matches_rps_float64(golden, fname, n):
    g = golden(fname)[n]
    params = physics.PRESETS[STEP_FILES[fname]]
    poses0, cmd = robot_major(g["poses0"]), robot_major(g["vel_cmd"])
    with jax.enable_x64(True):
        p1 = physics.integrate(params, jnp.asarray(poses0), jnp.asarray(cmd))
        p30 = physics.integrate(params, jnp.asarray(poses0), jnp.asarray(cmd), ticks=30)
        assert p1.dtype == jnp.float64
    assert _pose_err(p1, robot_major(g["poses1"])) <= 1e-12
    assert _pose_err(p30, robot_major(g["poses30"])) <= 1e-9
    # numpy path is the same code
    assert _pose_err(physics.integrate(params, poses0, cmd), robot_major(g["poses1"])) <= 1e-12
    # what set_velocities stores in 6bb184e is the thresholded command
    if STEP_FILES[fname] == "marbler":
        np.testing.assert_allclose(physics.threshold(params, cmd), robot_major(g["vel_after_set"]), atol=1e-15)


@pytest.mark.parametrize("fname", sorted(STEP_FILES))
@pytest.mark.parametrize("n", NS)
def test_trajectories_match_rps(golden, fname, n):
    g = golden(fname)[n]
    params = physics.PRESETS[STEP_FILES[fname]]
    traj_const, vel_cmd = robot_major(g["traj_const"]), robot_major(g["vel_cmd"])[: len(g["traj_const"])]
    traj_seq, vel_seq = robot_major(g["traj_seq"]), robot_major(g["vel_seq"])
    with jax.enable_x64(True):
        for t in (1, 7, 30):
            out = physics.integrate(params, jnp.asarray(traj_const[:, 0]), jnp.asarray(vel_cmd), ticks=t)
            assert _pose_err(out, traj_const[:, t]) <= 1e-9
        pose = jnp.asarray(traj_seq[:, 0])
        for t in range(vel_seq.shape[1]):
            pose = physics.integrate(params, pose, jnp.asarray(vel_seq[:, t]))
            assert _pose_err(pose, traj_seq[:, t + 1]) <= 1e-9


@pytest.mark.parametrize("fname", sorted(STEP_FILES))
def test_step_float32(golden, fname):
    g = golden(fname)[8]
    params = physics.PRESETS[STEP_FILES[fname]]
    poses0 = jnp.asarray(robot_major(g["poses0"]), jnp.float32)
    cmd = jnp.asarray(robot_major(g["vel_cmd"]), jnp.float32)
    p30 = physics.integrate(params, poses0, cmd, ticks=30)
    assert p30.dtype == jnp.float32
    assert _pose_err(p30, robot_major(g["poses30"])) <= 2e-5
    step = jax.jit(lambda p: physics.integrate(params, p, cmd))
    pose = poses0
    for _ in range(30):
        pose = step(pose)
    assert _pose_err(pose, robot_major(g["poses30"])) <= 2e-5


def test_multi_tick_equals_tick_loop_including_zero_omega():
    params = physics.PRESETS["robotarium"]
    rng = np.random.default_rng(0)
    poses = rng.uniform([-1.5, -0.9, -np.pi], [1.5, 0.9, np.pi], size=(64, 5, 3))
    vel = rng.uniform([-0.3, -5], [0.3, 5], size=(64, 5, 2))
    vel[:8, :, 1] = 0.0  # straight lines: the closed form's 0/0 case
    vel[8:16, :, 1] = 1e-9
    looped = poses
    for _ in range(29):
        looped = physics.integrate(params, looped, vel)
    closed = physics.integrate(params, poses, vel, ticks=29)
    assert _pose_err(closed, looped) <= 1e-12
    assert np.all(np.isfinite(closed))


def test_thresholding_modes():
    marbler, v2 = physics.PRESETS["marbler"], physics.PRESETS["robotarium"]
    cmd = np.array([[0.15, np.pi], [0.5, -7.0], [-0.3, 0.0]])
    np.testing.assert_allclose(physics.threshold(marbler, cmd), [[0.15, np.pi], [0.2, -0.4 / 0.11], [-0.2, 0.0]])
    wheels = physics.uni_to_diff(v2, physics.threshold(v2, cmd))
    assert np.all(np.abs(wheels) <= 12.5 + 1e-12)
    # within limits nothing changes; uni <-> diff round trip
    ok = np.array([[0.1, 0.5]])
    np.testing.assert_allclose(physics.threshold(v2, ok), ok)
    np.testing.assert_allclose(physics.diff_to_uni(v2, physics.uni_to_diff(v2, cmd)), cmd, atol=1e-14)


def test_collisions_and_boundary_match_rps_rules():
    params = physics.PRESETS["marbler"]
    # two robots facing each other: centres 0.185 apart, shifted centres 0.135 apart -> collide (<=)
    poses = np.array([[0.0, 0.0, 0.0], [0.185, 0.0, np.pi], [1.0, 0.5, 0.0]])
    np.testing.assert_array_equal(physics.collisions(params, poses), [True, True, False])
    assert physics.collision_pairs(params, poses) == 1
    # back to back at the same distance: shifted centres 0.235 apart -> no collision
    poses_back = np.array([[0.0, 0.0, np.pi], [0.185, 0.0, 0.0], [1.0, 0.5, 0.0]])
    assert not physics.collisions(params, poses_back).any()
    edge = np.array([[1.6, 0.0, 0.0], [1.6001, 0.0, 0.0], [0.0, -1.0001, 0.0]])
    np.testing.assert_array_equal(physics.out_of_bounds(params, edge), [False, True, True])


def test_jit_vmap_and_validation():
    params = physics.get_params()
    assert params is physics.PRESETS["robotarium"]
    poses = jnp.zeros((7, 4, 3))
    vel = jnp.ones((7, 4, 2)) * jnp.array([0.1, 1.0])
    jitted = jax.jit(physics.integrate, static_argnums=(0, 3))
    np.testing.assert_allclose(jitted(params, poses, vel, 15), physics.integrate(params, poses, vel, 15), atol=1e-6)
    vm = jax.vmap(lambda p, v: physics.integrate(params, p, v, 3))(poses, vel)
    np.testing.assert_allclose(vm, physics.integrate(params, poses, vel, 3), atol=1e-7)
    with pytest.raises(ValueError, match="unknown physics preset 'nope'"):
        physics.get_params("nope")
    with pytest.raises(ValueError, match=r"\[1, 50\]"):
        physics.check_num_robots(params, 51)
    with pytest.raises(ValueError, match="ticks"):
        physics.integrate(params, poses, vel, -1)


def test_trajectory_matches_tick_loop_and_rps(golden):
    g = golden("uni_step.npz")[4]
    params = physics.PRESETS["marbler"]
    traj = robot_major(g["traj_const"])  # [K, 31, N, 3]
    cmd = robot_major(g["vel_cmd"])[: len(traj)]
    with jax.enable_x64(True):
        out = physics.trajectory(params, jnp.asarray(traj[:, 0]), jnp.asarray(cmd), 30)
    assert out.shape == (31,) + traj[:, 0].shape
    assert _pose_err(np.moveaxis(np.asarray(out), 0, 1), traj) <= 1e-9
    # numpy path, and agreement with integrate at every tick
    out_np = physics.trajectory(params, traj[:, 0], cmd, 7)
    for k in range(8):
        assert _pose_err(out_np[k], physics.integrate(params, traj[:, 0], cmd, k)) <= 1e-12


def _held_ticks_reference(params, poses, vel, ticks, stop):
    """rps's loop, one tick at a time: check the pre-tick pose, then integrate (numpy, float64)."""
    vel = physics.threshold(params, vel)
    batch = poses.shape[:-2]
    hit, out, stopped = (np.zeros(batch, bool) for _ in range(3))
    dist = np.zeros(poses.shape[:-1])
    for _ in range(ticks):
        hit_now = physics.collisions(params, poses).any(-1)
        out_now = physics.out_of_bounds(params, poses).any(-1)
        live = ~stopped
        hit |= live & hit_now
        out |= live & out_now
        poses = np.where(live[..., None, None], physics.integrate(params, poses, vel, 1), poses)
        dist += np.where(live[..., None], np.abs(vel[..., 0]) * params.dt, 0)
        if stop:
            stopped |= hit_now | out_now
    return poses, hit, out, dist


def _crowded(rng, batch, n):
    """Poses in a small box (many close pairs, some robots outside the arena) and mixed commands."""
    xy = rng.uniform([-1.8, -0.6], [-1.8 + 0.22 * n, 0.6], size=(batch, n, 2))
    poses = np.concatenate([xy, rng.uniform(-np.pi, np.pi, size=(batch, n, 1))], axis=-1)
    vel = rng.uniform([-0.25, -4.0], [0.25, 4.0], size=(batch, n, 2))
    return poses, vel


@pytest.mark.parametrize("n", [1, 5, 20])
@pytest.mark.parametrize("stop", [True, False])
def test_held_ticks_matches_the_tick_by_tick_rps_loop(n, stop, monkeypatch):
    """numpy float64 == rps's loop; JAX float32 batched, vmapped and vmap(vmap) agree with it, with
    either collision test layout (static slices for small teams, cyclic shifts for large; odd and even N)."""
    params = physics.PRESETS["robotarium"]
    rng = np.random.default_rng(n)
    poses, vel = _crowded(rng, 24, n)
    ref = _held_ticks_reference(params, poses, vel, 15, stop)
    got = physics.held_ticks(params, poses, vel, 15, stop_on_violation=stop)
    for a, b in zip(got[1:], ref[1:]):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert _pose_err(got[0], ref[0]) <= 1e-12
    assert 0 < ref[1].sum() < len(poses) or n == 1  # the cases exercise both outcomes
    for threshold in (2, 100):  # force each collision layout
        monkeypatch.setattr(physics, "_SHIFTED_PAIRS_FROM", threshold)
        physics._jax_held_ticks.cache_clear()
        run = lambda p, v: physics.held_ticks(params, p, v, 15, stop_on_violation=stop)
        p32, v32 = jnp.asarray(poses, jnp.float32), jnp.asarray(vel, jnp.float32)
        outs = [jax.jit(run)(p32, v32), jax.jit(jax.vmap(run))(p32, v32),
                jax.tree_util.tree_map(lambda a: a.reshape((24,) + a.shape[2:]),
                                       jax.jit(jax.vmap(jax.vmap(run)))(p32.reshape(4, 6, n, 3), v32.reshape(4, 6, n, 2)))]
        for out in outs:
            # float32 rounding can flip a check that sits within ~1e-7 m of its threshold: allow one case
            flags_equal = (np.asarray(out[1]) == ref[1]) & (np.asarray(out[2]) == ref[2])
            assert flags_equal.sum() >= len(poses) - 1
            assert _pose_err(np.asarray(out[0])[flags_equal], ref[0][flags_equal]) <= 2e-5
            np.testing.assert_allclose(np.asarray(out[3])[flags_equal], ref[3][flags_equal], atol=1e-6)
    physics._jax_held_ticks.cache_clear()


def test_actuator_safe_commands_pass_every_rps_actuator_check():
    rng = np.random.default_rng(0)
    u = np.stack([rng.uniform(-0.4, 0.4, 100_000), rng.uniform(-8, 8, 100_000)], -1)
    safe = physics.actuator_safe(u)
    for preset in ("robotarium", "marbler", "rps2024"):          # L = 0.11 and 0.105
        params = physics.PRESETS[preset]
        checked = physics.threshold(params, safe) if preset == "marbler" else safe   # 6bb184e clips v, w first
        # rps's own conversion, as it checks (a wheel clipped to exactly 12.5 comes back 1.8e-15 above it)
        length, r = params.base_length, params.wheel_radius
        wheels = np.abs(np.stack([2 * checked[:, 0] - length * checked[:, 1],
                                  2 * checked[:, 0] + length * checked[:, 1]]) / (2 * r))
        assert not np.any(wheels > 12.5), preset
    # on rps v2 the clipped command moves the robot as rps's own wheel clip would
    np.testing.assert_allclose(physics.threshold(physics.PRESETS["robotarium"], u), safe, atol=1e-8)
    # a command within the limits is sent unchanged
    calm = np.array([[0.1, 1.0], [-0.05, -2.0]])
    np.testing.assert_allclose(physics.actuator_safe(calm), calm, atol=1e-12)


@pytest.mark.parametrize("ticks", [1, 5])
def test_held_ticks_counts_a_non_finite_position_as_out_of_bounds(ticks):
    """A NaN coordinate compares False with every bound; the tick loop still flags it (as
    ``out_of_bounds`` does), so an env step with a broken pose ends as a violation."""
    poses = jnp.asarray([[0.0, 0.0, 0.0], [0.5, jnp.nan, 0.0], [-0.5, 0.0, 0.0]])
    vel = jnp.zeros((3, 2))
    _, collided, outside, _ = physics.held_ticks(physics.get_params(), poses[None], vel[None], ticks)
    assert bool(outside[0]) and not bool(collided[0])
    assert bool(physics.out_of_bounds(physics.get_params(), poses)[1])
    _, _, inside, _ = physics.held_ticks(physics.get_params(), poses[None].at[0, 1, 1].set(0.0), vel[None], ticks)
    assert not bool(inside[0])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("bound", [0.13, 0.5, np.pi / 4])
def test_turn_equals_cos_and_sin_to_rounding(dtype, bound):
    """The per-tick turn's polynomial (cos, sin) is within an ulp of the exact values up to its bound,
    and a bound past pi/4 falls back to cos/sin (a truncated series would be off there)."""
    delta = np.linspace(-bound, bound, 20001).astype(dtype)
    exact = np.cos(delta.astype(np.float64)), np.sin(delta.astype(np.float64))
    got = physics.turn(delta, bound, np)
    eps = np.finfo(dtype).eps
    for value, reference in zip(got, exact):
        assert np.asarray(value).dtype == dtype
        assert np.max(np.abs(value - reference) / np.maximum(np.abs(reference), np.finfo(dtype).tiny)) <= eps
    wide = np.linspace(-3.0, 3.0, 101).astype(dtype)
    np.testing.assert_array_equal(physics.turn(wide, 3.0, np)[0], np.cos(wide))
