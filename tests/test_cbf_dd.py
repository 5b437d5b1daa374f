"""The robust differential-drive barriers (``uni_dd``, ``uni_dd_boundary``) against their wheel-space QP.

No golden file covers these kinds (rps solves them with CVXOPT; without boundary rows it cannot run at
all, see ``shared/spec/robotarium.md`` 10.7). The reference here is the QP exactly as the spec writes
it -- wheel speeds ``w``, objective ``(w - w_hat)^T P (w - w_hat)`` with ``P = 2 L^T L``, rows
``A w >= b`` -- built independently of :mod:`marbler_jax.cbf`, and the solver's output must satisfy
its KKT conditions: primal feasibility, and a non-negative combination of the active rows that
cancels the objective's gradient (non-negative least squares). For a strictly convex QP that point is
the unique solution.
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import nnls

from marbler_jax import cbf
from tests.helpers import slow_unless

RADIUS = 0.2   # what JaxRobotarium's deployment passes
BOUNDS = (-1.6, 1.6, -1.0, 1.0)


def wheel_space_qp(poses, dxu, boundary: bool, gain=150.0, radius=RADIUS, d=0.05, disturbance=5.0,
                   wheel_limit=12.5, base_length=0.105, wheel_radius=0.016):
    """``(P, w_hat, A, b, D, kinds)`` of rps ``create_unicycle_differential_drive_barrier_certificate
    [_with_boundary]`` (spec 10.7 / 10.8), rows ``A w >= b``; ``kinds`` names each row's type."""
    n = len(poses)
    D = np.array([[wheel_radius / 2, wheel_radius / 2], [-wheel_radius / base_length, wheel_radius / base_length]])
    w_hat = np.concatenate([np.linalg.solve(D, dxu[k]) for k in range(n)])
    L_all = np.kron(np.eye(n), np.diag([1.0, d]) @ D)
    P = 2 * L_all.T @ L_all
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    p = poses[:, :2] + d * np.stack([c, s], -1)
    G = [np.array([[c[k], -d * s[k]], [s[k], d * c[k]]]) @ D for k in range(n)]
    rows, rhs, kinds = [], [], []

    def add(coef_by_robot, value, kind):
        row = np.zeros(2 * n)
        for k, coef in coef_by_robot:
            row[2 * k:2 * k + 2] = coef
        rows.append(row), rhs.append(value), kinds.append(kind)

    for i, j in itertools.combinations(range(n), 2):
        delta = p[i] - p[j]
        h = delta @ delta - radius ** 2
        a_i, a_j = 2 * delta @ G[i], -2 * delta @ G[j]
        # min over the disturbance corners of a.w is -disturbance * |a|_1
        add([(i, a_i), (j, a_j)], -gain * h ** 3 + disturbance * (np.abs(a_i).sum() + np.abs(a_j).sum()), "pair")
    if boundary:
        x_min, x_max, y_min, y_max = BOUNDS
        g = 0.4 * gain
        for k in range(n):
            gx, gy = G[k]
            add([(k, -gy)], -g * (y_max - radius / 2 - p[k, 1]) ** 3, "wall")
            add([(k, gy)], -g * (p[k, 1] - y_min - radius / 2) ** 3, "wall")
            add([(k, -gx)], -g * (x_max - radius / 2 - p[k, 0]) ** 3, "wall")
            add([(k, gx)], -g * (p[k, 0] - x_min - radius / 2) ** 3, "wall")
    for sign in (-1.0, 1.0):
        for k in range(2 * n):
            row = np.zeros(2 * n)
            row[k] = sign
            rows.append(row), rhs.append(-wheel_limit), kinds.append("wheel")
    return P, w_hat, np.array(rows), np.array(rhs), D, np.array(kinds)


def _teams(rng, batch, n, spread):
    """Random poses ``[batch, n, 3]`` with centres > 0.25 m apart inside ``spread`` x the arena."""
    teams = []
    while len(teams) < batch:
        points = []
        while len(points) < n:
            q = rng.uniform([-1.4, -0.85], [1.4, 0.85]) * spread
            if all(np.linalg.norm(q - other) > 0.25 for other in points):
                points.append(q)
        teams.append(np.concatenate([np.array(points), rng.uniform(-np.pi, np.pi, (n, 1))], -1))
    return np.stack(teams)


def _commands(rng, batch, n):
    """(v, omega) up to 0.2 m/s and 3 rad/s: often beyond the 12.5 rad/s wheel limit."""
    return np.stack([rng.uniform(-0.2, 0.2, (batch, n)), rng.uniform(-3, 3, (batch, n))], -1)


