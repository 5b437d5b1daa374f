"""What every scenario shares: its config, MARBLER's discrete waypoint actions, spawn samplers.

A scenario is a small object with pure functions; the env core (:mod:`marbler_jax.env`) owns the
control loop, violations, the step counter and auto-reset. To write one, subclass
:class:`Scenario`, declare a frozen ``Config`` dataclass (subclass of :class:`ScenarioConfig`) and
implement ``reset``, ``goals``, ``update``, ``observe`` (and optionally ``metrics``,
``render_info``). ``goals``, ``update`` and ``observe`` take numpy *or* JAX arrays (use
``xp = namespace(...)`` and no JAX-only calls), so the numpy deployment bundle runs them as is.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, ClassVar

import numpy as np

from marbler_jax.xp import namespace

BARRIERS = ("safe", "default", "safe_v2", "none", "si", "si2", "si_boundary", "si_v2", "si_boundary_v2")

ROBOTARIUM_SETTINGS = {
    # MARBLER's simulator (rps 6bb184e): its velocity clip and its "safe" certificate
    "2023": {"physics": "marbler", "barrier_certificate": "safe"},
    # the Robotarium's rps v2: wheel clip with L = 0.11, the v2 certificate at MARBLER's radius 0.2
    "v2": {"physics": "robotarium", "barrier_certificate": "safe_v2"},
}
"""What ``robotarium=`` sets (the physics preset and the barrier); the collision and boundary rules
are the same in both (rps v2 checks the same offset centres, 0.135 m, and the same arena)."""

PROTOCOLS = {
    # MARBLER as shipped, where the paper's models trained and its Table II was measured: rps 6bb184e,
    # controller and barrier every 15 iterations with the command held between, all-zero first observation
    "marbler": {"robotarium": "2023", "control_period": 15, "zero_reset_obs": True},
    # the loop a bundle runs on today's robots: controller and barrier every iteration, rps v2 physics, the
    # real first observation (the defaults)
    "robots": {"control_period": 1, "physics": "robotarium", "zero_reset_obs": False},
}
"""What ``protocol=`` sets. Settings given beside it must agree with it (a conflict is an error)."""


def merge_settings(base: dict, overrides: dict) -> dict:
    """Env settings ``overrides`` on top of ``base`` (a recipe's, a run's), as one dict for ``make``.

    A ``protocol`` in ``overrides`` replaces every ``base`` setting it decides (``--protocol marbler`` on a
    recipe that trains in the robots' loop trains in MARBLER's loop). An override of a setting that a
    ``protocol`` or ``robotarium`` in ``base`` decides turns that name into its settings first, so only the
    overridden one changes (``control_period=1`` on a MARBLER-protocol run keeps MARBLER's simulator)."""
    def decided(key, value) -> dict:            # every setting a protocol or robotarium name decides
        settings = dict({"protocol": PROTOCOLS, "robotarium": ROBOTARIUM_SETTINGS}[key].get(value, {}))
        return {**settings, **ROBOTARIUM_SETTINGS.get(settings.get("robotarium"), {})}

    base = dict(base)
    if overrides.get("protocol") in PROTOCOLS:
        settings = decided("protocol", overrides["protocol"])
        drop = {"protocol", *settings}
        simulator = ROBOTARIUM_SETTINGS.get(base.get("robotarium"), {})
        if any(k in settings and settings[k] != v for k, v in simulator.items()):   # "robots" on a 2023 run
            drop.add("robotarium")
        return {**{k: v for k, v in base.items() if k not in drop}, **overrides}
    for key, table in (("protocol", PROTOCOLS), ("robotarium", ROBOTARIUM_SETTINGS)):
        if any(name in overrides and overrides[name] != value for name, value in decided(key, base.get(key)).items()):
            base = {**table[base[key]], **{k: v for k, v in base.items() if k != key}}
    return {**base, **overrides}


POSITIVE_LENGTHS = ("_dist", "_step", "_spacing", "_radius")
"""Config keys ending in these are lengths [m] that must be > 0 (step lengths, spawn spacings, radii)."""


@dataclasses.dataclass(frozen=True)
class ScenarioConfig:
    """Settings shared by every scenario (MARBLER ``config.yaml`` names where MARBLER has one).

    Attributes:
        max_episode_steps: horizon; an episode ends when the step counter exceeds it, so a full
            episode has ``max_episode_steps + 1`` steps (as in MARBLER).
        update_frequency: simulator ticks (0.033 s) per env step.
        control_period: the controller and barrier are recomputed every this many ticks and held
            in between. The default 1 is what runs on the real Robotarium (MARBLER's
            ``robotarium: True``): training then sees exactly the deployed closed loop, and the
            certificate keeps robots apart (zero collisions over thousands of random episodes).
            15 reproduces MARBLER's training (``robotarium: False``): the held command turns robots
            by up to 90 degrees between refreshes, so collisions and boundary violations occur.
        barrier_certificate: ``"safe"`` (MARBLER default: certificate2, radius 0.2), ``"default"``
            (certificate, radius 0.17), ``"safe_v2"`` (the Robotarium's rps v2 certificate,
            ``create_si_barrier_certificate``, at MARBLER's radius 0.2: octagon speed rows, and the
            whole team stopped when its QP has no solution), ``"none"``, or an SI kind of
            :mod:`marbler_jax.cbf`.
        cbf_safety_radius: the barrier's safety radius between projection points [m] (``None``:
            MARBLER's 0.2 for ``"safe"`` and ``"safe_v2"``, the rps default of any other kind).
        cbf_iterations: solver sweeps of the barrier per control refresh (``None``:
            :func:`marbler_jax.control_loop.default_cbf_iterations`, 12 cold or 6 warm-started at
            ``control_period=1`` for 4 robots, 20 cold or 10 warm for 20, chosen on env
            trajectories; see :func:`marbler_jax.cbf.default_iterations` for the budget that
            matches arbitrary, overlapping configurations at any N).
        cbf_relaxation: over-relaxation of those sweeps, in (0, 2) (``None``:
            :data:`marbler_jax.control_loop.ENV_RELAXATION` = 1.5).
        cbf_warm_start: start each control refresh's barrier sweeps from the previous refresh's
            multipliers (kept in the env state, zero at reset). The QP's solution does not depend
            on the start, only how close the fixed sweep budget gets to it. ``None`` (default): on
            at ``control_period=1``, where consecutive refreshes solve nearly the same problem, off
            otherwise (15 ticks apart the robots have moved too far for it to help).
        penalize_violations: end the step at the first collision / boundary tick, give every agent
            the scenario's violation reward and end the episode (MARBLER).
        physics: physics preset name (``"robotarium"``, ``"marbler"``, ``"rps2024"``).
        robotarium: ``"2023"`` (MARBLER's simulator) or ``"v2"`` (the Robotarium's rps v2) sets ``physics``
            and ``barrier_certificate`` together (:data:`ROBOTARIUM_SETTINGS`); ``None`` (default)
            leaves them to their own fields: rps v2 physics with MARBLER's certificate, what the
            benchmark's recipes train with.
        zero_reset_obs: return all-zero observations from ``reset`` as MARBLER does (a bug kept
            only as a switch for reproducing the paper; default False returns the real observation).
        protocol: ``"marbler"`` sets every setting in which MARBLER's shipped code differs from the
            defaults (:data:`PROTOCOLS`: its simulator, its 15-iteration loop, its zero first observation),
            the protocol of the paper's Table II; ``"robots"`` is the robots' loop; ``None`` (default)
            leaves each setting to its own field.
        x_min: smallest waypoint x [m] (MARBLER's ``LEFT``); also where the left spawn bands start.
        x_max: largest waypoint x [m] (``RIGHT``); also where the right spawn bands end.
        y_min: smallest waypoint y [m] (``UP``).
        y_max: largest waypoint y [m] (``DOWN``).
    """

    max_episode_steps: int = 50
    update_frequency: int = 29
    control_period: int = 1
    barrier_certificate: str = "safe"
    cbf_safety_radius: float | None = None
    cbf_iterations: int | None = None
    cbf_relaxation: float | None = None
    cbf_warm_start: bool | None = None
    penalize_violations: bool = True
    physics: str = "robotarium"
    robotarium: str | None = None
    zero_reset_obs: bool = False
    protocol: str | None = None
    x_min: float = -1.4
    x_max: float = 1.4
    y_min: float = -0.9
    y_max: float = 0.9

    @property
    def warm_start_barrier(self) -> bool:
        """Whether the barrier is warm-started (``cbf_warm_start`` with ``None`` resolved)."""
        if self.cbf_warm_start is None:
            return self.control_period == 1
        return bool(self.cbf_warm_start)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the bad value and what is allowed."""
        _positive_int(self, "max_episode_steps", "update_frequency", "control_period")
        for f in dataclasses.fields(self):          # step lengths, spacings and radii [m]
            value = getattr(self, f.name)
            if (f.name.endswith(POSITIVE_LENGTHS) and not f.name.startswith("cbf_")     # the barrier's: below
                    and value is not None
                    and not (isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0)):
                raise ValueError(f"{f.name} must be a distance > 0 [m], got {value!r}")
        if self.barrier_certificate not in BARRIERS:
            raise ValueError(f"barrier_certificate={self.barrier_certificate!r} is not one of {list(BARRIERS)}")
        if self.cbf_iterations is not None:
            _positive_int(self, "cbf_iterations")
        if self.cbf_safety_radius is not None and not 0 < self.cbf_safety_radius <= 1.0:
            raise ValueError(f"cbf_safety_radius={self.cbf_safety_radius!r} must lie in (0, 1] [m]")
        if self.cbf_relaxation is not None and not 0 < self.cbf_relaxation < 2:
            raise ValueError(f"cbf_relaxation={self.cbf_relaxation!r} must lie in (0, 2) (over-relaxation of the barrier sweeps)")
        from marbler_jax import physics

        for key, table in (("protocol", PROTOCOLS), ("robotarium", ROBOTARIUM_SETTINGS)):   # names of settings
            chosen = getattr(self, key)
            if chosen is None:
                continue
            if chosen not in table:
                raise ValueError(f"{key}={chosen!r} is not one of {list(table)} (or None)")
            for name, value in table[chosen].items():
                if getattr(self, name) != value:
                    raise ValueError(f"{key}={chosen!r} uses {name}={value!r}, "
                                     f"but {name}={getattr(self, name)!r} was given; drop one of the two")
        physics.get_params(self.physics)
        ax0, ax1, ay0, ay1 = physics.get_params(self.physics).arena
        if not (ax0 <= self.x_min < self.x_max <= ax1 and ay0 <= self.y_min < self.y_max <= ay1):
            raise ValueError(
                f"waypoint box x_min={self.x_min}, x_max={self.x_max}, y_min={self.y_min}, y_max={self.y_max} must "
                f"lie inside the arena [{ax0}, {ax1}] x [{ay0}, {ay1}] with x_min < x_max and y_min < y_max"
            )


@dataclasses.dataclass(frozen=True)
class JaxRobotariumConfig(ScenarioConfig):
    """Defaults shared by the scenarios ported from JaxRobotarium (Discovery, Foraging, RWARE): its
    waypoint box x in [-1.5, 1.5], 0.2 m waypoint steps, 101-step episodes, 30 ticks per step.

    Attributes:
        step_dist: waypoint offset of a move action [m].
    """

    step_dist: float = 0.2
    x_min: float = -1.5
    x_max: float = 1.5
    max_episode_steps: int = 100
    update_frequency: int = 30


@dataclasses.dataclass(frozen=True)
class BandSpawnConfig(ScenarioConfig):
    """Settings of the scenarios that spawn robots in a left band and their targets (prey, goals) in a
    right band, with MARBLER's ``generate_initial_locations`` (:func:`spawn_band`).

    Attributes:
        robot_band_right: right edge of the robots' spawn band [m] (it starts at ``x_min``; MARBLER's
            ``ROBOT_INIT_RIGHT_THRESH``).
        goal_band_left: left edge of the targets' spawn band [m] (it ends at ``x_max``; MARBLER's
            ``PREY_INIT_LEFT_THRESH``).
        step_dist: waypoint offset of a move action [m]; also the targets' spawn grid spacing.
        start_dist: spacing of the robots' spawn grid [m].
    """

    robot_band_right: float = -0.5
    goal_band_left: float = 0.5
    step_dist: float = 0.2
    start_dist: float = 0.3

    def check_bands(self, scenario: str, robots: int, targets: int, what: str) -> None:
        """Raise a clear error when either band's spawn grid cannot hold its robots / targets."""
        height = self.y_max - self.y_min
        check_capacity(scenario, robots, self.start_dist, self.robot_band_right - self.x_min, height)
        check_capacity(scenario, targets, self.step_dist, self.x_max - self.goal_band_left, height, what=what)


