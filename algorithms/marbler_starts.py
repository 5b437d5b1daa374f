"""marbler-jax env states from MARBLER's own episode starts, so that marbler-jax plays the very episodes
MARBLER's code played.

A start is what MARBLER's scenario object holds after ``reset()``: the robots' poses ``reset_poses [3, N]``
(rps's layout), the scenario's numeric attributes ``reset_state`` (e.g. Material Transport's ``zone1_load``)
and each agent's (``reset_agents``), as ``scripts/marbler_oracle.py`` records them. The lockstep parity
tests start from them, and ``scripts/paper_models.py`` evaluates the paper's models in marbler-jax from the
same starts as in MARBLER's code (a paired comparison: both sides share every episode's start state).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from marbler_jax.env import EnvState


def _simple(state, agents, dtype):
    from marbler_jax.scenarios.simple_navigation import SimpleState

    return SimpleState(goal=jnp.asarray(state["goal_loc"][0], dtype))


def _predator_capture_prey(state, agents, dtype):
    from marbler_jax.scenarios.predator_capture_prey import PredatorCapturePreyState

    return PredatorCapturePreyState(prey=jnp.asarray(state["prey_loc"], dtype), sensed=jnp.asarray(state["prey_sensed"]),
                                    captured=jnp.asarray(state["prey_captured"]))


def _warehouse(state, agents, dtype):
    from marbler_jax.scenarios.warehouse import WarehouseState

    return WarehouseState(loaded=jnp.asarray([a["loaded"] for a in agents]))


def _material_transport(state, agents, dtype):
    from marbler_jax.scenarios.material_transport import MaterialTransportState

    return MaterialTransportState(load=jnp.asarray([a["load"] for a in agents], jnp.int32),
                                  zone1=jnp.int32(state["zone1_load"]), zone2=jnp.int32(state["zone2_load"]),
                                  messages=jnp.asarray(state["messages"], jnp.int32))


def _arctic_transport(state, agents, dtype):
    from marbler_jax.scenarios.arctic_transport import ArcticTransportState

    return ArcticTransportState(grid=jnp.asarray(state["grid"], jnp.int32), goal_col=jnp.int32(state["goal_loc"][1]),
                                tile=jnp.asarray([a["pixel_type"] for a in agents], jnp.int32),
                                reached=jnp.asarray([a["reached_goal"] for a in agents]))


SCENARIOS = {      # MARBLER's scenario class -> (marbler-jax name, scenario state from MARBLER's attributes)
    "Simple": ("simple_navigation", _simple),
    "PredatorCapturePrey": ("predator_capture_prey", _predator_capture_prey),
    "Warehouse": ("warehouse", _warehouse),
    "MaterialTransport": ("material_transport", _material_transport),
    "ArcticTransport": ("arctic_transport", _arctic_transport),
}


def marbler_class(name: str) -> str:
    """MARBLER's scenario class of the canonical marbler-jax scenario ``name``."""
    for cls, (ours, _) in SCENARIOS.items():
        if ours == name:
            return cls
    raise ValueError(f"{name!r} is not one of MARBLER's scenarios {[ours for ours, _ in SCENARIOS.values()]}")


def env_state(env, marbler_class: str, reset_poses, reset_state: dict, reset_agents: list, dtype=jnp.float32) -> EnvState:
    """The :class:`~marbler_jax.env.EnvState` of ``env`` at one MARBLER start (``reset_poses [3, N]``), in the
    float ``dtype`` of its poses (float64 needs ``jax.enable_x64``)."""
    if marbler_class not in SCENARIOS:
        raise ValueError(f"unknown MARBLER scenario {marbler_class!r}; one of {sorted(SCENARIOS)}")
    try:
        scenario = SCENARIOS[marbler_class][1](reset_state, reset_agents, dtype)
    except KeyError as missing:
        raise ValueError(f"a {marbler_class} start needs {missing} (in reset_state or each of reset_agents); "
                         "is it another scenario's start?") from None
    if np.shape(reset_poses) != (3, env.num_agents):
        raise ValueError(f"reset_poses must be [3, {env.num_agents}] (rps's layout), got {np.shape(reset_poses)}")
    return EnvState(poses=jnp.asarray(np.swapaxes(np.asarray(reset_poses), 0, 1), dtype), scenario=scenario,
                    step=jnp.int32(0), episode_return=jnp.asarray(0, dtype), collided=jnp.bool_(False),
                    out_of_bounds=jnp.bool_(False), cbf_multipliers=env.initial_multipliers(dtype))


def batched_starts(env, marbler_class: str, starts: list[dict]) -> tuple[jax.Array, EnvState]:
    """``(obs [E, N, D], states [E, ...])`` of ``env`` at ``starts`` (dicts with ``reset_poses``,
    ``reset_state``, ``reset_agents``): the first observation as ``env.reset`` would give it."""
    states = [env_state(env, marbler_class, s["reset_poses"], s["reset_state"], s["reset_agents"]) for s in starts]
    state = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *states)
    return jax.vmap(env.reset_obs)(state), state


__all__ = ["SCENARIOS", "marbler_class", "env_state", "batched_starts"]