@pytest.mark.parametrize("kind", cbf.DD_KINDS)
def test_solution_satisfies_the_wheel_space_kkt_conditions(kind):
    rng = np.random.default_rng(7)
    boundary = kind.endswith("boundary")
    barrier = cbf.make_barrier(kind, safety_radius=RADIUS, iterations=2000)
    active_kinds = set()
    checked = 0
    for n, spread in ((2, 0.7), (3, 1.0), (4, 0.7), (6, 1.0), (10, 0.7)):   # spread 1.0: walls near
        poses, dxu = _teams(rng, 12, n, spread), _commands(rng, 12, n)
        out, info = barrier.solve(dxu, poses)           # float64 numpy: the same code as under jit
        for x, u_nom, u, feasible in zip(poses, dxu, out, info.feasible):
            if not feasible:     # crowded teams can be infeasible: checked in the next test
                continue
            P, w_hat, A, b, D, kinds = wheel_space_qp(x, u_nom, boundary)
            w = np.concatenate([np.linalg.solve(D, u[k]) for k in range(n)])
            slack = (A @ w - b) / np.linalg.norm(A, axis=1)
            assert slack.min() >= -1e-9, f"N={n}: a {kinds[np.argmin(slack)]} row is violated by {-slack.min():.2e}"
            active = slack <= 1e-7
            gradient = P @ (w - w_hat)
            _, residual = nnls(A[active].T, gradient) if active.any() else (None, np.linalg.norm(gradient))
            assert residual <= 1e-8 * (1 + np.linalg.norm(gradient)), f"N={n}: not optimal, residual {residual:.2e}"
            active_kinds |= set(kinds[active])
            checked += 1
    assert checked >= 40
    # every row type took part somewhere, so each was checked as an active constraint
    assert active_kinds == ({"pair", "wheel", "wall"} if boundary else {"pair", "wheel"})


# uni_dd_boundary's rows are uni_dd's plus the walls: the default run checks it, -m slow both
@pytest.mark.parametrize("kind", slow_unless(cbf.DD_KINDS, set(cbf.DD_KINDS) - {"uni_dd"}))
def test_default_sweeps_in_float32_match_the_converged_solution(kind):
    # the golden files' acceptance rule for unicycle kinds, on random teams of 4 / 10 / 20 robots
    rng = np.random.default_rng(3)
    for n, spread in ((4, 0.6), (10, 0.6), (20, 1.0)):
        poses, dxu = _teams(rng, 100, n, spread), _commands(rng, 100, n)
        with jax.enable_x64(True):
            ref, info = jax.jit(cbf.make_barrier(kind, safety_radius=RADIUS, iterations=3000).solve)(
                jnp.asarray(dxu), jnp.asarray(poses))
        out, info32 = jax.jit(cbf.make_barrier(kind, safety_radius=RADIUS).solve)(
            jnp.asarray(dxu, jnp.float32), jnp.asarray(poses, jnp.float32))
        ref, out, ok = np.asarray(ref), np.asarray(out, np.float64), np.asarray(info.feasible)
        assert np.all(np.isfinite(out)) and ok.mean() >= 0.9
        err, scale = np.abs(out - ref), np.abs(ref).max(axis=(1, 2))
        ratio = np.maximum(err[..., 0].max(1) / (5e-4 + 1e-3 * scale), err[..., 1].max(1) / (1e-2 + 2e-2 * scale))
        assert (ratio[ok] <= 1).mean() >= 0.97, f"{kind} N={n}: {(ratio[ok] <= 1).mean():.1%} match"
        # an infeasible team (robots too close to separate within the wheel limits) is flagged
        assert np.all(np.asarray(info32.feasible)[~ok] == False)  # noqa: E712


def test_crowded_team_is_flagged_infeasible_and_backs_away():
    # two robots facing each other with projection points 2 mm apart would have to separate faster
    # than their wheels allow: the QP is infeasible. The output is finite, flagged, and both robots
    # back away at about the wheel limit (the last sweep is not over-relaxed).
    poses = np.array([[0.0, 0.0, 0.0], [0.102, 0.0, np.pi]])
    for iterations in (4, None, 400):      # None: the default budget
        out, info = cbf.make_barrier("uni_dd", iterations=iterations).solve(np.zeros((2, 2)), poses)
        assert np.all(np.isfinite(out)) and not bool(info.feasible) and float(info.max_violation) > 0
        assert np.all(out[:, 0] < 0), out
        wheels = np.abs(out[:, :1] + np.array([-1, 1]) * out[:, 1:] * 0.105 / 2) / 0.016
        assert 12.5 * 0.99 <= wheels.max() <= 12.5 * 1.25, wheels


def test_nothing_changes_when_far_apart_and_slow():
    poses = np.array([[-1.0, 0.0, 0.3], [1.0, 0.0, -2.0], [0.0, 0.6, 1.0]])
    dxu = np.array([[0.1, 0.5], [-0.05, -1.0], [0.0, 0.0]])
    for kind in cbf.DD_KINDS:
        np.testing.assert_allclose(cbf.make_barrier(kind)(dxu, poses), dxu, atol=1e-12)


def test_bad_wheel_model_is_rejected_clearly():
    with pytest.raises(ValueError, match="disturbance must be a finite value >= 0"):
        cbf.make_barrier("uni_dd", disturbance=-1)
    with pytest.raises(ValueError, match="wheel_vel_limit must be finite and > 0"):
        cbf.make_barrier("uni_dd_boundary", wheel_vel_limit=0)
    with pytest.raises(ValueError, match="does not take \\['magnitude_limit'\\]"):
        cbf.make_barrier("uni_dd", magnitude_limit=0.2)
