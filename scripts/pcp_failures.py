"""Why a Predator Capture Prey policy loses reward: a breakdown of its greedy episodes.

    python scripts/pcp_failures.py runs/pcp-vdn --episodes 500 [--seed-index 0] [--eps 0.01 0.05] [--out f.json]

Plays ``--episodes`` greedy episodes (one per batched env, fresh initial states) with the run's best
checkpoint and reads the prey flags of the state each episode's last step started from. Reports the
share of episodes that capture every prey (and their mean length), that end by a violation, and that
time out with prey left -- split into prey that had been sensed (the blind capture robots knew of them
through the predators) and prey never sensed. ``--eps`` replays the same initial states with that
share of random actions, to see whether exploration noise breaks the failures (RESULTS.md).
A prey sensed on the very last step counts as never sensed (the flags are read before that step).

For the timeouts with a sensed prey left it also says where the blind capture robots were: the share
of their steps that began with a capture robot within its capture radius of a sensed, uncaptured
prey (where action 4 captures it: "in range"), the share of those in-range steps on which no capture
robot in range chose action 4, and the mean distance of the closest capture robot to such a prey at
the last step (m).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from marbler_jax_rl.run import load_run  # noqa: E402
from marbler_jax.rollout import as_stateful, at_first_done  # noqa: E402


def make_play(env, policy, episodes: int):
    """Jitted ``(key, eps) -> dict`` of ``[episodes]`` arrays, each env's first episode: return, steps,
    violation, prey left, sensed-but-uncaptured prey (``eps``: share of uniformly random actions)."""
    policy = as_stateful(policy)
    capture = env.scenario.radii(jnp, jnp.float32)[1]       # [N]; 0 for the sensing robots

    def play(key, eps):
        key_reset, key_run = jax.random.split(key)
        obs, state = jax.vmap(env.reset)(jax.random.split(key_reset, episodes))

        def body(carry, key_t):
            obs, state, memory, reset = carry
            key_act, key_noise, key_pick, key_step = jax.random.split(key_t, 4)
            actions, memory = policy.step(key_act, obs, memory, reset)
            noise = jax.random.randint(key_noise, actions.shape, 0, env.num_actions, actions.dtype)
            actions = jnp.where(jax.random.uniform(key_pick, actions.shape) < eps, noise, actions)
            flags = state.scenario.sensed & ~state.scenario.captured
            dist = jnp.linalg.norm(state.poses[:, :, None, :2] - state.scenario.prey[:, None], axis=-1)   # [E, N, P]
            near = jnp.where(flags[:, None, :] & (capture > 0)[None, :, None], dist, jnp.inf)
            in_range = near <= capture[None, :, None]                                                   # [E, N, P]
            pressed = jnp.any(jnp.any(in_range, -1) & (actions == 4), -1)
            obs, state, _, done, info = jax.vmap(env.step)(jax.random.split(key_step, episodes), state, actions)
            record = dict(sensed_left=jnp.sum(flags, -1), prey_left=info["prey_left"],
                          in_range=jnp.any(in_range, (-1, -2)), pressed=pressed, nearest=near.min((-1, -2)),
                          ret=info["episode_return"], steps=info["steps"],
                          violation=info["episode_collided"] | info["episode_out_of_bounds"])
            return (obs, state, memory, done), (done, record)

        start = (obs, state, policy.initial_carry((episodes,)), jnp.ones((episodes,), bool))
        _, (done, trace) = jax.lax.scan(body, start, jax.random.split(key_run, env.max_steps))
        live = (jnp.cumsum(done, 0) - done) == 0          # steps up to and including the first episode's end
        ep = {k: at_first_done(done, v) for k, v in trace.items()}
        ep["range_steps"] = jnp.sum(trace["in_range"] & live, 0)
        ep["range_idle_steps"] = jnp.sum(trace["in_range"] & ~trace["pressed"] & live, 0)
        ep["live_steps"] = jnp.sum(live, 0)
        return ep

    jitted = jax.jit(play)
    return lambda key, eps=0.0: jax.tree_util.tree_map(np.asarray, jitted(key, jnp.float32(eps)))


def breakdown(ep: dict[str, np.ndarray]) -> dict[str, float]:
    success = ~ep["violation"] & (ep["prey_left"] == 0)
    timeout = ~ep["violation"] & (ep["prey_left"] > 0)
    left = max(float(ep["prey_left"][timeout].sum()), 1.0)
    return dict(return_mean=float(ep["ret"].mean()), success=float(success.mean()),
                success_steps=float(ep["steps"][success].mean()) if success.any() else float("nan"),
                violation=float(ep["violation"].mean()), timeout=float(timeout.mean()),
                prey_left_per_timeout=float(ep["prey_left"][timeout].mean()) if timeout.any() else 0.0,
                sensed_share_of_left=float(ep["sensed_left"][timeout].sum()) / left,
                **_sensed_timeouts(ep, timeout & (ep["sensed_left"] > 0)))


def _sensed_timeouts(ep, rows) -> dict[str, float]:
    """Where the capture robots were in the timeouts that left a sensed prey (``rows``)."""
    if not rows.any():
        return dict(sensed_timeouts=0.0)
    in_range = ep["range_steps"][rows].sum()
    return dict(sensed_timeouts=float(rows.mean()),
                in_range_step_share=float(in_range / ep["live_steps"][rows].sum()),
                idle_share_of_in_range=float(ep["range_idle_steps"][rows].sum() / max(in_range, 1)),
                last_nearest_m=float(np.mean(ep["nearest"][rows])))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed-index", type=int, default=0)
    parser.add_argument("--key", type=int, default=5, help="PRNG seed of the initial states")
    parser.add_argument("--eps", type=float, nargs="*", default=[])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    config = json.loads((args.run / "config.json").read_text())
    if config["scenario"] != "predator_capture_prey":
        parser.error(f"{args.run} is a {config['scenario']} run; this breakdown is for predator_capture_prey")
    env, policy = load_run(args.run, args.seed_index, checkpoint="best")
    play = make_play(env, policy, args.episodes)
    result = {}
    for eps in [0.0] + args.eps:
        result[f"eps={eps:g}"] = row = breakdown(play(jax.random.PRNGKey(args.key), eps))
        print(f"eps {eps:g}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()), flush=True)
    if args.out:
        args.out.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
