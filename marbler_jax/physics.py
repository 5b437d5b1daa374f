"""Robotarium robot physics: unicycle kinematics, actuator limits, arena checks.

Conventions (robot-major, unlike rps's ``3 x N``):

* ``poses``: ``[..., N, 3]`` = (x [m], y [m], theta [rad] in (-pi, pi]).
* unicycle ``velocities``: ``[..., N, 2]`` = (v [m/s], omega [rad/s]).
* wheel speeds: ``[..., N, 2]`` = (left, right) [rad/s].

Every function is pure, batched over leading axes and works on numpy *or* JAX arrays (the
namespace follows the inputs, see :mod:`marbler_jax.xp`), so the numpy-only Robotarium bundle
runs the same code as training.

Simulator versions (see ``shared/spec/robotarium.md``):

* ``"marbler"`` -- rps commit 6bb184e, the version MARBLER pins. ``set_velocities`` clips v to
  +-0.2 m/s and omega to +-3.6364 rad/s *independently*; there is no wheel clip.
* ``"rps2024"`` -- rps 5ec16db / 1fb9dfe (last release of the old API, used by JaxRobotarium's
  deployment). ``step`` clips each *wheel* to +-12.5 rad/s with base length 0.105.
* ``"robotarium"`` -- rps v2 (b23069e, the Robotarium's simulator): per-wheel clip at 12.5 rad/s with base
  length 0.11. The default everywhere.

Integration is forward Euler with the pre-step heading, then theta is wrapped with
``atan2(sin, cos)``, exactly as rps does. Validation (collisions, boundary) is a separate pure
function; as in rps it never alters the motion.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import operator
from typing import Literal

import numpy as np

from marbler_jax.xp import fori_loop, from_minor, namespace, result_dtype, to_minor, vmap_in_place

ThresholdMode = Literal["components", "wheels"]


@dataclasses.dataclass(frozen=True)
class RobotariumParams:
    """Constants of one Robotarium simulator version (hashable; a static pytree under JAX).

    Attributes:
        dt: simulator tick [s].
        wheel_radius: r [m].
        base_length: axle length L [m] used in uni <-> wheel conversions.
        robot_diameter: body diameter [m]; only enters ``max_angular_velocity``.
        max_linear_velocity: |v| limit [m/s] (``"components"`` thresholding).
        max_angular_velocity: |omega| limit [rad/s] (``"components"`` thresholding).
        max_wheel_velocity: |wheel| limit [rad/s] (``"wheels"`` thresholding).
        threshold_mode: ``"components"`` (clip v and omega separately, rps 6bb184e) or
            ``"wheels"`` (clip each wheel, later rps versions).
        arena: (x_min, x_max, y_min, y_max) [m]; a centre strictly outside is out of bounds.
        collision_offset: forward shift of the collision-test centre [m].
        collision_diameter: two shifted centres at distance <= this collide [m].
        max_robots: largest team the simulator accepts.
    """

    dt: float = 0.033
    wheel_radius: float = 0.016
    base_length: float = 0.11
    robot_diameter: float = 0.11
    max_linear_velocity: float = 0.2
    max_angular_velocity: float = 2 * (0.016 / 0.11) * (0.2 / 0.016)
    max_wheel_velocity: float = 12.5
    threshold_mode: ThresholdMode = "wheels"
    arena: tuple[float, float, float, float] = (-1.6, 1.6, -1.0, 1.0)
    collision_offset: float = 0.025
    collision_diameter: float = 0.135
    max_robots: int = 50

    def __post_init__(self):
        if self.threshold_mode not in ("components", "wheels"):
            raise ValueError(
                f"threshold_mode={self.threshold_mode!r} is not supported; "
                "use 'components' or 'wheels'"
            )
        for name in ("dt", "wheel_radius", "base_length", "max_linear_velocity",
                     "max_angular_velocity", "max_wheel_velocity"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        x_min, x_max, y_min, y_max = self.arena
        if not (x_min < x_max and y_min < y_max):
            raise ValueError(f"arena must be (x_min, x_max, y_min, y_max) with min < max, got {self.arena}")

    def replace(self, **changes) -> "RobotariumParams":
        return dataclasses.replace(self, **changes)


PRESETS: dict[str, RobotariumParams] = {
    "marbler": RobotariumParams(base_length=0.105, threshold_mode="components"),
    "rps2024": RobotariumParams(base_length=0.105, threshold_mode="wheels"),
    "robotarium": RobotariumParams(base_length=0.11, threshold_mode="wheels"),
}
# What a bundle commands: rps v2's wheel clip a hair inside the limit (see actuator_safe); the replay of a
# bundle's run uses it, since after it neither rps's own clip changes anything.
PRESETS["deployed"] = PRESETS["robotarium"].replace(
    max_wheel_velocity=PRESETS["robotarium"].max_wheel_velocity * (1 - 1e-9))
DEFAULT_PRESET = "robotarium"


def get_params(preset: str | RobotariumParams = DEFAULT_PRESET) -> RobotariumParams:
    """Look up a preset by name (``RobotariumParams`` pass through)."""
    if isinstance(preset, RobotariumParams):
        return preset
    try:
        return PRESETS[preset]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown physics preset {preset!r}; choose one of {sorted(PRESETS)}"
        ) from None


def uni_to_diff(params: RobotariumParams, velocities):
    """Unicycle (v, omega) ``[..., N, 2]`` -> wheel speeds (left, right) ``[..., N, 2]`` [rad/s]."""
    xp = namespace(velocities)
    return xp.stack(_wheel_speeds(params, velocities[..., 0], velocities[..., 1]), axis=-1)


def diff_to_uni(params: RobotariumParams, wheels):
    """Wheel speeds (left, right) ``[..., N, 2]`` -> unicycle (v, omega) ``[..., N, 2]``."""
    xp = namespace(wheels)
    return xp.stack(_unicycle(params, wheels[..., 0], wheels[..., 1]), axis=-1)


def _wheel_speeds(params: RobotariumParams, v, w):
    """``(left, right)`` wheel speeds [rad/s] of (v, omega), any equal shapes."""
    r, length = params.wheel_radius, params.base_length
    return (2 * v - length * w) / (2 * r), (2 * v + length * w) / (2 * r)


def _unicycle(params: RobotariumParams, left, right):
    """``(v, omega)`` of wheel speeds ``left``, ``right`` [rad/s], any equal shapes."""
    r, length = params.wheel_radius, params.base_length
    return r / 2 * (left + right), r / length * (right - left)


def threshold(params: RobotariumParams, velocities):
    """Apply the simulator's actuator limits to (v, omega) ``[..., N, 2]``.

    ``"components"``: clip v to +-max_linear_velocity and omega to +-max_angular_velocity
    independently. ``"wheels"``: clip each wheel speed to +-max_wheel_velocity (sign
    preserving, not a proportional scaling -- curvature is not kept), then map back.
    """
    xp = namespace(velocities)
    v, w = threshold_vw(params, velocities[..., 0], velocities[..., 1], xp)
    return xp.stack([v, w], axis=-1)


def threshold_vw(params: RobotariumParams, v, w, xp):
    """:func:`threshold` on separate arrays ``v`` [m/s] and ``w`` [rad/s] of any (equal) shape."""
    if params.threshold_mode == "components":
        return (xp.clip(v, -params.max_linear_velocity, params.max_linear_velocity),
                xp.clip(w, -params.max_angular_velocity, params.max_angular_velocity))
    limit = params.max_wheel_velocity
    left, right = (xp.clip(wheel, -limit, limit) for wheel in _wheel_speeds(params, v, w))
    return _unicycle(params, left, right)


def actuator_safe(velocities):
    """(v, omega) ``[..., N, 2]`` with each wheel speed clipped to the 12.5 rad/s motor limit at the
    largest base length of any preset (0.11 m, rps v2), what a deployed command goes through.

    rps counts an actuator error whenever a commanded wheel speed exceeds the limit (rps v2 with
    L = 0.11, rps 6bb184e with L = 0.105 after its own v / omega clip). A command clipped this way
    passes both checks, and on rps v2 it moves the robots as rps's own wheel clip would, to 1e-9
    relative: the clip stops that far below the limit, because a wheel clipped to exactly 12.5 comes
    back from rps's (v, omega) -> wheel conversion as 12.500000000000002 in ~0.6 % of clipped commands.
    """
    return threshold(PRESETS["deployed"], velocities)


def wrap_angle(theta):
    """Wrap angles to (-pi, pi] the way rps does: ``atan2(sin, cos)``."""
    xp = namespace(theta)
    return xp.arctan2(xp.sin(theta), xp.cos(theta))


def _prepare(params, poses, velocities, ticks, minimum: int):
    """Validate ``ticks``, pick the array namespace and common dtype, threshold the command."""
    ticks = int(ticks)
    if ticks < minimum:
        raise ValueError(f"ticks must be >= {minimum}, got {ticks}")
    xp = namespace(poses, velocities)
    dtype = result_dtype(xp, poses, velocities)
    poses = xp.asarray(poses, dtype=dtype)
    return xp, poses, threshold(params, xp.asarray(velocities, dtype=dtype)), ticks


def integrate(params: RobotariumParams, poses, velocities, ticks: int = 1):
    """Advance ``poses [..., N, 3]`` by ``ticks`` simulator ticks holding ``velocities [..., N, 2]``.

    The command is thresholded once (as the preset does; thresholding is idempotent, so
    holding it is the same as re-thresholding every tick). Each tick is forward Euler with the
    pre-step heading followed by the atan2 wrap. For ``ticks > 1`` the heading advances by the
    constant angle ``delta = dt * omega`` per tick, so the Euler sum has the closed form
    ``sum_k cos(theta + k delta) = sin(T delta / 2) / sin(delta / 2) * cos(theta + (T-1) delta / 2)``
    -- one trig evaluation regardless of ``ticks`` (agrees with the tick loop to rounding).

    Args:
        params: simulator constants (``PRESETS[...]``).
        poses: ``[..., N, 3]`` current poses.
        velocities: ``[..., N, 2]`` commanded (v, omega), before limits.
        ticks: static number of ticks (>= 0).

    Returns:
        ``[..., N, 3]`` poses after ``ticks`` ticks, theta in (-pi, pi].
    """
    xp, poses, vel, ticks = _prepare(params, poses, velocities, ticks, minimum=0)
    if ticks == 0:
        return poses
    x, y, theta = poses[..., 0], poses[..., 1], poses[..., 2]
    v, w = vel[..., 0], vel[..., 1]
    dt = params.dt
    if ticks == 1:
        step = dt * v
        return xp.stack(
            [x + step * xp.cos(theta), y + step * xp.sin(theta), wrap_angle(theta + dt * w)],
            axis=-1,
        )
    return _held_pose(xp, x, y, theta, v, w, dt, ticks)


def _held_pose(xp, x, y, theta, v, w, dt, k):
    """Pose after ``k`` Euler ticks holding (v, w); ``k`` a number or an array broadcasting with x.

    The heading advances by ``delta = dt w`` per tick, so
    ``sum_{j<k} cos(theta + j delta) = sin(k delta / 2) / sin(delta / 2) * cos(theta + (k-1) delta / 2)``.
    """
    half = dt * w / 2
    small = xp.abs(half) < 1e-6
    safe_half = xp.where(small, xp.ones_like(half), half)
    # sin(k h)/sin(h); series k (1 - (k^2 - 1) h^2 / 6) where h is tiny (avoids 0/0).
    gain = xp.where(small, k * (1 - (k * k - 1) * half * half / 6), xp.sin(k * safe_half) / xp.sin(safe_half))
    mid = theta + (k - 1) * half
    travel = dt * v * gain
    return xp.stack([x + travel * xp.cos(mid), y + travel * xp.sin(mid), wrap_angle(theta + 2 * k * half)], axis=-1)


def trajectory(params: RobotariumParams, poses, velocities, ticks: int):
    """All poses visited while holding ``velocities`` for ``ticks`` ticks: ``[ticks + 1, ..., N, 3]``.

    Entry ``k`` is the pose after ``k`` ticks (entry 0 is ``poses``). Every entry is the closed form
    of :func:`integrate`, evaluated for all ``k`` at once (no sequential loop), so checks that rps
    runs at every tick (collisions, boundary) can be vectorized over the ticks of a control period.
    """
    xp, poses, vel, ticks = _prepare(params, poses, velocities, ticks, minimum=1)
    k = xp.arange(ticks + 1, dtype=poses.dtype).reshape((ticks + 1,) + (1,) * (poses.ndim - 1))
    return _held_pose(xp, poses[..., 0], poses[..., 1], poses[..., 2], vel[..., 0], vel[..., 1], params.dt, k)


def held_ticks(params: RobotariumParams, poses, velocities, ticks: int, stop_on_violation: bool = True):
    """Run ``ticks`` ticks holding ``velocities``, validating each pre-tick pose as rps does.

    rps checks the pose *before* integrating each tick (collision: shifted centres ``<=``
    ``collision_diameter``; boundary: centre strictly outside the arena) and then integrates. With
    ``stop_on_violation`` the motion stops after the first tick whose pre-tick pose violates (MARBLER
    ends the env step there). The heading is advanced by rotating ``(cos, sin)`` by the constant
    angle ``dt * omega`` (:func:`turn`), so the loop needs no trig; it agrees with :func:`integrate` to rounding.

    Under JAX the tick loop (``ticks > 1``) runs on robot-major, batch-minor arrays ``[N, B]``
    (also under ``jax.vmap``, through :func:`marbler_jax.xp.vmap_in_place`), so every per-tick op
    is a unit-stride vector op over the whole batch.

    Args:
        poses: ``[..., N, 3]``; velocities: ``[..., N, 2]`` (thresholded here); ticks: static.

    Returns:
        ``(poses [..., N, 3], collided [...], out_of_bounds [...], distance [..., N])`` where the flags
        say whether a checked pre-tick pose violated, and ``distance`` is the path length driven [m].
    """
    xp, poses, vel, ticks = _prepare(params, poses, velocities, ticks, minimum=0)
    if xp is not np and ticks > 1:  # a single tick is cheaper than the two transposes
        return _jax_held_ticks(params, ticks, bool(stop_on_violation))(poses, vel)
    return _held_ticks(params, ticks, bool(stop_on_violation), poses, vel)


_SHIFTED_PAIRS_FROM = 16


@functools.lru_cache(maxsize=None)
def _jax_held_ticks(params: RobotariumParams, ticks: int, stop_on_violation: bool):
    return vmap_in_place(functools.partial(_held_ticks, params, ticks, stop_on_violation))


def _held_ticks(params: RobotariumParams, ticks: int, stop_on_violation: bool, poses, vel):
    """:func:`held_ticks` on thresholded ``vel``; the loop state is ``[N, B]`` (batch folded, minor)."""
    xp = namespace(poses, vel)
    batch = poses.shape[:-2]
    nb = len(batch)
    x, y, theta = (to_minor(poses[..., k], nb, xp) for k in range(3))
    v, w = (to_minor(vel[..., k], nb, xp) for k in range(2))
    x, y, c, s, hit, out, dist = held_ticks_minor(params, x, y, xp.cos(theta), xp.sin(theta), v, w, ticks,
                                                  stop_on_violation)
    new_poses = from_minor(xp.stack([x, y, xp.arctan2(s, c)], axis=1), batch, xp)
    return new_poses, from_minor(hit, batch, xp), from_minor(out, batch, xp), from_minor(dist, batch, xp)


def turn(delta, bound: float, xp):
    """``(cos delta, sin delta)`` of a turn ``|delta| <= bound`` [rad] (``bound`` static).

    Up to ``bound = pi / 4`` (a tick's turn is at most ``dt`` times :func:`max_angular_velocity`, 0.13
    rad in every preset) both are their Taylor polynomials, cut where the first omitted term is below
    an eighth of the dtype's epsilon at ``bound``: the values of ``cos``/``sin`` to rounding, without
    the range reduction XLA's ``cos``/``sin`` run on every call (at ``control_period = 1``, every tick for
    every robot). Larger bounds use ``cos``/``sin``.
    """
    if bound > math.pi / 4:
        return xp.cos(delta), xp.sin(delta)
    eps = float(np.finfo(delta.dtype).eps)
    order = 2
    while bound ** (order + 1) / math.factorial(order + 1) >= eps / 8:
        order += 1
    d2 = delta * delta
    cos_d = sin_d = 1.0
    for k in range(order // 2, 0, -1):          # Horner in d2, from the highest kept term
        cos_d = 1 - cos_d * d2 / ((2 * k - 1) * (2 * k))
    for k in range((order - 1) // 2, 0, -1):
        sin_d = 1 - sin_d * d2 / ((2 * k) * (2 * k + 1))
    return cos_d, delta * sin_d


def held_ticks_minor(params: RobotariumParams, x, y, c, s, v, w, ticks: int, stop_on_violation: bool = True):
    """The tick loop of :func:`held_ticks` on batch-minor arrays, the heading as its unit vector.

    Args:
        x, y, c, s: ``[N, B]`` positions [m] and ``(cos, sin)`` of the headings.
        v, w: ``[N, B]`` thresholded command [m/s, rad/s], held for all ``ticks`` (static).

    Returns:
        ``(x, y, c, s, collided [B], out_of_bounds [B], distance [N, B])``; a pre-tick pose with a
        coordinate outside the arena or not finite counts as out of bounds.
    """
    xp = namespace(x, y, c, s, v, w)
    n = x.shape[0]
    x_min, x_max, y_min, y_max = params.arena
    off, diam2 = params.collision_offset, params.collision_diameter ** 2
    step = params.dt * v
    delta = params.dt * w
    cos_d, sin_d = turn(delta, params.dt * max_angular_velocity(params), xp)
    false = xp.zeros(x.shape[1:], dtype=bool)

    def collide(cx, cy):
        """Any pair i < j with shifted centres within the collision diameter: ``[B]``.

        Small teams compare robot i with robots i+1..N-1 (static slices). From 16 robots on, robot i
        meets robot i+s (mod N) for s = 1..N/2: every pair exactly once, as cyclic shifts of the
        ``[N, B]`` arrays reduced in one op: each pair computed once, where a masked ``[N, N, B]``
        block would compute it twice (the slices are faster below ~16 robots)."""
        if n >= _SHIFTED_PAIRS_FROM:
            gaps = []
            for shift in range(1, n // 2 + 1):
                rows = n // 2 if 2 * shift == n else n   # the half-way shift meets each pair twice
                dx = xp.roll(cx, -shift, axis=0)[:rows] - cx[:rows]   # robot i + shift minus robot i
                dy = xp.roll(cy, -shift, axis=0)[:rows] - cy[:rows]
                gaps.append(dx * dx + dy * dy)
            return xp.any(xp.concatenate(gaps, axis=0) <= diam2, axis=0)
        hit = false
        for i in range(n - 1):
            dx, dy = cx[i + 1:] - cx[i], cy[i + 1:] - cy[i]
            hit = hit | xp.any(dx * dx + dy * dy <= diam2, axis=0)
        return hit

    def tick(_, carry):
        x, y, c, s, stopped, hit, out, dist = carry
        hit_now = collide(x + off * c, y + off * s)
        out_now = ~xp.all((x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max), axis=0)
        live = ~stopped
        hit = hit | (live & hit_now)
        out = out | (live & out_now)
        x = xp.where(live, x + step * c, x)
        y = xp.where(live, y + step * s, y)
        c, s = xp.where(live, c * cos_d - s * sin_d, c), xp.where(live, s * cos_d + c * sin_d, s)
        dist = dist + xp.where(live, xp.abs(step), 0)
        if stop_on_violation:
            stopped = stopped | hit_now | out_now
        return x, y, c, s, stopped, hit, out, dist

    carry = (x, y, c, s, false, false, false, xp.zeros_like(x))
    x, y, c, s, _, hit, out, dist = fori_loop(xp, 0, int(ticks), tick, carry)
    return x, y, c, s, hit, out, dist


def collision_centres(params: RobotariumParams, poses):
    """Centres used by the collision test: positions shifted forward by ``collision_offset``."""
    xp = namespace(poses)
    theta = poses[..., 2]
    offset = params.collision_offset
    return poses[..., :2] + offset * xp.stack([xp.cos(theta), xp.sin(theta)], axis=-1)


def pair_distances(points):
    """Pairwise distances ``[..., N, N]`` of ``points [..., N, 2]`` (diagonal = +inf)."""
    xp = namespace(points)
    diff = points[..., :, None, :] - points[..., None, :, :]
    dist = xp.sqrt(xp.sum(diff * diff, axis=-1))
    n = points.shape[-2]
    eye = xp.eye(n, dtype=bool)
    return xp.where(eye, xp.asarray(xp.inf, dtype=dist.dtype), dist)


def collisions(params: RobotariumParams, poses):
    """Per-robot collision flags ``[..., N]`` (bool), as rps counts them.

    Robot i collides when some other robot's shifted centre lies within
    ``collision_diameter`` (``<=``) of its own shifted centre.
    """
    xp = namespace(poses)
    dist = pair_distances(collision_centres(params, poses))
    return xp.any(dist <= params.collision_diameter, axis=-1)


def collision_pairs(params: RobotariumParams, poses):
    """Number of colliding unordered pairs ``[...]`` (rps adds 2 per pair to its error dict)."""
    xp = namespace(poses)
    dist = pair_distances(collision_centres(params, poses))
    return xp.sum(dist <= params.collision_diameter, axis=(-1, -2)) // 2


def out_of_bounds(params: RobotariumParams, poses):
    """Per-robot boundary flags ``[..., N]``: centre strictly outside the arena (no margin), as rps
    checks it; a pose with a non-finite coordinate or heading counts as outside (rps would report
    nothing for it: every comparison with NaN is False)."""
    xp = namespace(poses)
    x_min, x_max, y_min, y_max = params.arena
    x, y = poses[..., 0], poses[..., 1]
    inside = (x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max) & xp.isfinite(poses[..., 2])
    return ~inside


def check_num_robots(params: RobotariumParams, num_robots: int) -> int:
    """Validate a team size against the simulator's limit; returns it as int."""
    try:
        n = operator.index(num_robots)
    except TypeError:
        raise TypeError(f"number of robots must be an integer, got {num_robots!r}") from None
    if not 1 <= n <= params.max_robots:
        raise ValueError(
            f"number of robots must be in [1, {params.max_robots}] for the Robotarium simulator, got {n}"
        )
    return n


def max_angular_velocity(params: RobotariumParams) -> float:
    """Largest |omega| reachable: the component limit, or a pure spin at the wheel limit."""
    if params.threshold_mode == "components":
        return params.max_angular_velocity
    return 2 * params.wheel_radius * params.max_wheel_velocity / params.base_length


__all__ = [
    "actuator_safe", "RobotariumParams", "PRESETS", "DEFAULT_PRESET", "get_params", "uni_to_diff", "diff_to_uni",
    "threshold", "threshold_vw", "wrap_angle", "integrate", "trajectory", "held_ticks", "held_ticks_minor", "turn", "collision_centres", "pair_distances", "collisions",
    "collision_pairs", "out_of_bounds", "check_num_robots",
    "max_angular_velocity",
]
