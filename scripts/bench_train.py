"""Training throughput: env-steps/s *including learning* for each algorithm and preset.

For every (algorithm, preset) it builds the trainer exactly as ``marbler-jax train`` does, compiles
one chunk of ``--updates`` updates, runs it ``--repeats`` times from the same runner state and
reports the best wall time (``block_until_ready``; compile time separately). Learning starts at
update 0 (``learning_starts=0``) so that value-based runs pay for their gradient steps. Writes JSON
and prints a Markdown table.

    python scripts/bench_train.py --out bench_out/train.json
    python scripts/bench_train.py --algos vdn --presets fast --scenario predator_capture_prey
    python scripts/bench_train.py --algos vdn qmix --presets fast --seeds 1 5   # seeds vmapped in one program
    python scripts/bench_train.py --algos vdn qmix --presets fast --learner-devices 1 2   # data-parallel steps
    python scripts/bench_train.py --algos vdn --presets fast --learner-devices 2 --hp cell=mingru   # preset + overrides

``--hp key=value`` (repeatable, as in ``marbler-jax train``) overrides a preset's hyperparameters for
every algorithm that has the setting.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
from tqdm.auto import tqdm

import marbler_jax
from algorithms.data_parallel import use_cpu_devices
from algorithms.driver import ALGORITHMS, atomic_write, build_config, has_setting
from algorithms.presets import preset
from marbler_jax.cli import parse_overrides


def bench(scenario: str, algo: str, preset_name: str, updates: int, repeats: int, seeds: int = 1,
          learner_devices: int = 1, overrides: dict | None = None) -> dict:
    env_overrides, hp, _ = preset(preset_name, scenario, algo)
    hp.update({key: value for key, value in (overrides or {}).items() if has_setting(algo, key)})
    if has_setting(algo, "learning_starts"):
        hp["learning_starts"] = 0
    if learner_devices > 1:
        hp["learner_devices"] = learner_devices
    env = marbler_jax.make(scenario, **env_overrides)
    cfg = build_config(algo, dict(hp, total_timesteps=10**9))
    trainer = ALGORITHMS[algo][1](env, cfg)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    runner = jax.block_until_ready(jax.jit(jax.vmap(trainer.init))(keys))   # seeds vmapped, as the driver does
    run = jax.jit(jax.vmap(lambda r: trainer.run(r, updates)))
    t0 = time.perf_counter()
    jax.block_until_ready(run(runner))
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(runner))
        best = min(best, time.perf_counter() - t0)
    steps = seeds * updates * trainer.steps_per_update
    return dict(scenario=scenario, algo=algo, preset=preset_name, seeds=seeds, learner_devices=learner_devices,
                env=env_overrides, hp=hp, updates=updates,
                env_steps=steps, seconds=best, compile_seconds=compile_s, env_steps_per_s=steps / best)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="predator_capture_prey")
    parser.add_argument("--algos", nargs="+", default=["ippo", "mappo", "vdn", "qmix", "qmix_ns"])
    parser.add_argument("--presets", nargs="+", default=["fast", "paper"])
    parser.add_argument("--updates", type=int, default=5, help="updates per timed chunk")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1], help="seed counts (vmapped in one program)")
    parser.add_argument("--learner-devices", type=int, nargs="+", default=[1],
                        help="value-based learners: devices each gradient step's batch is split over (CPU devices)")
    parser.add_argument("--hp", action="append", default=[], metavar="KEY=VALUE",
                        help="override a preset hyperparameter (repeatable), e.g. --hp cell=mingru")
    parser.add_argument("--out", default="bench_out/train.json")
    args = parser.parse_args()
    overrides = parse_overrides(args.hp)
    for key in overrides:
        if not any(has_setting(algo, key) for algo in args.algos):
            parser.error(f"--hp {key}: not a setting of {args.algos}")
    use_cpu_devices(max(args.learner_devices))
    rows = []
    combos = [(a, p, k, d) for a in args.algos for p in args.presets for k in args.seeds for d in args.learner_devices
              if d == 1 or has_setting(a, "learner_devices")]
    for algo, name, seeds, devices in tqdm(combos, desc="bench_train", unit="config"):
        rows.append(bench(args.scenario, algo, name, args.updates, args.repeats, seeds, devices, overrides))
        tqdm.write(f"{algo} {name} x{seeds} seeds, {devices} learner device(s): "
                   f"{rows[-1]['env_steps_per_s']:,.0f} env-steps/s")
    result = dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(), devices=jax.device_count(),
                  backend=jax.default_backend(), jax=jax.__version__, rows=rows)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(Path(args.out), json.dumps(result, indent=2))
    print(f"\n{args.scenario}, {jax.default_backend()} backend" + (f", overrides {overrides}" if overrides else "") + "\n")
    print("| algorithm | preset | seeds | learner devices | env steps / update (all seeds) | env-steps/s incl. learning | compile s |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['algo']} | {r['preset']} | {r['seeds']} | {r['learner_devices']} | {r['env_steps'] // r['updates']:,} | "
              f"{r['env_steps_per_s']:,.0f} | {r['compile_seconds']:.1f} |")
    print(f"\nwritten: {args.out}")


if __name__ == "__main__":
    main()
