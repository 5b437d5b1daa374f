"""One marbler-jax env as a ``gymnasium.Env`` (team view: joint actions, team reward)."""
from __future__ import annotations

import gymnasium
import numpy as np
from gymnasium import spaces

from marbler_jax.adapters._single import SingleEnv

# gymnasium id suffix -> scenario name
GYM_IDS = {
    "Simple": "simple_navigation",
    "PredatorCapturePrey": "predator_capture_prey",
    "Warehouse": "warehouse",
    "MaterialTransport": "material_transport",
    "ArcticTransport": "arctic_transport",
}


class GymnasiumEnv(gymnasium.Env):
    """``gymnasium.Env`` over one env: observations ``Box[num_agents, obs_dim]``, actions
    ``MultiDiscrete([num_actions] * num_agents)``, reward = the team reward MARBLER reports
    (shared reward, or the sum of individual rewards). ``terminated`` covers violations and task
    completion, ``truncated`` the step limit. ``info["rewards"]`` holds the per-agent rewards.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, name: str = "predator_capture_prey", render_mode: str | None = None, **overrides):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r} is not supported; use None or 'rgb_array'")
        self.render_mode = render_mode
        self._env = SingleEnv(name, **overrides)
        core = self._env.core
        bound = core.scenario.obs_bound
        self.observation_space = spaces.Box(-bound, bound, (core.num_agents, core.obs_dim), np.float32)
        self.action_space = spaces.MultiDiscrete(np.full(core.num_agents, core.num_actions, dtype=np.int64))

    @property
    def core(self):
        """The underlying pure env (``marbler_jax.env.MarblerEnv``)."""
        return self._env.core

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or self._env.state is None:
            self._env.seed(seed, self.np_random)
        return self._env.reset(), {}

    def step(self, action):
        obs, rewards, terminated, truncated, info = self._env.step(action)
        info = dict(info, rewards=rewards)
        reward = float(np.asarray(self.core.scenario.team_reward(rewards)))
        return obs, reward, terminated, truncated, info

    def render(self):
        return self._env.render() if self.render_mode == "rgb_array" else None


def register_gymnasium() -> None:
    """Register ``marbler_jax/<ScenarioName>-v0`` ids (idempotent)."""
    for suffix, name in GYM_IDS.items():
        env_id = f"marbler_jax/{suffix}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point="marbler_jax.adapters.gymnasium_env:GymnasiumEnv",
                               kwargs={"name": name})
