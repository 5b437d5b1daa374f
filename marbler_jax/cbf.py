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
  with exactly the Gauss-Seidel result (N-1 vector steps per sweep instead of C(N,2) scalar ones).
  The robots' velocities are kept in the circle's two rows of slots, the second row reversed, so
  that a turn of the circle is two shifts by one: no reversal or gather in the inner loop;
* pair rows are scaled to unit normals, so a row's step needs three numbers (normal, scaled
  ``b``) and no division;
* boundary rows act on one coordinate each and are handled as per-robot boxes in one step;
* distant pairs have ``b`` far above anything ``A u`` reaches and simply keep ``l = 0``;
* ``solve(..., warm_start=info.multipliers)`` starts from an earlier solve's multipliers and the
  primal point ``u_hat - A^T l`` they give (a consecutive control refresh barely moves the optimum).

The Robotarium's rps v2 (b23069e; ``shared/spec/robotarium.md`` section 10.11) has its own kinds
``"si_v2"``, ``"si_boundary_v2"``, ``"uni_v2"`` and ``"uni_boundary_v2"``: ``u_nom`` is not capped, each
robot instead gets eight magnitude rows ``n_j . u_k <= c_j`` (a regular octagon of unit normals from +x,
``c_j = magnitude_limit cos(pi/8)``, except the first row of ``si_v2``/``uni_v2`` at ``magnitude_limit``);
the unicycle kinds use radius ``safety_radius + 2 projection_distance`` and map back without clipping
omega; a team of fewer than two robots is returned unchanged; and when the QP has no solution
(``CertificateInfo.stopped``: the fixed budget's iterate still violates a row by more than
:data:`V2_TOLERANCE` and standing still violates one too) every robot of the team gets zero velocity,
as rps v2 commands when CVXOPT reports no optimum. ``uni_boundary_v2`` takes
``obstacles [..., M, 2]``: points entered as extra robots with zero nominal velocity, as rps v2 does.

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
from marbler_jax.xp import fori_loop, from_minor, is_jax, namespace, result_dtype, to_minor, vmap_in_place

V2_KINDS = ("si_v2", "si_boundary_v2", "uni_v2", "uni_boundary_v2")
SI_KINDS = ("si", "si2", "si_boundary", "si_v2", "si_boundary_v2")
DD_KINDS = ("uni_dd", "uni_dd_boundary")
UNI_KINDS = ("uni", "uni2", "uni_boundary", "uni_v2", "uni_boundary_v2") + DD_KINDS
KINDS = SI_KINDS + UNI_KINDS

# rps v2's magnitude polygon: 8 unit normals per robot, 45 degrees apart starting at +x.
FAR_AWAY = 100.0
"""[m] A robot with a coordinate beyond +-FAR_AWAY (thirty arena widths out) is treated like one with a
non-finite pose: taken out of the barrier's QP with zero velocity, so that squaring its distances (which
overflows float32 from about 1e19 m) cannot turn the other robots' commands into NaN."""


def _usable(xp, positions, axis):
    """Whether positions are finite and within :data:`FAR_AWAY` along ``axis`` (the coordinate axis)."""
    return xp.all(xp.isfinite(positions) & (xp.abs(positions) <= FAR_AWAY), axis=axis)


_R = 1 / math.sqrt(2)
_POLYGON_NORMALS = ((1.0, 0.0), (_R, _R), (0.0, 1.0), (-_R, _R), (-1.0, 0.0), (-_R, -_R), (0.0, -1.0), (_R, -_R))

