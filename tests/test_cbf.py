"""Barrier certificates: rps tight-QP golden cases, invariants, closed-loop safety, robustness."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from marbler_jax import cbf, controllers, physics
from tests.conftest import robot_major
from tests.helpers import slow_unless

# golden file -> (kind, kwargs)
GOLDEN_CBF = {
    "si_cert2_marbler_safe": ("si2", dict(safety_radius=0.2)),
    "si_cert_default": ("si", {}),
    "si_cert_boundary_default": ("si_boundary", {}),
    "si_cert_boundary_r020": ("si_boundary", dict(safety_radius=0.2)),
    "uni_cert_default": ("uni", {}),
    "uni_cert2_default": ("uni2", {}),
    "uni_cert_boundary_default": ("uni_boundary", {}),
    "uni_cert_boundary_r015": ("uni_boundary", dict(safety_radius=0.15)),
}
NS = [2, 4, 6, 8, 20]


def _golden_cases(golden, fname):
    g = golden(f"cbf/{fname}.npz")
    for n in NS:
        c = g[n]
        yield n, robot_major(c["x"]), robot_major(c["u_nom"]), robot_major(c["u_out_tight"]), c["status_tight"] == 1


def _case_errors(kind, u, ref):
    """Per-case error relative to the acceptance tolerance (<= 1 means the case matches)."""
    err = np.abs(u - ref)
    scale = np.abs(ref).max(axis=(1, 2))
    if kind in cbf.UNI_KINDS:
        ratio_v = err[..., 0].max(1) / (5e-4 + 1e-3 * scale)
        ratio_w = err[..., 1].max(1) / (1e-2 + 2e-2 * scale)
        return np.maximum(ratio_v, ratio_w), err.max(axis=(1, 2))
    return err.max(axis=(1, 2)) / (5e-4 + 1e-3 * scale), err.max(axis=(1, 2))


@pytest.mark.parametrize("fname", sorted(GOLDEN_CBF))
def test_matches_rps_tight_qp(golden, fname, cbf_report):
    kind, kwargs = GOLDEN_CBF[fname]
    barrier = cbf.make_barrier(kind, **kwargs)
    for n, x, u_nom, ref, ok in _golden_cases(golden, fname):
        with jax.enable_x64(True):
            u, info = jax.jit(barrier.solve)(jnp.asarray(u_nom), jnp.asarray(x))
            u = np.asarray(u)
        assert np.all(np.isfinite(u)), f"{fname} N={n}: non-finite output"
        ratio, abs_err = _case_errors(kind, u, ref)
        match = ratio[ok] <= 1.0
        cbf_report.append((fname, n, int(ok.sum()), float(match.mean()), float(abs_err[ok].max()),
                           float(np.percentile(abs_err[ok], 99)), float(np.asarray(info.feasible)[ok].mean())))
        assert match.mean() >= 0.98, (
            f"{fname} N={n}: only {match.mean():.1%} of {ok.sum()} cases match; worst ratio {ratio[ok].max():.2f}"
        )


@pytest.mark.parametrize("kind", ["si2", "uni_boundary"])
def test_float32_close_to_float64(golden, kind):
    fname = {"si2": "si_cert2_marbler_safe", "uni_boundary": "uni_cert_boundary_default"}[kind]
    barrier = cbf.make_barrier(kind, **GOLDEN_CBF[fname][1])
    for n, x, u_nom, ref, ok in _golden_cases(golden, fname):
        if n > 8:
            continue
        u32 = np.asarray(jax.jit(barrier)(jnp.asarray(u_nom, jnp.float32), jnp.asarray(x, jnp.float32)))
        assert u32.dtype == np.float32 and np.all(np.isfinite(u32))
        ratio, _ = _case_errors(kind, u32.astype(np.float64), ref)
        assert (ratio[ok] <= 1.0).mean() >= 0.95, f"float32 {kind} N={n}"


def _random_problem(rng, batch, n, spread=1.2):
    x = rng.uniform([-spread, -0.8], [spread, 0.8], size=(batch, n, 2))
    u = rng.normal(size=(batch, n, 2)) * 0.15
    return x, u


def _min_separated(rng, batch, n, radius):
    """Configurations where every pair is outside the safety radius (well-posed problems)."""
    out = []
    while len(out) < batch:
        x, _ = _random_problem(rng, 1, n)
        d = physics.pair_distances(x[0])
        if d.min() > radius * 1.05:
            out.append(x[0])
    return np.stack(out)


@pytest.mark.parametrize("kind", ["si", "si2", "si_boundary"])
def test_constraints_hold_after_certification(kind):
    rng = np.random.default_rng(1)
    barrier = cbf.make_barrier(kind)
    x = _min_separated(rng, 64, 8, barrier.si_radius)
    u_nom = rng.normal(size=x.shape) * 0.2
    with jax.enable_x64(True):
        u, info = barrier.solve(jnp.asarray(u_nom), jnp.asarray(x))
    assert bool(np.all(info.solved)), f"max violation {float(np.max(info.max_violation)):.2e}"
    # independent re-check of every pair row: -2 e.u_i + 2 e.u_j <= gain h^3 (relative 1e-4)
    u = np.asarray(u)
    iu, ju = np.triu_indices(8, 1)
    e = x[:, iu] - x[:, ju]
    h = (e ** 2).sum(-1) - barrier.si_radius ** 2
    lhs = 2 * (e * (u[:, ju] - u[:, iu])).sum(-1)
    rhs = barrier.barrier_gain * h ** 3
    assert np.all(lhs - rhs <= 1e-4 * (1 + np.abs(rhs)))
    # the certificate changes nothing when the nominal input is already safe
    calm = np.zeros_like(u_nom)
    with jax.enable_x64(True):
        np.testing.assert_allclose(barrier(jnp.asarray(calm), jnp.asarray(x)), 0.0, atol=1e-12)


@pytest.mark.parametrize("kind", ["si2", "si_boundary"])
@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8])
def test_converged_solve_meets_the_kkt_conditions(kind, n):
    """Long float64 solves on crowded teams: the returned u and multipliers satisfy the QP's KKT
    conditions row by row (odd N has a phantom robot, N = 2 a single slot pair), so the solver's
    internal slot layout maps every robot and row back to its place."""
    rng = np.random.default_rng(n)
    barrier = cbf.make_barrier(kind, iterations=1500)
    x = rng.uniform([-1.4, -0.8], [-1.4 + 0.15 * n + 0.2, 0.8], size=(16, n, 2))
    u_nom = rng.normal(size=x.shape) * 0.2
    with jax.enable_x64(True):
        u, info = barrier.solve(jnp.asarray(u_nom), jnp.asarray(x))
    u, lam = np.asarray(u), np.asarray(info.multipliers.pairs)
    norm = np.linalg.norm(u_nom, axis=-1, keepdims=True)
    u_hat = u_nom * np.minimum(1, 0.2 / norm)
    first, second = cbf.round_robin(n)
    real = (first < n) & (second < n)
    grad = np.zeros_like(u)                       # A^T lambda, robot-major
    slack = []
    for (r, k), ok in np.ndenumerate(real):
        if not ok:
            assert np.all(lam[:, r, k] == 0)
            continue
        i, j = first[r, k], second[r, k]
        e = x[:, i] - x[:, j]
        h = (e * e).sum(-1) - barrier.si_radius ** 2
        gain = np.where(h < 0, barrier.unsafe_barrier_gain or barrier.barrier_gain, barrier.barrier_gain)
        row = 2 * (e * (u[:, j] - u[:, i])).sum(-1) - gain * h ** 3     # <= 0
        slack.append((row, lam[:, r, k]))
        grad[:, i] -= 2 * e * lam[:, r, k, None]
        grad[:, j] += 2 * e * lam[:, r, k, None]
    if kind == "si_boundary":
        lo, hi = np.asarray(info.multipliers.lower), np.asarray(info.multipliers.upper)
        grad += hi - lo
        assert lo.min() >= 0 and hi.min() >= 0
    np.testing.assert_allclose(u, u_hat - grad, atol=1e-7)          # stationarity
    for row, mult in slack:
        assert mult.min() >= 0                                    # dual feasibility
        assert row.max() <= 1e-7                                  # primal feasibility
        assert np.abs(row * mult).max() <= 1e-7                   # complementary slackness
    assert bool(np.all(info.solved))
    # feasible: solved, and no robot asked to go faster than a robot can
    speed = np.linalg.norm(u, axis=-1).max(axis=-1)
    np.testing.assert_array_equal(info.feasible, speed <= barrier.speed_limit * (1 + barrier.tolerance))


@pytest.mark.parametrize("kind", ["si2", "uni2"])
def test_a_certificate_faster_than_a_robot_is_not_feasible(kind):
    """Two robots 1 cm apart: the unsafe gain (1e6) of the ``*2`` kinds pushes them apart at hundreds
    of m/s, which no robot can follow, so ``feasible`` is False although the QP is solved; robots far
    apart stay feasible."""
    barrier = cbf.make_barrier(kind, iterations=200)
    pose = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, np.pi]])
    x = pose if barrier.is_unicycle else pose[:, :2]
    u_nom = np.array([[0.1, 0.0], [-0.1, 0.0]])
    with jax.enable_x64(True):
        u, info = barrier.solve(jnp.asarray(u_nom), jnp.asarray(x))
        far = x + np.array([[-0.5, 0, 0], [0.5, 0, 0]])[:, :x.shape[1]]
        _, calm = barrier.solve(jnp.asarray(u_nom), jnp.asarray(far))
    assert bool(calm.feasible) and bool(calm.solved)
    assert bool(info.solved) and not bool(info.feasible)
    assert np.isfinite(np.asarray(u)).all()


def test_single_active_constraint_is_exact():
    # two robots closing in head-on: one active row, solved in closed form by the first sweep
    barrier = cbf.make_barrier("si", iterations=1)
    x = np.array([[[0.0, 0.0], [0.2, 0.0]]])
    u_nom = np.array([[[0.2, 0.0], [-0.2, 0.0]]])
    u = barrier(u_nom, x)
    e = x[0, 0] - x[0, 1]
    h = e @ e - 0.17 ** 2
    a = np.concatenate([-2 * e, 2 * e])
    lam = (a @ u_nom[0].ravel() - 100 * h ** 3) / (a @ a)
    np.testing.assert_allclose(u[0].ravel(), u_nom[0].ravel() - lam * a, atol=1e-15)


@pytest.mark.parametrize("kind", cbf.KINDS)
def test_jit_vmap_numpy_agree(kind):
    rng = np.random.default_rng(2)
    barrier = cbf.make_barrier(kind, iterations=6)
    x, u = _random_problem(rng, 3, 5)
    if kind in cbf.UNI_KINDS:
        x = np.concatenate([x, rng.uniform(-np.pi, np.pi, size=(3, 5, 1))], axis=-1)
    with jax.enable_x64(True):
        xj, uj = jnp.asarray(x), jnp.asarray(u)
        eager = barrier(uj, xj)
        jitted = jax.jit(barrier)(uj, xj)
        vmapped = jax.vmap(barrier)(uj, xj)
        one = jax.jit(barrier)      # eager == jit is checked above: the loop compiles once
        looped = jnp.stack([one(uj[i], xj[i]) for i in range(3)])
    numpy_out = barrier(u, x)  # the numpy path (deployment bundle) runs the same code
    assert isinstance(numpy_out, np.ndarray)
    np.testing.assert_allclose(jitted, eager, atol=1e-12)
    np.testing.assert_allclose(vmapped, looped, atol=1e-12)
    np.testing.assert_allclose(numpy_out, eager, atol=1e-10)


@pytest.mark.parametrize("kind", ["si2", "si_boundary", "uni2", "uni_dd_boundary", "si_v2", "uni_boundary_v2"])
def test_warm_start_from_the_solution_stays_there(kind):
    # Warm-started from converged multipliers, one sweep reproduces the converged solution (the
    # multipliers fix the primal point); a cold single sweep does not. Also: jit/vmap/numpy agree.
    rng = np.random.default_rng(5)
    x, u = _random_problem(rng, 6, 7)
    if kind in cbf.UNI_KINDS:
        x = np.concatenate([x, rng.uniform(-np.pi, np.pi, size=(6, 7, 1))], axis=-1)
    one = cbf.make_barrier(kind, iterations=1)
    with jax.enable_x64(True):
        xj, uj = jnp.asarray(x), jnp.asarray(u)
        exact, info = jax.jit(cbf.make_barrier(kind, iterations=400).solve)(uj, xj)
        lam = info.multipliers
        assert lam.pairs.shape == (6, 7, 4)   # 8 slots (one phantom): 7 rounds of 4 pairs
        assert float(jnp.max(lam.pairs)) > 0
        if kind == "uni_dd_boundary":   # the wheel rows' multipliers are warm-started too
            assert float(jnp.max(lam.wheel_lower)) > 0 and float(jnp.max(lam.wheel_upper)) > 0
        if kind in cbf.V2_KINDS:        # and the magnitude polygon's
            assert lam.polygon.shape == (6, 7, 8) and float(jnp.max(lam.polygon)) > 0
            assert not bool(jnp.any(info.stopped))
        warm, warm_info = jax.jit(one.solve)(uj, xj, lam)
        cold = jax.jit(one)(uj, xj)
        vmapped = jax.vmap(lambda a, b, c: one.solve(a, b, c)[0])(uj, xj, lam)
        single = jax.jit(one.solve)(uj[0], xj[0], jax.tree_util.tree_map(lambda z: z[0], lam))[0]
        lam_max = float(jnp.max(lam.pairs))
    scale = float(np.abs(exact).max())
    np.testing.assert_allclose(warm, exact, atol=1e-6 * scale)
    assert float(np.abs(np.asarray(cold) - np.asarray(exact)).max()) > 1e-3 * scale
    np.testing.assert_allclose(vmapped, warm, atol=1e-10 * scale)
    np.testing.assert_allclose(single, warm[0], atol=1e-10 * scale)
    numpy_out, _ = one.solve(u, x, jax.tree_util.tree_map(lambda z: None if z is None else np.asarray(z), lam))
    np.testing.assert_allclose(numpy_out, warm, atol=1e-9 * scale)
    np.testing.assert_allclose(warm_info.multipliers.pairs, lam.pairs, atol=1e-6 * lam_max)


def test_warm_start_of_the_wrong_shape_is_rejected():
    barrier = cbf.make_barrier("si2")
    x = np.zeros((5, 2)) + np.arange(5)[:, None] * 0.5
    with pytest.raises(ValueError, match="warm_start shapes"):
        barrier.solve(np.zeros((5, 2)), x, barrier.initial_multipliers(4))
    with pytest.raises(ValueError, match="warm_start shapes"):
        cbf.make_barrier("si_boundary").solve(np.zeros((5, 2)), x, barrier.initial_multipliers(5))


def _closed_loop(kind, ticks=1000, n=20, seed=0):
    """n robots on a circle swap to the antipodal point, controller + CBF refreshed every tick.

    ``kind=None`` runs the same loop without a certificate. The v2 kinds warm-start each refresh from
    the last, as the env's robots' loop does: they stop a team whose last iterate is not feasible, and a
    20-robot ring with every pair row binding needs far more sweeps than one refresh's budget (cold, the
    ring stops for good at tick 16; rps v2's CVXOPT keeps it moving).
    """
    params = physics.PRESETS["robotarium"]
    barrier = cbf.make_barrier(kind) if kind else (lambda u, x: u)
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rng = np.random.default_rng(seed)
    start = np.stack([1.1 * np.cos(angles), 0.8 * np.sin(angles), angles + np.pi + rng.normal(0, 0.3, n)], -1)
    goals = -start[:, :2]

    warm = kind in cbf.V2_KINDS

    def certify(u, x, lam):
        if warm:
            u, info = barrier.solve(u, x, warm_start=lam)
            return u, info.multipliers
        return barrier(u, x), lam

    def tick(carry, _):
        poses, lam = carry
        if kind is None or kind in cbf.SI_KINDS:
            xi = controllers.uni_to_si_states(poses)
            dxi, lam = certify(controllers.si_position_controller(xi, goals), xi, lam)
            dxu = controllers.si_to_uni_mapping(dxi, poses)
        else:
            dxu, lam = certify(controllers.clf_unicycle_position_controller(poses, goals), poses, lam)
        new = physics.integrate(params, poses, dxu)
        return (new, lam), (physics.collisions(params, poses).any(), physics.out_of_bounds(params, poses).any(),
                            jnp.min(physics.pair_distances(poses[:, :2])))

    lam0 = barrier.initial_multipliers(n) if warm else None
    (final, _), (hits, outside, closest) = jax.jit(lambda p: jax.lax.scan(tick, (p, lam0), None, length=ticks))(
        jnp.asarray(start, jnp.float32))
    return np.asarray(final), np.asarray(hits), np.asarray(outside), np.asarray(closest), goals


# The default run keeps one closed loop per family: si2 (MARBLER's certificate), uni_boundary (rps's unicycle
# barrier with walls), uni_dd_boundary (the robust barrier) and uni_boundary_v2 (every v2 code path: polygon
# rows, boundary rows, the unicycle map, the stop rule; the v2 loops take 3x the sweeps). The other kinds build
# the same rows with the same solver (with or without walls, one gain or two) and run under -m slow.
DEFAULT_CLOSED_LOOP = {"si2", "uni_boundary", "uni_dd_boundary", "uni_boundary_v2"}


@pytest.mark.parametrize("kind", slow_unless(cbf.KINDS, DEFAULT_CLOSED_LOOP))
def test_closed_loop_twenty_robots_never_collide(kind):
    final, hits, outside, closest, goals = _closed_loop(kind)
    assert not hits.any(), f"{kind}: first collision at tick {int(np.argmax(hits))}"
    if "boundary" in kind:
        assert not outside.any()
    assert np.all(np.isfinite(final))
    # the swap makes progress (robots are not frozen by the certificate)
    progress = np.linalg.norm(final[:, :2] - goals, axis=-1)
    if kind == "uni_dd":
        # The robust barrier keeps projection points ~0.37 m apart (its disturbance term) and, without
        # walls, pushes robots off the arena; this swap then gridlocks in the centre (median 1.4 m
        # from the goals after 3000 ticks, still 1.4 after 6000). With walls it completes (0.03 m).
        return
    assert np.median(progress) < 1.0, f"{kind}: median distance to goal {np.median(progress):.2f} m"


def test_closed_loop_without_certificate_collides():
    # the scenario above is a real test: without a barrier the swap crashes robots into each other
    _, hits, _, _, _ = _closed_loop(None, ticks=600)
    assert hits.any()


finite = st.floats(-3, 3, allow_nan=False, allow_infinity=False, width=32)


@settings(max_examples=5, deadline=None)   # each new (kind, N) compiles a solver; each run draws new ones
@given(
    kind=st.sampled_from(cbf.KINDS),
    n=st.integers(1, 6),
    data=st.data(),
)
def test_never_nan_or_inf(kind, n, data):
    state_dim = 3 if kind in cbf.UNI_KINDS else 2
    x = np.array(data.draw(st.lists(finite, min_size=n * state_dim, max_size=n * state_dim)), np.float32)
    u = np.array(data.draw(st.lists(finite, min_size=2 * n, max_size=2 * n)), np.float32)
    x = x.reshape(n, state_dim)
    if data.draw(st.booleans()) and n > 1:
        x[1] = x[0]  # coincident robots: a degenerate, infeasible row
    barrier = cbf.make_barrier(kind, iterations=8)
    out, info = barrier.solve(jnp.asarray(u.reshape(n, 2)), jnp.asarray(x))
    assert np.all(np.isfinite(np.asarray(out)))
    assert np.isfinite(float(info.max_violation))
    if n > 1 and np.array_equal(x[0, :2], x[1, :2]) and state_dim == 2:
        assert not bool(info.feasible)


def test_bad_arguments_are_rejected_clearly():
    with pytest.raises(ValueError, match="unknown barrier kind 'qp'"):
        cbf.make_barrier("qp")
    with pytest.raises(ValueError, match="does not take \\['boundary_points'\\]"):
        cbf.make_barrier("si", boundary_points=(-1, 1, -1, 1))
    with pytest.raises(ValueError, match="safety_radius must be >= 0.12"):
        cbf.make_barrier("si", safety_radius=0.05)
    with pytest.raises(ValueError, match="magnitude_limit"):
        cbf.make_barrier("si2", magnitude_limit=0.5)
    with pytest.raises(ValueError, match="relaxation"):
        cbf.make_barrier("si2", relaxation=2.5)
    barrier = cbf.make_barrier("uni")
    with pytest.raises(ValueError, match=r"x \[\.\.\., N, 3\]"):
        barrier(np.zeros((4, 2)), np.zeros((4, 2)))


def test_round_robin_covers_every_pair_once():
    for n in range(1, 12):
        first, second = cbf.round_robin(n)
        pairs = {tuple(sorted(p)) for p in zip(first.ravel(), second.ravel()) if max(p) < n}
        assert pairs == {(i, j) for i in range(n) for j in range(i + 1, n)}
        assert len([p for p in zip(first.ravel(), second.ravel()) if max(p) < n]) == n * (n - 1) // 2



@pytest.mark.parametrize("kind", cbf.KINDS)
def test_a_non_finite_robot_is_taken_out_and_the_others_are_still_certified(kind):
    rng = np.random.default_rng(3)
    barrier = cbf.make_barrier(kind)
    dim = 3 if kind in cbf.UNI_KINDS else 2
    x = np.concatenate([rng.uniform(-1, 1, (6, 2)), rng.uniform(-3, 3, (6, dim - 2))], -1)
    u = rng.normal(size=(6, 2)) * 0.1
    alone, _ = barrier.solve(u[:5], x[:5])
    for bad in (("x", np.nan), ("x", np.inf), ("u", np.nan), ("x", 1e20), ("x", -cbf.FAR_AWAY * 1.01)):
        xb, ub = x.copy(), u.copy()
        (xb if bad[0] == "x" else ub)[5, 0] = bad[1]
        out, info = barrier.solve(ub, xb)
        np.testing.assert_array_equal(out[5], 0.0)
        np.testing.assert_allclose(out[:5], alone, atol=1e-12)
        assert not bool(info.feasible)
        jitted = np.asarray(jax.jit(barrier)(jnp.asarray(ub, jnp.float32), jnp.asarray(xb, jnp.float32)))
        assert np.all(np.isfinite(jitted)) and np.all(jitted[5] == 0)


@pytest.mark.parametrize("kind", ["si2", "si_boundary", "si_v2", "si_boundary_v2"])
def test_batch_minor_solve_matches_solve(kind):
    """``solve_minor`` (the env's per-tick entry: batch-minor arrays, no diagnostics) returns what
    ``solve`` does, cold and warm-started (the v2 kinds with their stop rule applied)."""
    rng = np.random.default_rng(5)
    barrier = cbf.make_barrier(kind, iterations=12)
    x, u = _random_problem(rng, 6, 5)
    x[0, 1] = x[0, 0] + 1e-3                     # two robots nearly on top of each other
    u[0, 0], u[0, 1] = (0.3, 0.0), (-0.3, 0.0)    # and driven into each other
    minor = lambda a: np.moveaxis(a, 0, -1)       # [B, ...] -> [..., B]  # noqa: E731
    with jax.enable_x64(True):
        expected, info = barrier.solve(jnp.asarray(u), jnp.asarray(x))
        got, multipliers = barrier.solve_minor(jnp.asarray(minor(u)), jnp.asarray(minor(x)))
        np.testing.assert_allclose(np.moveaxis(np.asarray(got), -1, 0), expected, atol=1e-12)
        for want, have in zip(info.multipliers, multipliers):
            if want is not None:
                np.testing.assert_allclose(np.moveaxis(np.asarray(have), -1, 0), want, atol=1e-12)
        warm_expected, _ = barrier.solve(jnp.asarray(u), jnp.asarray(x), warm_start=info.multipliers)
        warm_got, _ = barrier.solve_minor(jnp.asarray(minor(u)), jnp.asarray(minor(x)), multipliers)
        np.testing.assert_allclose(np.moveaxis(np.asarray(warm_got), -1, 0), warm_expected, atol=1e-12)
    with pytest.raises(ValueError, match="solve_minor takes the SI kinds"):
        cbf.make_barrier("uni2").solve_minor(jnp.zeros((4, 2, 1)), jnp.zeros((4, 2, 1)))
