"""``make(name, **overrides)`` and ``registered()``: build envs by scenario name."""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

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
    """The scenario class for a registered name, a MARBLER alias, or ``"module:Class"`` /
    ``"path/to/file.py:Class"`` (a custom scenario, imported and registered on first use)."""
    if ":" in name:
        return _import_scenario(name)
    key = ALIASES.get(name, name)
    if key not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; registered scenarios: {registered()} "
                         "(or 'module:Class' / 'file.py:Class' for a custom scenario)")
    return SCENARIOS[key]


def canonical_name(name: str) -> str:
    """The one name of a scenario, as run folders, recipes and results store it: a MARBLER alias
    resolved (``"pcp"`` -> ``"predator_capture_prey"``), a custom scenario's ``file.py`` made absolute."""
    if ":" in name:
        where, cls = name.rsplit(":", 1)
        if where.endswith(".py"):
            return f"{Path(where).resolve()}:{cls}"
        return name
    return ALIASES.get(name, name)


def _import_scenario(spec: str) -> type[Scenario]:
    where, cls_name = spec.rsplit(":", 1)
    if where.endswith(".py"):
        path = Path(where).resolve()
        if not path.exists():
            raise ValueError(f"scenario file {where!r} does not exist")
        module = sys.modules.get(path.stem)
        if module is None or Path(getattr(module, "__file__", "")).resolve() != path:
            loader = importlib.util.spec_from_file_location(path.stem, path)
            module = importlib.util.module_from_spec(loader)
            sys.modules[path.stem] = module
            loader.loader.exec_module(module)
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as err:
            raise ValueError(f"cannot import scenario module {where!r}: {err}") from None
    cls = getattr(module, cls_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Scenario)):
        raise ValueError(f"{spec!r}: {cls_name!r} is not a Scenario subclass in {where}")
    return register(cls)


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
