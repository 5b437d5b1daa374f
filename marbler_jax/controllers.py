"""Goal-to-velocity controllers and SI <-> unicycle maps (rps 6bb184e semantics).

Shapes are robot-major: poses ``[..., N, 3]``, SI points/velocities ``[..., N, 2]``, unicycle
velocities ``[..., N, 2]`` = (v, omega). Works on numpy and JAX arrays alike.

MARBLER's pipeline (:func:`marbler_velocities`): project each pose forward by 0.05 m, drive the
*projected point* to its goal with the SI position controller, certify with an SI barrier, and
map back with :func:`si_to_uni_mapping` (omega clipped to +-pi).
"""
from __future__ import annotations

import math

from marbler_jax.xp import namespace


def _unit(theta, xp):
    return xp.cos(theta), xp.sin(theta)


def uni_to_si_states(poses, projection_distance: float = 0.05):
    """Projection point ``p = (x, y) + d (cos theta, sin theta)``: ``[..., N, 3] -> [..., N, 2]``."""
    xp = namespace(poses)
    c, s = _unit(poses[..., 2], xp)
    return poses[..., :2] + projection_distance * xp.stack([c, s], axis=-1)


def si_to_uni_mapping(dxi, poses, projection_distance: float = 0.05,
                      angular_velocity_limit: float = math.pi):
    """SI velocity of the projection point -> (v, omega), omega clipped to +-limit.

    ``v = c dx + s dy``, ``omega = (-s dx + c dy) / d`` (rps ``create_si_to_uni_mapping``).
    """
    xp = namespace(dxi, poses)
    c, s = _unit(poses[..., 2], xp)
    v, w = _si_to_uni(dxi[..., 0], dxi[..., 1], c, s, projection_distance, angular_velocity_limit, xp)
    return xp.stack([v, w], axis=-1)


def _si_to_uni(dx, dy, c, s, projection_distance, angular_velocity_limit, xp):
    """:func:`si_to_uni_mapping` on components: ``(v, omega)`` for headings ``(c, s) = (cos, sin)``."""
    v = c * dx + s * dy
    w = (-s * dx + c * dy) / projection_distance
    return v, xp.clip(w, -angular_velocity_limit, angular_velocity_limit)


def uni_to_si_dynamics(dxu, poses, projection_distance: float = 0.05):
    """(v, omega) -> velocity of the projection point (rps ``create_uni_to_si_dynamics``)."""
    xp = namespace(dxu, poses)
    c, s = _unit(poses[..., 2], xp)
    v, w = dxu[..., 0], dxu[..., 1]
    d = projection_distance
    return xp.stack([c * v - d * s * w, s * v + d * c * w], axis=-1)


def si_to_uni_dynamics(dxi, poses, linear_velocity_gain: float = 1.0,
                       angular_velocity_limit: float = math.pi):
    """SI velocity -> (v, omega) by the atan2 law (rps ``create_si_to_uni_dynamics``).

    ``v = k (c dx + s dy)``, ``omega = limit * atan2(-s dx + c dy, v) / (pi / 2)``; no clipping.
    """
    xp = namespace(dxi, poses)
    c, s = _unit(poses[..., 2], xp)
    dx, dy = dxi[..., 0], dxi[..., 1]
    v = linear_velocity_gain * (c * dx + s * dy)
    w = angular_velocity_limit * xp.arctan2(-s * dx + c * dy, v) / (math.pi / 2)
    return xp.stack([v, w], axis=-1)


SI_VELOCITY_LIMIT = 0.15
"""rps's SI position controller's norm cap [m/s] (``velocity_magnitude_limit``), MARBLER's setting."""


def si_position_controller(xi, goals, x_velocity_gain: float = 1.0, y_velocity_gain: float = 1.0,
                           velocity_magnitude_limit: float = SI_VELOCITY_LIMIT):
    """Proportional SI controller ``diag(kx, ky) (goal - xi)``, norms capped at the limit."""
    xp = namespace(xi, goals)
    gains = xp.asarray([x_velocity_gain, y_velocity_gain], dtype=xp.result_type(xi, goals))
    dxi = gains * (goals[..., :2] - xi)
    return cap_norm(dxi, velocity_magnitude_limit)


def cap_norm(vectors, limit: float):
    """Rescale rows of ``vectors [..., 2]`` whose norm exceeds ``limit`` to norm ``limit``."""
    xp = namespace(vectors)
    return vectors * cap_scale(xp.sqrt(xp.sum(vectors * vectors, axis=-1, keepdims=True)), limit, xp)


def cap_scale(norm, limit: float, xp):
    """The factor :func:`cap_norm` applies to a vector of norm ``norm``: ``min(1, limit / norm)``."""
    return xp.where(norm > limit, limit / xp.where(norm > limit, norm, 1), 1)


