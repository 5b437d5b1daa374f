"""Training presets: ``preset(name, scenario, algo) -> (env_overrides, hyperparameters, total_steps)``.

``"paper"`` reproduces the MARBLER paper's setup: the scenario defaults (robots PCP 4, Warehouse 6,
MT 4, AT 4; strict "safe" CBF; penalties and termination on violations), MARBLER's training control
loop (the controller and CBF recomputed every ``control_period = 15`` ticks) and the EPyMARL settings
of MARBLER's model files (``../shared/spec/scenarios.md`` E.2): GRU agents, gamma 0.99, buffer 5000
episodes, batch 32 episodes, epsilon 1 -> 0.05 over 50k steps, one gradient step per collected
episode (here 8 episodes and 8 gradient steps per update), Adam (EPyMARL's ``QLearner`` builds
``torch.optim.Adam``; the model files' ``optim_alpha``/``optim_eps`` are PyMARL's unused RMSprop
leftovers), 5M env steps (MAPPO 25M). It is slow on
a CPU by design (GRU-128 gradient steps dominate: ~1k env-steps/s).

``"fast"`` (the default of ``marbler-jax train``) is our CPU setting: the same env, smaller GRUs
(64), 32 episodes collected per update and 32 gradient steps per update (EPyMARL's one per
collected episode), target copies every 100 gradient steps, a longer epsilon decay; PPO with 64
envs x 64 steps. ``"none"`` leaves every setting at the algorithm's and scenario's defaults.

The value-based ``fast`` setting used 4 gradient steps per update (one per 8 episodes) until
2026-11-21: 8x the env-steps/s (~21k vs ~2.7k), but VDN on PCP levelled off at a training return of
~16 (greedy 16-18, 2 seeds, still 15.6 after 5M steps), where one step per episode reaches 23-29
after 2M steps; on Warehouse 1.9 -> 24.0 (RESULTS.md). Sample reuse, not env throughput, is what
these learners need.
"""
from __future__ import annotations

PRESET_NAMES = ("fast", "paper", "none")

_PAPER_ENV = {"control_period": 15}

_PAPER_HP = {
    "vdn": dict(hidden=128, lr=3e-4, target_update_interval=200, max_grad_norm=10.0, gamma=0.99,
                buffer_size=5000, batch_size=32, num_envs=8, train_steps=8, eps_decay_steps=50_000,
                learning_starts=32 * 81),
    "qmix": dict(hidden=128, lr=1e-4, tau=0.01, mixer_embed=32, hypernet_hidden=64, max_grad_norm=10.0,
                 gamma=0.99, buffer_size=5000, batch_size=32, num_envs=8, train_steps=8,
                 eps_decay_steps=50_000, learning_starts=32 * 81),
    "qmix_ns": dict(hidden=64, lr=5e-4, target_update_interval=200, max_grad_norm=10.0, gamma=0.99,
                    buffer_size=5000, batch_size=32, num_envs=8, train_steps=8, eps_decay_steps=50_000,
                    learning_starts=32 * 81),
    "mappo": dict(hidden=128, lr=2e-4, update_epochs=4, clip_eps=0.2, ent_coef=0.01, num_envs=64, num_steps=64),
    "ippo": dict(hidden=128, lr=2e-4, update_epochs=4, clip_eps=0.2, ent_coef=0.01, num_envs=64, num_steps=64),
}

_FAST_Q = dict(hidden=64, lr=5e-4, target_update_interval=100, num_envs=32, train_steps=32, buffer_size=1000,
               batch_size=32, eps_decay_steps=200_000, learning_starts=10_000)

_FAST_HP = {
    "vdn": _FAST_Q,
    "qmix": dict(_FAST_Q, lr=3e-4),
    "qmix_ns": dict(_FAST_Q, lr=5e-4),
    "mappo": dict(lr=1e-3, num_envs=64, num_steps=64),
    "ippo": dict(lr=1e-3, num_envs=64, num_steps=64),
}

_PAPER_STEPS = {"mappo": 25_000_000, "ippo": 25_000_000}


def preset(name: str, scenario: str, algo: str) -> tuple[dict, dict, int]:
    """``(env_overrides, hyperparameters, total_steps)`` of preset ``name`` for ``algo`` on ``scenario``."""
    if name not in PRESET_NAMES:
        raise ValueError(f"unknown preset {name!r}; available: {list(PRESET_NAMES)}")
    if name == "none":
        return {}, {}, 1_000_000
    if name == "paper":
        return dict(_PAPER_ENV), dict(_PAPER_HP[algo]), _PAPER_STEPS.get(algo, 5_000_000)
    steps = 300_000 if scenario == "simple_navigation" else 3_000_000
    return dict(_PAPER_ENV), dict(_FAST_HP[algo]), steps


__all__ = ["preset", "PRESET_NAMES"]
