"""Training: the loop that runs an algorithm's updates in chunks, tests each seed greedily and hands every
chunk to the run folder's writer (:class:`marbler_jax_rl.run_writer.RunWriter`, which owns the files).

:func:`train` takes a resolved env, algorithm config and run writer; :func:`train_run` resolves names
(scenario, algorithm, settings, output folder) and calls it.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
import typing

import jax
import numpy as np

import marbler_jax
from marbler_jax.registry import canonical_name
from . import registry
from .data_parallel import over_devices
from .run_writer import RunWriter, json_floats, nan_stat, run_config
from marbler_jax.rollout import batched_rollout, episode_stats, make_rollout, first_episode_metrics


def has_setting(algo: str, name: str) -> bool:
    """Whether ``algo``'s config has the setting ``name`` (e.g. ``learner_devices``)."""
    return name in registry.get(algo).settings()


def build_config(algo: str, overrides: dict):
    """``algo``'s config with ``overrides``, every value checked for type, finiteness and range (the
    error names the setting, the value and what is allowed)."""
    cls = registry.get(algo).config           # an unknown name: one ValueError naming what is available
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ValueError(f"unknown {algo} setting(s) {unknown}; valid: {sorted(names)}")
    hints = typing.get_type_hints(cls)
    for name, value in overrides.items():
        _check_type(algo, name, value, hints[name])
    cfg = cls(**overrides)
    cfg.validate()
    return cfg


def _check_type(algo: str, name: str, value, expected) -> None:
    if expected is bool:
        ok, allowed = isinstance(value, bool), "true or false"
    elif expected is int:
        ok, allowed = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif expected is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        allowed = "a finite number"
    elif expected is str:
        ok, allowed = isinstance(value, str), "a string"
    else:
        return
    if not ok:
        raise ValueError(f"{algo} setting {name}={value!r} is not valid: expected {allowed}")


def evaluate(env, policy, episodes: int, key) -> dict:
    """Greedy evaluation over at least ``episodes`` finished episodes (paper-style metrics)."""
    stats = episode_stats(make_rollout(env, episodes, env.max_steps, policy)(key)[1])
    return stats


# How ``train`` maps a function over the leading seed axis of its runner state.
SEED_BATCHING = {"vmap": lambda fn, xs: jax.vmap(fn)(xs), "map": jax.lax.map, "devices": over_devices}


def default_seed_batching(algo: str, platform: str | None = None) -> str:
    """How ``train`` maps the seeds when not told: ``"map"`` on a CPU for the algorithms that ask for it
    (``Algorithm.map_seeds_on_cpu``: the value-based learners), ``"vmap"`` otherwise. On a CPU a value-based
    update is many small per-seed matmuls and normalisations, which run faster one seed at a time than as
    batched matmuls with per-seed weights (and ``map`` keeps the ``learning_starts`` branch a real branch,
    where ``vmap`` computes both sides); PPO's larger minibatches gain from the batch (BENCHMARKS.md,
    *Training throughput*). ``platform``: the default backend's (``jax.default_backend()``) unless given."""
    platform = platform or jax.default_backend()
    return "map" if platform == "cpu" and registry.get(algo).map_seeds_on_cpu else "vmap"


def make_tester(env, greedy_of_params, episodes: int, over_seeds=SEED_BATCHING["vmap"]):
    """Jitted ``(params [S, ...], keys [S, 2]) -> {metric: [S, episodes]}``: each seed's greedy
    episodes (:func:`marbler_jax.rollout.first_episode_metrics` of the first episode of ``episodes``
    batched envs, fresh initial states from that seed's key). Every episode ends within
    ``env.max_steps`` steps, so each env contributes exactly one episode."""
    if episodes < 1:
        raise ValueError(f"test episodes must be >= 1 (or 0 for no test), got {episodes}")

    def one(args):
        params, key = args
        _, (_, done, info) = batched_rollout(env, key, episodes, env.max_steps, greedy_of_params(params))
        return first_episode_metrics(env, done, info)

    return jax.jit(lambda params, keys: over_seeds(one, (params, keys)))


