"""The Robotarium's rps v2 barriers: golden cases, the whole-team stop, the magnitude polygon, obstacles."""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from marbler_jax import cbf
from tests.conftest import robot_major
from tests.test_cbf import NS, _case_errors

# golden file (../shared/golden/cbf_v2, README section (e)) -> kind, all at rps v2's defaults
GOLDEN_V2 = {
    "si_v2_default": "si_v2",
    "si_boundary_v2_default": "si_boundary_v2",
    "uni_v2_default": "uni_v2",
    "uni_boundary_v2_default": "uni_boundary_v2",
}


def _cases(golden, fname):
    g = golden(f"cbf_v2/{fname}.npz")
    for n in NS:
        c = g[n]
        yield (n, robot_major(c["x"]), robot_major(c["u_nom"]), robot_major(c["u_out_tight"]),
               c["status_tight"] == 1, c["zeroed"].astype(bool))


@pytest.mark.parametrize("fname", sorted(GOLDEN_V2))
def test_matches_rps_v2_tight_qp(golden, fname, cbf_report):
    kind = GOLDEN_V2[fname]
    barrier = cbf.make_barrier(kind)
    for n, x, u_nom, ref, optimal, zeroed in _cases(golden, fname):
        with jax.enable_x64(True):
            u, info = jax.jit(barrier.solve)(jnp.asarray(u_nom), jnp.asarray(x))
            u = np.asarray(u)
        assert np.all(np.isfinite(u)), f"{fname} N={n}: non-finite output"
        ok = optimal & ~zeroed
        ratio, abs_err = _case_errors(kind, u, ref)
        match = ratio[ok] <= 1.0
        cbf_report.append((fname, n, int(ok.sum()), float(match.mean()), float(abs_err[ok].max()),
                           float(np.percentile(abs_err[ok], 99)), float(np.asarray(info.feasible)[ok].mean())))
        assert match.mean() >= 0.98, (
            f"{fname} N={n}: only {match.mean():.1%} of {ok.sum()} cases match; worst ratio {ratio[ok].max():.2f}")


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("fname", sorted(GOLDEN_V2))
def test_stops_exactly_the_teams_rps_v2_stops(golden, fname, dtype):
    """rps v2 commands zero velocity to every robot when its QP is not 'optimal' (``zeroed``): the
    same teams are stopped here, on every golden case, and no other team is; the decision also
    agrees with the tight solver's status wherever rps v2's own loose solver does."""
    barrier = cbf.make_barrier(GOLDEN_V2[fname])
    stops = agree = total = 0
    for n, x, u_nom, _, optimal, zeroed in _cases(golden, fname):
        with jax.enable_x64(dtype == np.float64):
            u, info = jax.jit(barrier.solve)(jnp.asarray(u_nom, dtype), jnp.asarray(x, dtype))
            u, stopped = np.asarray(u), np.asarray(info.stopped)
        mismatched = np.flatnonzero(stopped != zeroed)
        assert mismatched.size == 0, f"{fname} N={n} {dtype.__name__}: cases {mismatched} stopped != rps zeroed"
        assert np.all(u[zeroed] == 0) and np.all(np.abs(u[~zeroed]).max(axis=(1, 2)) > 0)
        stops += int(zeroed.sum())
        agree += int((stopped == ~optimal).sum())
        total += len(zeroed)
    assert agree >= total - 1, f"{fname}: stop decision agrees with status_tight on {agree}/{total}"
    if fname.startswith("uni_v2"):
        assert stops >= 40           # the golden set exercises the stop (1/2/4/10/26 of 100 at N = 2..20)


def test_polygon_rows_limit_the_magnitude_as_rps_v2():
    # Two robots far apart: only each robot's eight magnitude rows can act. si_v2's first row (+x) has
    # the full limit, the seven others cos(pi/8) of it; the boundary kind gives all eight cos(pi/8).
    x = np.array([[-1.0, 0.0], [1.0, 0.0]])
    u_nom = np.array([[0.5, 0.0], [0.0, 0.5]])
    inner = 0.2 * math.cos(math.pi / 8)
    u = cbf.make_barrier("si_v2")(u_nom, x)
    np.testing.assert_allclose(u, [[0.2, 0.0], [0.0, inner]], atol=1e-9)
    u = cbf.make_barrier("si_boundary_v2")(u_nom, x)
    np.testing.assert_allclose(u, [[inner, 0.0], [0.0, inner]], atol=1e-9)
    # a diagonal command lands on the diagonal row: n . u = cos(pi/8) m, u along the normal
    u = cbf.make_barrier("si_v2")(np.array([[0.3, 0.3], [0.0, 0.0]]), x)
    np.testing.assert_allclose(u[0], [inner / math.sqrt(2)] * 2, atol=1e-9)
    # a small command is left alone (no capping of u_nom in v2, no rows active)
    small = np.array([[0.05, -0.1], [0.0, 0.02]])
    np.testing.assert_allclose(cbf.make_barrier("si_v2")(small, x), small, atol=1e-12)


