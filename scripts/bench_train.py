"""Training throughput: env-steps/s *including learning* for each algorithm and recipe.

For every (algorithm, recipe) it builds the trainer exactly as ``marbler-jax train`` does and compiles
one chunk of ``--updates`` updates; then it runs every configuration's chunk ``--repeats`` times from
the same runner state, the configurations taking turns (round-robin, the order rotated each round), and
reports the best and the median wall time (``block_until_ready``; compile time separately). Taking turns
in one process matters on a shared machine: the same program timed in two processes can differ by far more
than two programs timed alternately in one (BENCHMARKS.md). Learning starts at update 0
(``learning_starts=0`` unless ``--hp``/``--variants`` set it) so that value-based runs pay for their gradient
steps. ``scripts/profile_train.py`` uses the same machinery to split an update's time into its parts. Writes JSON and prints a
Markdown table.

    python scripts/bench_train.py --out bench_out/train.json
    python scripts/bench_train.py --algos vdn --recipes recipe --scenario predator_capture_prey
    python scripts/bench_train.py --algos vdn qmix --recipes recipe --seeds 1 5   # seeds vmapped in one program
    python scripts/bench_train.py --algos vdn qmix --recipes recipe --learner-devices 1 2   # data-parallel steps
    python scripts/bench_train.py --algos ippo --recipes recipe --seeds 5 --seed-batching vmap devices  # seeds per device
    python scripts/bench_train.py --algos vdn --recipes recipe --learner-devices 2 --hp cell=mingru   # recipe + overrides
    python scripts/bench_train.py --algos qmix_ns --recipes recipe --learner-devices 2 --repeats 6 \
        --variants last_action=true last_action=false        # an A/B of one setting, timed alternately
    python scripts/bench_train.py --algos vdn mappo --recipes recipe --variants control_period=15 control_period=1

``--hp key=value`` (repeatable, as in ``marbler-jax train``) overrides a recipe's hyperparameters for
every algorithm that has the setting, and the env's config where the key is one of its fields (e.g.
``control_period=1``: the robots' loop). ``--variants`` adds one row per variant, each a comma-separated list
of ``key=value`` overrides applied on top of ``--hp`` (``""`` for none).
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
from tqdm.auto import tqdm

import marbler_jax
from marbler_jax_rl.data_parallel import use_cpu_devices
from marbler_jax_rl import registry
from marbler_jax_rl.checkpoints import atomic_write
from marbler_jax_rl.driver import SEED_BATCHING, build_config, default_seed_batching, has_setting
from marbler_jax.scenarios.base import merge_settings
from marbler_jax_rl.recipes import settings
from marbler_jax_rl.cli import parse_overrides


@functools.lru_cache(maxsize=None)
def env_settings(scenario: str) -> frozenset:
    """Names of the ``scenario`` env's config fields (what ``--hp``/``--variants`` may set on the env)."""
    return frozenset(f.name for f in dataclasses.fields(marbler_jax.make(scenario).config))


def prepare(scenario: str, algo: str, preset_name: str, updates: int, seeds: int = 1,
            learner_devices: int = 1, overrides: dict | None = None, seed_batching: str = "default") -> dict:
    """Builds and compiles one configuration's chunk of ``updates`` updates: its row (without timings)
    and ``run() -> None``, which runs the chunk once from the same runner state and waits for it.
    ``seed_batching="default"``: as ``marbler-jax train`` maps ``algo``'s seeds on this backend."""
    if seed_batching == "default":
        seed_batching = default_seed_batching(algo)
    env_overrides, hp, _ = settings(preset_name, scenario, algo)
    env_overrides = merge_settings(env_overrides, {key: value for key, value in (overrides or {}).items()
                                                   if key in env_settings(scenario)})
    hp.update({key: value for key, value in (overrides or {}).items() if has_setting(algo, key)})
    if has_setting(algo, "learning_starts") and "learning_starts" not in (overrides or {}):
        hp["learning_starts"] = 0
    if learner_devices > 1:
        hp["learner_devices"] = learner_devices
    env = marbler_jax.make(scenario, **env_overrides)
    cfg = build_config(algo, dict(hp, total_timesteps=10**9))
    trainer = registry.get(algo).make_train(env, cfg)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    over_seeds = SEED_BATCHING[seed_batching]                                 # as the driver maps the seeds
    runner = jax.block_until_ready(jax.jit(lambda k: over_seeds(trainer.init, k))(keys))
    chunk = jax.jit(lambda r: over_seeds(lambda s: trainer.run(s, updates), r))
    t0 = time.perf_counter()
    jax.block_until_ready(chunk(runner))
    compile_s = time.perf_counter() - t0
    row = dict(scenario=scenario, algo=algo, preset=preset_name, seeds=seeds, seed_batching=seed_batching,
               learner_devices=learner_devices,
               env=env_overrides, hp=hp, updates=updates, env_steps=seeds * updates * trainer.steps_per_update,
               compile_seconds=compile_s)
    return dict(row=row, run=lambda: jax.block_until_ready(chunk(runner)))