def clf_unicycle_position_controller(poses, goals, linear_velocity_gain: float = 0.8,
                                     angular_velocity_gain: float = 3.0):
    """CLF position controller on the robot centre (no saturation, as in rps)."""
    xp = namespace(poses, goals)
    ex = goals[..., 0] - poses[..., 0]
    ey = goals[..., 1] - poses[..., 1]
    rho = xp.sqrt(ex * ex + ey * ey)
    heading = xp.arctan2(ey, ex) - poses[..., 2]
    return xp.stack([linear_velocity_gain * rho * xp.cos(heading),
                     angular_velocity_gain * rho * xp.sin(heading)], axis=-1)


def clf_unicycle_pose_controller(poses, goals, approach_angle_gain: float = 1.0,
                                 desired_angle_gain: float = 2.7, rotation_error_gain: float = 1.0):
    """CLF pose controller (rps ``create_clf_unicycle_pose_controller``); goals ``[..., N, 3]``.

    Deviation from rps: at alpha == 0 rps divides by zero and returns NaN; we use the limit
    ``cos(alpha) sin(alpha) / alpha -> 1``.
    """
    xp = namespace(poses, goals)
    c, s = xp.cos(goals[..., 2]), xp.sin(goals[..., 2])
    dx = goals[..., 0] - poses[..., 0]
    dy = goals[..., 1] - poses[..., 1]
    egx = c * dx + s * dy
    egy = -s * dx + c * dy
    e = xp.sqrt(egx * egx + egy * egy)
    beta = xp.arctan2(egy, egx)
    alpha = beta - (poses[..., 2] - goals[..., 2])
    alpha = xp.arctan2(xp.sin(alpha), xp.cos(alpha))
    tiny = xp.abs(alpha) < 1e-9
    ratio = xp.where(tiny, 1.0, xp.cos(alpha) * xp.sin(alpha) / xp.where(tiny, 1.0, alpha))
    v = approach_angle_gain * e * xp.cos(alpha)
    w = desired_angle_gain * alpha + approach_angle_gain * ratio * (alpha + rotation_error_gain * beta)
    return xp.stack([v, w], axis=-1)


def marbler_velocities(poses, goals, barrier=None, projection_distance: float = 0.05):
    """MARBLER's ``Controller.set_velocities``: goals ``[..., N, 2|3]`` -> (v, omega) ``[..., N, 2]``.

    ``barrier`` is an SI certificate ``(dxi, xi) -> dxi`` (e.g. ``cbf.make_barrier("si2",
    safety_radius=0.2)``) or ``None`` for no barrier.
    """
    xi = uni_to_si_states(poses, projection_distance)
    dxi = si_position_controller(xi, goals)
    if barrier is not None:
        dxi = barrier(dxi, xi)
    return si_to_uni_mapping(dxi, poses, projection_distance)


def marbler_velocities_warm(poses, goals, barrier, multipliers, projection_distance: float = 0.05):
    """:func:`marbler_velocities` with a :class:`marbler_jax.cbf.Barrier` warm-started from
    ``multipliers`` (the previous solve's ``info.multipliers``); returns ``(velocities, multipliers)``."""
    xi = uni_to_si_states(poses, projection_distance)
    dxi, info = barrier.solve(si_position_controller(xi, goals), xi, warm_start=multipliers)
    return si_to_uni_mapping(dxi, poses, projection_distance), info.multipliers


def marbler_velocities_minor(x, y, c, s, goal_x, goal_y, barrier=None, multipliers=None,
                             projection_distance: float = 0.05):
    """:func:`marbler_velocities` on batch-minor arrays, the heading given as its unit vector.

    Args:
        x, y, c, s: ``[N, B]`` positions [m] and ``(cos, sin)`` of the headings.
        goal_x, goal_y: ``[N, B]`` goals of the projection points [m].
        barrier: an SI :class:`marbler_jax.cbf.Barrier` or ``None``.
        multipliers: batch-minor warm start of the barrier (see
            :meth:`marbler_jax.cbf.Barrier.solve_minor`) or ``None`` for a cold solve.

    Returns:
        ``(v [N, B], omega [N, B], multipliers)`` (omega clipped to +-pi; ``multipliers`` is ``None``
        without a barrier).
    """
    xp = namespace(x, goal_x)
    d = projection_distance
    px, py = x + d * c, y + d * s
    dx, dy = goal_x - px, goal_y - py               # si_position_controller: unit gains, norm capped
    scale = cap_scale(xp.sqrt(dx * dx + dy * dy), SI_VELOCITY_LIMIT, xp)
    dx, dy = dx * scale, dy * scale
    if barrier is not None:
        u, multipliers = barrier.solve_minor(xp.stack([dx, dy], axis=1), xp.stack([px, py], axis=1), multipliers)
        dx, dy = u[:, 0], u[:, 1]
    v, w = _si_to_uni(dx, dy, c, s, d, math.pi, xp)
    return v, w, multipliers

