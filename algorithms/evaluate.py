"""Paper-style evaluation of a run folder (MARBLER's Table II metrics).

``evaluate_run(run, episodes=100)`` restores the run's best checkpoint (``best/``; ``"final"`` uses
``params.npz``), plays ``episodes`` greedy episodes per seed (one episode in each of ``episodes``
batched envs, fresh random initial states) and reports, per seed and pooled over seeds, the mean
and standard deviation of: Reward (team episode return), Steps (episode length, set to the maximum
when the episode ended by a violation, as the paper does), Prey Left (PCP) / Material Left (MT),
and the percentage of episodes with a collision / a boundary violation. The paper's simulated
numbers are listed beside ours where the paper has them (``PAPER``).

The paper's Table II is not a mean over seeds: it trained five seeds per algorithm, "took the model
that achieved the highest reward" and ran that one model for 100 episodes. ``seed_selection="best"``
(``marbler-jax evaluate RUN --best-seed``) does the same with a multi-seed run: only the seed whose
best greedy test return was highest, from its best checkpoint (``best/`` keeps each seed's own).
"""
from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import marbler_jax
from marbler_jax.control_loop import ROBOTS_CONTROL_PERIOD
from marbler_jax.rollout import first_episode_metrics, make_rollout

# MARBLER paper, Table II, simulated experiments: (mean, std) per scenario / algorithm / metric.
PAPER = {
    "predator_capture_prey": {
        "mappo": {"reward": (23.48, 5.33), "steps": (80.4, 1.8), "prey_left": (1.6, 0.92)},
        "vdn": {"reward": (33.25, 0.46), "steps": (55.0, 9.18), "prey_left": (0.0, 0.0)},
        "qmix": {"reward": (30.02, 3.8), "steps": (69.7, 12.32), "prey_left": (0.5, 0.67)},
        "qmix_ns": {"reward": (31.76, 2.7), "steps": (62.9, 12.75), "prey_left": (0.2, 0.4)},
    },
    "warehouse": {
        "mappo": {"reward": (36.6, 1.8)}, "vdn": {"reward": (28.7, 1.49)},
        "qmix": {"reward": (27.4, 1.02)}, "qmix_ns": {"reward": (1.8, 1.25)},
    },
    "material_transport": {
        "mappo": {"reward": (4.47, 0.93), "steps": (71.0, 0.0), "material_left": (8.4, 4.41)},
        "vdn": {"reward": (5.15, 1.3), "steps": (65.5, 4.48), "material_left": (0.1, 0.3)},
        "qmix": {"reward": (3.55, 0.85), "steps": (71.0, 0.0), "material_left": (9.4, 4.59)},
        "qmix_ns": {"reward": (2.08, 0.85), "steps": (71.0, 0.0), "material_left": (28.7, 12.74)},
    },
    "arctic_transport": {
        "mappo": {"reward": (-7.23, 1.61), "steps": (41.7, 10.65)},
        "vdn": {"reward": (-6.98, 1.75), "steps": (38.1, 10.25)},
        "qmix": {"reward": (-7.13, 1.59), "steps": (35.8, 8.24)},
        "qmix_ns": {"reward": (-11.29, 3.29), "steps": (57.0, 7.71)},
    },
}

METRICS = ("reward", "steps", "prey_left", "material_left", "collisions", "out_of_bounds")


def first_episodes(env, traj) -> dict[str, np.ndarray]:
    """Per-env metrics of the first episode each env finished in ``traj`` (``[T, E]`` arrays)."""
    _, done, info = traj
    done = np.asarray(done)
    if not done.any(axis=0).all():
        raise ValueError("every env must finish an episode; roll out at least env.max_steps steps")
    return {k: np.asarray(v, dtype=float) for k, v in first_episode_metrics(env, done, info).items()}


def greedy_episodes(env, policy, episodes: int, key) -> dict[str, np.ndarray]:
    """``episodes`` greedy episodes (one per batched env) -> per-episode metric arrays."""
    return first_episodes(env, make_rollout(env, episodes, env.max_steps, policy)(key)[1])