def field_docs(config_cls: type) -> dict[str, str]:
    """Each field's meaning, one line, from the ``Attributes:`` sections of the dataclass ``config_cls``
    and its bases (a subclass's entry wins); fields without one are absent."""
    docs: dict[str, str] = {}
    for cls in reversed(config_cls.__mro__):
        docs.update(_attributes_section(cls.__dict__.get("__doc__") or ""))
    names = {f.name for f in dataclasses.fields(config_cls)}
    return {name: text for name, text in docs.items() if name in names}


def _attributes_section(doc: str) -> dict[str, str]:
    """``{name: text}`` of a Google-style ``Attributes:`` section (continuation lines joined)."""
    entries: dict[str, str] = {}
    lines = doc.expandtabs().splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:")
    except StopIteration:
        return entries
    indent, name = None, None
    for line in lines[start + 1:]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        indent = depth if indent is None else indent
        if depth < indent:
            break
        if depth == indent and ":" in line:
            name, text = line.strip().split(":", 1)
            entries[name] = text.strip()
        elif name is not None:
            entries[name] += " " + line.strip()
    return entries


def _positive_int(config, *names):
    for name in names:
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")


MARBLER_NAMES = {"LEFT": "x_min", "RIGHT": "x_max", "UP": "y_min", "DOWN": "y_max",
                 "ROBOT_INIT_RIGHT_THRESH": "robot_band_right", "PREY_INIT_LEFT_THRESH": "goal_band_left"}
