"""Thin single-env adapters: ``GymnasiumEnv`` (gymnasium.Env) and ``PettingZooEnv`` (ParallelEnv).

Both jit the pure core once and convert to numpy; use the core (``marbler_jax.make``) with
``vmap`` for throughput. Importing this module registers the gymnasium ids
``marbler_jax/<ScenarioName>-v0`` (gymnasium 1.x loads no plugin entry points).
"""
from marbler_jax.adapters.gymnasium_env import GYM_IDS, GymnasiumEnv, register_gymnasium

register_gymnasium()

__all__ = ["GymnasiumEnv", "PettingZooEnv", "register_gymnasium", "GYM_IDS"]


def __getattr__(name):
    if name == "PettingZooEnv":  # pettingzoo is optional (installed with the test extras)
        from marbler_jax.adapters.pettingzoo_env import PettingZooEnv

        return PettingZooEnv
    raise AttributeError(name)
