"""A run folder, opened: the one way the CLI and the Python API read what ``train`` wrote.

``Run.open(path)`` reads ``config.json`` once; from there ``env()``, ``algorithm_config()``,
``params(checkpoint)``, ``policy(seed_index, checkpoint)``, ``metrics()`` and ``best_seed()`` give the
pieces, and every command (``evaluate``, ``export``, ``render``, ``benchmark``) takes its parameters
from :data:`DEFAULT_CHECKPOINT` unless told otherwise.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

import marbler_jax

CHECKPOINTS = ("best", "final")
"""``"best"``: each seed's parameters at its best greedy test (orbax ``best/``); ``"final"``: the
parameters at the end of training (``params.npz``)."""
DEFAULT_CHECKPOINT = "best"
"""What every command evaluates, exports and renders unless ``--checkpoint`` says otherwise: the model
MARBLER's protocol reports (each seed's best greedy test return)."""

# A run folder's layout (read here, written by marbler_jax_rl.run_writer.RunWriter)
CONFIG_FILE = "config.json"          # the run's settings (run_writer.run_config)
METRICS_FILE = "metrics.jsonl"       # one line per update; each chunk's scores on its last line
TESTS_FILE = "tests.jsonl"           # one line per chunk: {"update", "env_steps", "episodes": {metric: [S][E]}}
PARAMS_FILE = "params.npz"           # the final parameters, seed-major (with params.npz.sha256)
EVALUATION_FILE = "evaluation.json"  # the first seed's greedy policy and the random policy at the end
CURVE_FILE = "learning_curve.png"
CHECKPOINTS_DIR = "checkpoints"      # orbax: the runner state (params, optimiser, envs, keys), the last k
BEST_DIR = "best"                    # orbax: each seed's parameters at its best chunk score
TENSORBOARD_DIR = "tensorboard"
LOCK_FILE = ".lock"                  # the writer lock (marbler_jax_rl.writer_lock)

# metrics.jsonl key of each seed's score on a chunk's last line: greedy test returns, else (runs with
# test_episodes=0) the chunk's mean training returns
SEED_SCORE_KEY = {True: "test_returns", False: "chunk_returns"}


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


def load_params(path: Path) -> dict:
    """The parameter pytree of a ``params.npz`` (keys ``a/b/c``); ``ValueError`` naming the file when it is
    damaged."""
    from .checkpoints import check_file

    check_file(path)
    try:
        params: dict = {}
        with np.load(path) as flat:
            for name in flat.files:
                node = params
                *parents, leaf = name.split("/")
                for p in parents:
                    node = node.setdefault(p, {})
                node[leaf] = flat[name]
        return params
    except Exception as err:   # zipfile, pickle and numpy errors of a damaged file
        raise ValueError(f"cannot read {path}: {type(err).__name__}: {err}") from err


@dataclasses.dataclass(frozen=True)
class Run:
    """A trained (or training) run folder: ``path`` and its parsed ``config.json``."""

    path: Path
    config: dict

    @classmethod
    def open(cls, path) -> "Run":
        """The run in folder ``path``; ``ValueError`` if it holds no ``config.json``."""
        path = Path(path)
        if not cls.holds_run(path):
            raise ValueError(f"{path} is not a run folder (no {CONFIG_FILE})")
        from marbler_jax.scenarios.base import renamed_keys

        from .checkpoints import read_json

        config = read_json(path / CONFIG_FILE)
        return cls(path, dict(config, env=renamed_keys(config.get("env", {}))))

    @staticmethod
    def holds_run(path) -> bool:
        """Whether folder ``path`` holds a run (its ``config.json``)."""
        return (Path(path) / CONFIG_FILE).is_file()

    @property
    def scenario(self) -> str:
        return self.config["scenario"]

    @property
    def algo(self) -> str:
        return self.config["algo"]

    @property
    def seeds(self) -> int:
        return int(self.config["seeds"])

    def env(self, **overrides):
        """The env the run trained in, with ``overrides`` (e.g. ``control_period=1``, or ``protocol="marbler"``,
        which replaces the settings it decides) on top."""
        from marbler_jax.scenarios.base import merge_settings

        return marbler_jax.make(self.scenario, **merge_settings(self.config["env"], overrides))

    def algorithm_config(self):
        """The algorithm's typed config as trained."""
        from . import registry

        return registry.get(self.algo).config(**self.config["algorithm"])

    def params(self, checkpoint: str = DEFAULT_CHECKPOINT):
        """Seed-major parameters (leaves ``[seeds, ...]``) of ``checkpoint`` (one of :data:`CHECKPOINTS`)."""
        if checkpoint not in CHECKPOINTS:
            raise ValueError(f"checkpoint must be one of {list(CHECKPOINTS)}, got {checkpoint!r}")
        if checkpoint == "final":
            if not (self.path / PARAMS_FILE).exists():
                raise ValueError(f"{self.path} has no {PARAMS_FILE} (the run has not finished); "
                                 "try checkpoint='best'")
            return load_params(self.path / PARAMS_FILE)
        import orbax.checkpoint as ocp

        from .checkpoints import MANIFEST, manifest_problem, step_folder

        best = self.path / BEST_DIR
        manager = ocp.CheckpointManager(best.absolute()) if best.exists() else None
        if manager is None or manager.latest_step() is None:
            raise ValueError(f"{self.path} has no best checkpoint in {best}; train first or use checkpoint='final'")
        folder = step_folder(manager, manager.latest_step())
        checked = self.config.get("manifests") or (folder / MANIFEST).exists()   # required where the run has them
        problem = manifest_problem(folder) if checked else None
        if problem:
            raise ValueError(f"the best checkpoint {folder} is damaged: {problem}; use checkpoint='final' or "
                             "resume the run to write a new one")
        try:
            return manager.restore(manager.latest_step(), args=ocp.args.StandardRestore())
        except Exception as err:   # orbax raises several types for damaged folders
            raise ValueError(f"cannot restore the best checkpoint in {best}: {err}") from err

    def seed_index(self, which) -> int:
        """The index of seed ``which``: an index, or ``"best"`` (:meth:`best_seed`; seed 0 of a one-seed
        run, or of a run that logged no per-seed scores)."""
        if which != "best":
            return which
        if self.seeds == 1:
            return 0
        try:
            return self.best_seed()[0]
        except ValueError:
            return 0

    def seed_params(self, seed_index: int = 0, checkpoint: str = DEFAULT_CHECKPOINT):
        """One seed's parameters (numpy leaves)."""
        return select_seed(self.params(checkpoint), seed_index)

    def policy(self, seed_index: int = 0, checkpoint: str = DEFAULT_CHECKPOINT, env=None):
        """Greedy policy ``(key, obs [N, obs_dim], carry) -> (actions, carry)`` of one seed, acting in
        ``env`` (default: :meth:`env`)."""
        from . import registry

        env = self.env() if env is None else env
        greedy = registry.get(self.algo).greedy_policy
        return greedy(env, self.algorithm_config(), self.seed_params(seed_index, checkpoint))

    @property
    def tested(self) -> bool:
        """Whether the run tests its seeds greedily after each chunk (else training returns score them)."""
        return bool(self.config.get("test_episodes", 0))

    def best_scores(self) -> np.ndarray:
        """Each seed's best chunk score so far ``[seeds]`` (:func:`seed_best_scores`)."""
        return seed_best_scores(self._metric_lines(), self.seeds, self.tested)

    def _metric_lines(self) -> list[str]:
        file = self.path / METRICS_FILE
        return [line for line in file.read_text().splitlines() if line.strip()] if file.exists() else []

    def metrics(self) -> list[dict[str, Any]]:
        """``metrics.jsonl`` as a list of dicts (one per update; empty before the first)."""
        return [json.loads(line) for line in self._metric_lines()]

    def tests(self) -> list[dict[str, Any]]:
        """``tests.jsonl`` as a list of dicts (one per chunk's greedy test; empty for an untested run)."""
        from .checkpoints import read_json_lines

        return read_json_lines(self.path / TESTS_FILE) if (self.path / TESTS_FILE).exists() else []

    def latest_checkpoint(self) -> int | None:
        """The update of the newest runner checkpoint (what a resume continues from), ``None`` if none."""
        from .checkpoints import latest_step

        return latest_step(self.path / CHECKPOINTS_DIR)

    def best_seed(self) -> tuple[int, float]:
        """``(index, score)`` of the seed with the highest best greedy test return (best training return
        for runs trained with ``test_episodes=0``): the model MARBLER's Table II reports ("we took the
        model that achieved the highest reward for each algorithm", of five seeds)."""
        lines = self._metric_lines()
        key = SEED_SCORE_KEY[self.tested]
        if self.seeds > 1 and not any(key in json.loads(line) for line in lines):
            raise ValueError(f"{self.path} logs no per-seed scores ({key!r} in {METRICS_FILE}); "
                             "evaluate all seeds instead")
        scores = self.best_scores()
        if not np.isfinite(scores).any():
            raise ValueError(f"{self.path} has no scored chunk yet ({METRICS_FILE}); train first")
        index = int(np.argmax(scores))                        # unscored seeds are -inf
        return index, float(scores[index])


def select_seed(params, seed_index: int):
    """One seed's parameters (numpy leaves) from seed-major ``params``, with a clear range error."""
    seeds = jax.tree_util.tree_leaves(params)[0].shape[0]
    if isinstance(seed_index, bool) or not isinstance(seed_index, (int, np.integer)) or not 0 <= seed_index < seeds:
        raise ValueError(f"seed index {seed_index!r} out of range: the run has {seeds} seed(s)")
    return jax.tree_util.tree_map(lambda x: np.asarray(x[seed_index]), params)


def load_run(run, seed_index: int = 0, checkpoint: str = DEFAULT_CHECKPOINT):
    """``(env, greedy policy)`` of seed ``seed_index`` of run folder ``run``."""
    opened = Run.open(run)
    env = opened.env()
    return env, opened.policy(seed_index, checkpoint, env)


__all__ = ["Run", "CHECKPOINTS", "DEFAULT_CHECKPOINT", "load_run", "select_seed", "load_params", "seed_best_scores"]