"""MARBLER ``config.yaml`` keys that have a different name here (only to point a user to the new one, and
to read run folders saved before the keys were renamed)."""


def renamed_keys(saved: dict[str, Any]) -> dict[str, Any]:
    """A saved env config (a run's ``config.json``) with renamed keys under their current names."""
    return {MARBLER_NAMES.get(key, key): value for key, value in saved.items()}


def build_config(config_cls: type[ScenarioConfig], overrides: dict[str, Any]) -> ScenarioConfig:
    """``config_cls(**overrides)`` with clear errors for unknown keys and wrong types, then validated."""
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        renamed = [f"{k} is {MARBLER_NAMES[k]} here" for k in unknown if MARBLER_NAMES.get(k) in fields]
        raise ValueError(
            f"unknown config key(s) {unknown} for {config_cls.__name__}"
            + (f" ({'; '.join(renamed)})" if renamed else "") + f"; valid keys: {sorted(fields)}"
        )
    hints = typing.get_type_hints(config_cls)
    clean = {}
    for name, value in overrides.items():
        clean[name] = _coerce(name, value, hints[name])
    if clean.get("protocol") in PROTOCOLS:                  # the protocol's settings, unless given explicitly
        clean = {**PROTOCOLS[clean["protocol"]], **clean}
    if clean.get("robotarium") in ROBOTARIUM_SETTINGS:      # the simulator's settings, unless given explicitly
        clean = {**ROBOTARIUM_SETTINGS[clean["robotarium"]], **clean}
    config = config_cls(**clean)
    config.validate()
    return config


