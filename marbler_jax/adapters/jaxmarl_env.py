"""Any marbler-jax scenario as a JaxMARL ``MultiAgentEnv`` (``pip install "marbler-jax[jaxmarl]"``).

``JaxMARLEnv(marbler_jax.make("predator_capture_prey"))`` speaks JaxMARL's API, so JaxMARL's wrappers
(``LogWrapper``, ``CTRolloutManager``) and training scripts run on it unchanged: observations, actions,
rewards and dones are dicts keyed by agent name (``agent_0``, ...), dones carry ``"__all__"`` (MARBLER's
robots end an episode together), ``observation_space(agent)`` is a ``Box`` of the robot's observation and
``action_space(agent)`` a ``Discrete`` of the scenario's actions (all always available). The observations
also hold ``"world_state"`` (every robot's observation concatenated, what MARBLER's centralised learners see,
``[N * obs_dim]``), which ``get_state(state)`` gives from a state. Rewards are each robot's own reward as the
scenario defines it (a shared reward repeats the team's for every robot); ``info`` is the env's info (episode
return, collisions, out of bounds, the scenario's metrics). Everything is a pure function of key and state:
jit and vmap it as any JaxMARL env.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxmarl.environments.multi_agent_env import MultiAgentEnv
from jaxmarl.environments.spaces import Box, Discrete

WORLD_STATE = "world_state"


class JaxMARLEnv(MultiAgentEnv):
    """``env`` (a :class:`marbler_jax.env.MarblerEnv`) behind JaxMARL's ``MultiAgentEnv`` interface."""

    def __init__(self, env):
        super().__init__(num_agents=env.num_agents)
        self.env = env
        self.observation_spaces = {a: Box(-jnp.inf, jnp.inf, (env.obs_dim,)) for a in self.agents}
        self.action_spaces = {a: Discrete(env.num_actions) for a in self.agents}
        self.state_size = env.num_agents * env.obs_dim

    @property
    def name(self) -> str:
        return f"marbler_jax/{self.env.name}"

    def _obs(self, obs) -> dict:
        """``obs [N, D]`` -> ``{agent: [D], "world_state": [N * D]}``."""
        return {**{a: obs[i] for i, a in enumerate(self.agents)}, WORLD_STATE: obs.reshape(-1)}

    def _actions(self, actions: dict):
        return jnp.stack([jnp.asarray(actions[a]) for a in self.agents], -1).astype(jnp.int32)

    def _out(self, obs, state, rewards, done, info):
        rewards = {a: rewards[i] for i, a in enumerate(self.agents)}
        dones = {**{a: done for a in self.agents}, "__all__": done}
        return self._obs(obs), state, rewards, dones, info

    @partial(jax.jit, static_argnums=(0,))
    def reset(self, key):
        obs, state = self.env.reset(key)
        return self._obs(obs), state

    @partial(jax.jit, static_argnums=(0,))
    def step(self, key, state, actions, reset_state=None):
        """One step with auto-reset (to ``reset_state`` where given, as JaxMARL's envs do)."""
        if reset_state is not None:
            return super().step(key, state, actions, reset_state)
        return self._out(*self.env.step(key, state, self._actions(actions)))

    def step_env(self, key, state, actions):
        return self._out(*self.env.step_env(key, state, self._actions(actions)))

    def get_obs(self, state) -> dict:
        return self._obs(self.env.observe(state))

    def get_state(self, state):
        """The global state ``[N * obs_dim]`` of ``state``: every robot's observation concatenated."""
        return self.env.observe(state).reshape(-1)

    @partial(jax.jit, static_argnums=(0,))
    def get_avail_actions(self, state) -> dict:
        return {a: jnp.ones((self.env.num_actions,), jnp.int32) for a in self.agents}

    @property
    def agent_classes(self) -> dict:
        return {"robots": self.agents}


__all__ = ["JaxMARLEnv", "WORLD_STATE"]
