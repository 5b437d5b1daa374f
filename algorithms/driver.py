"""Training driver: run an algorithm on a scenario, evaluate greedily, write the run folder.

A run folder holds ``config.json``, ``metrics.jsonl`` (one line per update: env steps, return mean
and std over seeds, episode length, collision / out-of-bounds rates; the greedy test return on the
last line of each chunk), ``tests.jsonl`` (each chunk's greedy test: every seed's per-episode
metrics), ``learning_curve.png``, orbax checkpoints (``checkpoints/`` last k,
``best/`` by greedy test return), ``params.npz`` (the final parameters,
seed-major) and ``evaluation.json``. Every file is written to a temporary name and renamed (orbax
does the same for checkpoints), so an interrupted run never leaves a half-written file, and
``resume=True`` continues it bit-exactly.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
import typing
import warnings
from pathlib import Path

import jax
import numpy as np

import marbler_jax
from marbler_jax.registry import canonical_name
from marbler_jax.scenarios.base import renamed_keys
from . import checkpoints, registry
from .checkpoints import atomic_write
from .common import flatten_params
from .data_parallel import over_devices
from .hang_guard import HangGuard, hang_message
from .writer_lock import writer_lock
from marbler_jax.rollout import batched_rollout, episode_stats, first_episode_metrics, make_rollout

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
LOCK_FILE = ".lock"
"""The run folder's writer lock (:mod:`marbler_jax_rl.writer_lock`): one ``train`` per folder at a time."""
SEED_BATCHING = {"vmap": lambda fn, xs: jax.vmap(fn)(xs), "map": jax.lax.map, "devices": over_devices}
def default_seed_batching(algo: str, platform: str | None = None) -> str:
    """How ``train`` maps the seeds when not told: ``"map"`` on a CPU for the algorithms that ask for it
    (``Algorithm.map_seeds_on_cpu``: the value-based learners), ``"vmap"`` otherwise. On a CPU a value-based update is many small per-seed matmuls and normalisations
    that run 1.1-1.3x faster one seed at a time than batched over seeds (and ``map`` keeps the
    ``learning_starts`` branch a real branch, where ``vmap`` computes both sides); PPO's larger
    minibatches gain from the batch (BENCHMARKS.md, *Training throughput*). ``platform``: the default
    backend's (``jax.default_backend()``) unless given."""
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