# Relative feasibility tolerance of the v2 kinds: a team whose fixed-budget iterate violates a row by more
# than ~3e-3 m/s (x (1 + max |u|)) is infeasible and stopped, as rps v2 stops it when CVXOPT (feastol 1e-2)
# reports no optimum. On the golden cases infeasible teams violate by >= 8e-3 m/s at any budget, feasible
# ones end below 1e-3 within the default sweeps.
V2_TOLERANCE = 2.5e-3

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
    # rps v2 (b23069e): create_si_barrier_certificate(_with_boundary), create_uni_barrier_certificate(_with_boundary)
    "si_v2": dict(barrier_gain=100.0, safety_radius=0.15, magnitude_limit=0.2),
    "si_boundary_v2": dict(barrier_gain=100.0, safety_radius=0.15, magnitude_limit=0.2,
                           boundary_points=(-1.7, 1.7, -1.1, 1.1)),
    "uni_v2": dict(barrier_gain=100.0, safety_radius=0.15, projection_distance=0.05, magnitude_limit=0.2),
    "uni_boundary_v2": dict(barrier_gain=150.0, safety_radius=0.12, projection_distance=0.03, magnitude_limit=0.2,
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
        polygon: ``[..., N, 8]`` multipliers of each robot's eight magnitude rows (``*_v2`` kinds),
            else ``None``.
    """

    pairs: Any
    lower: Any = None
    upper: Any = None
    wheel_lower: Any = None
    wheel_upper: Any = None
    polygon: Any = None


class CertificateInfo(NamedTuple):
    """Diagnostics of one certification, each ``[...]`` (batch shape) except ``multipliers``.

    Attributes:
        max_violation: largest constraint violation of the returned SI velocity, measured as a
            distance in velocity space ``(a.u - b) / |a|`` [m/s] (<= 0 when every row holds).
        feasible: ``solved`` and every robot's speed within :attr:`Barrier.speed_limit` (and every
            input finite); False means the returned input is no certificate a robot can follow: the
            best the fixed budget found for a problem that is infeasible or not yet solved, or a
            solution that asks for more speed than a robot has (crowded robots pushed apart).
        active: number of rows with a positive multiplier.
        multipliers: the final :class:`Multipliers`; pass them as ``warm_start`` to the next solve
            of a nearby problem (the next control refresh of the same team).
        stopped: ``*_v2`` kinds: the team was given zero velocity because its QP has no solution
            (not ``feasible`` although zero velocity is not an admissible input either: every team
            where standing still satisfies every row has a solution, however far the fixed budget got);
            ``None`` for the other kinds.
        solved: the QP's rows hold: ``max_violation <= tolerance * (1 + max |u|)`` and no degenerate
            row (coincident robots that must separate).
    """

    max_violation: Any
    feasible: Any
    active: Any
    multipliers: Any = None
    stopped: Any = None
    solved: Any = None


@functools.lru_cache(maxsize=None)
def round_robin(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of ``n`` robots grouped into rounds of disjoint pairs (circle method).

    Returns ``(first, second)``, each ``[R, H]``: round ``r`` pairs robot ``first[r, k]`` with
    ``second[r, k]``. ``R = n' - 1`` rounds of ``H = n'/2`` pairs with ``n' = n + n % 2``; index ``n``
    is a phantom robot for odd ``n``. The order is the circle method's: keep the players in a row,
    pair slot ``k`` with slot ``n' - 1 - k``, then rotate slots ``1..n'-1`` right by one, so the solver
    only ever slices and shifts -- no gathers in its inner loop (see :func:`_polygon`).
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


def default_iterations(n: int, kind: str = "si2") -> int:
    """Sweeps used when ``iterations`` is not given: ``20 + 4 N`` (at most 250); ``60 + 12 N`` (at
    most 750) for the ``*_v2`` kinds.

    Chosen on the rps tight-QP golden cases, where every kind then matches >= 99 % of the cases
    for N <= 20 (the clustered wall cases at N = 6 need ~45 sweeps, the stiff ``*2`` cases at
    N = 20 about 100). The v2 kinds decide infeasibility from the last iterate, so a feasible team
    must be converged below :data:`V2_TOLERANCE` by then: with 1.5x the sweeps every feasible golden
    v2 case ends below 1e-3 m/s, and 3x also converges a 20-robot ring whose pair rows all bind
    (``tests/test_cbf_v2.py``: at 150 sweeps it still violated by 6e-3 m/s). Callers with easier problems (robots kept apart by
    the certificate itself, as inside the env) can pass fewer ``iterations``.
    """
    if kind in V2_KINDS:
        return int(min(60 + 12 * n, 750))
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
    tolerance: float = 1e-4                 # relative; the v2 kinds default to V2_TOLERANCE

    @property
    def is_unicycle(self) -> bool:
        return self.kind in UNI_KINDS

    @property
    def is_differential_drive(self) -> bool:
        return self.kind in DD_KINDS

    @property
    def speed_limit(self) -> float | None:
        """The fastest SI velocity [m/s] a certified robot may be given: ``magnitude_limit / cos(pi/8)``,
        the corner of the speed octagon of rps v2's barrier (the most it certifies; a GRITSbot's
        projection point cannot move faster than its 0.2 m/s wheel-limited speed). ``None`` for the
        ``uni_dd`` kinds, whose wheel-speed rows bound it already."""
        return None if self.magnitude_limit is None else self.magnitude_limit / math.cos(math.pi / 8)

    @property
    def is_v2(self) -> bool:
        """rps v2 semantics: magnitude polygon rows instead of capping ``u_nom``, no omega clip, teams
        of fewer than two robots pass through, and zero velocity for the whole team when infeasible."""
        return self.kind in V2_KINDS

    @property
    def si_radius(self) -> float:
        """Safety radius of the SI problem: ``safety_radius + projection_distance`` for the rps
        2023 unicycle kinds, ``safety_radius + 2 projection_distance`` for ``uni*_v2``; the
        ``uni_dd`` kinds apply ``safety_radius`` to the projection points."""
        if self.is_differential_drive or not self.is_unicycle:
            return self.safety_radius
        return self.safety_radius + self.projection_distance * (2 if self.is_v2 else 1)

    def polygon_limits(self) -> tuple[float, ...]:
        """Right-hand sides of the eight magnitude rows (``*_v2`` kinds; rps v2 gives the first row
        of ``si_v2``/``uni_v2`` the full ``magnitude_limit`` and every other row ``cos(pi/8)`` of it)."""
        m = self.magnitude_limit
        inner = m * math.cos(math.pi / 8)
        first = inner if self.boundary_points is not None else m
        return (first,) + (inner,) * 7

    def sweeps(self, n: int) -> int:
        """Coordinate-ascent sweeps used for a team of ``n`` robots."""
        return self.iterations if self.iterations is not None else default_iterations(n, self.kind)

    def omega(self, n: int) -> float:
        """Over-relaxation factor used for a team of ``n`` robots."""
        return self.relaxation if self.relaxation is not None else default_relaxation(n)

    def __call__(self, u_nom, x, obstacles=None):
        return self.solve(u_nom, x, obstacles=obstacles)[0]

    def initial_multipliers(self, n: int, batch_shape=(), dtype=np.float32, xp=np) -> Multipliers:
        """Zero :class:`Multipliers` for a team of ``n`` robots (a cold start)."""
        rounds, half = round_robin(n)[0].shape
        per_robot = xp.zeros(tuple(batch_shape) + (n, 2), dtype)
        box = None if self.boundary_points is None else per_robot
        wheels = per_robot if self.is_differential_drive else None
        polygon = xp.zeros(tuple(batch_shape) + (n, 8), dtype) if self.is_v2 else None
        return Multipliers(xp.zeros(tuple(batch_shape) + (rounds, half), dtype), box, box, wheels, wheels, polygon)

    def solve(self, u_nom, x, warm_start: Multipliers | None = None, obstacles=None):
        """Certify ``u_nom`` at state ``x``; returns ``(u, CertificateInfo)``.

        ``warm_start``: multipliers of a previous solve of this barrier for the same team
        (``info.multipliers``), e.g. the last control refresh. The QP's solution does not depend
        on it (the problem is strictly convex); it only starts the sweeps nearer to it, so fewer
        ``iterations`` reach the same accuracy when the robots moved little since.
        ``obstacles [..., M, 2]`` (``uni_boundary_v2`` only, as rps v2): points the robots' projection
        points keep clear of, entered into the QP as extra robots with zero nominal velocity (their
        multipliers are part of ``info.multipliers``: warm-start with the same ``M``).
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
        team = x.shape[-2]
        if obstacles is not None:
            if self.kind != "uni_boundary_v2":
                raise ValueError(f"barrier {self.kind!r} takes no obstacles (only 'uni_boundary_v2' does, as rps v2)")
            obstacles = xp.asarray(obstacles, dtype=dtype)
            if obstacles.ndim < 2 or obstacles.shape[-1] != 2 or obstacles.shape[:-2] != x.shape[:-2]:
                raise ValueError(f"obstacles must be [..., M, 2] with the batch shape of x {tuple(x.shape[:-2])}; "
                                 f"got {tuple(obstacles.shape)}")
            team += obstacles.shape[-2]
        if warm_start is not None:
            warm_start = Multipliers(*(None if w is None else xp.asarray(w, dtype=dtype) for w in warm_start))
            expected = self.initial_multipliers(team, x.shape[:-2], xp=np)
            shapes = [None if w is None else tuple(w.shape) for w in warm_start]
            if shapes != [None if w is None else tuple(w.shape) for w in expected]:
                raise ValueError(f"warm_start shapes {shapes} do not match this barrier's multipliers for "
                                 f"x {tuple(x.shape)}: {[None if w is None else w.shape for w in expected]}")
        if is_jax(u_nom, x, obstacles):
            return _jax_solver(self)(u_nom, x, warm_start, obstacles)
        return self._solve(u_nom, x, warm_start, obstacles)

    def solve_minor(self, u_nom, points, warm_start: Multipliers | None = None):
        """SI kinds: the certified input for batch-minor ``u_nom``, ``points`` ``[N, 2, B]``, warm-started
        from batch-minor ``warm_start`` (see :func:`solve_si_minor`); returns ``(u [N, 2, B],
        multipliers)`` without diagnostics except where the result needs them (the v2 kinds' stop rule).

        What a batch-minor control loop calls every refresh: no layout change, no unused work.
        Every team is solved, also those whose nominal input already satisfies every row: on the CPU
        backend that check costs about what the few warm-started sweeps it would save do, and gathering
        the other teams along the minor axis costs more.
        """
        if self.is_unicycle:
            raise ValueError(f"solve_minor takes the SI kinds {SI_KINDS}, not {self.kind!r}")
        xp = namespace(u_nom, points)
        n = points.shape[0]
        if n == 0 or (self.is_v2 and n < 2):     # nothing to solve; rps v2 passes a lone robot through
            if warm_start is None:
                zeros = self.initial_multipliers(n, (points.shape[-1],), u_nom.dtype, xp)
                warm_start = Multipliers(*(None if v is None else xp.moveaxis(v, 0, -1) for v in zeros))
            return u_nom, warm_start
        u, multipliers, info = solve_si_minor(self, u_nom, points, warm_start, diagnose=self.is_v2)
        if self.is_v2:
            u = xp.where(info.stopped[None, None], xp.zeros_like(u), u)
        return u, multipliers

    def _solve(self, u_nom, x, warm_start=None, obstacles=None):
        if self.is_v2 and x.shape[-2] < 2:      # rps v2 returns a lone robot's command unchanged
            return u_nom, _pass_through(self, u_nom, x.shape[-2])
        if not self.is_unicycle:
            u, info = solve_si(self, u_nom, x, warm_start)
            return _zero_if_infeasible(self, u, info)
        d = self.projection_distance
        points = controllers.uni_to_si_states(x, d)
        dxi = controllers.uni_to_si_dynamics(u_nom, x, d)
        if self.is_differential_drive:   # exact inverse of uni_to_si_dynamics: no omega clip
            dxi, info = solve_si(self, dxi, points, warm_start, headings=x[..., 2])
            return _zero_broken(controllers.si_to_uni_mapping(dxi, x, d, angular_velocity_limit=math.inf), x, u_nom), info
        if not self.is_v2:
            dxi, info = solve_si(self, dxi, points, warm_start)
            return _zero_broken(controllers.si_to_uni_mapping(dxi, x, d), x, u_nom), info
        n = x.shape[-2]
        if obstacles is not None:
            xp = namespace(dxi, obstacles)
            points = xp.concatenate([points, obstacles], axis=-2)
            dxi = xp.concatenate([dxi, xp.zeros_like(obstacles)], axis=-2)
        dxi, info = solve_si(self, dxi, points, warm_start)
        u = controllers.si_to_uni_mapping(dxi[..., :n, :], x, d, angular_velocity_limit=math.inf)
        return _zero_if_infeasible(self, _zero_broken(u, x, u_nom), info)