def _coerce(name: str, value: Any, hint: Any) -> Any:
    """Check ``value`` against a simple type hint (bool, int, float, str, tuple, optional)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        try:
            return _coerce(name, value, inner[0])
        except ValueError as err:
            raise ValueError(f"{err} (or None for the default)" if type(None) in args else str(err)) from None
    if hint is bool:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        raise ValueError(f"{name} must be true or false, got {value!r}")
    if hint is int:
        if (isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number))
                or not math.isfinite(float(value)) or not float(value).is_integer()):
            raise ValueError(f"{name} must be an integer, got {value!r}")
        return int(value)
    if hint is float:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
            raise ValueError(f"{name} must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{name} must be a string, got {value!r}")
        return value
    if origin is tuple:
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
            raise ValueError(f"{name} must be a sequence of numbers, got {value!r}")
        items = tuple(value)
        if not all(isinstance(v, (int, float, np.number)) and not isinstance(v, (bool, np.bool_))
                   and math.isfinite(float(v)) for v in items):
            raise ValueError(f"{name} must hold finite numbers, got {value!r}")
        return tuple(float(v) for v in items)
    return value


class Scenario:
    """Base class of a scenario: static config plus pure functions of arrays.

    Subclasses set ``name``, ``Config``, ``violation_reward``, ``shared_reward`` and implement the
    methods below. Shapes: ``poses [N, 3]``, ``actions [N]`` int, ``goals [N, 2]``,
    ``rewards [N]``, ``obs [N, obs_dim]``. ``state`` is the scenario's own pytree
    (a ``flax.struct.dataclass``).
    """

    name: ClassVar[str]
    Config: ClassVar[type[ScenarioConfig]]
    violation_reward: ClassVar[float] = -5.0
    shared_reward: ClassVar[bool] = True  # team metric = rewards[0] if shared, else sum over agents

    def __init__(self, config: ScenarioConfig):
        self.config = config

    # --- sizes -------------------------------------------------------------------------------
    @property
    def num_agents(self) -> int:
        raise NotImplementedError

    @property
    def num_actions(self) -> int:
        return 5

    @property
    def obs_dim(self) -> int:
        raise NotImplementedError

    # --- dynamics ----------------------------------------------------------------------------
    @property
    def obs_bound(self) -> float:
        """A bound on ``|obs|`` for the adapters' Box spaces (positions, markers, small counts)."""
        return 10.0

    def reset(self, key) -> tuple[Any, Any]:
        """``(poses [N, 3], state)`` of a new episode (JAX only)."""
        raise NotImplementedError

    def step_sizes(self, poses, state):
        """Waypoint offset per agent ``[N]`` [m]; default ``config.step_dist`` for everyone."""
        xp = namespace(poses)
        return xp.full(poses.shape[:-1], self.config.step_dist, dtype=poses.dtype)

    def goals(self, poses, state, actions):
        """Waypoints ``[N, 2]`` from the poses at the start of the step (MARBLER's rule)."""
        return waypoints(self.config, poses, self.move_actions(actions), self.step_sizes(poses, state))

    def move_actions(self, actions):
        """The movement part (0..4) of each agent's action."""
        return actions

    def update(self, poses, state, actions):
        """Task events after the robots moved: ``(state, rewards [N], terminated)``."""
        raise NotImplementedError

    def observe(self, poses, state):
        """Observations ``[N, obs_dim]`` (float)."""
        raise NotImplementedError

    def observation_state(self, before, after):
        """The scenario state the step's observation shows (``after`` by default).

        MARBLER builds observations *before* it applies the step's task events, so scenarios whose
        observation shows event state (loads, captures) return ``before`` here to stay faithful.
        """
        return after

    def metrics(self, state) -> dict[str, Any]:
        """Scalar paper metrics of the current episode (e.g. ``prey_left``)."""
        return {}

    def render_layers(self, state) -> list[dict]:
        """Extra drawing for :func:`marbler_jax.render.render_frame` (goals, zones, ...)."""
        return []

    def team_reward(self, rewards):
        """The per-step reward MARBLER's evaluation reports: ``rewards[0]`` if shared, else the sum."""
        xp = namespace(rewards)
        return rewards[..., 0] if self.shared_reward else xp.sum(rewards, axis=-1)


