"""``make(name, **overrides)`` and ``registered()``: build envs by scenario name."""
from __future__ import annotations

from marbler_jax.env import MarblerEnv
from marbler_jax.scenarios import SCENARIOS
from marbler_jax.scenarios.base import Scenario, build_config

# MARBLER's class names are accepted as aliases.
ALIASES = {
    "Simple": "simple_navigation", "simple": "simple_navigation",
    "PredatorCapturePrey": "predator_capture_prey", "pcp": "predator_capture_prey",
    "Warehouse": "warehouse",
    "MaterialTransport": "material_transport", "mt": "material_transport",
    "ArcticTransport": "arctic_transport", "at": "arctic_transport",
}


def registered() -> list[str]:
    """Names of all registered scenarios."""
    return sorted(SCENARIOS)


def scenario_class(name: str) -> type[Scenario]:
    key = ALIASES.get(name, name)
    if key not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; registered scenarios: {registered()}")
    return SCENARIOS[key]


def make(name: str, **overrides) -> MarblerEnv:
    """Build the env for scenario ``name`` with config ``overrides`` (validated, clear errors)."""
    cls = scenario_class(name)
    config = build_config(cls.Config, overrides)
    return MarblerEnv(cls(config))


def register(cls: type[Scenario]) -> type[Scenario]:
    """Register a custom scenario class (usable as a decorator)."""
    if not getattr(cls, "name", None):
        raise ValueError("a scenario class needs a non-empty `name`")
    SCENARIOS[cls.name] = cls
    return cls