def _zero_broken(u, x, u_nom):
    """Zero velocity for robots whose pose or nominal input is not finite, or whose position is beyond
    :data:`FAR_AWAY` (mapping back through a non-finite heading would make their command NaN again)."""
    xp = namespace(u, x)
    finite = (_usable(xp, x[..., :2], -1) & xp.all(xp.isfinite(x), axis=-1)
              & xp.all(xp.isfinite(u_nom), axis=-1))
    return xp.where(finite[..., None], u, 0)


def _pass_through(barrier: Barrier, u_nom, n: int) -> CertificateInfo:
    """Diagnostics of a team that is not solved (rps v2: fewer than two robots)."""
    xp = namespace(u_nom)
    zero = xp.zeros(u_nom.shape[:-2], dtype=u_nom.dtype)
    return CertificateInfo(zero, zero == 0, zero.astype(xp.int32),
                           barrier.initial_multipliers(n, u_nom.shape[:-2], u_nom.dtype, xp), zero != 0, zero == 0)


def _zero_if_infeasible(barrier: Barrier, u, info: CertificateInfo):
    """rps v2: a team whose QP has no solution (``info.stopped``) gets zero velocity for every robot;
    other kinds return ``u`` as it is."""
    if not barrier.is_v2:
        return u, info
    xp = namespace(u)
    return xp.where(info.stopped[..., None, None], xp.zeros_like(u), u), info


