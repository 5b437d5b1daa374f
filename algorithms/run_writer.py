"""The one writer of a run folder: create or resume it, record each chunk, keep each seed's best, finish.

:class:`RunWriter` owns what ``train`` writes (the layout is :mod:`marbler_jax_rl.run`'s): it refuses a folder
that holds another run's files or files it did not write, takes the folder's writer lock, writes
``config.json``, keeps the orbax managers of ``checkpoints/`` and ``best/`` (every step with its SHA-256
manifest), restores the newest intact checkpoint on resume, and writes ``metrics.jsonl``, ``tests.jsonl``, the
learning curve and TensorBoard events in the order that makes a killed run resume bit-exactly: the chunk's
files first, its runner checkpoint last (the checkpoint commits the chunk).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
import warnings
from pathlib import Path

import jax
import numpy as np

from marbler_jax.scenarios.base import renamed_keys
from . import checkpoints
from .checkpoints import atomic_write
from .common import flatten_params
from .run import (BEST_DIR, CHECKPOINTS_DIR, CONFIG_FILE, CURVE_FILE, EVALUATION_FILE, LOCK_FILE, METRICS_FILE,
                  PARAMS_FILE, SEED_SCORE_KEY, TENSORBOARD_DIR, TESTS_FILE, seed_best_scores)
from .writer_lock import writer_lock

# The learning curve is redrawn after the first and the last chunk and otherwise at most this often [s]:
# drawing takes a fraction of a second, which short chunks would otherwise spend on it again and again.
PLOT_EVERY_S = 30.0


def run_config(scenario: str, algo: str, seeds: int, seed: int, env, cfg, test_episodes: int) -> dict:
    """What a run folder's ``config.json`` records: the settings a resume must repeat (canonical
    ``scenario``, ``env``'s and the algorithm config ``cfg``'s every field)."""
    return json.loads(json.dumps(dict(scenario=scenario, algo=algo, seeds=seeds, seed=seed,
                                      env=dataclasses.asdict(env.config), algorithm=dataclasses.asdict(cfg),
                                      test_episodes=test_episodes, manifests=True)))


# config.json keys that say how the folder is written, not what is trained: a resume does not compare them
FORMAT_KEYS = ("manifests",)


def changed_settings(out: Path, config: dict, env) -> list[str]:
    """The keys of :func:`run_config`'s ``config`` in which the run saved in ``out`` differs (``[]``: the
    same run). Env and algorithm settings added since the run was saved count as equal where ``config`` has
    them at their defaults, renamed env settings under their current names, and ``learner_devices`` is not
    compared (it splits the same computation over devices; checkpoints restore on any count)."""
    from .registry import get

    saved = {k: v for k, v in checkpoints.read_json(Path(out) / CONFIG_FILE).items() if k not in FORMAT_KEYS}
    config = {k: v for k, v in config.items() if k not in FORMAT_KEYS}
    config = dict(config, algorithm={k: v for k, v in config["algorithm"].items() if k != "learner_devices"})
    saved["algorithm"] = {k: v for k, v in saved.get("algorithm", {}).items() if k != "learner_devices"}
    saved.setdefault("test_episodes", 0)       # run folders from before the greedy tests
    saved["env"] = renamed_keys(saved.get("env", {}))
    _fill_defaults(saved["env"], config["env"], env.config)
    if saved.get("algo") == config["algo"]:
        _fill_defaults(saved["algorithm"], config["algorithm"], get(config["algo"]).config)
    return sorted(k for k in set(config) | set(saved) if saved.get(k) != config.get(k))


def _fill_defaults(saved: dict, current: dict, settings) -> None:
    """Give ``saved`` the settings it lacks where ``current`` has them at the defaults of the dataclass
    ``settings`` (a setting added since ``saved`` was written, which the saved run trained with)."""
    defaults = {f.name: f.default for f in dataclasses.fields(settings)}
    for name, value in current.items():
        if name not in saved and value == defaults.get(name, dataclasses.MISSING):
            saved[name] = value


def check_folder(out: Path, config: dict, env, resume: bool) -> None:
    """Refuse, before anything is written, a folder this run may not write: a file; on resume one without
    this run's ``config.json``; for a fresh run one that holds any file (another run's, or a user's)."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder for the run")
    if resume:
        if not (out / CONFIG_FILE).exists():
            raise ValueError(f"--resume: {out} has no {CONFIG_FILE} (nothing to resume)")
        diff = changed_settings(out, config, env)
        if diff:
            raise ValueError(f"--resume: the settings differ from the saved run in {diff}; use the same arguments")
        return
    held = sorted(p.name for p in out.iterdir() if p.name != LOCK_FILE) if out.is_dir() else []
    if held:
        what = "a run" if CONFIG_FILE in held else "files"
        raise ValueError(f"{out} already holds {what} ({', '.join(held[:4])}{', ...' if len(held) > 4 else ''}); "
                         "pass --resume to continue the run there, or choose a new --out")