def summarize(values: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    return {k: {"mean": float(np.mean(v)), "std": float(np.std(v))} for k, v in values.items()}


def restore_params(run: Path, checkpoint: str = "best"):
    """Seed-major parameters of a run: ``"best"`` (orbax ``best/``) or ``"final"`` (``params.npz``)."""
    from .driver import load_params

    run = Path(run)
    if checkpoint == "final":
        if not (run / "params.npz").exists():
            raise ValueError(f"{run} has no params.npz (the run has not finished); try checkpoint='best'")
        return load_params(run / "params.npz")
    if checkpoint != "best":
        raise ValueError(f"checkpoint must be 'best' or 'final', got {checkpoint!r}")
    import orbax.checkpoint as ocp

    best = run / "best"
    manager = ocp.CheckpointManager(best.absolute()) if best.exists() else None
    if manager is None or manager.latest_step() is None:
        raise ValueError(f"{run} has no best checkpoint in {best}; train first or use checkpoint='final'")
    try:
        return manager.restore(manager.latest_step(), args=ocp.args.StandardRestore())
    except Exception as err:   # orbax raises several types for damaged folders
        raise ValueError(f"cannot restore the best checkpoint in {best}: {err}") from err


def best_seed(run) -> tuple[int, float]:
    """``(index, score)`` of the run's seed with the highest best greedy test return (best training
    return for runs trained with ``test_episodes=0``), read from ``metrics.jsonl``: the model MARBLER's
    Table II reports ("we took the model that achieved the highest reward for each algorithm", of five
    seeds, and ran it for 100 episodes)."""
    from .driver import SEED_SCORE_KEY, seed_best_scores

    run = Path(run)
    config = json.loads((run / "config.json").read_text())
    metrics = run / "metrics.jsonl"
    lines = [line for line in metrics.read_text().splitlines() if line.strip()] if metrics.exists() else []
    tested = bool(config.get("test_episodes", 0))
    per_seed_key = SEED_SCORE_KEY[tested]
    if config["seeds"] > 1 and not any(per_seed_key in json.loads(line) for line in lines):
        raise ValueError(f"{run} logs no per-seed scores ({per_seed_key!r} in metrics.jsonl; runs from earlier "
                         "versions lack them); evaluate all seeds instead")
    scores = seed_best_scores(lines, config["seeds"], tested)
    if not np.isfinite(scores).any():
        raise ValueError(f"{run} has no scored chunk yet (metrics.jsonl); train first")
    index = int(np.argmax(scores))                        # unscored seeds are -inf
    return index, float(scores[index])


def evaluate_run(run, episodes: int = 100, checkpoint: str = "best", seed: int = 0, progress: bool = False,
                 seed_selection: str = "all") -> dict:
    """Table II metrics of every seed of run folder ``run`` and pooled over seeds, or with
    ``seed_selection="best"`` of the one seed :func:`best_seed` picks (the paper's protocol).

    The policy is evaluated in the loop it trained in (``pooled``, ``per_seed``) and, when that loop's
    ``control_period`` is not 1, also in the robots' loop that a bundle deploys (``deployed``: the same
    env with controller and barrier every tick, the same start states): MARBLER's sim-vs-real
    comparison as training loop vs deployment loop, in simulation."""
    from .driver import ALGORITHMS

    if seed_selection not in ("all", "best"):
        raise ValueError(f"seed_selection must be 'all' or 'best', got {seed_selection!r}")

    run = Path(run)
    if not (run / "config.json").exists():
        raise ValueError(f"{run} is not a run folder (no config.json)")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = json.loads((run / "config.json").read_text())
    env = marbler_jax.make(config["scenario"], **config["env"])
    cfg_cls, _, greedy = ALGORITHMS[config["algo"]]
    cfg = cfg_cls(**config["algorithm"])
    params = restore_params(run, checkpoint)
    n_seeds = jax.tree_util.tree_leaves(params)[0].shape[0]
    per_seed, pooled = [], {}
    seeds = [best_seed(run)[0]] if seed_selection == "best" else list(range(n_seeds))
    loops = {"trained": env}
    if env.config.control_period != ROBOTS_CONTROL_PERIOD:
        loops["deployed"] = marbler_jax.make(config["scenario"], **dict(config["env"], control_period=ROBOTS_CONTROL_PERIOD))
    jobs = [(name, s) for name in loops for s in seeds]
    if progress:
        from tqdm.auto import tqdm

        jobs = tqdm(jobs, unit="seed", desc=f"evaluating {episodes} episodes")
    per_seed = {name: [] for name in loops}
    pooled = {name: {} for name in loops}
    for name, s in jobs:
        loop_env = loops[name]
        p = jax.tree_util.tree_map(lambda x: jnp.asarray(x[s]), params)
        values = greedy_episodes(loop_env, greedy(loop_env, cfg, p), episodes, jax.random.PRNGKey(seed + 1000 * s))
        per_seed[name].append(summarize(values))
        for k, v in values.items():
            pooled[name].setdefault(k, []).append(v)
    summaries = {name: summarize({k: np.concatenate(v) for k, v in pooled[name].items()}) for name in loops}
    result = dict(scenario=config["scenario"], algo=config["algo"], checkpoint=checkpoint, episodes_per_seed=episodes,
                  seeds=n_seeds, seed_selection=seed_selection, seed_indices=list(seeds),
                  control_period=env.config.control_period, pooled=summaries["trained"], per_seed=per_seed["trained"],
                  paper=PAPER.get(config["scenario"], {}).get(config["algo"]))
    if "deployed" in loops:
        result["deployed"] = dict(control_period=ROBOTS_CONTROL_PERIOD, pooled=summaries["deployed"],
                                  per_seed=per_seed["deployed"])
    return result


def markdown_table(result: dict) -> str:
    """The evaluation as a Markdown table (ours vs the paper's simulated numbers)."""
    paper = result.get("paper") or {}
    if result.get("seed_selection") == "best":
        seeds = f"seed {result['seed_indices'][0]}, the best of {result['seeds']} by greedy test return"
    else:
        seeds = f"{result['seeds']} seed(s)"
    deployed = result.get("deployed")
    period = result.get("control_period", 1)
    header = ("| metric | marbler-jax | MARBLER paper (sim) |", "|---|---|---|")
    if deployed:
        header = (f"| metric | training loop (period {period}) | robots' loop (period {deployed['control_period']}, "
                  "what a bundle deploys) | MARBLER paper (sim) |", "|---|---|---|---|")
    lines = [f"### {result['algo']} on {result['scenario']} ({seeds} x "
             f"{result['episodes_per_seed']} episodes, {result['checkpoint']} checkpoint)", "", *header]
    extra = [k for k in result["pooled"] if k not in METRICS]            # e.g. deliveries, landmarks_left
    for key in METRICS[:4] + tuple(extra) + METRICS[4:]:
        if key not in result["pooled"]:
            continue
        ours = result["pooled"][key]
        unit = " %" if key in ("collisions", "out_of_bounds") else ""
        ref = paper.get(key)
        ref_text = f"{ref[0]:g} ± {ref[1]:g}" if ref else ("0" if key in ("collisions", "out_of_bounds") and paper else "—")
        cells = [f"{ours['mean']:.2f} ± {ours['std']:.2f}"]
        if deployed:
            there = deployed["pooled"][key]
            cells.append(f"{there['mean']:.2f} ± {there['std']:.2f}")
        lines.append(f"| {key.replace('_', ' ')}{unit} | {' | '.join(cells)} | {ref_text} |")
    return "\n".join(lines) + "\n"


__all__ = ["evaluate_run", "best_seed", "markdown_table", "greedy_episodes", "first_episodes", "restore_params", "PAPER"]