@functools.lru_cache(maxsize=None)
def _jax_solver(barrier: Barrier):
    """``barrier._solve`` with a vmap rule that keeps the batch on the minor axis (the solver folds
    every batch axis into the minor, SIMD, axis; see :func:`marbler_jax.xp.vmap_in_place`)."""
    return vmap_in_place(barrier._solve)


def make_barrier(kind: str = "si2", **params) -> Barrier:
    """Create a barrier certificate ``certify(u_nom, x) -> u`` (see module docstring).

    Args:
        kind: one of ``"si"``, ``"si2"``, ``"si_boundary"``, ``"uni"``, ``"uni2"``, ``"uni_boundary"``,
            ``"uni_dd"``, ``"uni_dd_boundary"`` (rps 2023/2024) or ``"si_v2"``, ``"si_boundary_v2"``,
            ``"uni_v2"``, ``"uni_boundary_v2"`` (rps v2).
        safety_radius, barrier_gain, unsafe_barrier_gain, magnitude_limit, projection_distance,
            boundary_points: as in rps (defaults per kind, rps 6bb184e or v2; v2's
            ``velocity_magnitude_limit`` is ``magnitude_limit`` here); ``boundary_points`` is
            ``(x_min, x_max, y_min, y_max)``.
        disturbance, wheel_vel_limit, base_length, wheel_radius: the ``uni_dd`` kinds' wheel model
            (rps-2023/2024 defaults 5 rad/s, 12.5 rad/s, 0.105 m, 0.016 m).
        iterations: solver sweeps (static); default grows with N (:func:`default_iterations`).
        relaxation: over-relaxation factor in (0, 2) of the coordinate-ascent sweeps; default
            :func:`default_relaxation`.
        tolerance: relative feasibility tolerance used by ``CertificateInfo.feasible`` (default 1e-4;
            :data:`V2_TOLERANCE` for the v2 kinds, where it decides which teams are stopped).
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
    for name, value in cfg.items():         # every number finite (boundary_points checked below)
        if name != "boundary_points" and value is not None and not (
                isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and math.isfinite(value)):
            raise ValueError(f"barrier {kind!r}: {name} must be a finite number, got {value!r}")
    gain = float(cfg["barrier_gain"])
    radius = float(cfg["safety_radius"])
    limit = cfg.get("magnitude_limit")
    if not gain > 0:
        raise ValueError(f"barrier_gain must be > 0, got {gain}")
    min_radius = 0.12 if kind in SI_KINDS and kind not in V2_KINDS else 0.0     # rps 2023 asserts it, v2 does not
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
        if len(bounds) != 4 or not all(map(math.isfinite, bounds)) or not (bounds[0] < bounds[1] and bounds[2] < bounds[3]):
            raise ValueError(f"boundary_points must be (x_min, x_max, y_min, y_max) with min < max, got {bounds}")
    iterations = cfg.get("iterations")
    if iterations is not None and (int(iterations) != iterations or iterations < 0):
        raise ValueError(f"iterations must be a non-negative integer, got {iterations}")
    relaxation = cfg.get("relaxation")
    if relaxation is not None and not 0 < float(relaxation) < 2:
        raise ValueError(f"relaxation must be in (0, 2), got {relaxation}")
    tolerance = cfg.get("tolerance")
    if tolerance is not None and not (0 < float(tolerance) < 1):
        raise ValueError(f"tolerance must be in (0, 1) (relative feasibility tolerance), got {tolerance}")
    return Barrier(
        kind=kind, safety_radius=radius, barrier_gain=gain, magnitude_limit=None if limit is None else float(limit),
        unsafe_barrier_gain=None if unsafe is None else float(unsafe),
        projection_distance=None if proj is None else float(proj), boundary_points=bounds,
        iterations=None if iterations is None else int(iterations),
        relaxation=None if relaxation is None else float(relaxation),
        tolerance=float(cfg.get("tolerance", V2_TOLERANCE if kind in V2_KINDS else 1e-4)), **wheel,
    )


def _pair_rows(barrier: Barrier, points, n: int, xp, headings=None, broken=None):
    """Pair rows in round layout, batch-minor.

    ``points [N', 2, B]`` are the robots' positions with a zero phantom row for odd ``n``
    (``headings [N', B]`` likewise, ``uni_dd`` kinds only). Returns ``e [R, H, 2, B]``, ``b`` and
    ``d2 = |e|^2`` ``[R, H, B]``, and the static mask ``valid [R, H]`` of rows between two real
    robots. Row (r, k) reads ``-2 e.u_first + 2 e.u_second <= b`` with ``e = x_first - x_second``.
    The rows of a ``broken [N', B]`` robot are emptied (``e = 0``, ``b = 1``: the solver skips them).
    """
    first, second = round_robin(n)
    valid = (first < n) & (second < n)
    e = points[first] - points[second]
    if not valid.all():
        e = e * valid[:, :, None, None].astype(e.dtype)
    d2 = e[:, :, 0] * e[:, :, 0] + e[:, :, 1] * e[:, :, 1]
    h = d2 - barrier.si_radius ** 2
    gain = barrier.barrier_gain
    if barrier.unsafe_barrier_gain is not None:
        gain = xp.where(h < 0, barrier.unsafe_barrier_gain, gain)
    b = gain * h ** 3
    if barrier.is_differential_drive:
        b = b - barrier.disturbance * (_wheel_l1(barrier, e, headings[first], xp)
                                       + _wheel_l1(barrier, e, headings[second], xp))
    b = xp.where(valid[:, :, None], b, xp.ones_like(h))
    if broken is not None:
        cut = broken[first] | broken[second]                            # [R, H, B]
        e = xp.where(cut[:, :, None], 0, e)
        b = xp.where(cut, 1, b)
        d2 = xp.where(cut, 0, d2)
    return e, b, d2, valid


def _wheel_l1(barrier: Barrier, e, theta, xp):
    """``|2 e^T M D|_1``: the 1-norm of a pair row's coefficients on one robot's wheel speeds
    (``M`` maps (v, omega) to the projection point's velocity, ``D`` wheel speeds to (v, omega));
    ``e [R, H, 2, B]``, ``theta [R, H, B]``."""
    c, s = xp.cos(theta), xp.sin(theta)
    along = 2 * (e[:, :, 0] * c + e[:, :, 1] * s)
    across = 2 * barrier.projection_distance * (-e[:, :, 0] * s + e[:, :, 1] * c)
    k_v, k_w = barrier.wheel_radius / 2, barrier.wheel_radius / barrier.base_length
    return xp.abs(along * k_v - across * k_w) + xp.abs(along * k_v + across * k_w)


def _wheel_rows(barrier: Barrier, headings, xp):
    """Wheel-speed rows on the projection-point velocity ``u``: ``|c_w . u| <= wheel_vel_limit`` with
    ``c_left, c_right`` each ``[N, 2, B]`` for ``headings [N, B]`` (the wheel speeds are
    ``D^-1 M^-1 u``), and ``|c_w|^2`` (a constant, the same for both wheels and every heading)."""
    c, s = xp.cos(headings), xp.sin(headings)
    k = barrier.base_length / (2 * barrier.projection_distance)
    r = barrier.wheel_radius
    left = xp.stack([c + k * s, s - k * c], axis=1) / r
    right = xp.stack([c - k * s, s + k * c], axis=1) / r
    return left, right, (1 + k * k) / (r * r)


def _boxes(barrier: Barrier, points, xp):
    """Boundary rows as per-robot boxes ``lo <= u <= hi`` for ``points [N, 2, B]`` (each ``[N, 2, B]``)."""
    x_min, x_max, y_min, y_max = barrier.boundary_points
    half = barrier.si_radius / 2
    g = 0.4 * barrier.barrier_gain
    upper = xp.asarray([[x_max], [y_max]], dtype=points.dtype)
    lower = xp.asarray([[x_min], [y_min]], dtype=points.dtype)
    return -g * (points - lower - half) ** 3, g * (upper - half - points) ** 3


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


@functools.lru_cache(maxsize=None)
def _polygon(n: int) -> np.ndarray:
    """``[N']`` robot held by each row of the solver's state at the start of a sweep.

    The state stacks the circle method's two rows of slots: the first ``H`` slots in order, then
    the other ``H`` reversed, so that state row ``k`` of the top half meets state row ``H + k`` in the
    current round, and one rotation of the circle is two shifts by one (no reversal). The map is its
    own inverse.
    """
    m = n + n % 2
    return np.concatenate([np.arange(m // 2), np.arange(m - 1, m // 2 - 1, -1)]).astype(np.int32)


def solve_si(barrier: Barrier, u_nom, positions, warm_start: Multipliers | None = None, headings=None):
    """The SI certificate QP for ``positions [..., N, 2]``; returns ``(u [..., N, 2], info)``.

    Every batch axis is folded into the last (minor) axis first and :func:`solve_si_minor` solves
    the folded problem. The ``uni_dd`` kinds pass the robots' ``headings [..., N]`` (their
    disturbance term and wheel rows).
    """
    xp = namespace(u_nom, positions)
    n = positions.shape[-2]
    batch = u_nom.shape[:-2]
    if n == 0:
        u_hat = u_nom if barrier.magnitude_limit is None or barrier.is_v2 else controllers.cap_norm(
            u_nom, barrier.magnitude_limit)
        zero = xp.zeros(batch, dtype=u_hat.dtype)
        return u_hat, CertificateInfo(zero, zero == 0, zero.astype(xp.int32),
                                      barrier.initial_multipliers(0, batch, u_hat.dtype, xp), solved=zero == 0)
    nb = len(batch)
    fold = lambda v: None if v is None else to_minor(v, nb, xp)  # noqa: E731
    unbatch = lambda v: None if v is None else from_minor(v, batch, xp)  # noqa: E731
    warm = None if warm_start is None else Multipliers(*(fold(v) for v in warm_start))
    u, multipliers, info = solve_si_minor(barrier, fold(u_nom), fold(positions), warm, fold(headings))
    info = CertificateInfo(*(None if v is None else v.reshape(batch) for v in info))
    return unbatch(u), info._replace(multipliers=Multipliers(*(unbatch(v) for v in multipliers)))


def solve_si_minor(barrier: Barrier, u_nom, points, warm_start: Multipliers | None = None, headings=None,
                   diagnose: bool = True):
    """:func:`solve_si` on batch-minor arrays: ``u_nom``, ``points`` ``[N, 2, B]`` (N >= 1),
    ``headings [N, B]`` (``uni_dd`` kinds), ``warm_start`` with each field batch-minor (``pairs
    [R, H, B]``, ``lower``/``upper``/``wheel_*`` ``[N, 2, B]``, ``polygon [N, 8, B]``).

    Returns ``(u [N, 2, B], multipliers (batch-minor), info)``, where ``info`` holds ``[B]`` arrays
    (``multipliers`` unset), or is ``None`` when ``diagnose`` is False: the row violations at ``u``
    are then not computed (a caller that only needs ``u`` and the multipliers saves that work).

    Each vector step -- the row set-up, the sweeps and the diagnostics -- runs over the whole batch
    with unit stride. Pair rows are scaled to unit normals (``e_hat . (u_second - u_first) <= b / (2
    |e|)``; the same QP, so the same iterates) and their multipliers carried scaled by ``2 |e|``: a
    row's step then needs three numbers per pair instead of four. ``warm_start`` (multipliers of a
    previous solve) sets the initial multipliers and the matching primal point ``u_hat - A^T lambda``.
    """
    xp = namespace(u_nom, points)
    n = points.shape[0]
    # A robot with a non-finite (or FAR_AWAY) position, a non-finite heading or nominal input is taken out
    # of the QP (no rows, zero velocity, the team reported not feasible): the others are still certified.
    broken = ~(_usable(xp, points, 1) & xp.all(xp.isfinite(u_nom), axis=1))     # [N, B]
    heads = headings
    if heads is not None:
        broken = broken | ~xp.isfinite(heads)
        heads = xp.where(broken, 0, heads)
    points = xp.where(broken[:, None], 0, points)
    u_nom = xp.where(broken[:, None], 0, u_nom)
    if barrier.magnitude_limit is None or barrier.is_v2:   # v2 limits the magnitude by QP rows instead
        u0 = u_nom
    else:
        norm = xp.sqrt(u_nom[:, 0] * u_nom[:, 0] + u_nom[:, 1] * u_nom[:, 1])[:, None]
        u0 = u_nom * controllers.cap_scale(norm, barrier.magnitude_limit, xp)
    rounds, half = round_robin(n)[0].shape
    m = n + n % 2
    dtype = u0.dtype
    flat_b = points.shape[-1]
    pad2 = xp.zeros((m - n, 2, flat_b), dtype=dtype)
    out = xp.concatenate([broken, xp.zeros((m - n, flat_b), dtype=bool)], axis=0)   # [N', B]
    e, b, d2, valid = _pair_rows(barrier, xp.concatenate([points, pad2], axis=0), n, xp,
                                 None if heads is None else xp.concatenate([heads, pad2[:, 0]], axis=0), out)
    usable = d2 > 0
    inv_norm = xp.where(usable, 1 / xp.sqrt(xp.where(usable, d2, 1)), 0)  # 1/|e|, 0 where unusable
    nx, ny = e[:, :, 0] * inv_norm, e[:, :, 1] * inv_norm
    bs = b * (0.5 * inv_norm)
    order = _polygon(n)

    def layout(v):  # [N, k, B] robot order -> [N', k, B] polygon order (phantom zero)
        return xp.concatenate([v, xp.zeros((m - n,) + v.shape[1:], dtype=dtype)], axis=0)[order]

    def robot_order(v):  # inverse of layout (the map is its own inverse)
        return v[order][:n]

    boxed = barrier.boundary_points is not None
    lo = hi = None
    if boxed:
        lo, hi = _boxes(barrier, points, xp)
        lo = xp.where(out[:n, None], -1, lo)
        hi = xp.where(out[:n, None], 1, hi)
        lo_p, hi_p = layout(lo), layout(hi)
    wheeled = barrier.is_differential_drive
    if wheeled:
        c_left, c_right, wheel_norm2 = _wheel_rows(barrier, heads, xp)
        dir_l, dir_r = layout(c_left), layout(c_right)
        inv_c2 = 1 / wheel_norm2
        limit = barrier.wheel_vel_limit
    polygon = barrier.is_v2
    if polygon:
        caps = barrier.polygon_limits()
    omega = barrier.omega(n)

    def box_step(u, lam_lo, lam_hi, w):
        step_hi = xp.maximum(-lam_hi, w * (u - hi_p))
        u = u - step_hi
        step_lo = xp.maximum(-lam_lo, w * (lo_p - u))
        return u + step_lo, lam_lo + step_lo, lam_hi + step_hi

    def slab_step(u, lam_lo, lam_hi, direction, w):
        """Rows ``dir.u <= limit`` (``lam_hi``) and ``-dir.u <= limit`` (``lam_lo``), one robot each."""
        step_hi = xp.maximum(-lam_hi, w * (xp.sum(direction * u, axis=1) - limit) * inv_c2)
        u = u - direction * step_hi[:, None]
        step_lo = xp.maximum(-lam_lo, w * (-limit - xp.sum(direction * u, axis=1)) * inv_c2)
        return u + direction * step_lo[:, None], lam_lo + step_lo, lam_hi + step_hi

    def polygon_step(u, lam_poly, w):
        """Each robot's eight magnitude rows ``n_j . u <= c_j`` (unit normals), one after another."""
        lam_poly = list(lam_poly)
        for j, ((cx, cy), cap) in enumerate(zip(_POLYGON_NORMALS, caps)):
            step = xp.maximum(-lam_poly[j], w * (cx * u[:, 0] + cy * u[:, 1] - cap))
            lam_poly[j] = lam_poly[j] + step
            u = u - xp.stack([cx * step, cy * step], axis=1)
        return u, tuple(lam_poly)

    def sweep(i, carry):
        state, lam, box, wheels, lam_poly = carry
        # The first sweep is plain Gauss-Seidel: it solves single-active-constraint problems exactly.
        # So is the last for the uni_dd kinds, whose wheel limits can make the QP infeasible: an
        # over-relaxed final step would throw the output past the wheel limits it just enforced.
        plain = (i == 0) | (i == last) if wheeled else i == 0
        w = (1.0 if plain else omega) if xp is np else xp.where(plain, 1.0, omega)
        lam = list(lam)
        top, bottom = state[:half], state[half:]
        for r in range(rounds):
            gap = bottom - top
            step = xp.maximum(-lam[r], (0.5 * w) * (nx[r] * gap[:, 0] + ny[r] * gap[:, 1] - bs[r]))
            lam[r] = lam[r] + step
            push = xp.stack([nx[r] * step, ny[r] * step], axis=1)
            top, bottom = top + push, bottom - push
            # One turn of the circle: slots 1..m-1 move right by one (two robots: nothing moves). The two
            # rows stay separate arrays within a sweep: rebuilding the whole state every round costs XLA's
            # CPU backend an extra materialised array per round.
            if half > 1:
                top, bottom = (xp.concatenate([top[:1], bottom[:1], top[1:half - 1]], axis=0),
                               xp.concatenate([bottom[1:], top[half - 1:]], axis=0))
        state = xp.concatenate([top, bottom], axis=0)
        if boxed:
            state, *box = box_step(state, *box, w)
        if wheeled:
            state, l_lo, l_hi = slab_step(state, wheels[0], wheels[1], dir_l, w)
            state, r_lo, r_hi = slab_step(state, wheels[2], wheels[3], dir_r, w)
            wheels = (l_lo, l_hi, r_lo, r_hi)
        if polygon:
            state, lam_poly = polygon_step(state, lam_poly, w)
        return state, tuple(lam), tuple(box), wheels, lam_poly

    lam0 = xp.zeros((rounds, half, flat_b), dtype=dtype)
    zero_box = xp.zeros((m, 2, flat_b), dtype=dtype)
    zero_wheel = xp.zeros((m, flat_b), dtype=dtype)
    box0 = (zero_box,) * 2 if boxed else ()
    wheels0 = (zero_wheel,) * 4 if wheeled else ()
    poly0 = (zero_wheel,) * 8 if polygon else ()
    if warm_start is not None:
        # Rows that cannot act (phantom, coincident robots) start at zero; u0 = u_hat - A^T lambda0.
        lam_w = xp.maximum(warm_start.pairs, 0) * (2 * d2 * inv_norm)  # scaled by 2|e|
        inc = xp.asarray(_incidence(n)[:n], dtype=dtype)
        u0 = u0 + xp.stack([xp.einsum("srh,rhb->sb", inc, nx * lam_w),
                            xp.einsum("srh,rhb->sb", inc, ny * lam_w)], axis=1)
        lam0 = lam_w
        if boxed:
            lo_w = xp.maximum(warm_start.lower, 0)   # [N, 2, B]
            hi_w = xp.maximum(warm_start.upper, 0)
            u0 = u0 + lo_w - hi_w
            box0 = (layout(lo_w), layout(hi_w))
        if wheeled:
            w_lo = xp.maximum(warm_start.wheel_lower, 0)   # [N, 2 wheels, B]
            w_hi = xp.maximum(warm_start.wheel_upper, 0)
            net = (w_lo - w_hi)[:, :, None]
            u0 = u0 + c_left * net[:, 0] + c_right * net[:, 1]
            w_lo, w_hi = layout(w_lo), layout(w_hi)
            wheels0 = (w_lo[:, 0], w_hi[:, 0], w_lo[:, 1], w_hi[:, 1])
        if polygon:
            p_w = xp.maximum(warm_start.polygon, 0)     # [N, 8, B]
            normals = xp.asarray(_POLYGON_NORMALS, dtype=dtype)            # [8, 2]
            u0 = u0 - xp.einsum("njb,jc->ncb", p_w, normals)
            p_w = layout(p_w)
            poly0 = tuple(p_w[:, j] for j in range(8))
    sweeps = barrier.sweeps(n)
    last = sweeps - 1
    init = (layout(u0), tuple(lam0[r] for r in range(rounds)), box0, wheels0, poly0)
    state, lam, box, wheels, lam_poly = fori_loop(xp, 0, sweeps, sweep, init)
    # (m - 1) turns per sweep bring the slots back to the polygon order of the start.
    u = robot_order(state)                                                # [N, 2, B]
    lam = xp.stack(lam, axis=0) * (0.5 * inv_norm)                          # [R, H, B], unscaled
    box = tuple(robot_order(v) for v in box)                               # lower, upper [N, 2, B]
    wheel_rows = None
    if wheeled:
        l_lo, l_hi, r_lo, r_hi = (robot_order(v) for v in wheels)
        wheels = (xp.stack([l_lo, r_lo], axis=1), xp.stack([l_hi, r_hi], axis=1))   # [N, 2 wheels, B]
        wheel_rows = (c_left, c_right, wheel_norm2) + wheels
    poly = robot_order(xp.stack(lam_poly, axis=1)) if polygon else None    # [N, 8, B]
    info = None
    if diagnose:
        info = _diagnostics(barrier, u, e, b, d2, valid, lam, lo, hi, box, xp, wheel_rows, poly)
        info = info._replace(feasible=info.feasible & ~xp.any(out, axis=0))
    u = xp.where(out[:n, None], 0, u)
    lower, upper = box if boxed else (None, None)
    wheel_lower, wheel_upper = wheels if wheeled else (None, None)
    return u, Multipliers(lam, lower, upper, wheel_lower, wheel_upper, poly), info


def _diagnostics(barrier, u, e, b, d2, valid, lam, lo, hi, box, xp, wheel_rows=None, poly=None):
    """Violation of every row at the returned ``u [N, 2, B]`` (not only the rows the solver touched);
    batch-minor like :func:`solve_si`'s internals, each result ``[B]``."""
    n, _, flat_b = u.shape
    first, second = round_robin(n)
    rows = (0, 1)
    if first.size:
        padded = xp.concatenate([u, xp.zeros((n % 2, 2, flat_b), dtype=u.dtype)], axis=0)
        gap = 2 * xp.sum(e * (padded[second] - padded[first]), axis=2) - b
        usable = d2 > 0
        row_norm = xp.sqrt(8 * xp.where(usable, d2, 1))                   # |a| = 2 sqrt(2) |e|
        real = valid[:, :, None]
        pair_viol = xp.where(usable, gap / row_norm, xp.where(real & (b < 0), -b, 0))
        worst = xp.max(pair_viol, axis=rows)
        active = xp.sum(lam > 0, axis=rows)
        degenerate = xp.any(real & ~usable & (b < 0), axis=rows)
    else:
        worst = xp.zeros((flat_b,), dtype=u.dtype)
        active = xp.zeros((flat_b,), dtype=xp.int32)
        degenerate = worst > 0
    # every right-hand side >= 0: standing still is admissible, so the QP has a solution
    zero_admissible = xp.all((b >= 0) | ~valid[:, :, None], axis=rows) if first.size else worst == 0
    if lo is not None:
        lam_lo, lam_hi = box
        worst = xp.maximum(worst, xp.max(xp.maximum(u - hi, lo - u), axis=rows))
        active = active + xp.sum((lam_lo > 0) | (lam_hi > 0), axis=rows)
        zero_admissible = zero_admissible & xp.all((lo <= 0) & (hi >= 0), axis=rows)
    if wheel_rows is not None:   # |c . u| <= limit, violation as a distance along c
        c_left, c_right, norm2, wheel_lo, wheel_hi = wheel_rows
        speeds = xp.stack([xp.sum(c_left * u, axis=1), xp.sum(c_right * u, axis=1)], axis=1)   # [N, 2, B]
        wheel_viol = (xp.abs(speeds) - barrier.wheel_vel_limit) / math.sqrt(norm2)
        worst = xp.maximum(worst, xp.max(wheel_viol, axis=rows))
        active = active + xp.sum((wheel_lo > 0) | (wheel_hi > 0), axis=rows)
    if poly is not None:         # n_j . u <= c_j, unit normals
        normals = xp.asarray(_POLYGON_NORMALS, dtype=u.dtype)                            # [8, 2]
        caps = xp.asarray(barrier.polygon_limits(), dtype=u.dtype)[None, :, None]
        poly_viol = xp.einsum("jc,ncb->njb", normals, u) - caps                         # [N, 8, B]
        worst = xp.maximum(worst, xp.max(poly_viol, axis=rows))
        active = active + xp.sum(poly > 0, axis=rows)
    scale = 1 + xp.max(xp.abs(u), axis=rows)
    solved = (worst <= barrier.tolerance * scale) & ~degenerate
    stopped = ~solved & ~zero_admissible if barrier.is_v2 else None
    feasible = solved
    if barrier.speed_limit is not None:   # a solution no robot can drive is no certificate either
        speed = xp.sqrt(xp.max(xp.sum(u * u, axis=1), axis=0))
        feasible = feasible & (speed <= barrier.speed_limit * (1 + barrier.tolerance))
    return CertificateInfo(worst, feasible, active, stopped=stopped, solved=solved)


__all__ = ["make_barrier", "Barrier", "CertificateInfo", "Multipliers", "KINDS", "SI_KINDS", "UNI_KINDS", "DD_KINDS",
           "V2_KINDS", "V2_TOLERANCE",
           "round_robin", "default_iterations", "default_relaxation", "solve_si", "solve_si_minor"]
