"""How many barrier sweeps the env needs: accuracy of cold and warm-started solves along env trajectories.

    python scripts/bench_cbf_env.py --out bench_out/cbf_env.json [--quick]

Random-policy Warehouse episodes (MARBLER's "safe" certificate: si2, radius 0.2) for N robots and a
control period (15: MARBLER's training loop, 1: the real Robotarium's). At every control refresh the
certificate is solved three ways on the same input: a reference (400 cold sweeps), ``k`` cold sweeps,
and ``k`` sweeps warm-started from the previous refresh's ``k``-sweep multipliers (what the env does
with ``cbf_warm_start``); ``k`` and the over-relaxation factor come from ``--sweeps`` and
``--relaxation`` (default: the env's, :data:`marbler_jax.control_loop.ENV_RELAXATION`). The robots
follow the reference, so every solve sees the same trajectory.
Reported: the share of refreshes whose ``k``-sweep output matches the reference within the golden
tolerance (every component within 5e-4 + 1e-3 max|u_ref|), and the largest constraint violation
[m/s] of the ``k``-sweep outputs. ``--drift SCENARIO`` adds the closed loop: random-policy episodes
run with ``k`` sweeps and with 400, and the share of envs whose robots end up > 1 mm / > 1 cm apart
(and whose ``done`` differs) within ``--drift-steps`` steps (``--drift-agents`` sets the team size).
Then env-steps/s of ``jit(scan(vmap(env.step)))`` at batch 4096 for the sweep budgets the env uses by
default (:func:`marbler_jax.control_loop.default_cbf_iterations`).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from datetime import date
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import marbler_jax  # noqa: E402
from marbler_jax import cbf, controllers, physics  # noqa: E402
from marbler_jax.control_loop import ENV_RELAXATION, finish_step  # noqa: E402
from marbler_jax.rollout import random_actions  # noqa: E402


def team(n: int) -> dict:
    """Warehouse overrides for ``n`` robots: beyond MARBLER's 6 a 0.3 m spawn spacing (the default 0.6 m grid holds 11)."""
    return dict(n_agents=n, **({"start_dist": 0.3} if n > 6 else {}))


def make_env(n: int, period: int, **overrides):
    return marbler_jax.make("warehouse", control_period=period, **team(n), **overrides)


