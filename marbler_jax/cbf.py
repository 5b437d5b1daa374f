"""Robotarium barrier certificates (CBF safety filters) as fixed-iteration, batched QP solvers.

``certify = make_barrier(kind, **params)`` returns a :class:`Barrier`; ``certify(u_nom, x)`` gives
the certified input and ``certify.solve(u_nom, x)`` also returns :class:`CertificateInfo`
diagnostics. Shapes are robot-major and batched over leading axes:

* SI kinds (``"si"``, ``"si2"``, ``"si_boundary"``): ``x`` = positions ``[..., N, 2]`` [m],
  ``u`` = SI velocities ``[..., N, 2]`` [m/s].
* unicycle kinds (``"uni"``, ``"uni2"``, ``"uni_boundary"``): ``x`` = poses ``[..., N, 3]``,
  ``u`` = (v [m/s], omega [rad/s]) ``[..., N, 2]``. They work on the projection point
  ``p = (x, y) + d (cos theta, sin theta)`` with the SI certificate at radius ``safety_radius + d``
  and map back with omega clipped to +-pi, as rps does.

The QP (rps 6bb184e, ``shared/spec/robotarium.md`` section 10) is
``min ||u - u_hat||^2  s.t.  A u <= b`` where ``u_hat`` is ``u_nom`` with each robot's norm capped
at ``magnitude_limit``, and for every pair i < j with ``e = x_i - x_j``, ``h = |e|^2 - r^2``::

    -2 e.u_i + 2 e.u_j <= gain * h^3          (gain -> unsafe_barrier_gain when h < 0 for *2 kinds)

``*_boundary`` kinds add, per robot, ``u_y <= 0.4 gain (y_max - r/2 - y)^3``,
``-u_y <= 0.4 gain (y - y_min - r/2)^3`` and the same for x. The output is not re-clipped.

The robust differential-drive kinds ``"uni_dd"`` / ``"uni_dd_boundary"`` (rps-2023/2024
``create_unicycle_differential_drive_barrier_certificate[_with_boundary]``, Glotfelter et al.;
``shared/spec/robotarium.md`` sections 10.7-10.8; the second is what JaxRobotarium's numpy
deployment runs, with ``safety_radius=0.2``) pose their QP in wheel speeds ``w_k = D^-1 (v, omega)_k``:
``min sum_k |diag(1, d) D (w_k - w_hat_k)|^2`` with pair rows on the projection points
(``h = |e|^2 - r^2``, no ``+ d``) tightened by a wheel-speed disturbance
``delta (|2 e^T M_i D|_1 + |2 e^T M_j D|_1)``, boundary rows as above (``0.4 gain``, margin ``r/2``) and
wheel limits ``|w| <= wheel_vel_limit``. Since ``diag(1, d) D w_k`` is the projection point's velocity
rotated into the robot's frame, the same QP in ``u_k`` = projection-point velocity has the identity
Hessian: pair rows of the form above with ``b = gain h^3 - disturbance term``, the boundary boxes, and
per robot two slabs ``|c_wheel . u_k| <= wheel_vel_limit``. It is solved in that form and mapped back
exactly (``omega`` is not clipped; ``u_hat`` is not capped: rps takes ``D^-1 dxu`` as it is). rps
builds its buffers for at most 30 robots; here any N works. rps solves it with CVXOPT (loose default
tolerances, status unchecked); this solver aims at the exact QP solution.

Solver. The Hessian is the identity, so the dual is a non-negative QP whose coordinate ascent
(Hildreth's method) has a closed-form step per row: ``dl = max(-l_k, w (a_k.u - b_k) / |a_k|^2)``,
``u -= a_k dl``. A single violated constraint is solved exactly by one such step. We run a
*fixed* number of sweeps (so the solver jits and vmaps) with over-relaxation ``w`` (SOR; the
stiff ``*2`` cases converge several times faster with ``w = 1.5 .. 1.7`` than plain Gauss-Seidel) and
exploit the structure:

* a pair row touches two robots only. The C(N,2) pairs are grouped into N-1 rounds of a
  round-robin tournament; the pairs of a round are disjoint, so a whole round is updated at once
  with exactly the Gauss-Seidel result (N-1 vector steps per sweep instead of C(N,2) scalar ones);
* boundary rows act on one coordinate each and are handled as per-robot boxes in one step;
* distant pairs have ``b`` far above anything ``A u`` reaches and simply keep ``l = 0``;
* ``solve(..., warm_start=info.multipliers)`` starts from an earlier solve's multipliers and the
  primal point ``u_hat - A^T l`` they give (a consecutive control refresh barely moves the optimum).

The solver never divides by zero: rows with ``e = 0`` (coincident robots) are skipped and reported.
If the constraints are infeasible (coincident robots, boxes with lo > hi, or conflicting walls)
the fixed budget still returns finite velocities, and ``CertificateInfo.feasible`` is False.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import numpy as np

from marbler_jax import controllers
from marbler_jax._xp import fori_loop, from_minor, is_jax, namespace, result_dtype, to_minor, vmap_in_place

SI_KINDS = ("si", "si2", "si_boundary")
DD_KINDS = ("uni_dd", "uni_dd_boundary")
UNI_KINDS = ("uni", "uni2", "uni_boundary") + DD_KINDS
KINDS = SI_KINDS + UNI_KINDS

# rps 6bb184e defaults per kind.
_DEFAULTS: dict[str, dict[str, Any]] = {
    "si": dict(barrier_gain=100.0, safety_radius=0.17, magnitude_limit=0.2),
    "si2": dict(barrier_gain=100.0, unsafe_barrier_gain=1e6, safety_radius=0.17, magnitude_limit=0.2),
    "si_boundary": dict(barrier_gain=100.0, safety_radius=0.17, magnitude_limit=0.2,
                        boundary_points=(-1.6, 1.6, -1.0, 1.0)),
    "uni": dict(barrier_gain=100.0, safety_radius=0.12, projection_distance=0.05, magnitude_limit=0.2),
    "uni2": dict(barrier_gain=500.0, unsafe_barrier_gain=1e6, safety_radius=0.12,
                 projection_distance=0.05, magnitude_limit=0.2),
    "uni_boundary": dict(barrier_gain=100.0, safety_radius=0.12, projection_distance=0.05,
                         magnitude_limit=0.2, boundary_points=(-1.6, 1.6, -1.0, 1.0)),
    # rps-2023/2024 create_unicycle_differential_drive_barrier_certificate(_with_boundary)
    "uni_dd": dict(barrier_gain=150.0, safety_radius=0.17, projection_distance=0.05, disturbance=5.0,
                   wheel_vel_limit=12.5, base_length=0.105, wheel_radius=0.016),
    "uni_dd_boundary": dict(barrier_gain=150.0, safety_radius=0.17, projection_distance=0.05, disturbance=5.0,
                            wheel_vel_limit=12.5, base_length=0.105, wheel_radius=0.016,
                            boundary_points=(-1.6, 1.6, -1.0, 1.0)),
}


class Multipliers(NamedTuple):
    """Dual variables of one certification (what :meth:`Barrier.solve` can warm-start from).

    Attributes:
        pairs: ``[..., R, H]`` pair-row multipliers in the round layout of :func:`round_robin`.
        lower, upper: ``[..., N, 2]`` multipliers of the boundary boxes (``*_boundary`` kinds),
            else ``None``.
        wheel_lower, wheel_upper: ``[..., N, 2]`` multipliers of the wheel-speed limits
            ``-limit <= omega_wheel`` and ``omega_wheel <= limit`` (left, right wheel; ``uni_dd*``
            kinds), else ``None``.
    """

    pairs: Any
    lower: Any = None
    upper: Any = None
    wheel_lower: Any = None
    wheel_upper: Any = None


class CertificateInfo(NamedTuple):
    """Diagnostics of one certification, each ``[...]`` (batch shape) except ``multipliers``.

    Attributes:
        max_violation: largest constraint violation of the returned SI velocity, measured as a
            distance in velocity space ``(a.u - b) / |a|`` [m/s] (<= 0 when every row holds).
        feasible: ``max_violation <= tolerance * (1 + max |u|)`` and no degenerate row
            (coincident robots that must separate); False means the returned input is the best
            the fixed budget found for a problem that is infeasible or not yet solved.
        active: number of rows with a positive multiplier.
        multipliers: the final :class:`Multipliers`; pass them as ``warm_start`` to the next solve
            of a nearby problem (the next control refresh of the same team).
    """

    max_violation: Any
    feasible: Any
    active: Any
    multipliers: Any = None


@functools.lru_cache(maxsize=None)
def round_robin(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of ``n`` robots grouped into rounds of disjoint pairs (circle method).

    Returns ``(first, second)``, each ``[R, H]``: round ``r`` pairs robot ``first[r, k]`` with
    ``second[r, k]``. ``R = n' - 1`` rounds of ``H = n'/2`` pairs with ``n' = n + n % 2``; index ``n``
    is a phantom robot for odd ``n``. The order is the circle method's: keep the players in a row,
    pair slot ``k`` with slot ``n' - 1 - k``, then rotate slots ``1..n'-1`` right by one, so the solver
    only ever slices, reverses and rotates -- no gathers in its inner loop.
    """
    m = n + n % 2
    players = list(range(m))
    firsts, seconds = [], []
    for _ in range(max(m - 1, 0)):
        firsts.append(players[: m // 2])
        seconds.append(players[m // 2:][::-1])
        players = [players[0], players[-1]] + players[1:-1]
    shape = (max(m - 1, 0), m // 2)
    return np.array(firsts, np.int32).reshape(shape), np.array(seconds, np.int32).reshape(shape)


def default_iterations(n: int) -> int:
    """Sweeps used when ``iterations`` is not given: ``20 + 4 N`` (at most 250).

    Chosen on the rps tight-QP golden cases, where every kind then matches >= 99 % of the cases
    for N <= 20 (the clustered wall cases at N = 6 need ~45 sweeps, the stiff ``*2`` cases at
    N = 20 about 100). Callers with easier problems (robots kept apart by the certificate itself,
    as inside the env) can pass fewer ``iterations``.
    """
    return int(min(20 + 4 * n, 250))


def default_relaxation(n: int) -> float:
    """Over-relaxation used when ``relaxation`` is not given: 1.5 up to 10 robots, 1.7 above.

    Larger teams have longer coupling chains; the stiff ``*2`` cases at N = 20 need 1.7 to converge
    within the default budget, while small teams converge faster with 1.5.
    """
    return 1.5 if n <= 10 else 1.7


@dataclasses.dataclass(frozen=True)
class Barrier:
    """A configured barrier certificate; call it as ``certify(u_nom, x) -> u``.

    Build it with :func:`make_barrier`. All fields are static (hashable), so a ``Barrier`` can be
    closed over or passed as a static argument to ``jax.jit``.
    """

    kind: str
    safety_radius: float
    barrier_gain: float
    magnitude_limit: float | None      # None: u_nom is not capped (uni_dd kinds)
    unsafe_barrier_gain: float | None = None
    projection_distance: float | None = None
    boundary_points: tuple[float, float, float, float] | None = None
    disturbance: float | None = None        # uni_dd kinds: wheel-speed disturbance [rad/s]
    wheel_vel_limit: float | None = None    # uni_dd kinds: |wheel speed| limit [rad/s]
    base_length: float | None = None        # uni_dd kinds: wheel separation [m]
    wheel_radius: float | None = None       # uni_dd kinds [m]
    iterations: int | None = None
    relaxation: float | None = None
    tolerance: float = 1e-4

    @property
    def is_unicycle(self) -> bool:
        return self.kind in UNI_KINDS

    @property
    def is_differential_drive(self) -> bool:
        return self.kind in DD_KINDS

    @property
    def si_radius(self) -> float:
        """Safety radius of the SI problem (``safety_radius + projection_distance`` for the rps
        unicycle kinds; the ``uni_dd`` kinds apply ``safety_radius`` to the projection points)."""
        if self.is_differential_drive:
            return self.safety_radius
        return self.safety_radius + (self.projection_distance or 0.0) * self.is_unicycle

    def sweeps(self, n: int) -> int:
        """Coordinate-ascent sweeps used for a team of ``n`` robots."""
        return self.iterations if self.iterations is not None else default_iterations(n)

    def omega(self, n: int) -> float:
        """Over-relaxation factor used for a team of ``n`` robots."""
        return self.relaxation if self.relaxation is not None else default_relaxation(n)

    def __call__(self, u_nom, x):
        return self.solve(u_nom, x)[0]

    def initial_multipliers(self, n: int, batch_shape=(), dtype=np.float32, xp=np) -> Multipliers:
        """Zero :class:`Multipliers` for a team of ``n`` robots (a cold start)."""
        rounds, half = round_robin(n)[0].shape
        per_robot = xp.zeros(tuple(batch_shape) + (n, 2), dtype)
        box = None if self.boundary_points is None else per_robot
        wheels = per_robot if self.is_differential_drive else None
        return Multipliers(xp.zeros(tuple(batch_shape) + (rounds, half), dtype), box, box, wheels, wheels)

    def solve(self, u_nom, x, warm_start: Multipliers | None = None):
        """Certify ``u_nom`` at state ``x``; returns ``(u, CertificateInfo)``.

        ``warm_start``: multipliers of a previous solve of this barrier for the same team
        (``info.multipliers``), e.g. the last control refresh. The QP's solution does not depend
        on it (the problem is strictly convex); it only starts the sweeps nearer to it, so fewer
        ``iterations`` reach the same accuracy when the robots moved little since.
        """
        xp = namespace(u_nom, x)
        dtype = result_dtype(xp, u_nom, x)
        u_nom = xp.asarray(u_nom, dtype=dtype)
        x = xp.asarray(x, dtype=dtype)
        state_dim = 3 if self.is_unicycle else 2
        if x.shape[-1] != state_dim or u_nom.shape[-1] != 2 or x.shape[-2] != u_nom.shape[-2]:
            raise ValueError(
                f"barrier {self.kind!r} expects x [..., N, {state_dim}] and u_nom [..., N, 2]; "
                f"got x {tuple(x.shape)} and u_nom {tuple(u_nom.shape)}"
            )
        if warm_start is not None:
            warm_start = Multipliers(*(None if w is None else xp.asarray(w, dtype=dtype) for w in warm_start))
            expected = self.initial_multipliers(x.shape[-2], x.shape[:-2], xp=np)
            shapes = [None if w is None else tuple(w.shape) for w in warm_start]
            if shapes != [None if w is None else tuple(w.shape) for w in expected]:
                raise ValueError(f"warm_start shapes {shapes} do not match this barrier's multipliers for "
                                 f"x {tuple(x.shape)}: {[None if w is None else w.shape for w in expected]}")
        if is_jax(u_nom, x):
            return _jax_solver(self)(u_nom, x, warm_start)
        return self._solve(u_nom, x, warm_start)

    def _solve(self, u_nom, x, warm_start=None):
        if not self.is_unicycle:
            return solve_si(self, u_nom, x, warm_start)
        d = self.projection_distance
        points = controllers.uni_to_si_states(x, d)
        dxi = controllers.uni_to_si_dynamics(u_nom, x, d)
        if self.is_differential_drive:   # exact inverse of uni_to_si_dynamics: no omega clip
            dxi, info = solve_si(self, dxi, points, warm_start, headings=x[..., 2])
            return controllers.si_to_uni_mapping(dxi, x, d, angular_velocity_limit=math.inf), info
        dxi, info = solve_si(self, dxi, points, warm_start)
        return controllers.si_to_uni_mapping(dxi, x, d), info


@functools.lru_cache(maxsize=None)
def _jax_solver(barrier: Barrier):
    """``barrier._solve`` with a vmap rule that keeps the batch on the minor axis (the solver folds
    every batch axis into the minor, SIMD, axis; see :func:`marbler_jax._xp.vmap_in_place`)."""
    return vmap_in_place(barrier._solve)


def make_barrier(kind: str = "si2", **params) -> Barrier:
    """Create a barrier certificate ``certify(u_nom, x) -> u`` (see module docstring).

    Args:
        kind: one of ``"si"``, ``"si2"``, ``"si_boundary"``, ``"uni"``, ``"uni2"``, ``"uni_boundary"``,
            ``"uni_dd"``, ``"uni_dd_boundary"``.
        safety_radius, barrier_gain, unsafe_barrier_gain, magnitude_limit, projection_distance,
            boundary_points: as in rps (defaults per kind, rps 6bb184e); ``boundary_points`` is
            ``(x_min, x_max, y_min, y_max)``.
        disturbance, wheel_vel_limit, base_length, wheel_radius: the ``uni_dd`` kinds' wheel model
            (rps-2023/2024 defaults 5 rad/s, 12.5 rad/s, 0.105 m, 0.016 m).
        iterations: solver sweeps (static); default grows with N (:func:`default_iterations`).
        relaxation: over-relaxation factor in (0, 2) of the coordinate-ascent sweeps; default
            :func:`default_relaxation`.
        tolerance: relative feasibility tolerance used by ``CertificateInfo.feasible``.
    """
    if kind not in _DEFAULTS:
        raise ValueError(f"unknown barrier kind {kind!r}; choose one of {list(KINDS)}")
    allowed = set(_DEFAULTS[kind]) | {"iterations", "relaxation", "tolerance"}
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise ValueError(
            f"barrier {kind!r} does not take {unknown}; valid keywords are {sorted(allowed)}"
        )
    cfg = {**_DEFAULTS[kind], **params}
    gain = float(cfg["barrier_gain"])
    radius = float(cfg["safety_radius"])
    limit = cfg.get("magnitude_limit")
    if not gain > 0:
        raise ValueError(f"barrier_gain must be > 0, got {gain}")
    min_radius = 0.12 if kind in SI_KINDS else 0.0
    if not radius >= min_radius or not math.isfinite(radius):
        raise ValueError(f"safety_radius must be >= {min_radius} for {kind!r}, got {radius}")
    if limit is not None and not 0 < float(limit) <= 0.2:
        raise ValueError(f"magnitude_limit must be in (0, 0.2] (the robots' top speed), got {limit}")
    wheel = {}
    if kind in DD_KINDS:
        wheel = {name: float(cfg[name]) for name in ("disturbance", "wheel_vel_limit", "base_length", "wheel_radius")}
        if not (wheel["disturbance"] >= 0 and math.isfinite(wheel["disturbance"])):
            raise ValueError(f"disturbance must be a finite value >= 0 [rad/s], got {wheel['disturbance']}")
        for name in ("wheel_vel_limit", "base_length", "wheel_radius"):
            if not (wheel[name] > 0 and math.isfinite(wheel[name])):
                raise ValueError(f"{name} must be finite and > 0, got {wheel[name]}")
    unsafe = cfg.get("unsafe_barrier_gain")
    if unsafe is not None and not float(unsafe) > 0:
        raise ValueError(f"unsafe_barrier_gain must be > 0, got {unsafe}")
    proj = cfg.get("projection_distance")
    if proj is not None and not float(proj) > 0:
        raise ValueError(f"projection_distance must be > 0, got {proj}")
    bounds = cfg.get("boundary_points")
    if bounds is not None:
        bounds = tuple(float(b) for b in bounds)
        if len(bounds) != 4 or not (bounds[0] < bounds[1] and bounds[2] < bounds[3]):
            raise ValueError(f"boundary_points must be (x_min, x_max, y_min, y_max) with min < max, got {bounds}")
    iterations = cfg.get("iterations")
    if iterations is not None and (int(iterations) != iterations or iterations < 0):
        raise ValueError(f"iterations must be a non-negative integer, got {iterations}")
    relaxation = cfg.get("relaxation")
    if relaxation is not None and not 0 < float(relaxation) < 2:
        raise ValueError(f"relaxation must be in (0, 2), got {relaxation}")
    return Barrier(
        kind=kind, safety_radius=radius, barrier_gain=gain, magnitude_limit=None if limit is None else float(limit),
        unsafe_barrier_gain=None if unsafe is None else float(unsafe),
        projection_distance=None if proj is None else float(proj), boundary_points=bounds,
        iterations=None if iterations is None else int(iterations),
        relaxation=None if relaxation is None else float(relaxation),
        tolerance=float(cfg.get("tolerance", 1e-4)), **wheel,
    )


def _pair_rows(barrier: Barrier, positions, xp, headings=None):
    """Pair rows in round layout: ``e [..., R, H, 2]``, ``b``, ``|a|^2`` and ``valid`` ``[..., R, H]``.

    Row (r, k) reads ``-2 e.u_first + 2 e.u_second <= b`` with ``e = x_first - x_second``. The
    ``uni_dd`` kinds pass the robots' ``headings [..., N]`` for their disturbance term.
    """
    n = positions.shape[-2]
    first, second = round_robin(n)
    if n % 2:  # phantom robot: its rows are masked out
        pad = xp.zeros(positions.shape[:-2] + (1, 2), dtype=positions.dtype)
        positions = xp.concatenate([positions, pad], axis=-2)
        if headings is not None:
            headings = xp.concatenate([headings, pad[..., 0]], axis=-1)
    e = positions[..., first, :] - positions[..., second, :]
    valid = (first < n) & (second < n)
    e = xp.where(valid[..., None], e, xp.zeros_like(e))
    h = xp.sum(e * e, axis=-1) - barrier.si_radius ** 2
    gain = barrier.barrier_gain
    if barrier.unsafe_barrier_gain is not None:
        gain = xp.where(h < 0, barrier.unsafe_barrier_gain, gain)
    b = gain * h ** 3
    if barrier.is_differential_drive:
        b = b - barrier.disturbance * (_wheel_l1(barrier, e, headings[..., first], xp)
                                       + _wheel_l1(barrier, e, headings[..., second], xp))
    b = xp.where(valid, b, xp.ones_like(h))
    a2 = 8 * xp.sum(e * e, axis=-1)
    return e, b, a2, valid


def _wheel_l1(barrier: Barrier, e, theta, xp):
    """``|2 e^T M D|_1``: the 1-norm of a pair row's coefficients on one robot's wheel speeds
    (``M`` maps (v, omega) to the projection point's velocity, ``D`` wheel speeds to (v, omega))."""
    c, s = xp.cos(theta), xp.sin(theta)
    along = 2 * (e[..., 0] * c + e[..., 1] * s)
    across = 2 * barrier.projection_distance * (-e[..., 0] * s + e[..., 1] * c)
    k_v, k_w = barrier.wheel_radius / 2, barrier.wheel_radius / barrier.base_length
    return xp.abs(along * k_v - across * k_w) + xp.abs(along * k_v + across * k_w)


def _wheel_rows(barrier: Barrier, headings, xp):
    """Wheel-speed rows on the projection-point velocity ``u``: ``|c_w . u| <= wheel_vel_limit`` with
    ``c_left, c_right`` each ``[..., N, 2]`` (the wheel speeds are ``D^-1 M^-1 u``), and ``|c_w|^2``
    (a constant, the same for both wheels and every heading)."""
    c, s = xp.cos(headings), xp.sin(headings)
    k = barrier.base_length / (2 * barrier.projection_distance)
    r = barrier.wheel_radius
    left = xp.stack([c + k * s, s - k * c], axis=-1) / r
    right = xp.stack([c - k * s, s + k * c], axis=-1) / r
    return left, right, (1 + k * k) / (r * r)


def _boxes(barrier: Barrier, positions, xp):
    """Boundary rows as per-robot boxes ``lo <= u <= hi`` (``[..., N, 2]`` each)."""
    x_min, x_max, y_min, y_max = barrier.boundary_points
    half = barrier.si_radius / 2
    g = 0.4 * barrier.barrier_gain
    hi = g * (xp.asarray([x_max, y_max], dtype=positions.dtype) - half - positions) ** 3
    lo = -g * (positions - xp.asarray([x_min, y_min], dtype=positions.dtype) - half) ** 3
    return lo, hi


@functools.lru_cache(maxsize=None)
def _incidence(n: int) -> np.ndarray:
    """``[N', R, H]`` signs of the pair rows on each slot: +1 for ``first``, -1 for ``second``."""
    first, second = round_robin(n)
    m = n + n % 2
    inc = np.zeros((m,) + first.shape, np.float32)
    rows = np.indices(first.shape)
    inc[first, rows[0], rows[1]] += 1
    inc[second, rows[0], rows[1]] -= 1
    return inc


def solve_si(barrier: Barrier, u_nom, positions, warm_start: Multipliers | None = None, headings=None):
    """The SI certificate QP for ``positions [..., N, 2]``; returns ``(u [..., N, 2], info)``.

    Internally every batch axis is folded into the last (minor) axis, so each vector step of the
    sweep runs over the whole batch with unit stride. ``warm_start`` (multipliers of a previous
    solve) sets the initial multipliers and the matching primal point ``u_hat - A^T lambda``.
    The ``uni_dd`` kinds pass the robots' ``headings [..., N]`` (their disturbance term and wheel rows).
    """
    xp = namespace(u_nom, positions)
    n = positions.shape[-2]
    if barrier.magnitude_limit is None:
        u_hat = u_nom
    else:
        u_hat = controllers.cap_norm(u_nom, barrier.magnitude_limit)
    batch = u_hat.shape[:-2]
    if n == 0:
        zero = xp.zeros(batch, dtype=u_hat.dtype)
        return u_hat, CertificateInfo(zero, zero == 0, zero.astype(xp.int32),
                                      barrier.initial_multipliers(0, batch, u_hat.dtype, xp))
    first, second = round_robin(n)
    rounds, half = first.shape
    m = n + n % 2
    nb = len(batch)
    e, b, a2, valid = _pair_rows(barrier, positions, xp, headings)
    usable = a2 > 0
    inv_a2 = to_minor(xp.where(usable, 1 / xp.where(usable, a2, 1), 0), nb, xp)  # [R, H, B]
    ex = to_minor(2 * e[..., 0], nb, xp)
    ey = to_minor(2 * e[..., 1], nb, xp)
    bm = to_minor(b, nb, xp)
    boxed = barrier.boundary_points is not None
    if boxed:
        lo, hi = _boxes(barrier, positions, xp)
        lo_x, lo_y = to_minor(lo[..., 0], nb, xp), to_minor(lo[..., 1], nb, xp)  # [N, B]
        hi_x, hi_y = to_minor(hi[..., 0], nb, xp), to_minor(hi[..., 1], nb, xp)
    wheeled = barrier.is_differential_drive
    if wheeled:
        c_left, c_right, wheel_norm2 = _wheel_rows(barrier, headings, xp)
        wheel_dirs = tuple(to_minor(c[..., i], nb, xp) for c in (c_left, c_right) for i in (0, 1))  # [N, B]
        inv_c2 = 1 / wheel_norm2
        limit = barrier.wheel_vel_limit
    omega = barrier.omega(n)

    def rotate(v):  # slots 1..m-1 right by one (circle method)
        return xp.concatenate([v[:1], v[-1:], v[1:-1]], axis=0)

    def box_step(uc, lam_lo, lam_hi, lo_c, hi_c, w):
        step_hi = xp.maximum(-lam_hi, w * (uc - hi_c))
        uc = uc - step_hi
        step_lo = xp.maximum(-lam_lo, w * (lo_c - uc))
        return uc + step_lo, lam_lo + step_lo, lam_hi + step_hi

    def slab_step(cx, cy, lam_lo, lam_hi, dir_x, dir_y, w):
        """Rows ``dir.u <= limit`` (``lam_hi``) and ``-dir.u <= limit`` (``lam_lo``), one robot each."""
        step_hi = xp.maximum(-lam_hi, w * (dir_x * cx + dir_y * cy - limit) * inv_c2)
        cx, cy = cx - dir_x * step_hi, cy - dir_y * step_hi
        step_lo = xp.maximum(-lam_lo, w * (-limit - dir_x * cx - dir_y * cy) * inv_c2)
        return cx + dir_x * step_lo, cy + dir_y * step_lo, lam_lo + step_lo, lam_hi + step_hi

    def sweep(i, carry):
        ux, uy, lam, box, wheels = carry
        # The first sweep is plain Gauss-Seidel: it solves single-active-constraint problems exactly.
        # So is the last for the uni_dd kinds, whose wheel limits can make the QP infeasible: an
        # over-relaxed final step would throw the output past the wheel limits it just enforced.
        plain = (i == 0) | (i == last) if wheeled else i == 0
        w = (1.0 if plain else omega) if xp is np else xp.where(plain, 1.0, omega)
        lam = list(lam)
        for r in range(rounds):
            ax, bx = ux[:half], ux[half:][::-1]
            ay, by = uy[:half], uy[half:][::-1]
            exr, eyr = ex[r], ey[r]
            viol = exr * (bx - ax) + eyr * (by - ay) - bm[r]
            step = xp.maximum(-lam[r], w * viol * inv_a2[r])
            lam[r] = lam[r] + step
            px, py = exr * step, eyr * step
            ux = rotate(xp.concatenate([ax + px, (bx - px)[::-1]], axis=0))
            uy = rotate(xp.concatenate([ay + py, (by - py)[::-1]], axis=0))
        if boxed or wheeled:
            cx, cy = ux[:n], uy[:n]
            if boxed:
                llx, lhx, lly, lhy = box
                cx, llx, lhx = box_step(cx, llx, lhx, lo_x, hi_x, w)
                cy, lly, lhy = box_step(cy, lly, lhy, lo_y, hi_y, w)
                box = (llx, lhx, lly, lhy)
            if wheeled:
                l_lo, l_hi, r_lo, r_hi = wheels
                cx, cy, l_lo, l_hi = slab_step(cx, cy, l_lo, l_hi, wheel_dirs[0], wheel_dirs[1], w)
                cx, cy, r_lo, r_hi = slab_step(cx, cy, r_lo, r_hi, wheel_dirs[2], wheel_dirs[3], w)
                wheels = (l_lo, l_hi, r_lo, r_hi)
            ux = xp.concatenate([cx, ux[n:]], axis=0)
            uy = xp.concatenate([cy, uy[n:]], axis=0)
        return ux, uy, tuple(lam), box, wheels

    flat_b = bm.shape[-1]
    uh = to_minor(u_hat, nb, xp)  # [N, 2, B]
    pad = xp.zeros((m - n, flat_b), dtype=u_hat.dtype)
    ux0 = xp.concatenate([uh[:, 0], pad], axis=0)
    uy0 = xp.concatenate([uh[:, 1], pad], axis=0)
    lam0 = tuple(xp.zeros((half, flat_b), dtype=u_hat.dtype) for _ in range(rounds))
    zero_box = xp.zeros((n, flat_b), dtype=u_hat.dtype)
    box0 = (zero_box,) * 4 if boxed else ()
    wheels0 = (zero_box,) * 4 if wheeled else ()
    if warm_start is not None:
        # Rows that cannot act (phantom, coincident robots) start at zero; u0 = u_hat - A^T lambda0.
        lam_w = xp.where(inv_a2 > 0, xp.maximum(to_minor(warm_start.pairs, nb, xp), 0), 0)   # [R, H, B]
        inc = xp.asarray(_incidence(n), dtype=u_hat.dtype)
        ux0 = ux0 + xp.einsum("srh,rhb->sb", inc, ex * lam_w)
        uy0 = uy0 + xp.einsum("srh,rhb->sb", inc, ey * lam_w)
        lam0 = tuple(lam_w[r] for r in range(rounds))
        if boxed:
            lo_w = xp.maximum(to_minor(warm_start.lower, nb, xp), 0)   # [N, 2, B]
            hi_w = xp.maximum(to_minor(warm_start.upper, nb, xp), 0)
            shift = xp.concatenate([lo_w - hi_w, xp.zeros((m - n, 2, flat_b), dtype=u_hat.dtype)], axis=0)
            ux0, uy0 = ux0 + shift[:, 0], uy0 + shift[:, 1]
            box0 = (lo_w[:, 0], hi_w[:, 0], lo_w[:, 1], hi_w[:, 1])
        if wheeled:
            w_lo = xp.maximum(to_minor(warm_start.wheel_lower, nb, xp), 0)   # [N, 2 wheels, B]
            w_hi = xp.maximum(to_minor(warm_start.wheel_upper, nb, xp), 0)
            net = w_lo - w_hi
            pad_n = xp.zeros((m - n, flat_b), dtype=u_hat.dtype)
            ux0 = ux0 + xp.concatenate([wheel_dirs[0] * net[:, 0] + wheel_dirs[2] * net[:, 1], pad_n], axis=0)
            uy0 = uy0 + xp.concatenate([wheel_dirs[1] * net[:, 0] + wheel_dirs[3] * net[:, 1], pad_n], axis=0)
            wheels0 = (w_lo[:, 0], w_hi[:, 0], w_lo[:, 1], w_hi[:, 1])
    sweeps = barrier.sweeps(n)
    last = sweeps - 1
    ux, uy, lam, box, wheels = fori_loop(xp, 0, sweeps, sweep, (ux0, uy0, lam0, box0, wheels0))
    # (m - 1) rotations per sweep bring the slots back to robot order.
    u = from_minor(xp.stack([ux[:n], uy[:n]], axis=1), batch, xp)
    lam = from_minor(xp.stack(lam, axis=0), batch, xp)  # [..., R, H]
    if boxed:
        llx, lhx, lly, lhy = (from_minor(v, batch, xp) for v in box)
        lam_lo, lam_hi = xp.stack([llx, lly], axis=-1), xp.stack([lhx, lhy], axis=-1)
    else:
        lo = hi = lam_lo = lam_hi = None
    wheel_rows = wheel_lo = wheel_hi = None
    if wheeled:
        l_lo, l_hi, r_lo, r_hi = (from_minor(v, batch, xp) for v in wheels)
        wheel_lo, wheel_hi = xp.stack([l_lo, r_lo], axis=-1), xp.stack([l_hi, r_hi], axis=-1)
        wheel_rows = (c_left, c_right, wheel_norm2, wheel_lo, wheel_hi)
    info = _diagnostics(barrier, u, e, b, a2, valid, lam, lo, hi, lam_lo, lam_hi, xp, wheel_rows)
    multipliers = Multipliers(lam, lam_lo, lam_hi, wheel_lo, wheel_hi)
    return u, info._replace(multipliers=multipliers)


def _diagnostics(barrier, u, e, b, a2, valid, lam, lo, hi, lam_lo, lam_hi, xp, wheel_rows=None):
    """Violation of every row at the returned ``u`` (not only the rows the solver touched)."""
    n = u.shape[-2]
    first, second = round_robin(n)
    batch = u.shape[:-2]
    flat = batch + (-1,)
    if first.size:
        padded = xp.concatenate([u, xp.zeros(batch + (n % 2, 2), dtype=u.dtype)], axis=-2)
        gap = 2 * xp.sum(e * (padded[..., second, :] - padded[..., first, :]), axis=-1) - b
        usable = a2 > 0
        row_norm = xp.sqrt(xp.where(usable, a2, 1))
        pair_viol = xp.where(usable, gap / row_norm, xp.where(valid & (b < 0), -b, 0))
        worst = xp.max(pair_viol.reshape(flat), axis=-1)
        active = xp.sum((lam > 0).reshape(flat), axis=-1)
        degenerate = xp.any((valid & ~usable & (b < 0)).reshape(flat), axis=-1)
    else:
        worst = xp.zeros(batch, dtype=u.dtype)
        active = xp.zeros(batch, dtype=xp.int32)
        degenerate = worst > 0
    if lo is not None:
        box_viol = xp.maximum(u - hi, lo - u)
        worst = xp.maximum(worst, xp.max(box_viol.reshape(flat), axis=-1))
        active = active + xp.sum(((lam_lo > 0) | (lam_hi > 0)).reshape(flat), axis=-1)
    if wheel_rows is not None:   # |c . u| <= limit, violation as a distance along c
        c_left, c_right, norm2, wheel_lo, wheel_hi = wheel_rows
        speeds = xp.stack([xp.sum(c_left * u, axis=-1), xp.sum(c_right * u, axis=-1)], axis=-1)
        wheel_viol = (xp.abs(speeds) - barrier.wheel_vel_limit) / math.sqrt(norm2)
        worst = xp.maximum(worst, xp.max(wheel_viol.reshape(flat), axis=-1))
        active = active + xp.sum(((wheel_lo > 0) | (wheel_hi > 0)).reshape(flat), axis=-1)
    scale = 1 + xp.max(xp.abs(u).reshape(flat), axis=-1)
    feasible = (worst <= barrier.tolerance * scale) & ~degenerate
    return CertificateInfo(worst, feasible, active)


__all__ = ["make_barrier", "Barrier", "CertificateInfo", "Multipliers", "KINDS", "SI_KINDS", "UNI_KINDS", "DD_KINDS",
           "round_robin", "default_iterations", "default_relaxation", "solve_si"]
