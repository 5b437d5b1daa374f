"""Controllers and SI <-> unicycle maps against rps (golden controllers.npz)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from marbler_jax import controllers as ctl
from tests.conftest import robot_major

NS = [2, 4, 6, 8, 20]


def _cases(golden, n):
    g = golden("controllers.npz")[n]
    return {k: robot_major(v) if v.ndim == 3 else v for k, v in g.items()}


@pytest.mark.parametrize("n", NS)
@pytest.mark.parametrize("as_jax", [False, True], ids=["numpy", "jax64"])
def test_maps_match_rps(golden, n, as_jax):
    g = _cases(golden, n)
    conv = (lambda a: jnp.asarray(a)) if as_jax else (lambda a: a)
    with jax.enable_x64(True):
        poses = conv(g["poses"])
        out = {
            "xi": ctl.uni_to_si_states(poses),
            "dxi_pos": ctl.si_position_controller(conv(g["xi"]), conv(g["goals"])),
            "dxu_si2uni": ctl.si_to_uni_mapping(conv(g["dxi_rand"]), poses),
            "dxi_uni2si": ctl.uni_to_si_dynamics(conv(g["dxu_rand"]), poses),
            "dxu_si2uni_atan": ctl.si_to_uni_dynamics(conv(g["dxi_rand"]), poses),
            "dxu_marbler_nocbf": ctl.marbler_velocities(poses, conv(g["goals"]), barrier=None),
        }
    for key, value in out.items():
        np.testing.assert_allclose(np.asarray(value), g[key], rtol=0, atol=1e-12, err_msg=key)


def test_maps_float32(golden):
    g = _cases(golden, 8)
    poses = jnp.asarray(g["poses"], jnp.float32)
    out = jax.jit(ctl.marbler_velocities)(poses, jnp.asarray(g["goals"], jnp.float32))
    assert out.dtype == jnp.float32
    np.testing.assert_allclose(out, g["dxu_marbler_nocbf"], atol=2e-5)
    np.testing.assert_allclose(ctl.uni_to_si_states(poses), g["xi"], atol=1e-6)


def test_unicycle_controllers_are_finite_and_converge():
    rng = np.random.default_rng(3)
    poses = rng.uniform([-1, -0.8, -np.pi], [1, 0.8, np.pi], size=(50, 3))
    goals = rng.uniform([-1, -0.8, -np.pi], [1, 0.8, np.pi], size=(50, 3))
    pos_u = ctl.clf_unicycle_position_controller(poses, goals)
    # rps formula: v = 0.8 rho cos(phi - theta), w = 3 rho sin(phi - theta)
    e = goals[:, :2] - poses[:, :2]
    phi = np.arctan2(e[:, 1], e[:, 0])
    rho = np.linalg.norm(e, axis=1)
    np.testing.assert_allclose(pos_u, np.stack([0.8 * rho * np.cos(phi - poses[:, 2]), 3 * rho * np.sin(phi - poses[:, 2])], 1))
    pose_u = ctl.clf_unicycle_pose_controller(poses, goals)
    assert np.all(np.isfinite(pose_u))
    # heading straight at the goal (alpha == 0): rps divides 0/0; we return the limit
    np.testing.assert_allclose(
        ctl.clf_unicycle_pose_controller(np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])), [[1.0, 0.0]]
    )