@dataclasses.dataclass(frozen=True)
class LoopOptions:
    """How :func:`train` runs a run's updates; none of it changes what the seeds learn.

    ``checkpoint_every``: updates per chunk (a greedy test and a checkpoint after each; default a tenth
    of the run); ``eval_episodes``: episodes of the final ``evaluation.json`` (0: none); ``seed_batching``:
    how the seeds share the program (:data:`SEED_BATCHING`; default :func:`default_seed_batching`);
    ``progress``: a progress bar."""
    checkpoint_every: int | None = None
    eval_episodes: int = 256
    seed_batching: str | None = None
    progress: bool = True

    def validate(self, cfg) -> None:
        """Every option checked, also against the algorithm config ``cfg`` it runs."""
        every = self.checkpoint_every
        if every is not None and (isinstance(every, bool) or not isinstance(every, int) or every < 1):
            raise ValueError(f"checkpoint_every must be an integer >= 1 (updates per chunk), got {every!r}")
        if self.eval_episodes < 0:
            raise ValueError(f"eval_episodes must be >= 0 (0 = no final evaluation), got {self.eval_episodes}")
        if self.seed_batching is not None and self.seed_batching not in SEED_BATCHING:
            raise ValueError(f"seed_batching must be one of {list(SEED_BATCHING)}, got {self.seed_batching!r}")
        if self.seed_batching == "devices" and getattr(cfg, "learner_devices", 1) > 1:
            raise ValueError(f"seed_batching='devices' splits the seeds over the devices; it cannot also split each "
                             f"seed's work (learner_devices={cfg.learner_devices}): use one or the other")


