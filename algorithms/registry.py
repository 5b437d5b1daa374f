"""The algorithm registry: every algorithm ``train``, ``benchmark``, ``report``, ``evaluate``, ``render`` and
``export`` can run, built in or not, as one :class:`Algorithm` record.

An algorithm (:class:`~marbler_jax_rl.algorithm.Algorithm`) is found by name (``get("vdn")``) among the built-ins
(:mod:`marbler_jax_rl.builtin_algorithms`),
the algorithms that installed packages declare in the entry-point group ``marbler_jax.algorithms`` (each entry
point names an :class:`Algorithm`), and, for ``package.module:NAME``, the :class:`Algorithm` ``NAME`` of an
importable module (one that is not installed as a package: a file on ``PYTHONPATH``). docs/algorithms.md shows
how to write one.
"""
from __future__ import annotations

import dataclasses
import importlib
from importlib.metadata import entry_points

from .algorithm import Algorithm
from .builtin_algorithms import BUILTIN

ENTRY_POINT_GROUP = "marbler_jax.algorithms"


_REGISTRY: dict[str, Algorithm] = {}


def register(algorithm: Algorithm, replace: bool = False) -> Algorithm:
    """Add ``algorithm`` under its name (``replace``: over an algorithm of that name)."""
    if not isinstance(algorithm, Algorithm):
        raise TypeError(f"register takes an Algorithm, got {type(algorithm).__name__}")
    if algorithm.name in _REGISTRY and not replace and _REGISTRY[algorithm.name] is not algorithm:
        raise ValueError(f"an algorithm named {algorithm.name!r} is already registered")
    _REGISTRY[algorithm.name] = algorithm
    return algorithm


def _installed() -> dict:
    """Entry points of the group, by name."""
    return {point.name: point for point in entry_points(group=ENTRY_POINT_GROUP)}


def names() -> list[str]:
    """Built-in and installed algorithms' names, built-ins first."""
    return list(_REGISTRY) + sorted(set(_installed()) - set(_REGISTRY))


def get(name: str) -> Algorithm:
    """The algorithm ``name``: registered, an installed entry point, or ``module:NAME``; a ``ValueError``
    naming it and what is available otherwise."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    point = _installed().get(name)
    if point is not None:
        return _checked(point.load(), f"entry point {name!r} of {ENTRY_POINT_GROUP}", name)
    if ":" in name:
        module_name, _, attribute = name.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as err:
            raise ValueError(f"algorithm {name!r}: cannot import {module_name!r} ({err})") from err
        if not hasattr(module, attribute):
            raise ValueError(f"algorithm {name!r}: module {module_name!r} has no {attribute!r}")
        return _checked(getattr(module, attribute), name, name)
    raise ValueError(f"unknown algorithm {name!r}; available: {names()} or MODULE:NAME of an Algorithm")


def _checked(found, where: str, name: str) -> Algorithm:
    """``found`` registered under ``name`` (a ``module:NAME`` algorithm is known by that reference in run
    folders and results files, so that ``evaluate`` and ``export`` find it again)."""
    if not isinstance(found, Algorithm):
        raise ValueError(f"{where} is {type(found).__name__}, not a marbler_jax_rl.registry.Algorithm")
    if ":" in name:
        found = dataclasses.replace(found, name=name)
    elif found.name != name:
        raise ValueError(f"{where} names itself {found.name!r}; declare the entry point under that name")
    return register(found, replace=True)


for _builtin in BUILTIN:
    register(_builtin)

__all__ = ["Algorithm", "register", "get", "names", "ENTRY_POINT_GROUP"]
