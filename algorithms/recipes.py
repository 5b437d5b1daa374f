"""Training recipes: one typed recipe per algorithm, used on every scenario.

A :class:`Recipe` is an algorithm's config (its own frozen dataclass, every field typed and validated
by the algorithm), the env settings it trains under and its step budget per scenario. ``marbler-jax
train`` and ``marbler-jax benchmark`` start from :func:`recipe` unless told otherwise, so the command a
user types is the one the benchmark's table reports.

The algorithms keep the MARBLER paper's definitions, since its Table II compares them: VDN, QMIX and
MAPPO share one network across robots (with an agent-ID one-hot), QMIX_NS has one per robot, IPPO shares
one with a critic on each robot's own observation. All train in the robots' loop: controller and barrier
recomputed every tick (``control_period = 1``), the loop a bundle runs on the robots. Against MARBLER's
training loop (every 15 ticks, where the paper's models trained) it costs a little more wall time per
env step for the same reward, without the collisions that a command held for 15 ticks lets through
(BENCHMARKS.md, ``results/robots-loop``); ``marbler-jax benchmark --set control_period=15`` trains a cell
in MARBLER's loop.

The value-based recipe learns from parallel fresh episodes the way PQN does (Gallici et al. 2024): 256
episodes per update, no replay beyond them, each sample used eight times (32 gradient steps of 64
sequences, the target network synced once per update), TD(lambda 0.8) targets from the network that
collected the episodes, a minimal GRU of 32 units with LayerNorm, gamma 0.95, Adam at 1.5e-3 decaying
to 0, epsilon 1 -> 0.01 over the first 1M steps (the remaining steps exploit) and each robot's previous
action in its input; VDN on Material Transport discounts by 0.99 and the three explore Foraging for half of
their 10M steps, down to epsilon 0.05 (``Recipe.why`` says why). The PPO
recipe is CleanRL/MAPPO's clipped PPO over 64 parallel envs with 128-unit networks, trained for 20M steps on
MARBLER's scenarios and for the value-based budgets on JaxRobotarium's.

``paper`` holds the settings of MARBLER's EPyMARL model files instead (``../shared/spec/scenarios.md``
E.2), in MARBLER's training loop: GRU 128 agents, gamma 0.99, 5000-episode buffer, one gradient step per
collected episode, 5M env steps (MAPPO 25M). It is for comparison: one gradient step per episode makes it far
slower per env step (BENCHMARKS.md).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from types import MappingProxyType
from typing import Any, Mapping

from marbler_jax.control_loop import ROBOTS_CONTROL_PERIOD

from .ippo import IPPOConfig
from .mappo import MAPPOConfig
from .pqn import PQNConfig
from .qmix import QMIXConfig, QMIXNSConfig
from .vdn import VDNConfig

RECIPE_NAMES = ("recipe", "paper", "none")
"""What ``marbler-jax train --recipe`` accepts: the algorithm's recipe (default), MARBLER's EPyMARL
settings, or every setting at the algorithm's and scenario's defaults."""

# The robots' loop: controller and barrier every tick, as a bundle runs them on the robots.
TRAINING_ENV = MappingProxyType({"control_period": ROBOTS_CONTROL_PERIOD})
# MARBLER's training control loop: controller and barrier every 15 ticks (0.5 s), where its models trained.
MARBLER_TRAINING_ENV = MappingProxyType({"control_period": 15})


@dataclasses.dataclass(frozen=True)
class Recipe:
    """How one algorithm is trained: ``config`` (the algorithm's typed config; its ``total_timesteps``
    is replaced by the scenario's budget), ``env`` (env config overrides), ``steps`` (env steps per seed
    for each scenario, ``default_steps`` elsewhere), ``scenario_hp`` (config fields one scenario trains
    with instead) and ``why`` (one sentence for each scenario in ``scenario_hp``; the report marks its cell)."""

    algo: str
    config: Any
    env: Mapping[str, Any] = dataclasses.field(default_factory=lambda: TRAINING_ENV)
    steps: Mapping[str, int] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    default_steps: int = 10_000_000
    scenario_hp: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    why: Mapping[str, str] = dataclasses.field(default_factory=lambda: MappingProxyType({}))

    def __post_init__(self):
        if set(self.scenario_hp) != set(self.why):
            raise ValueError(f"{self.algo} recipe: scenarios with their own settings {sorted(self.scenario_hp)} "
                             f"and scenarios with a reason {sorted(self.why)} must be the same")
        for overrides in self.scenario_hp.values():
            dataclasses.replace(self.config, **overrides)     # the config refuses unknown or invalid fields

    def total_steps(self, scenario: str) -> int:
        """Env steps per seed on the canonical ``scenario``."""
        return int(self.steps.get(scenario, self.default_steps))

    def hyperparameters(self, scenario: str) -> dict:
        """The config's fields on the canonical ``scenario`` as ``marbler-jax train --hp`` would give them
        (no ``total_timesteps``)."""
        hp = dataclasses.asdict(dataclasses.replace(self.config, **self.scenario_hp.get(scenario, {})))
        hp.pop("total_timesteps")
        return hp

    def settings(self, scenario: str) -> tuple[dict, dict, int]:
        """``(env_overrides, hyperparameters, total_steps)`` for the canonical ``scenario``."""
        return dict(self.env), self.hyperparameters(scenario), self.total_steps(scenario)

    def digest(self, scenario: str) -> str:
        """:func:`settings_digest` of this recipe on the canonical ``scenario``."""
        return settings_digest(*self.settings(scenario))


# Algorithm settings added after results files began to record settings digests, each with the value that trains
# as before it existed: at that value a setting is left out of the digest, so a cell made before it existed keeps
# its digest (and stays "done" for the benchmark and on-recipe in the report).
NEUTRAL_SETTINGS: Mapping[str, Any] = MappingProxyType({"cell": "none"})     # IPPO/MAPPO's feed-forward actors


def settings_digest(env_overrides: Mapping, hyperparameters: Mapping, total_steps: int) -> str:
    """12 hex digits naming what a run trains with, so a results file can tell which cells the current
    recipe made. ``learner_devices`` is left out: it splits the same computation over devices; so is a
    setting at its :data:`NEUTRAL_SETTINGS` value."""
    hp = {k: v for k, v in hyperparameters.items()
          if k != "learner_devices" and not (k in NEUTRAL_SETTINGS and v == NEUTRAL_SETTINGS[k])}
    blob = json.dumps({"env": dict(env_overrides), "hp": hp, "steps": int(total_steps)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def _frozen(**kw) -> Mapping:
    return MappingProxyType(dict(kw))


_VALUE = dict(hidden=32, cell="mingru", layer_norm=True, num_envs=256, buffer_size=256, batch_size=64,
              train_steps=32, target_update_interval=32, td_lambda=0.8, double_q=False, lr=1.5e-3,
              lr_decay=True, gamma=0.95, eps_finish=0.01, eps_decay_steps=1_000_000, learning_starts=0,
              last_action=True)
# 128-unit PPO networks: 64-unit MAPPO plateaus on Warehouse (BENCHMARKS.md, "Network width").
_PPO = dict(lr=1e-3, num_envs=64, num_steps=64, hidden=128, update_epochs=4, num_minibatches=4, ent_coef=0.01)

# Env steps per seed on MARBLER's scenarios: 10M for QMIX and QMIX_NS, 20M for PPO (on-policy, so less
# sample-efficient) and for VDN, whose test return still rises after 10M; 30M for VDN on Predator Capture Prey,
# where it still rises after 20M (results/pcp-vdn-10m, results/pcp-vdn-20m). The value-based algorithms train
# JaxRobotarium's scenarios for JaxRobotarium's own budgets (its Q-learning configs), so those rows compare at
# equal samples, except Foraging (10M, see _FORAGING_WHY); Simple Navigation is the quick check.
_VALUE_STEPS = _frozen(simple_navigation=2_000_000, discovery=5_000_000, foraging=10_000_000, rware=20_000_000)
_VDN_STEPS = _frozen(**_VALUE_STEPS, predator_capture_prey=30_000_000)
# PPO trains JaxRobotarium's scenarios for the same budgets, so those rows (no paper value) compare all five
# algorithms at equal samples; JaxRobotarium publishes no PPO budget for them.
_JAXROBOTARIUM_STEPS = {s: _VALUE_STEPS[s] for s in ("discovery", "foraging", "rware")}
_PPO_STEPS = _frozen(simple_navigation=300_000, **_JAXROBOTARIUM_STEPS)
_VALUE_DEFAULT_STEPS, _VDN_DEFAULT_STEPS, _PPO_DEFAULT_STEPS = 10_000_000, 20_000_000, 20_000_000

_MT_VDN_WHY = ("Material Transport pays three quarters of its reward at the drop-off, up to 14 steps after the "
               "loading that earns it, which gamma 0.95 discounts to half (0.99: 0.87), and with 0.95 VDN's best "
               "seed stays below the paper (results/mt-vdn-gamma95).")

_FORAGING_WHY = ("Foraging pays only when two or three robots meet at a resource, which random moves do in 2.5 % of "
                 "episodes: with epsilon at 0.01 after 1M steps QMIX's seeds score -1.03 to 0.81 after 5M steps and "
                 "0.52 to 4.52 after 10M, exploring for half of the 10M steps 4.54 to 4.85 (results/foraging-qmix-5m, "
                 "results/foraging-qmix-10m, results/foraging-qmix-10m-eps5).")
_JAXROBOTARIUM_EPS_FINISH = 0.05     # the final epsilon of JaxRobotarium's Q-learning configs
# Foraging: explore for the first half of the budget, down to JaxRobotarium's final epsilon.
_VALUE_HP = _frozen(foraging=_frozen(eps_decay_steps=_VALUE_STEPS["foraging"] // 2,
                                     eps_finish=_JAXROBOTARIUM_EPS_FINISH))
_VALUE_WHY = _frozen(foraging=_FORAGING_WHY)
# RWARE's longer exploration is QMIX's alone: VDN's seeds all deliver with the shared schedule and score less
# with the longer one (results/rware-vdn-eps5).
_RWARE_QMIX_WHY = ("RWARE pays only for a delivered shelf: with epsilon at 0.01 after 1M steps three of QMIX's five "
                   "seeds stay at 0 to 0.02 reward for 20M steps (the other two 2.86 and 2.88, "
                   "results/rware-qmix-eps1m), exploring for the first 5M steps down to 0.05 every seed delivers "
                   "(1.41 to 6.61).")

RECIPES: Mapping[str, Recipe] = MappingProxyType({
    "vdn": Recipe("vdn", VDNConfig(**_VALUE), steps=_VDN_STEPS, default_steps=_VDN_DEFAULT_STEPS,
                  scenario_hp=_frozen(**_VALUE_HP, material_transport=_frozen(gamma=0.99)),
                  why=_frozen(**_VALUE_WHY, material_transport=_MT_VDN_WHY)),
    "qmix": Recipe("qmix", QMIXConfig(**_VALUE), steps=_VALUE_STEPS, default_steps=_VALUE_DEFAULT_STEPS,
                   scenario_hp=_frozen(**_VALUE_HP, rware=_frozen(eps_decay_steps=5_000_000,
                                                                   eps_finish=_JAXROBOTARIUM_EPS_FINISH)),
                   why=_frozen(**_VALUE_WHY, rware=_RWARE_QMIX_WHY)),
    "qmix_ns": Recipe("qmix_ns", QMIXNSConfig(**_VALUE), steps=_VALUE_STEPS, default_steps=_VALUE_DEFAULT_STEPS,
                      scenario_hp=_VALUE_HP, why=_VALUE_WHY),
    "mappo": Recipe("mappo", MAPPOConfig(**_PPO), steps=_PPO_STEPS, default_steps=_PPO_DEFAULT_STEPS),
    "ippo": Recipe("ippo", IPPOConfig(**_PPO), steps=_PPO_STEPS, default_steps=_PPO_DEFAULT_STEPS),
    # PQN (not in the paper) at its own defaults, for the value-based budgets
    "pqn": Recipe("pqn", PQNConfig(), steps=_VALUE_STEPS, default_steps=_VALUE_DEFAULT_STEPS),
})

_PAPER_Q = dict(hidden=128, max_grad_norm=10.0, gamma=0.99, buffer_size=5000, batch_size=32, num_envs=8,
                train_steps=8, eps_decay_steps=50_000, learning_starts=32 * 81)
# EPyMARL's PPO agents are its RNNAgent (a 128-unit GRU: MARBLER's mappo.json, agent "rnn", use_rnn True)
_PAPER_PPO = dict(hidden=128, cell="gru", lr=2e-4, update_epochs=4, clip_eps=0.2, ent_coef=0.01, num_envs=64,
                  num_steps=64)
_PAPER_Q_STEPS = 5_000_000
_MARBLER = dict(env=MARBLER_TRAINING_ENV)

PAPER_RECIPES: Mapping[str, Recipe] = MappingProxyType({
    "vdn": Recipe("vdn", VDNConfig(**_PAPER_Q, lr=3e-4, target_update_interval=200), default_steps=_PAPER_Q_STEPS,
                  **_MARBLER),
    "qmix": Recipe("qmix", QMIXConfig(**_PAPER_Q, lr=1e-4, tau=0.01, mixer_embed=32, hypernet_hidden=64),
                   default_steps=_PAPER_Q_STEPS, **_MARBLER),
    "qmix_ns": Recipe("qmix_ns", QMIXNSConfig(**dict(_PAPER_Q, hidden=64), lr=5e-4, target_update_interval=200),
                      default_steps=_PAPER_Q_STEPS, **_MARBLER),
    "mappo": Recipe("mappo", MAPPOConfig(**_PAPER_PPO), default_steps=25_000_000, **_MARBLER),
    "ippo": Recipe("ippo", IPPOConfig(**_PAPER_PPO), default_steps=25_000_000, **_MARBLER),
})


def recipe(algo: str, name: str = "recipe") -> Recipe:
    """The ``name`` recipe (see :data:`RECIPE_NAMES`) of ``algo``: a built-in's from :data:`RECIPES` /
    :data:`PAPER_RECIPES` (the paper's five algorithms), another algorithm's own (``Algorithm.recipes``), or its config's defaults where it has
    none by that name or for ``"none"``."""
    from .registry import get

    if name not in RECIPE_NAMES:
        raise ValueError(f"unknown recipe {name!r}; available: {list(RECIPE_NAMES)}")
    algorithm = get(algo)            # an unknown name: one ValueError naming what is available
    named = ({"recipe": RECIPES[algo], **({"paper": PAPER_RECIPES[algo]} if algo in PAPER_RECIPES else {})}
             if algo in RECIPES else algorithm.recipes)
    if name != "none" and name in named:
        return named[name]
    return Recipe(algo, algorithm.config(), env=MappingProxyType({}), default_steps=1_000_000)


def settings(name: str, scenario: str, algo: str) -> tuple[dict, dict, int]:
    """``(env_overrides, hyperparameters, total_steps)`` of recipe ``name`` for ``algo`` on the canonical
    ``scenario``; ``"none"`` gives no hyperparameters (the algorithm's defaults)."""
    chosen = recipe(algo, name)
    if name == "none":
        return {}, {}, chosen.default_steps
    return chosen.settings(scenario)


__all__ = ["Recipe", "RECIPES", "PAPER_RECIPES", "RECIPE_NAMES", "TRAINING_ENV", "MARBLER_TRAINING_ENV", "recipe", "settings",
           "settings_digest"]