def waypoints(config, poses, moves, step):
    """MARBLER's action -> waypoint rule.

    From the current position, action 0 moves -x (``max(x - d, x_min)``), 1 +x (``min(x + d, x_max)``),
    2 -y (``max(y - d, y_min)``), 3 +y (``min(y + d, y_max)``), 4 stays; the coordinate that does not move
    is clamped into the box on both sides.
    """
    xp = namespace(poses)
    x, y = poses[..., 0], poses[..., 1]
    x_rest = xp.clip(x, config.x_min, config.x_max)
    y_rest = xp.clip(y, config.y_min, config.y_max)
    gx = xp.where(moves == 0, xp.maximum(x - step, config.x_min),
                  xp.where(moves == 1, xp.minimum(x + step, config.x_max), x_rest))
    gy = xp.where(moves == 2, xp.maximum(y - step, config.y_min),
                  xp.where(moves == 3, xp.minimum(y + step, config.y_max), y_rest))
    return xp.stack([gx, gy], axis=-1)


def grid_size(spacing: float, width: float, height: float) -> tuple[int, int]:
    """``(Xn, Yn)`` of rps's ``generate_initial_conditions`` grid (float floor, as numpy does)."""
    return int(math.floor(width / spacing)), int(math.floor(height / spacing))


def grid_capacity(spacing: float, width: float, height: float) -> int:
    """How many robots the rps grid sampler can place (it asserts ``Xn * Yn > N``)."""
    nx, ny = grid_size(spacing, width, height)
    return nx * ny - 1 if nx and ny else 0


