"""Shared plumbing of the adapters: one jitted env, numpy in and out, seeding, rendering."""
from __future__ import annotations

import jax
import numpy as np

from marbler_jax.registry import make


class SingleEnv:
    """One env of the core with jitted ``reset``/``step_env`` and numpy conversion."""

    def __init__(self, name: str, **overrides):
        self.core = make(name, **overrides)
        self._reset = jax.jit(self.core.reset)
        self._step = jax.jit(self.core.step_env)
        self.state = None
        self.key = jax.random.PRNGKey(0)
        self._drawer = None          # render(): one FrameDrawer (figure) for all of this env's frames, made on first use

    def seed(self, seed: int | None, rng: np.random.Generator) -> None:
        self.key = jax.random.PRNGKey(int(rng.integers(0, 2**31 - 1)) if seed is None else int(seed))

    def reset(self) -> np.ndarray:
        self.key, sub = jax.random.split(self.key)
        obs, self.state = self._reset(sub)
        return np.asarray(obs, dtype=np.float32)

    def check_actions(self, actions) -> np.ndarray:
        a = np.asarray(actions)
        n, k = self.core.num_agents, self.core.num_actions
        if a.shape != (n,) or not np.issubdtype(a.dtype, np.integer) or a.min() < 0 or a.max() >= k:
            raise ValueError(f"{self.core.name}: expected {n} integer actions in [0, {k}), got {a.tolist()}")
        return a.astype(np.int32)

    def step(self, actions):
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        a = self.check_actions(actions)
        self.key, sub = jax.random.split(self.key)
        obs, self.state, rewards, done, info = self._step(sub, self.state, a)
        info = {k: np.asarray(v) for k, v in info.items()}
        done = bool(done)
        truncated = done and not bool(info["violation"]) and int(info["steps"]) > self.core.config.max_episode_steps
        terminated = done and not truncated
        return np.asarray(obs, dtype=np.float32), np.asarray(rewards, dtype=np.float32), terminated, truncated, info

    def render(self) -> np.ndarray:
        from marbler_jax.render import FrameDrawer

        if self.state is None:
            raise RuntimeError("call reset() before render()")
        if self._drawer is None:
            self._drawer = FrameDrawer(self.core)
        state = jax.device_get(self.state)
        return self._drawer(state, step=int(state.step), reward=float(state.episode_return))
