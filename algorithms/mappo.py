"""MAPPO: multi-agent PPO with a centralised critic.

The actors are IPPO's (decentralised: each agent acts on its own observation, with an agent-ID
one-hot when parameters are shared); the critic is trained on the global state, which for MARBLER's
scenarios is every agent's observation concatenated (``marbler_jax_rl.common.global_state``; MARBLER
exposes no other state), plus the agent ID so that individual-reward scenarios (Simple Navigation,
Warehouse) get per-agent values. Everything else -- GAE, clipped surrogate and value losses,
minibatch epochs, the jitted chunked training loop -- is :mod:`marbler_jax_rl.ippo`'s, so the two
algorithms differ in exactly one input.
"""
from __future__ import annotations

import dataclasses

from . import ippo


@dataclasses.dataclass(frozen=True)
class MAPPOConfig(ippo.IPPOConfig):
    """IPPO's settings with the critic on the global state (``critic_input="global"``)."""

    critic_input: str = "global"


make_train = ippo.make_train
greedy_policy = ippo.greedy_policy

__all__ = ["MAPPOConfig", "make_train", "greedy_policy"]