def json_floats(values) -> list:
    """Floats for JSON (NaN -> None)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, dtype=float)]


def nan_stat(fn, x):
    """``fn`` over the finite entries of ``x`` (seeds whose rollout finished an episode), else None."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(fn(x)) if x.size else None


def keep_improved(improved: np.ndarray, params, best_params):
    """Seed-major ``params`` where ``improved [S]``, else ``best_params`` (``None``: nothing kept yet)."""
    if best_params is None:
        return params

    def pick(new, old):
        return np.where(improved.reshape((-1,) + (1,) * (np.ndim(new) - 1)), new, old)
    return jax.tree_util.tree_map(pick, params, best_params)


class RunWriter:
    """Writes one run folder; made by :meth:`open`, which holds the folder's lock while the run trains.

    ``done``: updates committed so far (the resumed checkpoint's, then each recorded chunk's);
    ``best_scores [S]``: each seed's best chunk score so far (``-inf`` before any)."""

    def __init__(self, path: Path, config: dict, keep: int, log):
        import orbax.checkpoint as ocp

        self.path, self.config, self.log = path, config, log
        self.seeds, self.tested = int(config["seeds"]), bool(config["test_episodes"])
        self.manager = ocp.CheckpointManager(path / CHECKPOINTS_DIR, options=ocp.CheckpointManagerOptions(
            max_to_keep=keep, enable_async_checkpointing=False))
        self.best_manager = ocp.CheckpointManager(path / BEST_DIR, options=ocp.CheckpointManagerOptions(
            max_to_keep=1, enable_async_checkpointing=False))
        self.lines: list[str] = []
        self.test_lines: list[str] = []
        self.done = 0
        self.best_scores = np.full(self.seeds, -np.inf)
        self.best_params = None
        self.board = None
        self.plotted_at = -np.inf

    @classmethod
    @contextlib.contextmanager
    def open(cls, out, config: dict, env, resume: bool = False, keep: int = 3, log=print):
        """The writer of run folder ``out`` for the run ``config`` (:func:`run_config`) in ``env``: the
        folder is checked (:func:`check_folder`), made, locked (a second writer gets one line naming the
        first) and its ``config.json`` written; the lock is held until the block ends."""
        out = Path(out).absolute()
        check_folder(out, config, env, resume)
        if resume:        # a folder from before manifests stays one: its steps are trusted on orbax's restore
            config = dict(config, manifests=bool(checkpoints.read_json(out / CONFIG_FILE).get("manifests")))
        out.mkdir(parents=True, exist_ok=True)      # only once every setting is valid: a refused run leaves nothing
        with writer_lock(out / LOCK_FILE, f"run folder {out}"):
            atomic_write(out / CONFIG_FILE, json.dumps(config, indent=2))
            writer = cls(out, config, keep, log)
            try:
                yield writer
            finally:
                if writer.board is not None:
                    writer.board.close()

    def restore(self, runner):
        """``runner`` (a fresh runner state, the template) replaced by the newest intact checkpoint's, laid
        out like the template (one device, or spread over devices as the run's programs expect), with the
        metrics and tests up to it and each seed's best; the fresh ``runner`` where there is none."""
        manifests = bool(self.config.get("manifests"))        # every step of this folder has one
        step, restored = checkpoints.restore_latest(self.manager, runner, warn=self.log, manifests=manifests)
        if step is not None:
            self.done = int(step)
            runner = jax.tree_util.tree_map(lambda saved, fresh: jax.device_put(np.asarray(saved), fresh.sharding),
                                            restored, runner)
            self.lines = _lines_upto(self.path / METRICS_FILE, self.done)
            self.test_lines = _lines_upto(self.path / TESTS_FILE, self.done)
        self.best_scores = seed_best_scores(self.lines, self.seeds, self.tested)
        try:
            best = checkpoints.restore_latest(self.best_manager, warn=self.log, manifests=manifests)[1]
        except ValueError:           # damaged and moved aside: every seed's best starts anew
            self.log("warning: the best checkpoint starts anew from the next test")
            best = None
        if best is None:
            self.best_scores = np.full(self.seeds, -np.inf)
        else:
            self.best_params = jax.tree_util.tree_map(np.asarray, best)
        return runner

    def start_events(self) -> None:
        """TensorBoard events (where tensorboardX is installed) from the metrics kept so far."""
        self.board = tensorboard_writer(self.path, self.lines)

    def record_chunk(self, metrics: dict, steps_per_update: int, seconds: float, runner, tests: dict | None) -> None:
        """Commit one chunk: ``metrics`` (``{name: [S, n]}`` of its ``n`` updates: return, length, collision and
        out-of-bounds rates), trained in ``seconds``; ``runner`` the runner state after it (host arrays);
        ``tests`` the greedy test's per-episode metrics ``{name: [S, episodes]}`` (``None`` for an untested
        run: the chunk's mean training return scores each seed). Each seed's best parameters are kept; the
        runner checkpoint is written last."""
        n, done, seeds = metrics["return"].shape[1], self.done, self.seeds
        for i in range(n):
            self.lines.append(json.dumps(dict(
                update=done + i + 1, env_steps=(done + i + 1) * steps_per_update,
                return_mean=nan_stat(np.nanmean, metrics["return"][:, i]),
                return_std=nan_stat(np.nanstd, metrics["return"][:, i]),
                length=nan_stat(np.nanmean, metrics["length"][:, i]),
                collision_rate=nan_stat(np.nanmean, metrics["collision_rate"][:, i]),
                out_of_bounds_rate=nan_stat(np.nanmean, metrics["out_of_bounds_rate"][:, i]),
                sps=seeds * n * steps_per_update / seconds)))
        if tests is not None:
            scores = tests["reward"].mean(-1)
        else:
            with warnings.catch_warnings():           # a seed that finished no episode in the chunk: NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                scores = np.nanmean(metrics["return"], axis=1)
        last = json.loads(self.lines[-1])
        if tests is not None:
            last.update(test_return_mean=nan_stat(np.nanmean, scores), test_return_std=nan_stat(np.nanstd, scores))
        last[SEED_SCORE_KEY[tests is not None]] = json_floats(scores)
        self.lines[-1] = json.dumps(last)
        if self.board is not None:
            log_scalars(self.board, self.lines[-n:])
        self.done = done = done + n
        improved = np.asarray(scores) > self.best_scores            # NaN never improves
        if improved.any():
            self.best_scores = np.where(improved, scores, self.best_scores)
            self.best_params = keep_improved(improved, runner["params"], self.best_params)
            if done in self.best_manager.all_steps():              # written before a kill, now written again
                self.best_manager.delete(done)
            checkpoints.save(self.best_manager, done, self.best_params)
        atomic_write(self.path / METRICS_FILE, "\n".join(self.lines) + "\n")
        if tests is not None:
            rounded = {name: [json_floats(np.round(np.asarray(row, float), 5)) for row in values]
                       for name, values in tests.items()}
            self.test_lines.append(json.dumps(dict(update=done, env_steps=done * steps_per_update, episodes=rounded)))
            atomic_write(self.path / TESTS_FILE, "\n".join(self.test_lines) + "\n")
        if time.perf_counter() - self.plotted_at >= PLOT_EVERY_S:      # and always at the end (finish)
            self.plot()
        checkpoints.save(self.manager, done, runner)    # last: the checkpoint (with its manifest) commits the chunk

    def plot(self) -> None:
        plot_learning_curve(self.path / METRICS_FILE, self.path / CURVE_FILE,
                            f"{self.config['algo']} on {self.config['scenario']}")
        self.plotted_at = time.perf_counter()

    def finish(self, params, evaluation: dict) -> None:
        """The final parameters (``params.npz``, seed-major, with its checksum) and ``evaluation.json``."""
        self.plot()
        save_params(self.path / PARAMS_FILE, params)
        atomic_write(self.path / EVALUATION_FILE, json.dumps(evaluation, indent=2))


def _lines_upto(path: Path, update: int) -> list[str]:
    """The lines of a JSON-lines log up to ``update`` (a resumed run drops what came after its checkpoint)."""
    if not path.exists():
        return []
    return [json.dumps(row) for row in checkpoints.read_json_lines(path) if row["update"] <= update]


def save_params(path: Path, params) -> None:
    """Write a parameter pytree of nested dicts as ``.npz`` (keys ``a/b/c``), atomically."""
    flat = flatten_params(params)
    tmp = Path(path).with_name(Path(path).stem + ".tmp.npz")
    np.savez(tmp, **flat)
    os.replace(tmp, path)
    checkpoints.write_file_checksum(path)


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
    folder = Path(out) / TENSORBOARD_DIR
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


def plot_learning_curve(metrics_path: Path, png: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = checkpoints.read_json_lines(metrics_path) if metrics_path.exists() else []
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


__all__ = ["RunWriter", "run_config", "changed_settings", "check_folder", "save_params", "plot_learning_curve"]
