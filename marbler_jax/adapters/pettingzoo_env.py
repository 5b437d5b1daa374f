"""One marbler-jax env as a ``pettingzoo.ParallelEnv`` (per-agent observations and rewards)."""
from __future__ import annotations

import functools

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from marbler_jax.adapters._single import SingleEnv


class PettingZooEnv(ParallelEnv):
    """Agents ``agent_0 .. agent_{N-1}``; all agents finish together (MARBLER's episodes are
    team episodes)."""

    metadata = {"name": "marbler_jax_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, name: str = "predator_capture_prey", render_mode: str | None = None, **overrides):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r} is not supported; use None or 'rgb_array'")
        self.render_mode = render_mode
        self._env = SingleEnv(name, **overrides)
        self.possible_agents = [f"agent_{i}" for i in range(self._env.core.num_agents)]
        self.agents = []
        self._rng = np.random.default_rng()

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent):
        bound = self._env.core.scenario.obs_bound
        return spaces.Box(-bound, bound, (self._env.core.obs_dim,), np.float32)

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent):
        return spaces.Discrete(self._env.core.num_actions)

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        if seed is not None or self._env.state is None:
            self._env.seed(seed, self._rng)
        obs = self._env.reset()
        self.agents = list(self.possible_agents)
        return {a: obs[i] for i, a in enumerate(self.agents)}, {a: {} for a in self.agents}

    def step(self, actions: dict):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"missing actions for {missing}")
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            raise ValueError(f"actions for unknown agent(s) {unknown}; the agents are {self.agents}")
        joint = np.array([actions[a] for a in self.possible_agents], dtype=np.int64)
        obs, rewards, terminated, truncated, info = self._env.step(joint)
        agents = self.agents
        out = (
            {a: obs[i] for i, a in enumerate(agents)},
            {a: float(rewards[i]) for i, a in enumerate(agents)},
            {a: terminated for a in agents},
            {a: truncated for a in agents},
            {a: {k: v for k, v in info.items()} for a in agents},
        )
        if terminated or truncated:
            self.agents = []
        return out

    def render(self):
        return self._env.render() if self.render_mode == "rgb_array" else None

    def state(self):
        """Global state: all agents' observations concatenated."""
        return np.asarray(self._env.core.observe(self._env.state)).reshape(-1)
