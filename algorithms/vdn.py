"""VDN: value decomposition networks -- the team value is the sum of the agents' Q-values.

``Q_tot(s, a) = sum_i Q_i(o_i, a_i)``; trained end to end by :mod:`marbler_jax_rl.q_learning` (episode
replay, recurrent agents, double-Q targets, hard target copies). EPyMARL's VDN settings used by
MARBLER (``marbler_jax_rl.recipes.PAPER_RECIPES``): GRU 128, lr 3e-4, target copy every 200 gradient steps, gradient
clip 10, gamma 0.99, epsilon 1 -> 0.05 over 50k steps, buffer 5000 episodes, batch 32.
"""
from __future__ import annotations

import dataclasses

import flax.linen as nn

from . import q_learning


class SumMixer(nn.Module):
    """``Q_tot = sum_i q_i``: ``q [..., N]``, state ignored -> ``[...]`` (no parameters)."""

    @nn.compact
    def __call__(self, q, state):
        del state
        return q.sum(-1)


@dataclasses.dataclass(frozen=True)
class VDNConfig(q_learning.QConfig):
    pass


def make_train(env, cfg: VDNConfig):
    return q_learning.make_train(env, cfg, SumMixer())


greedy_policy = q_learning.greedy_policy

__all__ = ["VDNConfig", "SumMixer", "make_train", "greedy_policy"]
