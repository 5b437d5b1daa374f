"""``marbler-jax report``: a benchmark's results as tables, sample-efficiency curves and probabilities of
improvement.

Statistics follow Agarwal et al. 2021 ("Deep RL at the edge of the statistical precipice") through
``rliable``: a run's score is its mean over the absolute metric's episodes (its best checkpoint, fresh
episodes); a cell reports the interquartile mean (IQM) of its runs with a 95 % stratified-bootstrap
confidence interval. Beside it stands the MARBLER paper's protocol -- the model of the seed with the
best greedy test return during training, mean and std over its episodes -- and the paper's own value
(Table II, simulation). Curves show the IQM (and its CI) of the runs' mean test reward against env
steps; the probability of improvement ``P(X > Y)`` compares two algorithms' runs on one scenario.
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import hashlib
import json
import os
import warnings
from importlib import metadata
from pathlib import Path

import numpy as np

from .benchmark import (ABSOLUTE, ENV_NAME, JAXROBOTARIUM_SCENARIOS, PAPER_ALGOS, PAPER_SCENARIOS, UNRECORDED_DEVICE,
                        cell_digest, load_results)
from .checkpoints import atomic_write, read_json
from .evaluate import PAPER_TABLE2
from .recipes import RECIPES, settings_digest
from marbler_jax.scenarios.base import PROTOCOLS, merge_settings

# Table order and direction: True where higher is better.
METRICS = {"reward": True, "steps": False, "prey_left": False, "material_left": False, "landmarks_left": False,
           "resources_left": False, "deliveries": True, "success": True, "collisions": False, "out_of_bounds": False}
# What is left of a scenario's task at an episode's end (a count); an episode succeeds where none is.
TASK_LEFT = ("prey_left", "material_left", "landmarks_left", "resources_left")
TITLES = {"reward": "Reward (team episode return)", "steps": "Steps (episode length; the limit after a violation)",
          "prey_left": "Prey left (Predator Capture Prey)", "material_left": "Material left (Material Transport)",
          "landmarks_left": "Landmarks left (Discovery)", "resources_left": "Resources left (Foraging)",
          "deliveries": "Deliveries (RWARE)",
          "success": "Success (% of episodes that end with no prey, material, landmarks or resources left)",
          "collisions": "Collisions (% of episodes)", "out_of_bounds": "Out of bounds (% of episodes)"}
VIOLATION_LIMIT = 1.0        # % of episodes: the benchmark's bound for collisions and out of bounds
ALGO_ORDER = PAPER_ALGOS
SCENARIO_ORDER = PAPER_SCENARIOS + JAXROBOTARIUM_SCENARIOS      # MARBLER's Table II first


def _rliable():
    try:
        from rliable import library as rly
        from rliable import metrics
    except ImportError as err:
        raise ValueError(f"marbler-jax report needs rliable ({err}); install it with "
                         "pip install 'marbler-jax[benchmark]'") from None
    return rly, metrics


# The bootstrap results of the report being written, by input (see bootstrap_cache); None outside it.
_CACHE: contextvars.ContextVar[dict | None] = contextvars.ContextVar("bootstrap_cache", default=None)
CACHE_FILE = ".report-cache.json"


@contextlib.contextmanager
def bootstrap_cache(path: Path):
    """Within it, :func:`_bootstrap` reuses the results kept in ``path`` for the same statistic of the same
    scores (the bootstrap is seeded, so a result depends on nothing else), and ``path`` keeps those used.
    A report after a new cell then bootstraps only what that cell changed; an unreadable file is ignored."""
    try:
        kept = json.loads(path.read_text()) if path.exists() else {}
    except (OSError, json.JSONDecodeError):
        kept = {}
    kept = kept if isinstance(kept, dict) else {}
    used: dict = {}
    token = _CACHE.set({"kept": kept, "used": used})
    try:
        yield
    except BaseException:
        atomic_write(path, json.dumps({**kept, **used}))      # an interrupted report loses nothing computed
        raise
    else:
        atomic_write(path, json.dumps(used))
    finally:
        _CACHE.reset(token)


@functools.cache
def _statistics_versions() -> tuple[str, str]:
    """The versions of the libraries that compute the bootstraps (part of a cached result's key)."""
    return metadata.version("rliable"), metadata.version("arch")


def _cache_key(statistic: str, score_dict: dict, reps: int, seed: int) -> str:
    digest = hashlib.sha256(json.dumps([statistic, reps, seed, *_statistics_versions()]).encode())
    for name in sorted(score_dict):
        arrays = score_dict[name] if isinstance(score_dict[name], list) else [score_dict[name]]
        for array in arrays:
            array = np.ascontiguousarray(array, np.float64)
            digest.update(f"{name}{array.shape}".encode() + array.tobytes())
    return digest.hexdigest()


def _bootstrap(score_dict: dict, func, reps: int, seed: int = 0, statistic: str | None = None):
    """rliable's ``get_interval_estimates`` (95 % percentile CIs), reproducible: its stratified bootstrap
    draws run indices from numpy's global generator whatever ``random_state`` says, so that generator is
    seeded for the call and restored after it. ``statistic`` names what ``func`` computes; with it, a result
    is taken from (and kept in) the :func:`bootstrap_cache` in force."""
    cache = _CACHE.get()
    key = _cache_key(statistic, score_dict, reps, seed) if cache is not None and statistic else None
    if key is not None and (key in cache["used"] or key in cache["kept"]):
        point, interval = cache["used"].setdefault(key, cache["kept"].get(key))
        return ({k: np.asarray(v) for k, v in point.items()}, {k: np.asarray(v) for k, v in interval.items()})
    rly, _ = _rliable()
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():      # arch deprecates the RandomState that rliable hands it
            warnings.simplefilter("ignore", FutureWarning)
            point, interval = rly.get_interval_estimates(score_dict, func, reps=reps,
                                                         random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(saved)
    if key is not None:
        cache["used"][key] = [{k: np.asarray(v).tolist() for k, v in point.items()},
                              {k: np.asarray(v).tolist() for k, v in interval.items()}]
    return point, interval


def episode_values(entry: dict, metric: str) -> np.ndarray | None:
    """``metric`` of every episode in ``entry`` (a run's ``absolute_metrics`` or one test's), None where
    the scenario has no such metric. ``"success"`` is derived: 100 where nothing of the task is left
    (:data:`TASK_LEFT`), else 0."""
    if metric == "success":
        left = next((key for key in TASK_LEFT if key in entry), None)
        return None if left is None else 100.0 * (np.asarray(entry[left]) == 0)
    return np.asarray(entry[metric]) if metric in entry else None


def run_scores(runs: dict, metric: str) -> np.ndarray:
    """Each run's mean of ``metric`` over its absolute-metric episodes, ``[runs]``."""
    return np.array([np.mean(episode_values(runs[name][ABSOLUTE], metric)) for name in sorted(runs, key=_run_index)])


def _run_index(name: str) -> int:
    return int(name.rsplit("_", 1)[1])


def iqm_ci(scores: np.ndarray, reps: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """``(IQM, low, high)`` of ``scores [runs]`` with a 95 % bootstrap CI over runs (rliable)."""
    _, metrics = _rliable()
    point, interval = _bootstrap({"x": np.asarray(scores, float)[:, None]},
                                 lambda x: np.array([metrics.aggregate_iqm(x)]), reps, seed, "iqm")
    return float(point["x"][0]), float(interval["x"][0, 0]), float(interval["x"][1, 0])


def best_seed_run(runs: dict) -> str:
    """The run whose best greedy test return during training was highest (the paper's pick)."""
    return max(sorted(runs, key=_run_index), key=lambda name: runs[name][ABSOLUTE]["best_test_return"][0])


def probability_of_improvement(x: np.ndarray, y: np.ndarray, reps: int = 2000,
                               seed: int = 0) -> tuple[float, float, float]:
    """``(P(X > Y), low, high)`` for run scores ``x [n]``, ``y [m]`` (ties count one half), 95 % CI."""
    _, metrics = _rliable()
    point, interval = _bootstrap({"xy": [np.asarray(x, float)[:, None], np.asarray(y, float)[:, None]]},
                                 lambda a, b: np.array([metrics.probability_of_improvement(a, b)]), reps, seed,
                                 "probability_of_improvement")
    return float(point["xy"][0]), float(interval["xy"][0, 0]), float(interval["xy"][1, 0])


def _ordered(names, order):
    return sorted(names, key=lambda n: (order.index(n) if n in order else len(order), n))


def _fmt(x: float) -> str:
    return f"{x:.2f}" if abs(x) < 1000 else f"{x:,.0f}"


def reached(metric: str, ours: float, paper: float | None) -> bool | None:
    """Whether ``ours`` is at least as good as the paper's value (violations: at most 1 % of episodes)."""
    if metric in ("collisions", "out_of_bounds"):
        return ours <= VIOLATION_LIMIT
    if paper is None:
        return None
    return ours >= paper if METRICS[metric] else ours <= paper


def recipe_digests(scenario: str, algo: str) -> set[str]:
    """Settings digests of ``algo``'s current recipe on ``scenario``: as it is, and in each protocol
    (``benchmark --protocol``)."""
    env, hp, steps = RECIPES[algo].settings(scenario)
    return {settings_digest(merge_settings(env, extra), hp, steps)
            for extra in ({}, *({"protocol": name} for name in PROTOCOLS))}


def off_recipe(scenario: str, algo: str, runs: dict) -> bool:
    """Whether a cell was trained with other settings than ``algo``'s current recipe, in any protocol (an
    earlier recipe, a ``--total-steps`` budget, a ``--set`` env setting, or a results file that does not say)."""
    return algo not in RECIPES or cell_digest(runs) not in recipe_digests(scenario, algo)


OFF_RECIPE_MARK = "†"
SCENARIO_SETTING_MARK = "‡"


def _settings_text(settings: dict) -> str:
    return ", ".join(f"`{k}={v}`" for k, v in settings.items())


def cell_mark(scenario: str, algo: str, runs: dict) -> str:
    """:data:`OFF_RECIPE_MARK` for a cell made off the recipe, :data:`SCENARIO_SETTING_MARK` for one made with
    the recipe's own settings for that scenario (``Recipe.scenario_hp``), else nothing."""
    if off_recipe(scenario, algo, runs):
        return OFF_RECIPE_MARK
    return SCENARIO_SETTING_MARK if scenario in RECIPES[algo].scenario_hp else ""


def paper_model_scores(folder: Path | None, metric: str) -> dict[tuple[str, str], str]:
    """``{(scenario, algo): "mean ± half-width of its 95 % CI"}`` of ``metric`` for MARBLER's own paper models,
    from the ``evaluate --json`` files ``<scenario>-<algo>.json`` in ``folder`` (``scripts/paper_models.py
    evaluate`` writes them); ``{}`` without a folder."""
    scores = {}
    for path in sorted(Path(folder).glob("*-*.json")) if folder else ():
        data = read_json(path)
        values = data.get("episodes_metrics", {}).get(metric)
        if values:
            mean, half = mean_ci(values)
            scores[(data["scenario"], data["algo"])] = f"{_fmt(mean)} ± {_fmt(half)}"
    return scores


def mean_ci(values) -> tuple[float, float]:
    """Mean of per-episode ``values`` and the half-width of its 95 % confidence interval (normal
    approximation; 0 for a single value)."""
    values = np.asarray(values, float)
    half = 1.96 * values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else 0.0
    return float(values.mean()), float(half)


def metric_table(results: dict, metric: str, reps: int, paper_models: Path | None = None) -> str | None:
    """One metric's Markdown table over every cell that has it; None where no cell does. With
    ``paper_models`` (:func:`paper_model_scores`'s folder) a column holds the paper's own model's score."""
    tasks = results.get(ENV_NAME, {})
    models = paper_model_scores(paper_models, metric)
    rows = []
    for scenario in _ordered(tasks, SCENARIO_ORDER):
        for algo in _ordered(tasks[scenario], ALGO_ORDER):
            runs = tasks[scenario][algo]
            if episode_values(next(iter(runs.values()))[ABSOLUTE], metric) is None:
                continue
            scores = run_scores(runs, metric)
            iqm, low, high = iqm_ci(scores, reps)
            best = episode_values(runs[best_seed_run(runs)][ABSOLUTE], metric)
            best_mean = float(np.mean(best))
            paper = PAPER_TABLE2.get(scenario, {}).get(algo, {}).get(metric)
            ok = reached(metric, best_mean, paper[0] if paper else None)
            steps = runs["run_0"][ABSOLUTE]["env_steps"][0]
            mark = cell_mark(scenario, algo, runs)
            rows.append(f"| {scenario} | {algo}{mark} | {len(runs)} | {steps / 1e6:.1f}M | {_fmt(iqm)} [{_fmt(low)}, {_fmt(high)}] "
                        f"| {_fmt(best_mean)} ± {_fmt(float(np.std(best)))} | "
                        f"{f'{paper[0]:g} ± {paper[1]:g}' if paper else '—'} | "
                        + (f"{models.get((scenario, algo), '—')} | " if paper_models else "")
                        + f"{'—' if ok is None else ('yes' if ok else '**no**')} |")
    if not rows:
        return None
    model = " paper's model, here (mean ± 95 % CI) |" if paper_models else ""
    head = [f"### {TITLES[metric]}", "",
            f"| scenario | algorithm | seeds | env steps / seed | IQM [95 % CI] | best seed (mean ± std) | paper |{model} "
            "reached |", "|---|---|---|---|---|---|---|" + "---|" * bool(paper_models) + "---|"]
    return "\n".join(head + rows) + "\n"


def shortfall_table(results: dict) -> str | None:
    """The evidence for every cell whose best seed misses the paper on some metric: what it misses, each
    seed's score, each seed's best greedy test during training and when it came, and each seed's
    :func:`late_gain`; None where every cell reaches it."""
    tasks = results.get(ENV_NAME, {})
    rows = []
    for scenario in _ordered(tasks, SCENARIO_ORDER):
        for algo in _ordered(tasks[scenario], ALGO_ORDER):
            runs = tasks[scenario][algo]
            best = runs[best_seed_run(runs)][ABSOLUTE]
            missed = []
            for metric, higher in METRICS.items():
                paper = PAPER_TABLE2.get(scenario, {}).get(algo, {}).get(metric)
                if metric in best and reached(metric, float(np.mean(best[metric])), paper[0] if paper else None) is False:
                    limit = paper[0] if paper else VIOLATION_LIMIT
                    missed.append(f"{metric} {_fmt(float(np.mean(best[metric])))} {'<' if higher else '>'} {limit:g}")
            if not missed:
                continue
            steps, tests = curve_points(runs)
            peaks = tests.argmax(axis=1)
            gains = ", ".join("—" if np.isnan(g) else f"{g:+.2f}" for g in late_gain(steps, tests))
            peak_text = ", ".join(f"{_fmt(float(tests[k, i]))} ({steps[i] / 1e6:.1f}M)" for k, i in enumerate(peaks))
            scores = ", ".join(_fmt(float(x)) for x in run_scores(runs, "reward"))
            mark = cell_mark(scenario, algo, runs)
            rows.append(f"| {scenario} | {algo}{mark} | {'; '.join(missed)} | {scores} | {peak_text} | {gains} |")
    if not rows:
        return None
    head = ["### Cells short of the paper", "",
            "What each cell's best seed misses, each seed's score (reward), each seed's best greedy test during "
            "training (at env steps), and each seed's gain in the last quarter: its mean greedy test return over "
            "the last quarter of training minus that over the quarter before (near 0: the seed has levelled off).",
            "", "| scenario | algorithm | short on | seeds' scores | best test during training, per seed | "
            "gain in the last quarter, per seed |", "|---|---|---|---|---|---|"]
    return "\n".join(head + rows) + "\n"


def improvement_table(runs_by_algo: dict, reps: int) -> str:
    """Markdown matrix of ``P(row > column)`` of the runs' absolute reward, with 95 % CIs."""
    algos = _ordered(runs_by_algo, ALGO_ORDER)
    scores = {a: run_scores(runs_by_algo[a], "reward") for a in algos}
    lines = ["| P(row > column) | " + " | ".join(algos) + " |", "|---|" + "---|" * len(algos)]
    for x in algos:
        cells = []
        for y in algos:
            if x == y:
                cells.append("—")
                continue
            p, low, high = probability_of_improvement(scores[x], scores[y], reps)
            cells.append(f"{p:.2f} [{low:.2f}, {high:.2f}]")
        lines.append(f"| {x} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def late_gain(steps: np.ndarray, tests: np.ndarray) -> np.ndarray:
    """``[runs]``: each run's mean test reward over the last quarter of training (``steps`` in
    ``(0.75, 1] x steps[-1]``) minus its mean over the quarter before; NaN where a quarter has no test."""
    last, before = steps > 0.75 * steps[-1], (steps > 0.5 * steps[-1]) & (steps <= 0.75 * steps[-1])
    if not last.any() or not before.any():
        return np.full(len(tests), np.nan)
    return tests[:, last].mean(axis=1) - tests[:, before].mean(axis=1)


def curve_points(runs: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(env_steps [P], scores [runs, P])``: each run's mean test reward at every test point."""
    names = sorted(runs, key=_run_index)
    steps_keys = sorted((k for k in runs[names[0]] if k.startswith("step_")), key=_run_index)
    steps = np.array([runs[names[0]][k]["step_count"] for k in steps_keys], float)
    scores = np.array([[np.mean(runs[n][k]["reward"]) for k in steps_keys] for n in names])
    return steps, scores


def curve_title(scenario: str) -> str:
    """The curve plot's title: the scenario, and how the paper's reward is drawn where the paper has one."""
    return f"{scenario} (dotted: the paper's reward, same colour)" if scenario in PAPER_TABLE2 else scenario


def plot_curves(scenario: str, runs_by_algo: dict, png: Path, reps: int) -> None:
    """IQM (95 % CI band) of the runs' test reward against env steps, one line per algorithm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, metrics = _rliable()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for algo in _ordered(runs_by_algo, ALGO_ORDER):
        steps, scores = curve_points(runs_by_algo[algo])
        point, interval = _bootstrap(
            {algo: scores[:, None, :]},
            lambda x: np.array([metrics.aggregate_iqm(x[..., j]) for j in range(x.shape[-1])]), reps,
            statistic="iqm_per_point")
        line, = ax.plot(steps, point[algo], lw=1.6, label=f"{algo} ({scores.shape[0]} seeds)")
        ax.fill_between(steps, interval[algo][0], interval[algo][1], color=line.get_color(), alpha=0.2)
        paper = PAPER_TABLE2.get(scenario, {}).get(algo)
        if paper:
            ax.axhline(paper["reward"][0], ls=":", lw=1.2, color=line.get_color())
    ax.set_xlabel("env steps per seed")
    ax.set_ylabel("greedy test reward (IQM, 95 % CI)")
    ax.set_title(curve_title(scenario))
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    tmp = png.with_name(png.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(png)


def training_time(tasks: dict) -> str:
    """The cells' summed training hours per device that trained them (a cell's ``device``; cells written
    before the results recorded it count as ``device not recorded``), e.g. ``"15.95 h on cpu (13 cells)"``."""
    hours, counts = {}, {}
    for algos in tasks.values():
        for runs in algos.values():
            first = next(iter(runs.values()))[ABSOLUTE]
            device = first.get("device", [UNRECORDED_DEVICE])[0]
            hours[device] = hours.get(device, 0.0) + first.get("train_seconds", [0.0])[0] / 3600
            counts[device] = counts.get(device, 0) + 1
    return ", ".join(f"{hours[d]:.2f} h on {d} ({counts[d]} cell{'s' if counts[d] > 1 else ''})"
                     for d in sorted(hours, key=lambda d: (-counts[d], d)))


def time_table(results: dict) -> str:
    """Each cell's env steps, the device(s) that trained it, its training time (updates only) and wall time
    (everything its processes did or waited for, over every invocation), and the sums over the cells (and
    over the paper's cells alone when the results also hold others)."""
    tasks = results.get(ENV_NAME, {})
    rows, times = [], []                          # times: (in the paper's table, train s, wall s or None)
    for scenario in _ordered(tasks, SCENARIO_ORDER):
        for algo in _ordered(tasks[scenario], ALGO_ORDER):
            runs = tasks[scenario][algo]
            first = next(iter(runs.values()))[ABSOLUTE]
            train = first.get("train_seconds", [0.0])[0]
            wall = first.get("wall_seconds", [None])[0]
            times.append((algo in PAPER_TABLE2.get(scenario, {}), train, wall))
            mark = cell_mark(scenario, algo, runs)
            rows.append(f"| {scenario} | {algo}{mark} | {first['env_steps'][0] / 1e6:.1f}M | "
                        f"{first.get('device', [UNRECORDED_DEVICE])[0]} | {train / 60:.1f} min | "
                        + (f"{wall / 60:.1f} min |" if wall is not None else "— |"))

    def total(label: str, cells: list) -> str:
        walls = [w for _, _, w in cells if w is not None]
        return (f"| {label} {len(cells)} cells | | | | {sum(t for _, t, _ in cells) / 3600:.2f} h | "
                f"{sum(walls) / 3600:.2f} h"
                + (f" ({len(walls)} of {len(cells)} cells recorded)" if len(walls) < len(cells) else "") + " |")

    paper = [cell for cell in times if cell[0]]
    if 0 < len(paper) < len(times):
        rows.append(total("the paper's", paper))
    rows.append(total("all", times))
    head = ["### Time per cell", "",
            "*Training*: the updates alone; *wall time*: everything the cell's processes did or waited for "
            "(compilation, greedy tests, checkpoints, the final evaluation, other processes on the same CPU), "
            "summed over the invocations that trained it.", "",
            "| scenario | algorithm | env steps / seed | device | training | wall time |",
            "|---|---|---|---|---|---|"]
    return "\n".join(head + rows) + "\n"


SUMMARY_START = "<!-- reward summary: written by marbler-jax report --readme; edit there, not here -->"
SUMMARY_END = "<!-- end of reward summary -->"


def summary_table(results: dict, reps: int = 2000) -> str:
    """The reward of MARBLER's Table II in one table (scenarios x the paper's algorithms): per cell our best
    seed (bold where it reaches the paper; marked as :func:`cell_mark` says), the IQM over
    seeds with its 95 % CI, and the paper's value; ``—`` for a cell not run yet. Negative numbers get a
    typographic minus."""
    def num(x: float) -> str:
        return _fmt(x).replace("-", "\u2212")

    tasks = results.get(ENV_NAME, {})
    algos = [a for a in ALGO_ORDER if any(a in paper for paper in PAPER_TABLE2.values())]
    lines = ["| reward: ours, best seed (IQM [95 % CI]) / paper | " + " | ".join(a.upper() for a in algos) + " |",
             "|---|" + "---|" * len(algos)]
    for scenario in PAPER_SCENARIOS:
        cells = []
        for algo in algos:
            paper = PAPER_TABLE2[scenario][algo]["reward"][0]
            runs = tasks.get(scenario, {}).get(algo)
            if runs is None:
                cells.append(f"— / {num(paper)}")
                continue
            best = float(np.mean(episode_values(runs[best_seed_run(runs)][ABSOLUTE], "reward")))
            iqm, low, high = iqm_ci(run_scores(runs, "reward"), reps)
            ours = f"**{num(best)}**" if reached("reward", best, paper) else num(best)
            mark = cell_mark(scenario, algo, runs)
            cells.append(f"{ours}{mark} ({num(iqm)} [{num(low)}, {num(high)}]) / {num(paper)}")
        lines.append(f"| {scenario.replace('_', ' ').title()} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def replace_summary(text: str, table: str, name: str = "README.md") -> str:
    """``text`` with the block between :data:`SUMMARY_START` and :data:`SUMMARY_END` replaced by ``table``."""
    start, end = text.find(SUMMARY_START), text.find(SUMMARY_END)
    if start < 0 or end < start:
        raise ValueError(f"{name} has no reward summary to replace: put the lines {SUMMARY_START!r} and "
                         f"{SUMMARY_END!r} where the table goes")
    return text[:start + len(SUMMARY_START)] + "\n" + table + text[end:]


BLOCK = "<!-- {} {}: generated by {} -->"


def _block_marks(name: str, command: str) -> tuple[str, str]:
    return BLOCK.format("begin", name, command), BLOCK.format("end", name, command)


def replace_block(text: str, name: str, command: str, content: str) -> str:
    """``text`` with its block ``name`` (written by ``command``) replaced by ``content``, or with the block
    appended where it has none. Blocks are how other commands add sections to a page ``report`` writes:
    ``report`` keeps them (:func:`kept_blocks`)."""
    start_mark, end_mark = _block_marks(name, command)
    block = f"{start_mark}\n{content.rstrip()}\n{end_mark}"
    start, end = text.find(start_mark), text.find(end_mark)
    if start < 0 or end < start:
        return text.rstrip() + "\n\n" + block + "\n"
    return text[:start] + block + text[end + len(end_mark):]


def kept_blocks(text: str) -> str:
    """Every block of ``text`` that :func:`replace_block` wrote, in order, as one string."""
    import re

    pattern = re.compile(r"<!-- begin (\S+): generated by (.+?) -->\n.*?<!-- end \1: generated by \2 -->", re.S)
    return "\n\n".join(m.group(0) for m in pattern.finditer(text))


def _scenario_setting_notes(tasks: dict) -> list[str]:
    """One ‡ note per scenario and reason: algorithms whose recipes share the settings and the why share a line."""
    notes: dict[tuple[str, str, str], list[str]] = {}
    for s in _ordered(tasks, SCENARIO_ORDER):
        for a in _ordered(tasks[s], ALGO_ORDER):
            if cell_mark(s, a, tasks[s][a]) == SCENARIO_SETTING_MARK:
                key = (s, _settings_text(RECIPES[a].scenario_hp[s]), RECIPES[a].why[s])
                notes.setdefault(key, []).append(a)
    lines = []
    for (s, settings, why), algos in notes.items():
        names = algos[0] if len(algos) == 1 else ", ".join(algos[:-1]) + " and " + algos[-1]
        lines += [f"{SCENARIO_SETTING_MARK} {names} on {s}: the recipe's own settings for this scenario "
                  f"({settings}): {why}", ""]
    return lines


def report_markdown(results: dict, reps: int = 2000, paper_models: Path | None = None) -> str:
    """The whole report as Markdown, its curves linked as ``curves_<scenario>.png`` beside it (``paper_models``:
    see :func:`metric_table`)."""
    tasks = results.get(ENV_NAME, {})
    if not tasks:
        raise ValueError("the results hold no cell yet; run marbler-jax benchmark first")
    cells = [(s, a) for s in tasks for a in tasks[s]]
    parts = [f"{len(cells)} cell(s); a run's score is its best checkpoint's mean over "
             f"{len(next(iter(tasks[cells[0][0]][cells[0][1]].values()))[ABSOLUTE]['reward'])} fresh greedy episodes. "
             "IQM over seeds with a 95 % stratified-bootstrap CI (rliable); *best seed* is the paper's protocol "
             "(the seed with the best greedy test return during training, mean ± std over its episodes); "
             "*reached*: best seed at least as good as the paper (collisions and out of bounds: at most "
             f"{VIOLATION_LIMIT:g} % of episodes). Training time (updates only, summed over cells): "
             f"{training_time(tasks)}.", ""]
    for metric in METRICS:
        table = metric_table(results, metric, reps, paper_models)
        if table:
            parts += [table, ""]
    if any(off_recipe(s, a, tasks[s][a]) for s, a in cells):
        parts += [f"{OFF_RECIPE_MARK} trained with other settings than the algorithm's current recipe (an earlier "
                  "recipe, another step budget or another env setting); rerun the cell to compare it with the recipe.", ""]
    parts += _scenario_setting_notes(tasks)
    shortfalls = shortfall_table(results)
    if shortfalls:
        parts += [shortfalls, ""]
    missing = [f"{a} on {s}" for s in PAPER_SCENARIOS for a in PAPER_ALGOS if a not in tasks.get(s, {})]
    if missing:
        parts += ["### Cells not in the results yet", "", ", ".join(missing) + ".", ""]
    parts += [time_table(results), ""]
    parts.append("### Sample efficiency and probability of improvement\n")
    for scenario in _ordered(tasks, SCENARIO_ORDER):
        parts += [f"#### {scenario}", "", f"![{scenario}](curves_{scenario}.png)", ""]
        if len(tasks[scenario]) > 1:
            parts += [improvement_table(tasks[scenario], reps), ""]
    return "\n".join(parts)


RESULTS_HEAD = """# Results

MARBLER's Table II (simulation) reproduced with `marbler-jax benchmark`: every cell trained with its
algorithm's recipe (`algorithms/recipes.py`; † marks a cell made with other settings, ‡ one made with
its recipe's own settings for that scenario, with the reason below the tables), five seeds in one program, each seed tested greedily at 20 points of training and then its best checkpoint evaluated
over fresh episodes. This file is generated:

```bash
marbler-jax benchmark --devices 2 --out results/marbler-table2     # resumable; cells are independent
marbler-jax benchmark --scenarios discovery foraging rware --devices 2 --out results/marbler-table2
marbler-jax report results/marbler-table2 --results-md RESULTS.md --readme README.md
```

The second command adds JaxRobotarium's three scenarios (rows without paper values). *Success* is the
share of episodes that end with nothing of the task left (prey, material, landmarks or resources), the
measure JaxRobotarium reports.

The results file (`results/marbler-table2/results*.json`, marl-eval's layout) holds every test episode of
every seed; the wall time of each cell is in its runs' `absolute_metrics`.

"""


def write_report(folder: str | Path, out: str | Path | None = None, reps: int = 2000,
                 results_md: str | Path | None = None, readme: str | Path | None = None,
                 progress: bool = False, paper_models: str | Path | None = None) -> list[Path]:
    """``report.md`` and ``curves_<scenario>.png`` of the benchmark in ``folder`` (into ``out``), with
    ``results_md`` the same report as the project's results page (image links relative to it), and with
    ``readme`` that file's reward summary (:func:`summary_table`, between its markers) rewritten.
    ``progress``: a bar over the scenarios' curves, then the tables (the bootstraps take minutes for a
    whole table, seconds once ``.report-cache.json`` holds them). ``paper_models``: a folder of the paper's own
    models' scores to show beside the cells (:func:`paper_model_scores`)."""
    if not isinstance(reps, int) or reps < 10:
        raise ValueError(f"reps must be an integer >= 10, got {reps!r}")
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder} is not a benchmark folder")
    if readme is not None:
        readme = Path(readme)
        if not readme.is_file():
            raise ValueError(f"--readme {readme} is not a file")
        replace_summary(readme.read_text(), "", readme.name)     # no markers: refused before any work
    if paper_models is not None and not Path(paper_models).is_dir():
        raise ValueError(f"--paper-models {paper_models} is not a folder")
    results = load_results(folder)
    out = Path(out) if out else folder
    out.mkdir(parents=True, exist_ok=True)
    written = []
    from tqdm.auto import tqdm

    scenarios = results.get(ENV_NAME, {})
    with bootstrap_cache(out / CACHE_FILE), tqdm(total=len(scenarios) + 1, unit="part", disable=not progress,
                                                 dynamic_ncols=True) as bar:
        for scenario, runs_by_algo in scenarios.items():
            bar.set_description(f"curves of {scenario}")
            png = out / f"curves_{scenario}.png"
            plot_curves(scenario, runs_by_algo, png, reps)
            written.append(png)
            bar.update()
        bar.set_description("tables")
        report = out / "report.md"
        body = report_markdown(results, reps, paper_models and Path(paper_models))   # bootstraps run once for both
        bar.update()
        atomic_write(report, "## MARBLER benchmark\n\n" + body)
        written.insert(0, report)
        if results_md:
            results_md = Path(results_md)
            prefix = Path(os.path.relpath(out.resolve(), results_md.resolve().parent)).as_posix() + "/"
            kept = kept_blocks(results_md.read_text()) if results_md.is_file() else ""
            page = RESULTS_HEAD + body.replace("](curves_", f"]({prefix}curves_")
            atomic_write(results_md, page + (f"\n{kept}\n" if kept else ""))
            written.append(results_md)
        if readme is not None:
            atomic_write(readme, replace_summary(readme.read_text(), summary_table(results, reps), readme.name))
            written.append(readme)
    return written


__all__ = ["write_report", "report_markdown", "iqm_ci", "probability_of_improvement", "run_scores",
           "best_seed_run", "metric_table", "shortfall_table", "summary_table", "time_table", "replace_summary",
           "replace_block", "kept_blocks", "curve_points", "reached", "off_recipe", "cell_mark", "training_time"]