def accuracy(n: int, period: int, budgets, n_envs: int, steps: int, seed: int = 0):
    """``{(k, relaxation): (cold match, warm match, cold worst violation, warm worst violation)}`` for
    ``budgets``, a list of ``(sweeps, relaxation)``."""
    env = make_env(n, period)
    ref = cbf.make_barrier("si2", safety_radius=0.2, iterations=400)
    budgets = list(budgets)
    solvers = [cbf.make_barrier("si2", safety_radius=0.2, iterations=k, relaxation=r) for k, r in budgets]
    total = env.config.update_frequency

    def episode(key):
        k_reset, key = jax.random.split(key)
        _, state = env.reset(k_reset)
        warm = [b.initial_multipliers(n, (), jnp.float32, jnp) for b in solvers]

        def step(carry, key):
            state, warm = carry
            k_act, k_reset = jax.random.split(key)
            actions = jax.random.randint(k_act, (n,), 0, env.num_actions)
            goals = env.scenario.goals(state.poses, state.scenario, actions)

            def refresh(carry, length):
                pose, warm = carry
                xi = controllers.uni_to_si_states(pose, 0.05)
                dxi = controllers.si_position_controller(xi, goals)
                u_ref = ref(dxi, xi)
                tol = 5e-4 + 1e-3 * jnp.abs(u_ref).max()
                row, new_warm = [], []
                for b, w in zip(solvers, warm):
                    u_cold, info_cold = b.solve(dxi, xi)
                    u_warm, info_warm = b.solve(dxi, xi, warm_start=w)
                    new_warm.append(info_warm.multipliers)
                    row.append(jnp.stack([jnp.abs(u_cold - u_ref).max() <= tol, jnp.abs(u_warm - u_ref).max() <= tol,
                                          info_cold.max_violation, info_warm.max_violation]))
                vel = controllers.si_to_uni_mapping(u_ref, pose, 0.05)
                pose, *_ = physics.held_ticks(env.params, pose, vel, length, stop_on_violation=False)
                return (pose, new_warm), jnp.stack(row)

            full, rest = divmod(total, period)
            (pose, warm), rows = jax.lax.scan(lambda c, _: refresh(c, period), (state.poses, warm), None, length=full)
            rows = list(rows)
            if rest:
                (pose, warm), row = refresh((pose, warm), rest)
                rows.append(row)
            scenario, _, done, _, _, count = finish_step(env.scenario, pose, state.scenario, actions,
                                                         jnp.bool_(False), jnp.bool_(False), state.step)
            state = state.replace(poses=pose, scenario=scenario, step=count)
            _, fresh = env.reset(k_reset)
            state = jax.tree_util.tree_map(lambda a, b: jnp.where(done, a, b), fresh, state)
            warm = [jax.tree_util.tree_map(lambda z: jnp.where(done, 0.0, z), w) for w in warm]
            return (state, warm), jnp.stack(rows)

        return jax.lax.scan(step, (state, warm), jax.random.split(key, steps))[1]

    out = np.asarray(jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(seed), n_envs)))
    out = out.reshape(-1, len(budgets), 4)                        # [refreshes, budget, 4]
    return {key: dict(cold_match=float(out[:, i, 0].mean()), warm_match=float(out[:, i, 1].mean()),
                      cold_max_violation=float(out[:, i, 2].max()), warm_max_violation=float(out[:, i, 3].max()))
            for i, key in enumerate(budgets)}


def closed_loop_drift(name: str, period: int, budgets, batch: int = 512, steps: int = 40, **overrides):
    """``{(k, relaxation): (share of envs > 1 mm off, > 1 cm off, with a different done)}`` against 400
    sweeps, for ``budgets`` a list of ``(sweeps, relaxation)``; ``overrides`` go to ``make``."""
    def rollout(env):
        def run(key):
            _, state = jax.vmap(env.reset)(jax.random.split(key, batch))

            def body(state, k):
                k_act, k_step = jax.random.split(k)
                actions = random_actions(env, k_act, (batch,))
                _, state, _, done, _ = jax.vmap(env.step_env)(jax.random.split(k_step, batch), state, actions)
                return state, (state.poses[..., :2], done)
            return jax.lax.scan(body, state, jax.random.split(key, steps))[1]
        return jax.jit(run)(jax.random.PRNGKey(1))

    exact, exact_done = rollout(marbler_jax.make(name, control_period=period, cbf_iterations=400, **overrides))
    out = {}
    for k, r in budgets:
        poses, done = rollout(marbler_jax.make(name, control_period=period, cbf_iterations=k, cbf_relaxation=r,
                                               **overrides))
        drift = np.asarray(jnp.abs(poses - exact).max(axis=(0, 2, 3)))
        out[(k, r)] = dict(envs_over_1mm=float((drift > 1e-3).mean()), envs_over_1cm=float((drift > 1e-2).mean()),
                           envs_done_differs=float(np.asarray(done != exact_done).any(0).mean()))
    return out