def test_unicycle_v2_keeps_omega_unclipped_and_uses_twice_the_projection():
    # omega = lateral / d: 3.5 rad/s at d = 0.05 is 0.175 m/s laterally, inside the polygon, and
    # rps v2 maps back without the 2023 mapping's +-pi clip.
    poses = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    u_nom = np.array([[0.0, 3.5], [0.05, -3.0]])
    barrier = cbf.make_barrier("uni_v2")
    np.testing.assert_allclose(barrier(u_nom, poses), u_nom, atol=1e-9)
    assert barrier.si_radius == pytest.approx(0.15 + 2 * 0.05)
    assert cbf.make_barrier("uni_boundary_v2").si_radius == pytest.approx(0.12 + 2 * 0.03)
    assert cbf.make_barrier("uni").si_radius == pytest.approx(0.12 + 0.05)


@pytest.mark.parametrize("kind", cbf.V2_KINDS)
def test_a_lone_robot_passes_through(kind):
    state = 3 if kind in cbf.UNI_KINDS else 2
    u_nom = np.array([[0.9, 7.0]])                      # beyond every limit: rps v2 returns it as is
    x = np.zeros((1, state))
    u, info = cbf.make_barrier(kind).solve(u_nom, x)
    np.testing.assert_array_equal(u, u_nom)
    assert bool(info.feasible) and not bool(info.stopped)
    u = jax.jit(cbf.make_barrier(kind))(jnp.asarray(u_nom[None], jnp.float32), jnp.zeros((1, 1, state)))
    np.testing.assert_allclose(u[0], u_nom, rtol=1e-6)


def test_a_team_that_cannot_be_made_safe_is_stopped_and_one_that_can_stand_still_is_not():
    barrier = cbf.make_barrier("uni_v2")
    # projection points 0.02 m apart (radius 0.25): the required separation speed exceeds the polygon
    poses = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0]])
    u, info = barrier.solve(np.array([[0.1, 0.0], [0.1, 0.0]]), poses)
    assert bool(info.stopped) and not bool(info.feasible)
    np.testing.assert_array_equal(u, 0.0)
    # outside each other's radius every right-hand side is >= 0: standing still is admissible, so the
    # team is never stopped, whatever the budget reached
    apart = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, np.pi]])
    u, info = cbf.make_barrier("uni_v2", iterations=1).solve(np.array([[0.2, 0.0], [0.2, 0.0]]), apart)
    assert not bool(info.stopped) and np.abs(u).max() > 0


def test_obstacles_are_robots_with_zero_nominal_velocity():
    barrier = cbf.make_barrier("uni_boundary_v2")
    poses = np.array([[-0.5, 0.0, 0.0], [0.8, 0.5, 0.0]])
    u_nom = np.array([[0.2, 0.0], [0.0, 0.0]])
    free = barrier(u_nom, poses)
    # an obstacle 0.25 m ahead of robot 0 slows it; one far away changes nothing
    near = barrier(u_nom, poses, obstacles=np.array([[-0.2, 0.0]]))
    far = barrier(u_nom, poses, obstacles=np.array([[1.4, -0.8]]))
    assert near[0, 0] < 0.7 * free[0, 0]
    np.testing.assert_allclose(far, free, atol=1e-9)
    # the same through jit with a batch, and the multipliers cover robots + obstacles
    with jax.enable_x64(True):
        u, info = jax.jit(barrier.solve)(jnp.asarray(u_nom[None]), jnp.asarray(poses[None]),
                                         obstacles=jnp.asarray([[[-0.2, 0.0]]]))
    np.testing.assert_allclose(u[0], near, atol=1e-9)
    assert info.multipliers.polygon.shape == (1, 3, 8)
    with pytest.raises(ValueError, match="takes no obstacles"):
        cbf.make_barrier("uni_v2")(u_nom, poses, obstacles=np.zeros((1, 2)))
    with pytest.raises(ValueError, match="obstacles must be"):
        barrier(u_nom, poses, obstacles=np.zeros((2, 3)))
