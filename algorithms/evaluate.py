"""Paper-style evaluation of a run folder (MARBLER's Table II metrics).

``evaluate_run(run, episodes=100)`` restores the run's best checkpoint (``best/``; ``"final"`` uses
``params.npz``), plays ``episodes`` greedy episodes per seed (one episode in each of ``episodes``
batched envs, fresh random initial states) and reports, per seed and pooled over seeds, the mean
and standard deviation of: Reward (team episode return), Steps (episode length, set to the maximum
when the episode ended by a violation, as the paper does), Prey Left (PCP) / Material Left (MT),
and the percentage of episodes with a collision / a boundary violation. The paper's simulated
numbers are listed beside ours where the paper has them (``PAPER_TABLE2``).

The paper's Table II is not a mean over seeds: it trained five seeds per algorithm, "took the model
that achieved the highest reward" and ran that one model for 100 episodes. ``seed_selection="best"``
(``marbler-jax evaluate RUN --best-seed``) does the same with a multi-seed run: only the seed whose
best greedy test return was highest, from its best checkpoint (``best/`` keeps each seed's own).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from marbler_jax.control_loop import ROBOTS_CONTROL_PERIOD
from marbler_jax.deploy.bundle import deployment_settings
from marbler_jax.rollout import batched_rollout, first_episode_metrics
from . import registry
from .run import DEFAULT_CHECKPOINT, Run

# MARBLER paper, Table II, simulated experiments: (mean, std) per scenario / algorithm / metric.
PAPER_TABLE2 = {
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


def greedy_episodes(env, policy, episodes: int, key, start=None) -> dict[str, np.ndarray]:
    """``episodes`` greedy episodes (one per batched env) -> per-episode metric arrays; ``start``: ``(obs,
    state)`` of the ``episodes`` envs to begin from instead of fresh resets."""
    rollout = jax.jit(lambda key, start: batched_rollout(env, key, episodes, env.max_steps, policy, start))
    return first_episodes(env, rollout(key, start)[1])


def summarize(values: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    return {k: {"mean": float(np.mean(v)), "std": float(np.std(v))} for k, v in values.items()}


def evaluate_run(run, episodes: int = 100, checkpoint: str = DEFAULT_CHECKPOINT, seed: int = 0, progress: bool = False,
                 seed_selection: str = "all", env_overrides: dict | None = None) -> dict:
    """Table II metrics of every seed of run folder ``run`` and pooled over seeds, or with
    ``seed_selection="best"`` of the one seed :meth:`Run.best_seed` picks (the paper's protocol).

    The policy is evaluated in the loop it trained in (``pooled``, ``per_seed``) and, when that loop's
    ``control_period`` is not 1, also in the loop a bundle deploys (``deployed``:
    :func:`~marbler_jax.deploy.bundle.deployment_settings`, today's robots; the same start states): MARBLER's sim-vs-real
    comparison as training loop vs deployment loop, in simulation. ``env_overrides`` (e.g.
    ``{"protocol": "marbler"}``) evaluate in another env than the one the run trained in."""
    if seed_selection not in ("all", "best"):
        raise ValueError(f"seed_selection must be 'all' or 'best', got {seed_selection!r}")

    opened = Run.open(run)
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = opened.config
    env = opened.env(**(env_overrides or {}))
    greedy = registry.get(opened.algo).greedy_policy
    cfg = opened.algorithm_config()
    params = opened.params(checkpoint)
    n_seeds = jax.tree_util.tree_leaves(params)[0].shape[0]
    seeds = [opened.best_seed()[0]] if seed_selection == "best" else list(range(n_seeds))
    loops = {"trained": env}
    if env.config.control_period != ROBOTS_CONTROL_PERIOD:
        loops["deployed"] = opened.env(**deployment_settings())
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
                  control_period=env.config.control_period, protocol=env.config.protocol,
                  pooled=summaries["trained"], per_seed=per_seed["trained"],
                  paper=PAPER_TABLE2.get(config["scenario"], {}).get(config["algo"]))
    if "deployed" in loops:
        result["deployed"] = dict(control_period=ROBOTS_CONTROL_PERIOD, pooled=summaries["deployed"],
                                  per_seed=per_seed["deployed"])
    return result


def open_policy(folder, env_overrides: dict | None = None):
    """``(env, policy)`` of the numpy policy folder ``folder`` (exported, or imported with ``marbler-jax
    import``): its scenario with the env settings its spec records (``env``) and ``env_overrides`` on top
    (e.g. ``{"protocol": "robots"}``), checked to fit the policy."""
    import marbler_jax
    from marbler_jax.numpy_policy import load_policy
    from marbler_jax.scenarios.base import merge_settings

    policy = load_policy(folder)
    spec = policy.spec
    if "scenario" not in spec:
        raise ValueError(f"the policy in {folder} names no scenario in its spec")
    settings = merge_settings(spec.get("env", {}), env_overrides or {})
    env = marbler_jax.make(spec["scenario"], **settings)
    if (env.num_agents, env.obs_dim, env.num_actions) != (policy.num_agents, policy.obs_dim, spec["num_actions"]):
        raise ValueError(f"the policy in {folder} is for {policy.num_agents} robots with {policy.obs_dim} observation "
                         f"features and {spec['num_actions']} actions; {env.name} with {settings} has "
                         f"{env.num_agents}, {env.obs_dim} and {env.num_actions}")
    return env, policy


def evaluate_policy(folder, episodes: int = 100, seed: int = 0, env_overrides: dict | None = None,
                    per_episode: bool = False, marbler_starts: list[dict] | None = None) -> dict:
    """Table II metrics of the numpy policy folder ``folder`` acting greedily in ``episodes`` batched
    episodes (env as :func:`open_policy` builds it). The policy's forward pass runs in JAX;
    ``per_episode`` keeps every episode's metrics (``episodes_metrics``). ``marbler_starts``: the episodes
    begin at these MARBLER starts (:mod:`marbler_jax_rl.marbler_starts`), one each, instead of fresh resets."""
    from marbler_jax.rollout import numpy_policy_greedy

    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    env, policy = open_policy(folder, env_overrides)
    start = None
    if marbler_starts is not None:
        from .marbler_starts import batched_starts, marbler_class

        if len(marbler_starts) != episodes:
            raise ValueError(f"episodes = {episodes} must equal the number of MARBLER starts, {len(marbler_starts)}")
        start = batched_starts(env, marbler_class(env.name), marbler_starts)
    values = greedy_episodes(env, numpy_policy_greedy(policy), episodes, jax.random.PRNGKey(seed), start)
    result = dict(scenario=env.name, algo=policy.spec.get("algo"), policy=str(folder), env=policy.spec.get("env", {}),
                  env_overrides=env_overrides or {}, episodes=episodes, seed=seed,
                  control_period=env.config.control_period, protocol=env.config.protocol, pooled=summarize(values),
                  paper=PAPER_TABLE2.get(env.name, {}).get(policy.spec.get("algo")))
    if per_episode:
        result["episodes_metrics"] = {k: v.tolist() for k, v in values.items()}
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


__all__ = ["evaluate_run", "evaluate_policy", "open_policy", "markdown_table", "greedy_episodes", "first_episodes", "PAPER_TABLE2"]
