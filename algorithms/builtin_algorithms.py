"""The built-in algorithms as :class:`~marbler_jax_rl.algorithm.Algorithm` records (their recipes are
:data:`marbler_jax_rl.recipes.RECIPES`, the paper's five also ``PAPER_RECIPES``; :mod:`marbler_jax_rl.registry`
registers them)."""
from __future__ import annotations

from . import ippo, mappo, q_learning, qmix, vdn
from .pqn import PQN
from .algorithm import Algorithm

_PPO = dict(make_train=ippo.make_train, greedy_policy=ippo.greedy_policy, policy_tensors=ippo.policy_tensors)
_VALUE = dict(greedy_policy=q_learning.greedy_policy, policy_tensors=q_learning.policy_tensors, map_seeds_on_cpu=True)

BUILTIN = (
    Algorithm("vdn", "value decomposition: the team value is the sum of the robots' Q-values (one shared network)",
              vdn.VDNConfig, vdn.make_train, **_VALUE),
    Algorithm("qmix", "a monotonic hypernetwork mixer of the robots' Q-values on the global state (one shared "
              "network)", qmix.QMIXConfig, qmix.make_train, **_VALUE),
    Algorithm("qmix_ns", "QMIX with one network per robot (no parameter sharing)", qmix.QMIXNSConfig, qmix.make_train,
              **_VALUE),
    Algorithm("mappo", "PPO with a centralised critic on the global state (every robot's observation)",
              config=mappo.MAPPOConfig, **_PPO),
    Algorithm("ippo", "independent PPO: a shared actor-critic, the critic on each robot's own observation",
              config=ippo.IPPOConfig, **_PPO),
    PQN,
)

__all__ = ["BUILTIN"]
