"""Benchmark the batched envs: env-steps/s via ``jit(scan(vmap(step)))`` with random actions.

    python scripts/bench_env.py --out bench_out/env.json [--quick]
    python scripts/bench_env.py --scenarios predator_capture_prey --batches 4096 65536 --settings safe:15 safe:1
    python scripts/bench_env.py --scenarios predator_capture_prey --batches 256 4096 --settings safe:15 safe:1 --devices 2

For every scenario, batch in {1, 256, 4096} (``--batches``), barrier off / safe and control period 15 / 1
(``--settings barrier:period ...``):
env-steps/s, agent-steps/s and compile time (measured separately). ``--devices N`` splits each batch over N
devices (:func:`marbler_jax.rollout.make_rollout`; on a CPU, N CPU devices). Also the cost per robot-tick of
Warehouse with 4 and 20 robots (safe barrier, control period 15, batch 4096). Writes JSON and a
Markdown table next to it after every measurement, so an interrupted run keeps what it measured.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path

import jax
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import marbler_jax  # noqa: E402
from marbler_jax_rl.checkpoints import atomic_write  # noqa: E402
from marbler_jax_rl.data_parallel import use_cpu_devices  # noqa: E402
from marbler_jax.rollout import make_rollout  # noqa: E402


def measure(env, batch: int, steps: int, repeats: int = 3, devices: int = 1):
    """(env-steps/s, compile seconds) of a jitted rollout of ``steps`` steps over ``batch`` envs (split over
    ``devices`` devices)."""
    rollout = make_rollout(env, batch, steps, devices=devices)
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(jax.random.PRNGKey(0)))
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(rollout(jax.random.PRNGKey(r + 1)))
        best = min(best, time.perf_counter() - t0)
    return batch * steps / best, compile_s


def parse_setting(parser, text: str) -> tuple[str, int]:
    """``"safe:15"`` -> ``("safe", 15)``; a malformed pair is a usage error naming it."""
    barrier, _, period = text.partition(":")
    if not barrier or not period.isdigit() or int(period) < 1:
        parser.error(f"--settings takes BARRIER:PERIOD pairs such as safe:15 or none:1, got {text!r}")
    return barrier, int(period)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench_out/env.json")
    parser.add_argument("--quick", action="store_true", help="tiny grid (smoke test)")
    parser.add_argument("--scenarios", default=",".join(marbler_jax.registered()))
    parser.add_argument("--batches", type=int, nargs="+", help="env batch sizes (default 1 256 4096)")
    parser.add_argument("--settings", nargs="+", metavar="BARRIER:PERIOD",
                        help="barrier and control period pairs (default safe:15 none:15 safe:1 none:1)")
    parser.add_argument("--devices", type=int, default=1,
                        help="split every batch over this many devices (on a CPU: CPU devices, one per core)")
    args = parser.parse_args(argv)
    batches = args.batches or ([1, 64] if args.quick else [1, 256, 4096])
    if any(b < 1 for b in batches):
        parser.error(f"--batches must be positive integers, got {batches}")
    scaling_batch = 64 if args.quick else 4096
    if args.devices < 1 or any(b % args.devices for b in batches + [scaling_batch]):
        parser.error(f"--devices must be >= 1 and divide every batch, got {args.devices} for batches "
                     f"{batches + [scaling_batch]}")
    use_cpu_devices(args.devices)          # before JAX first computes (on a CPU: one device per share)
    settings = [("safe", 15), ("none", 15), ("safe", 1), ("none", 1)]
    if args.settings:
        settings = [parse_setting(parser, text) for text in args.settings]
    elif args.quick:
        settings = settings[:1]
    device = jax.devices()[0].device_kind
    if len(jax.local_devices()) < args.devices:
        parser.error(f"--devices {args.devices}: JAX has {len(jax.local_devices())} {jax.default_backend()} "
                     "device(s) (on a CPU it makes as many CPU devices as asked for)")
    result = dict(date=str(date.today()), jax=jax.__version__, backend=jax.default_backend(), device=device,
                  machine=f"{platform.machine()}, {os.cpu_count()} CPU cores, {device}", devices=args.devices,
                  rows=[], scaling=[])
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def save():      # after every measurement: an interrupted run keeps what it measured
        atomic_write(out, json.dumps(result, indent=2))
        atomic_write(out.with_suffix(".md"), markdown(result))

    names = args.scenarios.split(",")
    bar = tqdm(total=len(names) * len(settings) * len(batches), desc="env benchmarks", unit="config")
    for name in names:
        for barrier, period in settings:
            env = marbler_jax.make(name, barrier_certificate=barrier, control_period=period)
            for batch in batches:
                steps = 8 if args.quick else (20 if batch >= 256 else 50)
                sps, compile_s = measure(env, batch, steps, repeats=1 if args.quick else 3, devices=args.devices)
                result["rows"].append(dict(scenario=name, barrier=barrier, control_period=period, batch=batch,
                                           agents=env.num_agents, env_steps_per_s=sps,
                                           agent_steps_per_s=sps * env.num_agents, compile_s=compile_s))
                save()
                bar.update()
                tqdm.write(f"{name:22s} cbf={barrier:4s} period={period:2d} batch={batch:5d} "
                           f"{sps:12,.0f} env-steps/s (compile {compile_s:.1f} s)")
    bar.close()
    for n in ([4] if args.quick else [4, 20]):
        env = marbler_jax.make("warehouse", n_agents=n, start_dist=0.3, control_period=15)
        batch = scaling_batch
        sps, _ = measure(env, batch, 8 if args.quick else 10, repeats=1 if args.quick else 3, devices=args.devices)
        per_tick = 1e9 / (sps * n * env.config.update_frequency)
        result["scaling"].append(dict(scenario="warehouse", agents=n, batch=batch, env_steps_per_s=sps,
                                      ns_per_robot_tick=per_tick))
        save()
        print(f"scaling warehouse N={n:2d}: {sps:12,.0f} env-steps/s, {per_tick:.2f} ns per robot-tick", flush=True)
    print(markdown(result))
    return result


def markdown(result: dict) -> str:
    """The measurements of ``result`` as Markdown tables."""
    lines = [f"Machine: {result['machine']}; batches split over {result.get('devices', 1)} device(s); "
             f"jax {result['jax']}; {result['date']}", "",
             "| scenario | CBF | control period | batch | env-steps/s | agent-steps/s | compile s |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['scenario']} | {r['barrier']} | {r['control_period']} | {r['batch']} | "
                     f"{r['env_steps_per_s']:,.0f} | {r['agent_steps_per_s']:,.0f} | {r['compile_s']:.1f} |")
    lines += ["", "| scaling (warehouse, safe CBF, period 15) | N | env-steps/s | ns per robot-tick |", "|---|---:|---:|---:|"]
    for s in result["scaling"]:
        lines.append(f"| batch {s['batch']} | {s['agents']} | {s['env_steps_per_s']:,.0f} | {s['ns_per_robot_tick']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
