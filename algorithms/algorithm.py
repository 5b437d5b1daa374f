"""What an algorithm is to marbler-jax: one :class:`Algorithm` record (registered in
:mod:`marbler_jax_rl.registry`; docs/algorithms.md shows how to write one)."""
from __future__ import annotations

import dataclasses
from typing import Any, Callable


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """One training algorithm.

    Attributes:
        name: what ``--algo`` takes and results files record.
        summary: one line for ``marbler-jax list``.
        config: its settings, a frozen dataclass of typed fields with defaults (``total_timesteps`` among
            them) and a ``validate()`` that raises ``ValueError`` naming a bad value.
        make_train: ``make_train(env, cfg) -> train``; ``train(key) -> (params, metrics)``, with
            ``train.init(key) -> runner`` (a pytree holding ``"params"``), ``train.run(runner, n) -> (runner,
            metrics)`` for ``n`` updates (static), ``train.num_updates`` and ``train.steps_per_update`` (env
            steps of one seed); ``metrics`` holds ``[n]`` arrays ``return``, ``length``, ``collision_rate`` and
            ``out_of_bounds_rate`` (:func:`marbler_jax_rl.common.rollout_metrics`).
        greedy_policy: ``greedy_policy(env, cfg, params)`` -> the policy ``evaluate``, ``render`` and the greedy
            tests run: ``(key, obs [..., N, D]) -> actions [..., N]`` or a
            :class:`marbler_jax.rollout.StatefulPolicy`.
        policy_tensors: ``policy_tensors(cfg, params) -> (spec fields, tensors)`` of one seed's ``params``:
            what ``export`` writes for :class:`marbler_jax.numpy_policy.NumpyPolicy` (the fields ``kind``,
            ``recurrent``, ``cell``, ``hidden``, ``activation``, ``layers``, ``shared``, ``agent_ids`` and, for
            ``q_agent``, ``layer_norm``, ``last_action``; the acting network's ``float32`` arrays by name).
        recipes: ``{"recipe": Recipe, "paper": Recipe}`` (:class:`marbler_jax_rl.recipes.Recipe`), what
            ``--recipe`` trains with; a recipe it lacks trains with its config's defaults (the built-ins'
            recipes are :data:`marbler_jax_rl.recipes.RECIPES` and ``PAPER_RECIPES``).
        map_seeds_on_cpu: its seeds run one after another on a CPU (``lax.map``) rather than vmapped, where
            that is faster (:func:`marbler_jax_rl.driver.default_seed_batching`).
    """

    name: str
    summary: str
    config: type
    make_train: Callable
    greedy_policy: Callable
    policy_tensors: Callable
    recipes: dict[str, Any] = dataclasses.field(default_factory=dict)
    map_seeds_on_cpu: bool = False

    def __post_init__(self):
        if not dataclasses.is_dataclass(self.config):
            raise TypeError(f"algorithm {self.name!r}: config must be a dataclass, got {self.config!r}")
        for name in ("make_train", "greedy_policy", "policy_tensors"):
            if not callable(getattr(self, name)):
                raise TypeError(f"algorithm {self.name!r}: {name} must be callable")

    def settings(self) -> set[str]:
        """Names of its config's fields."""
        return {f.name for f in dataclasses.fields(self.config)}


def trainer(init: Callable, run: Callable, num_updates: int, steps_per_update: int) -> Callable:
    """The ``train`` an :class:`Algorithm`'s ``make_train`` returns, from its ``init(key) -> runner`` and
    ``run(runner, n) -> (runner, metrics)``: ``train(key) -> (params, metrics)`` runs all ``num_updates``
    updates, and carries ``init``, ``run``, ``num_updates`` and ``steps_per_update`` for the driver."""
    def train(key):
        runner, metrics = run(init(key), num_updates)
        return runner["params"], metrics

    train.init, train.run = init, run
    train.num_updates, train.steps_per_update = num_updates, steps_per_update
    return train


__all__ = ["Algorithm", "trainer"]
