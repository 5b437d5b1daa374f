"""Where a benchmark cell's training time goes: one update split into its parts, plus what each chunk adds.

A cell trains its seeds in updates (collect, then learn) and after every chunk of ``updates / 20`` updates
tests the greedy policy and writes a checkpoint (``marbler-jax benchmark``). The parts are measured by
difference between programs built as ``marbler-jax train`` builds them (``scripts/bench_train.py``'s
:func:`prepare`), timed in turns in one process (best of ``--repeats``):

* value-based (VDN, QMIX, QMIX_NS): the recipe's update; the same with no learning (``learning_starts``
  never reached: collection and the buffer only); with half the gradient steps (``train_steps`` and
  ``target_update_interval`` halved). Gradient steps = 2 x (whole - half); the rest of learning (the
  targets of the buffered sequences once per update, the reward statistics) = whole - collection - gradient steps.
* PPO (IPPO, MAPPO): the recipe's update and the same with one epoch. Epochs = (whole - one epoch) x E / (E - 1);
  rollout (with the advantages) = whole - epochs.
* both: the env alone, stepping as many envs as the update (``num_envs x seeds``) for as many steps with
  random actions; action selection (and the buffer) = collection - env.
* per chunk: the greedy test (the driver's tester: ``--test-episodes`` episodes per seed), moving the runner
  state to the host, and the orbax checkpoint of it, each divided by the updates of a chunk.

    python scripts/profile_train.py --algo vdn --scenario predator_capture_prey --out bench_out/profile-vdn.json
    python scripts/profile_train.py --algo mappo --scenario warehouse --protocol marbler

Writes JSON and prints a Markdown table (ms per update and share of the cell's time).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_train import prepare, time_in_turns  # noqa: E402

import marbler_jax  # noqa: E402
from marbler_jax.rollout import make_rollout  # noqa: E402
from marbler_jax.scenarios.base import PROTOCOLS, merge_settings  # noqa: E402
from marbler_jax_rl import checkpoints  # noqa: E402
from marbler_jax_rl.data_parallel import use_cpu_devices  # noqa: E402
from marbler_jax_rl import registry  # noqa: E402
from marbler_jax_rl.checkpoints import atomic_write  # noqa: E402
from marbler_jax_rl.driver import SEED_BATCHING, build_config, default_seed_batching, make_tester  # noqa: E402
from marbler_jax_rl.recipes import settings  # noqa: E402

NEVER = 2**31 - 1          # a learning_starts no run reaches: collection only
EVAL_POINTS = 20           # greedy tests per cell (marbler-jax benchmark's default)


def variants(hp: dict) -> dict[str, dict]:
    """The programs whose differences give the parts: ``{name: overrides}``."""
    if "train_steps" in hp:
        half = max(1, hp["train_steps"] // 2)
        return {"whole": {}, "no learning": {"learning_starts": NEVER},
                "half the gradient steps": {"train_steps": half, "target_update_interval": half}}
    return {"whole": {}, "one epoch": {"update_epochs": 1}}


def parts(hp: dict, seconds: dict[str, float], env_seconds: float) -> dict[str, float]:
    """Seconds per update of each part from the variants' ``seconds`` and the env alone's."""
    whole = seconds["whole"]
    if "train_steps" in hp:
        collect, fewer = seconds["no learning"], hp["train_steps"] - max(1, hp["train_steps"] // 2)
        steps = (whole - seconds["half the gradient steps"]) / max(fewer, 1) * hp["train_steps"]
        return {"env step": env_seconds, "action selection and buffer": collect - env_seconds,
                f"gradient steps ({hp['train_steps']})": steps,
                "targets and the rest of learning": whole - collect - steps}
    epochs = hp["update_epochs"]
    learn = (whole - seconds["one epoch"]) * epochs / max(epochs - 1, 1)
    return {"env step": env_seconds, "action selection and advantages": whole - learn - env_seconds,
            f"epochs ({epochs} x {hp['num_minibatches']} minibatches)": learn}


def time_env(env, batch: int, steps: int, repeats: int) -> float:
    """Best seconds of ``steps`` random-action steps of ``batch`` envs."""
    rollout = make_rollout(env, batch, steps)
    jax.block_until_ready(rollout(jax.random.PRNGKey(0)))
    best = np.inf
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(rollout(jax.random.PRNGKey(r + 1)))
        best = min(best, time.perf_counter() - t0)
    return best


def time_chunk_work(scenario, algo, env_settings, hp, seeds, batching, test_episodes, repeats) -> dict[str, float]:
    """Best seconds of one greedy test, one move of the runner state to the host, and one checkpoint."""
    import orbax.checkpoint as ocp

    env = marbler_jax.make(scenario, **env_settings)
    cfg = build_config(algo, dict(hp, total_timesteps=10**9))
    trainer = registry.get(algo).make_train(env, cfg)
    over_seeds = SEED_BATCHING[batching]
    runner = jax.block_until_ready(jax.jit(lambda k: over_seeds(trainer.init, k))(
        jax.random.split(jax.random.PRNGKey(0), seeds)))
    tester = make_tester(env, lambda p: registry.get(algo).greedy_policy(env, cfg, p), test_episodes, over_seeds)
    keys = jax.random.split(jax.random.PRNGKey(1), seeds)
    jax.block_until_ready(tester(runner["params"], keys))
    best = dict(test=np.inf, host=np.inf, checkpoint=np.inf)
    with tempfile.TemporaryDirectory() as folder:
        manager = ocp.CheckpointManager(Path(folder), options=ocp.CheckpointManagerOptions(
            max_to_keep=2, enable_async_checkpointing=False))
        for r in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(tester(runner["params"], keys))
            t1 = time.perf_counter()
            host = jax.tree_util.tree_map(np.asarray, runner)
            t2 = time.perf_counter()
            checkpoints.save(manager, r + 1, host)
            t3 = time.perf_counter()
            for name, seconds in zip(best, (t1 - t0, t2 - t1, t3 - t2)):
                best[name] = min(best[name], seconds)
    return best


def profile(algo: str, scenario: str, protocol: str | None, seeds: int, batching: str, learner_devices: int,
            test_episodes: int, updates: int, repeats: int) -> dict:
    env_settings, hp, steps = settings("recipe", scenario, algo)
    protocol_setting = {"protocol": protocol} if protocol else {}
    env_settings = merge_settings(env_settings, protocol_setting)
    prepared = [prepare(scenario, algo, "recipe", updates, seeds, learner_devices, dict(protocol_setting, **overrides),
                        batching) for overrides in variants(hp).values()]
    rows = time_in_turns(prepared, repeats)
    seconds = {name: row["seconds"] / updates for name, row in zip(variants(hp), rows)}
    steps_per_update = rows[0]["env_steps"] // (updates * seeds)
    env = marbler_jax.make(scenario, **env_settings)
    episode = steps_per_update // hp["num_envs"]
    env_seconds = time_env(env, hp["num_envs"] * seeds, episode, repeats)
    cell_updates = max(1, steps // steps_per_update)
    chunk = max(1, cell_updates // EVAL_POINTS)
    chunk_work = time_chunk_work(scenario, algo, env_settings, hp, seeds, batching,
                                 test_episodes, repeats)
    per_update = parts(hp, seconds, env_seconds)
    per_update.update({f"greedy test ({test_episodes} episodes per seed, every {chunk} updates)":
                       chunk_work["test"] / chunk,
                       "runner state to the host": chunk_work["host"] / chunk,
                       "checkpoint": chunk_work["checkpoint"] / chunk})
    total = sum(per_update.values())
    return dict(algo=algo, scenario=scenario, protocol=protocol or "recipe's loop", seeds=seeds, seed_batching=batching,
                learner_devices=learner_devices, env=env_settings, env_steps_per_update=steps_per_update * seeds,
                updates_per_cell=cell_updates, updates_per_chunk=chunk, variant_seconds=seconds,
                parts_seconds=per_update, cell_minutes=total * cell_updates / 60,
                env_steps_per_s=steps_per_update * seeds / total)


def markdown(result: dict) -> str:
    total = sum(result["parts_seconds"].values())
    lines = [f"{result['algo']} on {result['scenario']} ({result['protocol']}), {result['seeds']} seeds "
             f"({result['seed_batching']}), {result['learner_devices']} learner device(s): "
             f"{result['env_steps_per_update']:,} env steps per update, {result['updates_per_cell']} updates per cell",
             "", "| part | ms per update | share |", "|---|---:|---:|"]
    for name, seconds in result["parts_seconds"].items():
        lines.append(f"| {name} | {seconds * 1000:,.1f} | {seconds / total:.0%} |")
    lines.append(f"| **all** | **{total * 1000:,.1f}** | {result['env_steps_per_s']:,.0f} env-steps/s, "
                 f"{result['cell_minutes']:.0f} min per cell |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="vdn", help="an algorithm, as `marbler-jax train --algo` takes it")
    parser.add_argument("--scenario", default="predator_capture_prey")
    parser.add_argument("--protocol", choices=sorted(PROTOCOLS), default=None,
                        help="train in this protocol instead of the recipe's loop")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--seed-batching", choices=["default", *SEED_BATCHING], default="default")
    parser.add_argument("--learner-devices", type=int, default=1)
    parser.add_argument("--test-episodes", type=int, default=64)
    parser.add_argument("--updates", type=int, default=1, help="updates per timed program run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="JSON file (default bench_out/profile-ALGO-SCENARIO.json)")
    args = parser.parse_args()
    for name in ("seeds", "learner_devices", "test_episodes", "updates", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    use_cpu_devices(args.learner_devices)
    batching = default_seed_batching(args.algo) if args.seed_batching == "default" else args.seed_batching
    result = profile(args.algo, args.scenario, args.protocol, args.seeds, batching, args.learner_devices,
                     args.test_episodes, args.updates, args.repeats)
    result.update(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(), jax=jax.__version__,
                  backend=jax.default_backend(), repeats=args.repeats)
    out = Path(args.out or f"bench_out/profile-{args.algo}-{args.scenario}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, json.dumps(result, indent=2))
    print(markdown(result))
    print(f"\nwritten: {out}")


if __name__ == "__main__":
    main()