def grid_positions(key, n: int, spacing: float, width: float, height: float):
    """JAX port of rps ``generate_initial_conditions`` positions: ``[n, 2]``.

    Draws ``n`` distinct cells ``c`` from ``{1, ..., Xn*Yn}`` and places them at
    ``((c // Yn) * spacing - width/2, (c % Yn) * spacing - height/2)`` -- the same distribution
    as rps (cell 0 is never used, cell ``Xn*Yn`` is), with JAX randomness.
    """
    nx, ny = grid_size(spacing, width, height)
    cells = distinct_indices(key, n, nx * ny) + 1
    x = (cells // ny) * spacing - width / 2
    y = (cells % ny) * spacing - height / 2
    import jax.numpy as jnp

    return jnp.stack([x, y], axis=-1).astype(jnp.float32)


def distinct_indices(key, n: int, m: int):
    """``n`` distinct integers drawn uniformly, in uniformly random order, from ``range(m)``: ``[n]``.

    Floyd's algorithm (``n`` draws, ``O(n^2)`` compares) followed by a shuffle of the ``n`` picks,
    instead of ``jax.random.choice(replace=False)``, which sorts ``m`` keys. This matters because
    auto-reset evaluates ``reset`` on every step. The draw ``floor(u (j + 1))`` from a float32
    uniform has a bias below 1e-5 for grids of up to 100 cells.
    """
    import jax
    import jax.numpy as jnp

    if not 0 <= n <= m:
        raise ValueError(f"cannot draw {n} distinct cells from {m}")
    k_draw, k_shuffle = jax.random.split(key)
    u = jax.random.uniform(k_draw, (n,))
    picks = []
    for i, j in enumerate(range(m - n, m)):
        t = jnp.minimum(jnp.floor(u[i] * (j + 1)).astype(jnp.int32), j)
        taken = jnp.any(jnp.stack(picks) == t) if picks else jnp.bool_(False)
        picks.append(jnp.where(taken, j, t))
    picks = jnp.stack(picks).astype(jnp.int32) if picks else jnp.zeros((0,), jnp.int32)
    keys = jax.random.uniform(k_shuffle, (n,))
    rank = jnp.sum(keys[None, :] < keys[:, None], axis=1)  # a random permutation of 0..n-1
    return picks[rank]


def spawn_band(key, n, config, spacing, left: bool):
    """MARBLER's ``generate_initial_locations``: rps grid in a band, shifted to the left or right."""
    if left:
        width = config.robot_band_right - config.x_min
        shift = -(width / 2 - config.robot_band_right)
    else:
        width = config.x_max - config.goal_band_left
        shift = width / 2 - config.robot_band_right
    xy = grid_positions(key, n, spacing, width, config.y_max - config.y_min)
    import jax.numpy as jnp

    return xy + jnp.array([shift, 0.0], jnp.float32)


def check_capacity(name: str, n: int, spacing: float, width: float, height: float, what: str = "robots"):
    """Raise a clear error when the spawn grid cannot hold ``n`` items."""
    capacity = grid_capacity(spacing, width, height)
    if n > capacity:
        raise ValueError(
            f"{name}: cannot place {n} {what} -- the spawn grid (spacing {spacing} m over "
            f"{width:.2f} x {height:.2f} m) holds at most {capacity}"
        )


def nearest_others(poses, k: int):
    """Indices ``[N, k]`` of each robot's ``k`` other robots: index order when ``k >= N - 1``
    (what MARBLER does), else the nearest ``k`` by distance, nearest first."""
    xp = namespace(poses)
    n = poses.shape[-2]
    others = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int32).reshape(n, n - 1)
    if k >= n - 1:
        return xp.asarray(others)
    d = poses[..., :, None, :2] - poses[..., None, :, :2]
    dist = xp.sum(d * d, axis=-1)
    dist = xp.take_along_axis(dist, xp.asarray(others), axis=-1)
    order = xp.argsort(dist, axis=-1)[..., :k]
    return xp.take_along_axis(xp.asarray(others), order, axis=-1)


