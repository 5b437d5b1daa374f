"""QMIX: a monotonic mixing network conditioned on the global state.

``Q_tot = elu(q @ |W1(s)| + b1(s)) @ |w2(s)| + V(s)``: hypernetworks map the global state ``s``
(every agent's observation concatenated) to the mixing weights, and the absolute value keeps
``dQ_tot / dq_i >= 0``, so the greedy joint action is the agents' independent argmaxes. ``W1`` and
``w2`` come from two-layer hypernetworks (``hypernet_hidden`` units, ReLU), ``b1`` from one layer,
``V`` from ``Dense(embed) -> ReLU -> Dense(1)``, as EPyMARL's ``QMixer`` with ``hypernet_layers=2``,
with PyTorch's default ``nn.Linear`` kernel initialisation (:data:`marbler_jax_rl.networks.TORCH_LINEAR_INIT`; biases start at
zero): flax's default kernels made the mixer's initial gain on the agents' Q-values ~8x larger, and
QMIX's TD loss diverged on PCP.

QMIX_NS is QMIX without parameter sharing (``shared=False``: per-agent networks vmapped over
agents, no agent-ID one-hot). Training is :mod:`marbler_jax_rl.q_learning`'s.
"""
from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax.numpy as jnp

from . import q_learning
from .networks import TORCH_LINEAR_INIT


class QMixer(nn.Module):
    """``q [..., N]``, ``state [..., S]`` -> ``Q_tot [...]``, monotonic in every ``q_i``."""

    embed: int = 32
    hypernet_hidden: int = 64

    @nn.compact
    def __call__(self, q, state):
        n = q.shape[-1]

        dense = functools.partial(nn.Dense, kernel_init=TORCH_LINEAR_INIT)

        def hyper(out, name):
            h = nn.relu(dense(self.hypernet_hidden, name=f"{name}_0")(state))
            return dense(out, name=f"{name}_1")(h)

        w1 = jnp.abs(hyper(n * self.embed, "hyper_w1")).reshape(state.shape[:-1] + (n, self.embed))
        b1 = dense(self.embed, name="hyper_b1")(state)
        hidden = nn.elu(jnp.einsum("...n,...ne->...e", q, w1) + b1)
        w2 = jnp.abs(hyper(self.embed, "hyper_w2"))
        v = dense(1, name="value_1")(nn.relu(dense(self.embed, name="value_0")(state)))[..., 0]
        return jnp.sum(hidden * w2, -1) + v


@dataclasses.dataclass(frozen=True)
class QMIXConfig(q_learning.QConfig):
    """VDN's settings plus the mixer's.

    Attributes:
        mixer_embed: width of the mixing network's hidden layer.
        hypernet_hidden: hidden units of the hypernetworks that make the mixer's weights.
    """

    mixer_embed: int = 32
    hypernet_hidden: int = 64


@dataclasses.dataclass(frozen=True)
class QMIXNSConfig(QMIXConfig):
    """QMIX_NS: QMIX with per-agent (non-shared) agent networks and no agent IDs."""

    shared: bool = False
    agent_ids: bool = False


def make_train(env, cfg: QMIXConfig):
    return q_learning.make_train(env, cfg, QMixer(cfg.mixer_embed, cfg.hypernet_hidden))


greedy_policy = q_learning.greedy_policy

__all__ = ["QMixer", "QMIXConfig", "QMIXNSConfig", "make_train", "greedy_policy"]