def train(env, cfg, run: RunWriter, options: LoopOptions = LoopOptions(), on_chunk=None, log=print) -> dict:
    """Train the run that ``run`` writes (its ``config.json`` names the algorithm, the seeds, the base seed
    and the greedy test episodes) in ``env`` with the algorithm config ``cfg``: every seed in one jitted
    program, in chunks of ``options.checkpoint_every`` updates; returns what ``evaluation.json`` holds.

    ``seed_batching="vmap"`` vectorizes the seeds (one batch of ``seeds x num_envs`` envs); ``"map"`` runs
    them one after another inside the program (the memory of one seed); ``"devices"`` spreads them over the
    process's devices, each vmapping its share (:func:`marbler_jax_rl.data_parallel.over_devices`). All give
    every seed the same result up to float rounding.

    After every chunk each seed is tested greedily (``test_episodes`` episodes, the same initial states at
    every test so that checkpoints are compared on equal terms; MARBLER and EPyMARL keep the model with the
    best greedy test return; with ``test_episodes=0`` the chunk's mean training return scores it) and
    :meth:`RunWriter.record_chunk` commits the chunk. The tests draw no training randomness: a run trains
    the same with or without them. A resumed run (``RunWriter.open(..., resume=True)``) continues from its
    newest intact checkpoint bit-exactly. ``on_chunk(update)`` is called after each chunk is committed
    (tests use it to simulate interruptions). At the end ``evaluation.json`` holds the first seed's greedy
    policy and the random policy over ``eval_episodes`` episodes each (``None`` with ``eval_episodes=0``).
    """
    from tqdm.auto import tqdm

    options.validate(cfg)
    algo, seeds, seed = run.config["algo"], int(run.config["seeds"]), int(run.config["seed"])
    test_episodes = int(run.config["test_episodes"])
    seed_batching = options.seed_batching or default_seed_batching(algo)
    over_seeds, greedy = SEED_BATCHING[seed_batching], registry.get(algo).greedy_policy
    trainer = registry.get(algo).make_train(env, cfg)
    num_updates, steps_per_update = trainer.num_updates, trainer.steps_per_update
    runner = jax.jit(lambda keys: over_seeds(trainer.init, keys))(jax.random.split(jax.random.PRNGKey(seed), seeds))
    runner = run.restore(runner)
    if run.done:
        log(f"resuming from update {run.done} of {num_updates}")
    tester = make_tester(env, lambda p: greedy(env, cfg, p), test_episodes, over_seeds) if test_episodes else None
    test_keys = jax.random.split(jax.random.PRNGKey(seed + 7919), seeds)   # apart from the training keys
    chunk = options.checkpoint_every or max(1, num_updates // 10)
    spread = f" over {min(seeds, jax.local_device_count())} device(s)" if seed_batching == "devices" else ""
    trained_steps, asked = num_updates * steps_per_update, int(cfg.total_timesteps)
    rounded = (f" (--total-steps {asked:,} rounded to whole updates: {trained_steps:,} per seed)"
               if trained_steps != asked else "")
    log(f"training {algo} on {run.config['scenario']}: {num_updates} updates x {steps_per_update} env steps"
        f"{rounded}, {seeds} seed(s) in one program{spread}, checkpoint every {chunk} updates")
    t_start, resumed_at = time.perf_counter(), run.done
    # every program is compiled before the bar starts, so its rate, ETA and sps are the steady state's
    run_fns = {}
    for n in sorted({min(chunk, num_updates - run.done), (num_updates - run.done) % chunk} - {0}):
        run_fns[n] = jax.jit(lambda r, n=n: over_seeds(lambda s: trainer.run(s, n), r))
        run_fns[n].lower(runner).compile()
    if tester and run_fns:
        tester.lower(runner["params"], test_keys).compile()
    compile_seconds = time.perf_counter() - t_start
    if run_fns:
        log(f"compiled in {compile_seconds:.1f} s")
    run.start_events()
    bar = tqdm(total=num_updates, initial=run.done, unit="update", disable=not options.progress, dynamic_ncols=True)
    while run.done < num_updates:
        n = min(chunk, num_updates - run.done)
        t0 = time.perf_counter()
        runner, metrics = jax.block_until_ready(run_fns[n](runner))
        seconds = time.perf_counter() - t0
        tests = jax.tree_util.tree_map(np.asarray, tester(runner["params"], test_keys)) if tester else None
        # saved as host arrays: no device layout in the checkpoint, so a run trained on several devices
        # (learner_devices) restores anywhere (evaluate, export, resume)
        run.record_chunk(jax.tree_util.tree_map(np.asarray, metrics), steps_per_update, seconds,
                         jax.tree_util.tree_map(np.asarray, runner), tests)
        last = json.loads(run.lines[-1])
        bar.update(n)
        bar.set_postfix(ret="n/a" if last["return_mean"] is None else f"{last['return_mean']:.2f}",
                        **({"test": f"{last['test_return_mean']:.2f}"}
                           if last.get("test_return_mean") is not None else {}),
                        sps=f"{last['sps']:,.0f}")
        if on_chunk is not None:
            on_chunk(run.done)
    bar.close()
    seconds = time.perf_counter() - t_start
    trained = random = None
    if options.eval_episodes:
        first = jax.tree_util.tree_map(lambda x: x[0], runner["params"])
        key = jax.random.PRNGKey(12345)
        trained = evaluate(env, greedy(env, cfg, first), options.eval_episodes, key)
        random = evaluate(env, None, options.eval_episodes, key)
    update_seconds = seconds - compile_seconds
    result = dict(trained=trained, random=random, train_seconds=seconds, compile_seconds=compile_seconds,
                  # this invocation's updates only (a resumed run trained the rest before), after compilation
                  env_steps_per_s=seeds * (num_updates - resumed_at) * steps_per_update / max(update_seconds, 1e-9),
                  best_return=nan_stat(np.mean, run.best_scores), best_return_per_seed=json_floats(run.best_scores),
                  best_by="greedy test return" if test_episodes else "training return")
    run.finish(runner["params"], result)
    log(f"trained in {seconds:.1f} s ({compile_seconds:.1f} s of it compiling; "
        f"{result['env_steps_per_s']:,.0f} env-steps/s including learning, after compilation)")
    if options.eval_episodes:
        log(f"greedy return {trained['return']:.2f} vs random {random['return']:.2f}; "
            f"collisions {trained['collision_rate']:.1%}, out of bounds {trained['out_of_bounds_rate']:.1%}")
    return result


def train_run(scenario: str, algo: str, total_steps: int, seeds: int, out, *, env_overrides: dict | None = None,
              hp: dict | None = None, seed: int = 0, test_episodes: int = 64, resume: bool = False, keep: int = 3,
              on_chunk=None, log=print, **options) -> dict:
    """:func:`train` by names: ``scenario`` (any accepted name) made with ``env_overrides``, ``algo``'s
    config with ``hp`` and ``total_steps`` env steps per seed, written to the run folder ``out``
    (:class:`RunWriter`: a fresh folder, or with ``resume`` the same run's; the last ``keep`` checkpoints
    kept). ``options``:
    :class:`LoopOptions`' fields. Every setting is checked before anything is written."""
    unknown = sorted(set(options) - {f.name for f in dataclasses.fields(LoopOptions)})
    if unknown:
        raise TypeError(f"train_run() got unexpected option(s) {unknown}")
    loop = LoopOptions(**options)
    scenario = canonical_name(scenario)
    env = marbler_jax.make(scenario, **(env_overrides or {}))
    cfg = build_config(algo, dict(hp or {}, total_timesteps=int(total_steps)))
    loop.validate(cfg)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"seeds must be an integer >= 1, got {seeds!r}")
    if test_episodes < 0:
        raise ValueError(f"test_episodes must be >= 0 (0 = no greedy test), got {test_episodes}")
    config = run_config(scenario, algo, seeds, seed, env, cfg, test_episodes)
    with RunWriter.open(out, config, env, resume=resume, keep=keep, log=log) as run:
        return train(env, cfg, run, loop, on_chunk, log)


__all__ = ["train", "train_run", "LoopOptions", "evaluate", "build_config", "make_tester", "SEED_BATCHING",
           "default_seed_batching"]
