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

``"parallel"`` trains the value-based learners the way PQN (Gallici et al. 2024, "Simplifying deep
temporal difference learning") does: many parallel episodes per update (256), no replay beyond them
(the buffer holds exactly the update's own sequences), each sample used 4 times (16 gradient steps of
64 sequences), TD(lambda = 0.65) targets from the network that collected the episodes (the target copy
is refreshed once per update; max instead of double-Q), minimal-GRU agents and a learning rate decaying
to 0 over 50M env steps; VDN and QMIX_NS: each agent's previous action in its input (QMIX_NS also:
lambda 0.8, epsilon down to 0.01, 45M steps). It spends 8x less
gradient work per env step than ``fast`` and computes its targets once per update
(``cache_targets``): VDN on PCP runs 71-82k env-steps/s (one or two learner devices) and reached 28-31
in ~14 minutes, QMIX_NS 32.55-33.03 in 13-14 (three seeds; with ``last_action``, its preset now, 33.40 / 33.33 /
32.16 / 33.03 / 32.77 / 33.28 in 45M steps on a half-speed VM, the best of three seeds 33.28 by the
paper's rule; ``fast`` recipes: ~9k env-steps/s, ~31-32 in 15 minutes; RESULTS.md). PQN's LayerNorm is an
option (``layer_norm``), off in general: with GRU 64 on this CPU it cost 1.7x the wall time for ~1 point per
sample. QMIX_NS and VDN on PCP have their own tuned setting (since 2026-11-24): per-robot GRU 32 with LayerNorm,
gamma 0.95, lr 1.5e-3 -- QMIX_NS 28M steps, 33.46 / 33.61 for two seeds in 13-15 minutes on a half-speed 2-core VM;
VDN (per-robot networks instead of the paper's shared one) 36M steps, 33.14 / 33.47 (seeds 0 / 2) in 13 minutes there.
IPPO/MAPPO use ``fast``.

The value-based ``fast`` setting used 4 gradient steps per update (one per 8 episodes) until
2026-11-21: 8x the env-steps/s (~21k vs ~2.7k), but VDN on PCP levelled off at a training return of
~16 (greedy 16-18, 2 seeds, still 15.6 after 5M steps), where one step per episode reaches 23-29
after 2M steps; on Warehouse 1.9 -> 24.0 (RESULTS.md). Sample reuse, not env throughput, is what
these learners need.
"""
from __future__ import annotations

PRESET_NAMES = ("fast", "parallel", "paper", "none")

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

# PQN-style value learning (Gallici et al. 2024): 256 fresh episodes per update, no replay beyond them
# (buffer = the update's own sequences), 16 gradient steps of 64 sequences (each sample used 4 times),
# TD(lambda) targets from the network as it was when the episodes were collected (target copied once
# per update, max instead of double-Q), minimal-GRU agents, lr decaying to 0.
_PARALLEL_Q = dict(hidden=64, cell="mingru", num_envs=256, buffer_size=256, batch_size=64,
                   train_steps=16, target_update_interval=16, td_lambda=0.65, double_q=False, lr=5e-4,
                   lr_decay=True, eps_decay_steps=5_000_000, learning_starts=0)

# QMIX_NS: longer TD(lambda) traces and less exploration noise once epsilon has decayed learn faster on PCP
# (greedy test 29.4-30.1 at 13.5M steps, two seeds, against 17-25 at 13.5-15M in four runs with epsilon
# 0.05 and lambda 0.65 or 0.8), so 45M steps (13-14 minutes) end at least where 50M did: 32.88 / 32.55
# (500 episodes; seed 2: 33.03) against 32.54 / 32.59 (RESULTS.md). Each agent's previous action in its
# input (last_action) learned far faster again on the same seed (greedy test 27.0 against 13.0 at 9M
# steps, 32.7 against 29.3 at 22M) and ended at 33.40 against 32.34 (RESULTS.md). VDN with last_action:
# 31.81 / 31.43 (seeds 0 / 1, 500 episodes; greedy test 26.7 / 26.2 at 10M steps) against 31.44 / 28.40
# without (20.1 / 19.5 at 10M), so VDN's preset has it too (2026-11-24).
# The discount stays EPyMARL's 0.99: QMIX_NS with gamma 0.95 learned faster (greedy test 31.0 against 20.7 at
# 9M steps; 32.53 against 30.97 when cut to 22M steps) but ended level over the 45M steps (33.15 against 33.33),
# and 0.9 was too short-sighted (29.93 against 31.34 with GRU 32 in 31M). --hp gamma=0.95 suits short budgets.
_LONGER_TRACES = dict(td_lambda=0.8, eps_finish=0.01)
_PARALLEL_HP = {"vdn": dict(_PARALLEL_Q, last_action=True), "qmix": dict(_PARALLEL_Q, lr=3e-4),
                "qmix_ns": dict(_PARALLEL_Q, **_LONGER_TRACES, last_action=True)}
_PARALLEL_STEPS = {"qmix_ns": 45_000_000}

# QMIX_NS on Predator Capture Prey (tuned there, so only there): per-robot minimal GRU 32 with PQN's LayerNorm,
# gamma 0.95 (PCP's rewards come a few steps after the moves that earn them) and three times the general
# learning rate (1.5e-3, decaying to 0; LayerNorm keeps it stable), for 28M steps: VDN's paper reward (33.25)
# within 15 minutes on the 2-core CPU. Two seeds: 33.46 / 33.61 over 500 episodes (~45.5 steps per episode) in
# 894 / 781 s for the whole command on a VM at half the earlier host's speed. lr 1e-3 needed 34M steps for the
# same level (33.56 / 33.51, ~18 minutes there) and ended at 32.8-32.9 in 24-28M; the general settings gave
# 33.00 on average over six seeds in 45M steps of GRU 64 (~2.2x the compute; RESULTS.md, 2026-11-24).
#
# VDN on Predator Capture Prey takes the same recipe with per-robot networks (``shared=False``, so no agent-ID input):
# the one shared network levels off at 31.4-31.8 (two seeds of the general settings) and at 31.25 with this recipe
# (at GRU 64: 32.91 in 28M steps, level with per-robot GRU 32, but at 0.57x the env-steps/s, 18 minutes),
# where per-robot networks reach 32.86 in 28M steps, 33.46 in 40M (seed 0) and 33.37 in 36M (seed 1), and this
# preset 33.14 / 33.47 (seeds 0 / 2; 500 episodes each) in 788 / 778 s for the whole command on the half-speed VM.
# The paper's VDN shares one network (EPyMARL's default); ``--hp shared=true --hp agent_ids=true`` restores it.
_SHORT_PCP = dict(hidden=32, layer_norm=True, gamma=0.95, lr=1.5e-3)
_PARALLEL_TUNED = {("qmix_ns", "predator_capture_prey"): (_SHORT_PCP, 28_000_000),
                   ("vdn", "predator_capture_prey"): (dict(_SHORT_PCP, **_LONGER_TRACES, shared=False, agent_ids=False),
                                                           36_000_000)}


def preset(name: str, scenario: str, algo: str) -> tuple[dict, dict, int]:
    """``(env_overrides, hyperparameters, total_steps)`` of preset ``name`` for ``algo`` on ``scenario``."""
    if name not in PRESET_NAMES:
        raise ValueError(f"unknown preset {name!r}; available: {list(PRESET_NAMES)}")
    if name == "none":
        return {}, {}, 1_000_000
    if name == "paper":
        return dict(_PAPER_ENV), dict(_PAPER_HP[algo]), _PAPER_STEPS.get(algo, 5_000_000)
    if name == "parallel" and algo in _PARALLEL_HP:      # IPPO/MAPPO: already parallel, same as "fast"
        steps = 5_000_000 if scenario == "simple_navigation" else _PARALLEL_STEPS.get(algo, 50_000_000)
        tuned, steps = _PARALLEL_TUNED.get((algo, scenario), ({}, steps))
        return dict(_PAPER_ENV), dict(_PARALLEL_HP[algo], **tuned), steps
    steps = 300_000 if scenario == "simple_navigation" else 3_000_000
    return dict(_PAPER_ENV), dict(_FAST_HP[algo]), steps


__all__ = ["preset", "PRESET_NAMES"]