def train(scenario: str, algo: str, total_steps: int, seeds: int, out: str | Path,
          env_overrides: dict | None = None, hp: dict | None = None, eval_episodes: int = 256,
          checkpoint_every: int | None = None, keep: int = 3, resume: bool = False, seed: int = 0,
          progress: bool = True, on_chunk=None, log=print, seed_batching: str | None = None,
          on_hang=None, hang_seconds: float = 120.0, test_episodes: int = 64) -> dict:
    """Train ``seeds`` seeds in one jitted program, in chunks of ``checkpoint_every`` updates.

    ``seed_batching="vmap"`` vectorizes the seeds (``jax.vmap``: one batch of ``seeds x num_envs``
    envs); ``"map"`` runs them one after another inside the program (``jax.lax.map``: the memory of one
    seed); ``None`` (default) picks the faster of the two for ``algo`` on this backend
    (:func:`default_seed_batching`); ``"devices"`` spreads the
    seeds over the process's devices, each vmapping its share
    (:func:`marbler_jax_rl.data_parallel.over_devices`: on a CPU split into several devices with
    ``use_cpu_devices``, a device per core). All give every seed the same result up to float rounding.

    If the process stays idle for ``hang_seconds`` inside a chunk (the jaxlib CPU hang, see
    :mod:`marbler_jax_rl.hang_guard`), ``on_hang(idle_seconds)`` runs on a watcher thread (default: a
    warning through ``log``; the CLI restarts itself with ``--resume``). ``hang_seconds=0`` turns
    the watcher off.

    After every chunk the parameters are tested greedily (``test_episodes`` episodes per seed, the
    same initial states at every test so that checkpoints are compared on equal terms; MARBLER and
    EPyMARL keep the model with the best greedy test return) and the runner state (parameters,
    optimiser, envs, keys) is saved with orbax (``checkpoints/``, the last ``keep``; ``best/`` holds,
    for each seed, the parameters of that seed's best test return -- each seed is an independent run,
    as each of the paper's five EPyMARL runs kept its own best model; with ``test_episodes=0`` the best
    mean training return of a chunk's updates, which are epsilon-greedy or sampled). ``metrics.jsonl``
    (the test return, mean/std and per seed, on each chunk's last line) and the learning curve are
    rewritten atomically before the runner checkpoint, which commits the chunk: a run killed in
    between repeats that chunk on resume and loses no metrics line. The tests draw no training
    randomness: a run trains the same with or without them. ``resume=True`` continues
    from the latest checkpoint bit-exactly (same final parameters as an uninterrupted run).
    ``on_chunk(update)`` is called after each chunk is saved (tests use it to simulate interruptions).
    At the end ``evaluation.json`` holds the first seed's greedy policy and the random policy over
    ``eval_episodes`` episodes each (``trained``/``random``; ``None`` with ``eval_episodes=0``).
    """
    import orbax.checkpoint as ocp
    from tqdm.auto import tqdm

    scenario = canonical_name(scenario)
    env = marbler_jax.make(scenario, **(env_overrides or {}))
    cfg = build_config(algo, dict(hp or {}, total_timesteps=int(total_steps)))
    if seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {seeds}")
    seed_batching = seed_batching or default_seed_batching(algo)
    if seed_batching not in SEED_BATCHING:
        raise ValueError(f"seed_batching must be one of {list(SEED_BATCHING)}, got {seed_batching!r}")
    over_seeds = SEED_BATCHING[seed_batching]
    if seed_batching == "devices" and getattr(cfg, "learner_devices", 1) > 1:
        raise ValueError(f"seed_batching='devices' splits the seeds over the devices; it cannot also split each "
                         f"seed's work (learner_devices={cfg.learner_devices}): use one or the other")
    if test_episodes < 0:
        raise ValueError(f"test_episodes must be >= 0 (0 = no greedy test), got {test_episodes}")
    if eval_episodes < 0:
        raise ValueError(f"eval_episodes must be >= 0 (0 = no final evaluation), got {eval_episodes}")
    make_train, greedy = registry.get(algo).make_train, registry.get(algo).greedy_policy
    if checkpoint_every is not None and (isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int)
                                         or checkpoint_every < 1):
        raise ValueError(f"checkpoint_every must be an integer >= 1 (updates per chunk), got {checkpoint_every!r}")
    out = Path(out).absolute()
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder for the run")
    config = run_config(scenario, algo, seeds, seed, env, cfg, test_episodes)
    config_json = json.dumps(config, indent=2)
    checkpoint_dir = out / "checkpoints"
    if resume:
        if not (out / "config.json").exists():
            raise ValueError(f"--resume: {out} has no config.json (nothing to resume)")
        diff = changed_settings(out, config, env)
        if diff:
            raise ValueError(f"--resume: the settings differ from the saved run in {diff}; use the same arguments")
    elif checkpoint_dir.exists() and any(checkpoint_dir.iterdir()):
        raise ValueError(f"{out} already holds checkpoints; pass --resume to continue or choose a new --out")
    out.mkdir(parents=True, exist_ok=True)      # only once every setting is valid: a refused run leaves nothing
    with writer_lock(out / LOCK_FILE, f"run folder {out}"):     # one writer at a time
        atomic_write(out / "config.json", config_json)

        trainer = make_train(env, cfg)
        num_updates, steps_per_update = trainer.num_updates, trainer.steps_per_update
        runner = jax.jit(lambda keys: over_seeds(trainer.init, keys))(jax.random.split(jax.random.PRNGKey(seed), seeds))
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False)
        manager = ocp.CheckpointManager(checkpoint_dir, options=options)
        best_manager = ocp.CheckpointManager(out / "best", options=ocp.CheckpointManagerOptions(
            max_to_keep=1, enable_async_checkpointing=False))
        lines, test_lines, done = [], [], 0
        step, restored = checkpoints.restore_latest(manager, runner, warn=log) if resume else (None, None)
        if step is not None:
            done = int(step)
            # laid out like a fresh runner (one device, the seeds spread over devices, or as a learner split over
            # devices lays out its state), so the resumed run executes the very programs a fresh one compiles,
            # and every chunk the one compiled up front
            runner = jax.tree_util.tree_map(lambda saved, fresh: jax.device_put(np.asarray(saved), fresh.sharding),
                                            restored, runner)
            lines = _lines_upto(out / "metrics.jsonl", done)
            test_lines = _lines_upto(out / TESTS_FILE, done)
            log(f"resuming from update {done} of {num_updates}")
        best_scores = seed_best_scores(lines, seeds, tested=bool(test_episodes))
        best_params = None
        if resume:
            try:
                best_params = checkpoints.restore_latest(best_manager, warn=log)[1]
            except ValueError:           # damaged and moved aside: every seed's best starts anew
                log("warning: the best checkpoint starts anew from the next test")
            if best_params is None:
                best_scores = np.full(seeds, -np.inf)
            else:
                best_params = jax.tree_util.tree_map(np.asarray, best_params)
        tester = make_tester(env, lambda p: greedy(env, cfg, p), test_episodes, over_seeds) if test_episodes else None
        test_keys = jax.random.split(jax.random.PRNGKey(seed + 7919), seeds)   # apart from the training keys
        chunk = checkpoint_every or max(1, num_updates // 10)
        run_fns = {}
        if on_hang is None:
            def on_hang(idle):
                log(f"warning: {hang_message(idle)}; stop this process and rerun with --resume (no checkpoint is lost)")

        def guard():
            return HangGuard(on_hang, hang_seconds) if hang_seconds else contextlib.nullcontext()
        spread = f" over {min(seeds, jax.local_device_count())} device(s)" if seed_batching == "devices" else ""
        trained_steps = num_updates * steps_per_update
        rounded = (f" (--total-steps {int(total_steps):,} rounded to whole updates: {trained_steps:,} per seed)"
                   if trained_steps != int(total_steps) else "")
        log(f"training {algo} on {scenario}: {num_updates} updates x {steps_per_update} env steps{rounded}, "
            f"{seeds} seed(s) in one program{spread}, checkpoint every {chunk} updates")
        t_start, resumed_at = time.perf_counter(), done
        # every program is compiled before the bar starts, so its rate, ETA and sps are the steady state's
        sizes = sorted({min(chunk, num_updates - done), (num_updates - done) % chunk} - {0})
        with guard():
            for n in sizes:
                run_fns[n] = jax.jit(lambda r, n=n: over_seeds(lambda s: trainer.run(s, n), r))
                run_fns[n].lower(runner).compile()
            if tester:
                tester.lower(runner["params"], test_keys).compile()
        compile_seconds = time.perf_counter() - t_start
        if sizes:
            log(f"compiled in {compile_seconds:.1f} s")
        board = tensorboard_writer(out, lines)
        bar = tqdm(total=num_updates, initial=done, unit="update", disable=not progress, dynamic_ncols=True)
        plotted_at = -np.inf
        while done < num_updates:
            n = min(chunk, num_updates - done)
            t0 = time.perf_counter()
            with guard():
                runner, metrics = jax.block_until_ready(run_fns[n](runner))
            chunk_s = time.perf_counter() - t0
            with guard():
                episodes = jax.tree_util.tree_map(np.asarray, tester(runner["params"], test_keys)) if tester else None
            test = episodes["reward"].mean(-1) if tester else None
            test_mean = _nan_stat(np.nanmean, test) if tester else None
            metrics = jax.tree_util.tree_map(np.asarray, metrics)
            for i in range(n):
                ret = metrics["return"][:, i]
                lines.append(json.dumps(dict(
                    update=done + i + 1, env_steps=(done + i + 1) * steps_per_update,
                    return_mean=_nan_stat(np.nanmean, ret), return_std=_nan_stat(np.nanstd, ret),
                    length=_nan_stat(np.nanmean, metrics["length"][:, i]),
                    collision_rate=_nan_stat(np.nanmean, metrics["collision_rate"][:, i]),
                    out_of_bounds_rate=_nan_stat(np.nanmean, metrics["out_of_bounds_rate"][:, i]),
                    sps=seeds * n * steps_per_update / chunk_s)))
            with warnings.catch_warnings():           # a seed that finished no episode in the chunk: NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                chunk_returns = np.nanmean(metrics["return"], axis=1)
            # the parameters at the chunk's end (after its last update) are scored: greedy test, else training return
            scores = test if tester else chunk_returns
            last = json.loads(lines[-1])
            if tester:
                last.update(test_return_mean=test_mean, test_return_std=_nan_stat(np.nanstd, test))
            last[SEED_SCORE_KEY[bool(tester)]] = _json_floats(scores)
            lines[-1] = json.dumps(last)
            if board is not None:
                log_scalars(board, lines[-n:])
            done += n
            # saved as host arrays: no device layout in the checkpoint, so a run trained on several devices
            # (learner_devices) restores anywhere (evaluate, export, resume)
            host = jax.tree_util.tree_map(np.asarray, runner)
            improved = np.asarray(scores) > best_scores            # NaN never improves
            if improved.any():
                best_scores = np.where(improved, scores, best_scores)
                best_params = keep_improved(improved, host["params"], best_params)
                if done in best_manager.all_steps():              # written before a kill, now written again
                    best_manager.delete(done)
                checkpoints.save(best_manager, done, best_params)
            atomic_write(out / "metrics.jsonl", "\n".join(lines) + "\n")
            if tester:
                rounded = {name: [_json_floats(np.round(np.asarray(row, float), 5)) for row in values]
                           for name, values in episodes.items()}
                test_lines.append(json.dumps(dict(update=done, env_steps=done * steps_per_update, episodes=rounded)))
                atomic_write(out / TESTS_FILE, "\n".join(test_lines) + "\n")
            if done == num_updates or time.perf_counter() - plotted_at >= PLOT_EVERY_S:
                plot_learning_curve(out / "metrics.jsonl", out / "learning_curve.png", f"{algo} on {scenario}")
                plotted_at = time.perf_counter()
            checkpoints.save(manager, done, host)    # last: the checkpoint (with its manifest) commits the chunk
            recent = [json.loads(line)["return_mean"] for line in lines[-n:]]
            recent = [r for r in recent if r is not None]
            bar.update(n)
            bar.set_postfix(ret=f"{recent[-1]:.2f}" if recent else "n/a",
                            **({"test": f"{test_mean:.2f}"} if test_mean is not None else {}),
                            sps=f"{seeds * n * steps_per_update / chunk_s:,.0f}")
            if on_chunk is not None:
                on_chunk(done)
        bar.close()
        if board is not None:
            board.close()
        seconds = time.perf_counter() - t_start
        params = runner["params"]
        save_params(out / "params.npz", params)
        trained = random = None
        if eval_episodes:
            first = jax.tree_util.tree_map(lambda x: x[0], params)
            key = jax.random.PRNGKey(12345)
            trained = evaluate(env, greedy(env, cfg, first), eval_episodes, key)
            random = evaluate(env, None, eval_episodes, key)
        update_seconds = seconds - compile_seconds
        result = dict(trained=trained, random=random, train_seconds=seconds, compile_seconds=compile_seconds,
                      # this invocation's updates only (a resumed run trained the rest before), after compilation
                      env_steps_per_s=seeds * (num_updates - resumed_at) * steps_per_update / max(update_seconds, 1e-9),
                      best_return=_nan_stat(np.mean, best_scores), best_return_per_seed=_json_floats(best_scores),
                      best_by="greedy test return" if test_episodes else "training return")
        atomic_write(out / "evaluation.json", json.dumps(result, indent=2))
        log(f"trained in {seconds:.1f} s ({compile_seconds:.1f} s of it compiling; "
            f"{result['env_steps_per_s']:,.0f} env-steps/s including learning, after compilation)")
        if eval_episodes:
            log(f"greedy return {trained['return']:.2f} vs random {random['return']:.2f}; "
                f"collisions {trained['collision_rate']:.1%}, out of bounds {trained['out_of_bounds_rate']:.1%}")
        return result


def run_config(scenario: str, algo: str, seeds: int, seed: int, env, cfg, test_episodes: int) -> dict:
    """What a run folder's ``config.json`` records: the settings a resume must repeat (canonical
    ``scenario``, ``env``'s and the algorithm config ``cfg``'s every field)."""
    return json.loads(json.dumps(dict(scenario=scenario, algo=algo, seeds=seeds, seed=seed,
                                      env=dataclasses.asdict(env.config), algorithm=dataclasses.asdict(cfg),
                                      test_episodes=test_episodes)))


def changed_settings(out: Path, config: dict, env) -> list[str]:
    """The keys of :func:`run_config`'s ``config`` in which the run saved in ``out`` differs (``[]``: the
    same run). Env settings added since the run was saved count as equal where ``config`` has them at
    their defaults, renamed env settings under their current names, and ``learner_devices`` is not
    compared (it splits the same computation over devices; checkpoints restore on any count)."""
    saved = checkpoints.read_json(Path(out) / "config.json")
    config = dict(config, algorithm={k: v for k, v in config["algorithm"].items() if k != "learner_devices"})
    saved["algorithm"] = {k: v for k, v in saved.get("algorithm", {}).items() if k != "learner_devices"}
    saved.setdefault("test_episodes", 0)       # run folders from before the greedy tests
    saved["env"] = renamed_keys(saved.get("env", {}))
    defaults = {f.name: f.default for f in dataclasses.fields(env.config)}
    for name, value in config["env"].items():
        if name not in saved["env"] and value == defaults.get(name, dataclasses.MISSING):
            saved["env"][name] = value
    return sorted(k for k in set(config) | set(saved) if saved.get(k) != config.get(k))


# one line per chunk: the greedy test's per-episode metrics of every seed ({"update", "env_steps",
# "episodes": {metric: [seeds][episodes]}})
TESTS_FILE = "tests.jsonl"
# The learning curve is redrawn after the first and the last chunk and otherwise at most this often [s]:
# drawing takes a fraction of a second, which short chunks would otherwise spend on it again and again.
PLOT_EVERY_S = 30.0


def _lines_upto(path: Path, update: int) -> list[str]:
    """The lines of a JSON-lines log up to ``update`` (a resumed run drops what came after its checkpoint)."""
    if not path.exists():
        return []
    return [line for line in path.read_text().splitlines() if line.strip() and json.loads(line)["update"] <= update]


# metrics.jsonl key of each seed's score on a chunk's last line: greedy test returns, else (runs with
# test_episodes=0) the chunk's mean training returns
SEED_SCORE_KEY = {True: "test_returns", False: "chunk_returns"}


def _json_floats(values) -> list:
    """Floats for JSON (NaN -> None)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, dtype=float)]


def seed_best_scores(lines: list[str], seeds: int, tested: bool) -> np.ndarray:
    """Each seed's best chunk score ``[seeds]`` in ``metrics.jsonl`` lines (``-inf`` before any): the
    greedy test returns (``test_returns``) or, for runs without tests, the chunks' mean training
    returns (``chunk_returns``). Lines without per-seed scores (older run folders) count
    their test mean for every seed; an untested run from before then starts its best anew on resume."""
    best = np.full(seeds, -np.inf)
    for line in lines:
        row = json.loads(line)
        per_seed = row.get(SEED_SCORE_KEY[tested])
        if per_seed is None:
            mean = row.get("test_return_mean") if tested else None
            if mean is None:
                continue
            per_seed = [mean] * seeds
        best = np.fmax(best, np.array([np.nan if v is None else v for v in per_seed], dtype=float))
    return best


def keep_improved(improved: np.ndarray, params, best_params):
    """Seed-major ``params`` where ``improved [S]``, else ``best_params`` (``None``: nothing kept yet)."""
    if best_params is None:
        return params
    def pick(new, old):
        return np.where(improved.reshape((-1,) + (1,) * (np.ndim(new) - 1)), new, old)
    return jax.tree_util.tree_map(pick, params, best_params)


def save_params(path: Path, params) -> None:
    """Write a parameter pytree of nested dicts as ``.npz`` (keys ``a/b/c``), atomically."""
    flat = flatten_params(params)
    tmp = Path(path).with_name(Path(path).stem + ".tmp.npz")
    np.savez(tmp, **flat)
    os.replace(tmp, path)
    checkpoints.write_file_checksum(path)


def load_params(path: Path) -> dict:
    """Inverse of :func:`save_params`; ``ValueError`` naming the file when it is damaged."""
    checkpoints.check_file(path)
    try:
        return _unflatten_npz(path)
    except Exception as err:   # zipfile, pickle and numpy errors of a damaged file
        raise ValueError(f"cannot read {path}: {type(err).__name__}: {err}") from err


def _unflatten_npz(path: Path) -> dict:
    params: dict = {}
    with np.load(path) as flat:
        for name in flat.files:
            node = params
            *parents, leaf = name.split("/")
            for p in parents:
                node = node.setdefault(p, {})
            node[leaf] = flat[name]
    return params


def tensorboard_writer(out: Path, lines: list[str] = ()):
    """A ``tensorboardX.SummaryWriter`` on ``out/tensorboard`` when tensorboardX is installed, else None
    (``pip install "marbler-jax[tensorboard]"``; view with ``tensorboard --logdir runs``).

    The event files are derived from ``metrics.jsonl``: earlier ones are replaced by one that holds
    ``lines`` (a resumed run's metrics up to its checkpoint), so an interrupted run's updates after its
    checkpoint are neither doubled nor missing."""
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    folder = Path(out) / "tensorboard"
    for old in folder.glob("events.out.tfevents.*"):
        old.unlink()
    board = SummaryWriter(str(folder))
    log_scalars(board, lines)
    return board


def log_scalars(board, lines: list[str]) -> None:
    """The numeric fields of ``metrics.jsonl`` lines as ``train/<field>`` scalars at their env step."""
    for line in lines:
        row = json.loads(line)
        for name, value in row.items():
            if name not in ("update", "env_steps") and isinstance(value, (int, float)):  # no lists
                board.add_scalar(f"train/{name}", value, row["env_steps"])
    board.flush()


def _nan_stat(fn, x):
    """``fn`` over the finite entries of ``x`` (seeds whose rollout finished an episode), else None."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(fn(x)) if x.size else None


def plot_learning_curve(metrics_path: Path, png: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = checkpoints.read_json_lines(metrics_path)
    rows = [r for r in rows if r["return_mean"] is not None]
    if not rows:
        return
    steps = np.array([r["env_steps"] for r in rows])
    mean = np.array([r["return_mean"] for r in rows])
    std = np.array([r["return_std"] or 0.0 for r in rows])
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(steps, mean, lw=1.5, label="training")
    ax.fill_between(steps, mean - std, mean + std, alpha=0.25)
    tests = [r for r in rows if r.get("test_return_mean") is not None]
    if tests:
        ax.plot([r["env_steps"] for r in tests], [r["test_return_mean"] for r in tests], "o-", ms=3, lw=1,
                label="greedy test")
        ax.legend(loc="lower right")
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return (team)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    tmp = png.with_name(png.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, png)


__all__ = ["train", "evaluate", "plot_learning_curve", "atomic_write", "save_params",
           "load_params"]