def throughput(env, batch: int = 4096, steps: int = 10, repeats: int = 3):
    import time

    def run(keys, state):
        def body(state, key):
            k_act, k_step = jax.random.split(key)
            actions = jax.random.randint(k_act, (batch, env.num_agents), 0, env.num_actions)
            _, state, *_ = jax.vmap(env.step)(jax.random.split(k_step, batch), state, actions)
            return state, None
        return jax.lax.scan(body, state, keys)[0]

    _, state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), batch))
    fn = jax.jit(run)
    keys = jax.random.split(jax.random.PRNGKey(2), steps)
    state = jax.block_until_ready(fn(keys, state))
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        state = jax.block_until_ready(fn(keys, state))
        best = min(best, time.perf_counter() - t)
    return batch * steps / best


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench_out/cbf_env.json")
    parser.add_argument("--quick", action="store_true", help="tiny grid (smoke test)")
    parser.add_argument("--no-throughput", action="store_true")
    parser.add_argument("--ns", type=int, nargs="+", default=[4, 8, 12, 20])
    parser.add_argument("--periods", type=int, nargs="+", default=[15, 1])
    parser.add_argument("--sweeps", type=int, nargs="+", default=[2, 4, 6, 8, 12, 16, 24, 32])
    parser.add_argument("--drift", metavar="SCENARIO", help="also measure closed-loop drift on this scenario")
    parser.add_argument("--drift-steps", type=int, default=40)
    parser.add_argument("--drift-agents", type=int, help="n_agents of the drift scenario (default: its own)")
    parser.add_argument("--relaxation", type=float, nargs="+", default=[ENV_RELAXATION],
                        help=f"over-relaxation factor(s) of the k-sweep solves (default: the env's, {ENV_RELAXATION})")
    parser.add_argument("--no-accuracy", action="store_true", help="skip the per-refresh accuracy grid")
    args = parser.parse_args(argv)
    ns = [4] if args.quick else args.ns
    sweeps = [2, 4] if args.quick else args.sweeps
    budgets = [(k, r) for r in args.relaxation for k in sweeps]
    rows = []
    for period in [] if args.no_accuracy else args.periods:
        for n in ns:
            n_envs = 8 if args.quick else (256 if period == 15 else 48) // (1 + n // 8)
            steps = 5 if args.quick else 60
            for (k, w), r in accuracy(n, period, budgets, n_envs, steps).items():
                rows.append(dict(n=n, control_period=period, sweeps=k, relaxation=w, envs=n_envs, steps=steps, **r))
                print(f"N={n:2d} period={period:2d} sweeps={k:2d} relaxation={w}: cold {r['cold_match']:.4f} warm {r['warm_match']:.4f} "
                      f"(max violation cold {r['cold_max_violation']:.2e}, warm {r['warm_max_violation']:.2e})", flush=True)
    drift = []
    if args.drift:
        overrides = team(args.drift_agents) if args.drift_agents else {}
        for period in args.periods:
            for (k, w), r in closed_loop_drift(args.drift, period, budgets, steps=args.drift_steps, **overrides).items():
                drift.append(dict(scenario=args.drift, control_period=period, sweeps=k, relaxation=w,
                                  steps=args.drift_steps, **overrides, **r))
                print(f"{args.drift} period={period:2d} sweeps={k:2d} relaxation={w}: envs > 1 mm {r['envs_over_1mm']:.3f}, "
                      f"> 1 cm {r['envs_over_1cm']:.3f}, done differs {r['envs_done_differs']:.3f}", flush=True)
    speed = []
    if not args.no_throughput:
        for period in (15, 1):
            for n in ([4] if args.quick else [4, 20]):
                for warm in (False, True):
                    env = make_env(n, period, cbf_warm_start=warm)
                    sps = throughput(env, batch=64 if args.quick else 4096, steps=2 if args.quick else 10)
                    speed.append(dict(n=n, control_period=period, warm_start=warm, sweeps=env.barrier.iterations,
                                      env_steps_per_s=sps,
                                      ns_per_robot_tick=1e9 / (sps * n * env.config.update_frequency)))
                    print(f"throughput N={n:2d} period={period:2d} warm={warm!s:5s} sweeps={env.barrier.iterations}: "
                          f"{sps:,.0f} env-steps/s", flush=True)
    result = dict(date=str(date.today()), jax=jax.__version__,
                  machine=f"{platform.machine()}, {jax.default_backend()}", accuracy=rows, drift=drift, throughput=speed)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