def arange_grid(spacing: float, width: float, height: float) -> np.ndarray:
    """JaxRobotarium's spawn grid: ``x in arange(-w/2, w/2, s)`` x ``y in arange(-h/2, h/2, s)``: ``[M, 2]``."""
    xs = np.arange(-width / 2, width / 2, spacing)
    ys = np.arange(-height / 2, height / 2, spacing)
    return np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2).astype(np.float32)


def check_grid_capacity(name: str, n: int, spacing: float, area, what: str = "robots") -> None:
    """Raise a clear error when :func:`arange_grid` over ``area = (width, height)`` cannot hold ``n`` items."""
    capacity = len(arange_grid(spacing, *area))
    if n > capacity:
        raise ValueError(f"{name}: cannot place {n} {what} -- the spawn grid (spacing {spacing} m over "
                         f"{area[0]} x {area[1]} m) holds at most {capacity}")


def sample_grid_points(key, n: int, spacing: float, width: float, height: float):
    """``n`` distinct points of :func:`arange_grid`, uniformly: ``[n, 2]`` (JAX)."""
    import jax.numpy as jnp

    grid = arange_grid(spacing, width, height)
    if n > len(grid):
        raise ValueError(f"cannot place {n} items on a {len(grid)}-point grid (spacing {spacing}, {width} x {height})")
    return jnp.asarray(grid)[distinct_indices(key, n, len(grid))]


def cyclic_others(n: int) -> np.ndarray:
    """``[n, n - 1]`` indices of the other agents in cyclic order ``i+1, ..., n-1, 0, ..., i-1``."""
    return (np.arange(n)[:, None] + 1 + np.arange(n - 1)[None, :]) % n


def cyclic_blocks(rows):
    """Each agent's own row followed by the others' rows in cyclic order: ``[N, k] -> [N, N * k]``."""
    n = rows.shape[0]
    order = np.concatenate([np.arange(n)[:, None], cyclic_others(n)], axis=1)
    return rows[order].reshape(n, -1)
