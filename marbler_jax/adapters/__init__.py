"""Adapters: ``GymnasiumEnv`` (gymnasium.Env) and ``PettingZooEnv`` (ParallelEnv), thin single-env
wrappers that jit the pure core once and convert to numpy (use the core, ``marbler_jax.make``, with
``vmap`` for throughput); ``JaxMARLEnv``, a JaxMARL ``MultiAgentEnv`` that stays pure JAX (jit and vmap it). Importing this module registers the gymnasium ids
``marbler_jax/<ScenarioName>-v0`` (gymnasium 1.x loads no plugin entry points).
"""
from marbler_jax.adapters.gymnasium_env import GYM_IDS, GymnasiumEnv, register_gymnasium

register_gymnasium()

__all__ = ["GymnasiumEnv", "PettingZooEnv", "JaxMARLEnv", "register_gymnasium", "GYM_IDS"]


def __getattr__(name):
    if name == "PettingZooEnv":  # pettingzoo is optional (installed with the test extras)
        from marbler_jax.adapters.pettingzoo_env import PettingZooEnv

        return PettingZooEnv
    if name == "JaxMARLEnv":     # jaxmarl is optional (pip install "marbler-jax[jaxmarl]", also in the test extras)
        from marbler_jax.adapters.jaxmarl_env import JaxMARLEnv

        return JaxMARLEnv
    raise AttributeError(name)