def time_in_turns(prepared: list[dict], repeats: int) -> list[dict]:
    """Runs every prepared chunk ``repeats`` times, the configurations taking turns (the order rotated by
    one each round); returns their rows with the best and median seconds and env-steps/s."""
    times = [[] for _ in prepared]
    for round_ in range(repeats):
        for i in [(round_ + j) % len(prepared) for j in range(len(prepared))]:
            t0 = time.perf_counter()
            prepared[i]["run"]()
            times[i].append(time.perf_counter() - t0)
    rows = []
    for item, seconds in zip(prepared, times):
        best, median = min(seconds), statistics.median(seconds)
        steps = item["row"]["env_steps"]
        rows.append(dict(item["row"], seconds=best, median_seconds=median, all_seconds=seconds,
                         env_steps_per_s=steps / best, median_env_steps_per_s=steps / median))
    return rows


def parse_variant(text: str) -> dict:
    """``"key=value,key=value"`` -> overrides (``""``: none)."""
    return parse_overrides([pair for pair in text.split(",") if pair])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="predator_capture_prey")
    parser.add_argument("--algos", nargs="+", default=["ippo", "mappo", "vdn", "qmix", "qmix_ns"])
    parser.add_argument("--recipes", "--presets", dest="presets", nargs="+", default=["recipe", "paper"],
                        help="recipes to start from, as train's --recipe takes them")
    parser.add_argument("--updates", type=int, default=5, help="updates per timed chunk")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1], help="seed counts (vmapped in one program)")
    parser.add_argument("--learner-devices", type=int, nargs="+", default=[1],
                        help="value-based learners: devices each gradient step's batch is split over (CPU devices)")
    parser.add_argument("--seed-batching", nargs="+", default=["default"], choices=["default", *SEED_BATCHING],
                        help="how the seeds are mapped (as `marbler-jax train --seed-batching`; default: as train "
                             "maps each algorithm's seeds); devices: one CPU device per core, never combined with "
                             "--learner-devices > 1")
    parser.add_argument("--hp", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe hyperparameter (repeatable), e.g. --hp cell=mingru")
    parser.add_argument("--variants", nargs="+", default=[""], metavar="KEY=VALUE[,KEY=VALUE]",
                        help="one row per variant: overrides on top of --hp, timed alternately with the others")
    parser.add_argument("--out", default="bench_out/train.json")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    overrides = parse_overrides(args.hp)
    variants = {text: parse_variant(text) for text in args.variants}
    for key in set(overrides).union(*variants.values()):
        if key not in env_settings(args.scenario) and not any(has_setting(algo, key) for algo in args.algos):
            parser.error(f"--hp/--variants {key}: not a setting of {args.algos} or of the {args.scenario} env")
    use_cpu_devices(max(args.learner_devices + [os.cpu_count() or 1] * ("devices" in args.seed_batching)))
    combos = [(a, p, k, b, d, v) for a in args.algos for p in args.presets for k in args.seeds
              for b in args.seed_batching for d in args.learner_devices for v in args.variants
              if d == 1 or b != "devices"]
    prepared = []
    for algo, name, seeds, batching, devices, variant in tqdm(combos, desc="compiling", unit="config"):
        prepared.append(prepare(args.scenario, algo, name, args.updates, seeds, devices,
                                dict(overrides, **variants[variant]), batching))
        prepared[-1]["row"]["variant"] = variant
    rows = time_in_turns(prepared, args.repeats)
    result = dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(), devices=jax.device_count(),
                  backend=jax.default_backend(), jax=jax.__version__, repeats=args.repeats, rows=rows)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(Path(args.out), json.dumps(result, indent=2))
    print(f"\n{args.scenario}, {jax.default_backend()} backend" + (f", overrides {overrides}" if overrides else "")
          + f", best and median of {args.repeats} chunks per row, rows timed in turns\n")
    print("| algorithm | recipe | variant | seeds | seed batching | learner devices | env steps / update (all seeds) "
          "| env-steps/s incl. learning (best) | (median) | compile s |")
    print("|---|---|---|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['algo']} | {r['preset']} | {r['variant'] or '-'} | {r['seeds']} | {r['seed_batching']} | {r['learner_devices']} | "
              f"{r['env_steps'] // r['updates']:,} | {r['env_steps_per_s']:,.0f} | "
              f"{r['median_env_steps_per_s']:,.0f} | {r['compile_seconds']:.1f} |")
    print(f"\nwritten: {args.out}")


if __name__ == "__main__":
    main()
