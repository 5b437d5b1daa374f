"""``marbler-jax benchmark``: MARBLER's Table II grid trained with the recipes, several seeds per cell.

Each cell (scenario x algorithm) trains its seeds in one program (vmapped; with ``devices > 1`` spread
over the process's local devices, see :func:`run_benchmark`) with the algorithm's recipe
(:mod:`marbler_jax_rl.recipes`) into ``OUT/runs/<scenario>/<algo>``, tests every seed greedily at
``eval_points`` evenly spaced points of training (``test_episodes`` episodes each, the same initial
states at every point) and ends with the *absolute metric*: each seed's best checkpoint (by test
return) over ``absolute_factor x test_episodes`` fresh episodes. The cell is then appended to the
results file in marl-eval's layout::

    {"marbler": {scenario: {algo: {"run_<seed>": {
        "step_<i>": {"step_count": env_steps, metric: [per-episode values]},
        "absolute_metrics": {metric: [per-episode values], "best_test_return": [x],
                             "env_steps": [per seed], "train_seconds": [updates' time, all seeds],
                             "wall_seconds": [the cell's wall time, summed over invocations],
                             "device": [the accelerator(s) that trained it, e.g. "cpu" or "NVIDIA H200 + cpu"]}}}}}}

with the metrics of :data:`marbler_jax.rollout.EPISODE_METRICS` and the scenario's own (``prey_left``,
``material_left``, ...). The file is rewritten atomically after every cell. A rerun skips the cells the
file holds and resumes an interrupted cell from its last checkpoint (bit-exactly); :func:`plan_cells` says
beforehand what a run will do with each cell (``marbler-jax benchmark --dry-run``).

Several processes (or hosts) share the grid through JAX's distributed runtime: process ``i`` of ``n``
takes every ``n``-th cell and writes ``results-p<i>.json``; ``marbler-jax report`` merges the files.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

import marbler_jax
from .checkpoints import atomic_write
from . import registry
from .driver import build_config, has_setting, make_tester, train_run
from .run import Run
from .results_file import ABSOLUTE, ENV_NAME, add_cell, load_results, read_results, results_name
from .run_writer import changed_settings, run_config
from .recipes import recipe, settings_digest
from .writer_lock import writer_lock
from marbler_jax.registry import canonical_name
from marbler_jax.scenarios.base import merge_settings

PAPER_ALGOS = ("vdn", "qmix", "qmix_ns", "mappo", "ippo")
PAPER_SCENARIOS = ("predator_capture_prey", "warehouse", "material_transport", "arctic_transport")
DEFAULT_RESULTS = {None: "results/marbler-table2", "robots": "results/marbler-table2",
                   "marbler": "results/marbler-table2-protocol"}
"""The results folder of ``marbler-jax benchmark`` by ``--protocol``: the recipes' table (robots' loop) and
MARBLER's protocol, the like-for-like comparison with the paper."""
# JaxRobotarium's scenarios: benchmark rows without paper values (``--scenarios`` names them)
JAXROBOTARIUM_SCENARIOS = ("discovery", "foraging", "rware")
WALL_FILE = "wall_seconds.json"
UNRECORDED_DEVICE = "device not recorded"


class WallClock:
    """A cell's wall time summed over the invocations that trained it, and the device each ran on, kept in
    ``run/wall_seconds.json`` (``{"invocations": [seconds, ...], "devices": [device kind, ...]}``). The current
    invocation's entry is rewritten after every saved checkpoint, so an interrupted invocation counts up to its
    last checkpoint (the work a resume keeps)."""

    def __init__(self, run: Path, resume: bool, device: str):
        self.path = Path(run) / WALL_FILE
        saved = json.loads(self.path.read_text()) if resume and self.path.exists() else {}
        previous = [float(x) for x in saved.get("invocations", [])]
        devices = saved.get("devices", [])
        devices = devices + [UNRECORDED_DEVICE] * (len(previous) - len(devices))
        self.invocations = previous + [0.0]
        self.devices = devices[:len(previous)] + [device]
        self.start = time.perf_counter()

    def save(self) -> float:
        """Record this invocation's seconds so far; returns the cell's total."""
        self.invocations[-1] = round(time.perf_counter() - self.start, 1)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path, json.dumps({"invocations": self.invocations, "devices": self.devices}))
        return float(sum(self.invocations))

    def device(self) -> str:
        """The devices that trained the cell, in order, each once (``"NVIDIA H200 + cpu"`` for a cell
        resumed on a CPU)."""
        return " + ".join(dict.fromkeys(self.devices))


def cell_settings(chosen, scenario: str, total_steps: int | None = None, env_overrides: dict | None = None,
                  hp_overrides: dict | None = None) -> tuple[dict, dict, int]:
    """``(env_overrides, hyperparameters, steps)`` a cell trains with: recipe ``chosen`` on ``scenario``,
    its step budget replaced by ``total_steps``, ``env_overrides`` on top of its env settings and those of
    ``hp_overrides`` that its algorithm has on top of its hyperparameters, where given."""
    env, hp, steps = chosen.settings(scenario)
    hp.update({k: v for k, v in (hp_overrides or {}).items() if has_setting(chosen.algo, k)})
    return merge_settings(env, env_overrides or {}), hp, int(total_steps or steps)


def check_hp_overrides(hp_overrides: dict, algos) -> None:
    """Refuse a hyperparameter override that no algorithm of ``algos`` has, or that another option sets."""
    for name in hp_overrides:
        if name in ("total_timesteps", "learner_devices"):
            raise ValueError(f"--hp {name}: set it with {'--total-steps' if name == 'total_timesteps' else '--devices'}")
        if not any(has_setting(algo, name) for algo in algos):
            raise ValueError(f"--hp {name}: none of the algorithms {sorted(set(algos))} has this setting")


def cell_digest(runs: dict) -> str | None:
    """The settings digest (:func:`marbler_jax_rl.recipes.settings_digest`) a results cell was made with;
    ``None`` where the file does not say."""
    return next(iter(runs.values()))[ABSOLUTE].get("recipe", [None])[0]


def set_aside(run: Path) -> Path:
    """Rename the run folder ``run`` to the first free ``<name>.set-aside-<k>`` beside it; returns the new path."""
    k = 1
    while run.with_name(f"{run.name}.set-aside-{k}").exists():
        k += 1
    aside = run.with_name(f"{run.name}.set-aside-{k}")
    run.rename(aside)
    return aside


def finished_cells(results: dict) -> set[tuple[str, str]]:
    """``{(scenario, algo)}`` the results hold."""
    return {(task, algo) for task, algos in results.get(ENV_NAME, {}).items() for algo in algos}


def grid(algos, scenarios, process_index: int = 0, process_count: int = 1) -> list[tuple[str, str]]:
    """This process's share of the ``scenarios x algos`` cells (canonical names, every ``process_count``-th)."""
    for algo in algos:
        registry.get(algo)          # an unknown name: one ValueError naming what is available
    cells = [(canonical_name(s), a) for s in scenarios for a in algos]
    if len(set(cells)) != len(cells):
        raise ValueError(f"the grid names a cell twice: {cells}")
    return cells[process_index::process_count]


CELL_STATUSES = ("done", "resume", "restart", "new")
"""What :func:`run_benchmark` does with a cell (:attr:`CellPlan.status`): skip it (the results file holds it
with these settings), resume it from its latest checkpoint, set its run folder aside (other settings) and
train from the start, or train it from the start."""


@dataclasses.dataclass(frozen=True)
class CellPlan:
    """One cell of a benchmark and what :func:`run_benchmark` would do with it.

    ``env_settings``, ``hp`` and ``steps`` (env steps per seed) are what it trains with, ``digest`` their
    :func:`~marbler_jax_rl.recipes.settings_digest`, ``updates`` its number of updates; ``status`` is a key of
    :data:`CELL_STATUSES`; ``checkpoint`` the latest checkpoint's update of a run to resume; ``replaces``: the
    results file holds the cell made with other settings, which this run replaces."""

    scenario: str
    algo: str
    env_settings: dict
    hp: dict
    steps: int
    digest: str
    updates: int
    status: str
    checkpoint: int | None = None
    replaces: bool = False


def check_counts(**counts) -> None:
    """Refuse a count (seeds, episodes, devices, ...) that is not an integer >= 1, by name."""
    for name, value in counts.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def plan_cells(out: str | Path, algos=PAPER_ALGOS, scenarios=PAPER_SCENARIOS, seeds: int = 5,
               total_steps: int | None = None, test_episodes: int = 64, seed: int = 0, process_index: int = 0,
               process_count: int = 1, recipes=None, env_overrides: dict | None = None,
               hp_overrides: dict | None = None) -> list[CellPlan]:
    """This process's cells in ``out`` (arguments as :func:`run_benchmark`'s) and what a run would do with
    each; reads the results file and run folders, writes nothing."""
    recipes = dict(recipes or {})
    check_counts(seeds=seeds, test_episodes=test_episodes)
    if total_steps is not None and total_steps < 1:
        raise ValueError(f"total_steps must be >= 1, got {total_steps}")
    check_hp_overrides(hp_overrides or {}, algos)
    cells = grid(algos, scenarios, process_index, process_count)
    path = Path(out) / results_name(process_index, process_count)
    results = read_results(path)
    held = {cell: cell_digest(results[ENV_NAME][cell[0]][cell[1]]) for cell in finished_cells(results)}
    plans = []
    for scenario, algo in cells:
        env_settings, hp, steps = cell_settings(recipes.get(algo) or recipe(algo), scenario, total_steps,
                                                env_overrides, hp_overrides)
        digest = settings_digest(env_settings, hp, steps)
        env = marbler_jax.make(scenario, **env_settings)
        cfg = build_config(algo, dict(hp, total_timesteps=steps))
        run = Path(out) / "runs" / scenario / algo
        checkpoint = None
        if held.get((scenario, algo)) == digest:
            status = "done"
        elif not Run.holds_run(run):
            status = "new"
        elif changed_settings(run, run_config(scenario, algo, seeds, seed, env, cfg, test_episodes), env):
            status = "restart"
        else:
            checkpoint = Run.open(run).latest_checkpoint()
            status = "new" if checkpoint is None else "resume"
        plans.append(CellPlan(scenario, algo, env_settings, hp, steps, digest,
                              registry.get(algo).make_train(env, cfg).num_updates, status, checkpoint,
                              replaces=status != "done" and (scenario, algo) in held))
    return plans


def remaining_steps(plan: CellPlan, seeds: int) -> int:
    """Env steps (all seeds) ``plan``'s cell has left to train."""
    if plan.status == "done":
        return 0
    done = plan.checkpoint if plan.status == "resume" else 0
    return round(plan.steps * seeds * (plan.updates - done) / plan.updates)


def measured_rates(results: dict, device: str | None = None) -> dict[tuple[str, str], float]:
    """Env steps per second (all seeds, updates only) each finished cell of ``results`` trained at (only the
    cells trained on ``device`` alone, e.g. ``"cpu"``, where given)."""
    rates = {}
    for scenario, algos in results.get(ENV_NAME, {}).items():
        for algo, runs in algos.items():
            first = next(iter(runs.values()), {}).get(ABSOLUTE, {})
            seconds = first.get("train_seconds", [0.0])[0]
            if seconds > 0 and (device is None or first.get("device", [None])[0] == device):
                steps = sum(run.get(ABSOLUTE, {}).get("env_steps", [0])[0] for run in runs.values())
                rates[(scenario, algo)] = steps / seconds
    return rates


def describe_plan(plans: list[CellPlan], seeds: int, where: str, rates: dict | None = None,
                  rates_from: str = "") -> str:
    """``benchmark --dry-run``'s text: one line per cell of ``where`` (the results file) and a summary; with
    ``rates`` (:func:`measured_rates` of the cells' earlier runs, from ``rates_from``) the time each cell and
    the whole plan should take at those rates."""
    rates = rates or {}
    counts = {status: sum(p.status == status for p in plans) for status in CELL_STATUSES}
    lines = [f"{where}: {len(plans)} cell(s), " + ", ".join(f"{n} {s}" for s, n in counts.items() if n)
             + f"; {sum(remaining_steps(p, seeds) for p in plans):,} env steps to train ({seeds} seed(s) per cell)"]
    width = max((len(p.scenario) for p in plans), default=0)
    hours, unmeasured = 0.0, []
    for k, plan in enumerate(plans, 1):
        what = {"done": "done", "new": "new", "restart": "restart (its run folder is set aside)",
                "resume": f"resume from update {plan.checkpoint} of {plan.updates}"}[plan.status]
        if plan.replaces:
            what += "; replaces its cell made with other settings"
        left = remaining_steps(plan, seeds)
        rate = rates.get((plan.scenario, plan.algo))
        if left and rate:
            hours += left / rate / 3600
            what += f"; ~{left / rate / 3600:.1f} h"
        elif left:
            unmeasured.append(f"{plan.scenario}/{plan.algo}")
        lines.append(f"{k:>3}/{len(plans)}  {plan.scenario:<{width}}  {plan.algo:<7}  {plan.steps:>12,} steps/seed  "
                     + what)
    if hours:
        lines.append(f"estimated {hours:.1f} h of updates at the rates its cells trained at in {rates_from} (on this "
                     "kind of device; compilation, tests and evaluation add a few %)"
                     + (f"; no measurement for {', '.join(unmeasured)}" if unmeasured else ""))
    return "\n".join(lines)


def training_seconds(metrics: list[dict], seeds: int) -> float:
    """Seconds the run's updates took (from each ``metrics.jsonl`` line's env-steps/s; no compilation, tests
    or checkpoints), summed over every invocation of a resumed run."""
    steps = [m["env_steps"] for m in metrics]
    per_update = [b - a for a, b in zip([0] + steps[:-1], steps)]
    return float(sum(seeds * n / m["sps"] for n, m in zip(per_update, metrics)))


def cell_runs(run: Path, env, greedy_of_params, seeds: int, absolute_episodes: int, key, digest: str) -> dict:
    """The marl-eval ``{"run_<k>": ...}`` entries of a trained cell's run folder ``run``: every seed's best
    checkpoint plays ``absolute_episodes`` fresh greedy episodes, all seeds in one program. ``digest``
    (:func:`~marbler_jax_rl.recipes.settings_digest` of the cell's settings) is kept as ``recipe``."""
    opened = Run.open(run)
    tests, metrics, best_scores = opened.tests(), opened.metrics(), opened.best_scores()
    absolute = make_tester(env, greedy_of_params, absolute_episodes)(opened.params("best"),
                                                                      jax.random.split(key, seeds))
    absolute = jax.tree_util.tree_map(np.asarray, absolute)
    runs = {}
    for s in range(seeds):
        entry = {f"step_{i}": {"step_count": t["env_steps"], **{m: v[s] for m, v in t["episodes"].items()}}
                 for i, t in enumerate(tests)}
        entry[ABSOLUTE] = {m: [round(float(x), 5) for x in v[s]] for m, v in absolute.items()}
        entry[ABSOLUTE].update(best_test_return=[float(best_scores[s])], env_steps=[int(tests[-1]["env_steps"])],
                               train_seconds=[round(training_seconds(metrics, seeds), 1)], recipe=[digest])
        runs[f"run_{s}"] = entry
    return runs


POLICIES = "policies"
"""The folder of a benchmark's published policies: each cell's best seed as ``<scenario>-<algo>/``."""


def publish_policy(run: Path, target: Path) -> dict:
    """Export the best seed of run folder ``run`` (:meth:`Run.best_seed`, the model the paper's protocol
    reports) from its best checkpoint as the numpy policy folder ``target``, so the table's policies can be
    evaluated, rendered and deployed without retraining; returns the policy spec."""
    from .export import export_policy

    index = Run.open(run).best_seed()[0]
    return export_policy(run, target, seed_index=index, force=True)


def run_benchmark(out: str | Path, algos=PAPER_ALGOS, scenarios=PAPER_SCENARIOS, seeds: int = 5,
                  total_steps: int | None = None, eval_points: int = 20, test_episodes: int = 64,
                  absolute_factor: int = 10, devices: int = 1, seed: int = 0, progress: bool = True,
                  process_index: int = 0, process_count: int = 1, recipes=None, log=print, on_chunk=None,
                  env_overrides: dict | None = None, hp_overrides: dict | None = None, force: bool = False) -> dict:
    """Train and evaluate this process's share of the grid into ``out``; returns its results dict.
    A finished cell of the results file made with other settings is replaced only with ``force`` (a
    smoke run with ``--total-steps`` belongs in a folder of its own): without, nothing trains and a
    ``ValueError`` names the cells.
    ``devices > 1`` spreads each cell over that many devices (on a CPU, ask for them with
    :func:`marbler_jax_rl.data_parallel.use_cpu_devices` first) through the algorithm's
    ``learner_devices``: value-based algorithms split each gradient step, PPO algorithms each rollout's
    envs and each minibatch; either way every seed trains as on one device, up to float rounding.
    ``recipes``: ``{algo: Recipe}`` instead of :data:`marbler_jax_rl.recipes.RECIPES`; ``env_overrides``:
    env settings on top of every recipe's (e.g. ``{"control_period": 15}``); ``hp_overrides``:
    hyperparameters on top of the recipe of every algorithm that has them (e.g. ``{"hidden": 64}``)."""
    check_counts(eval_points=eval_points, absolute_factor=absolute_factor, devices=devices)
    if devices > jax.local_device_count():
        raise ValueError(f"devices={devices} but this process has {jax.local_device_count()} JAX device(s) "
                         f"({jax.local_devices()[0].platform}); on a CPU ask for them first with "
                         f"marbler_jax_rl.data_parallel.use_cpu_devices({devices}) (marbler-jax benchmark does)")
    # a bad setting (an unknown algorithm, scenario or env override) fails here, before any cell trains
    plans = plan_cells(out, algos, scenarios, seeds, total_steps, test_episodes, seed, process_index, process_count,
                       recipes, env_overrides, hp_overrides)
    out = Path(out)
    path = out / results_name(process_index, process_count)
    todo = [plan for plan in plans if plan.status != "done"]
    redo = sum(plan.replaces for plan in todo)
    if redo and not force:
        cells = ", ".join(f"{plan.scenario}/{plan.algo}" for plan in todo if plan.replaces)
        raise ValueError(f"{path} holds {cells} made with other settings; this run would replace "
                         f"{'it' if redo == 1 else 'them'}: give another --out (e.g. for a smoke run), or --force")
    out.mkdir(parents=True, exist_ok=True)
    with writer_lock(path.with_name(path.name + ".lock"), f"results file {path}"):     # one writer at a time
        log(f"benchmark: {len(plans)} cell(s) for this process, {len(plans) - len(todo)} already in {path}"
            + (f"; {redo} of its cells were made with other settings and train again" if redo else ""))
        spent_steps, spent_seconds = 0, 0.0
        budgets = [plan.steps * seeds for plan in todo]
        results = read_results(path)
        for i, plan in enumerate(todo):
            k = len(plans) - len(todo) + i + 1
            scenario, algo, env_settings, steps = plan.scenario, plan.algo, plan.env_settings, plan.steps
            hp = dict(plan.hp)
            if devices > 1:
                hp["learner_devices"] = devices
            env = marbler_jax.make(scenario, **env_settings)
            cfg = build_config(algo, dict(hp, total_timesteps=steps))
            eta = f", ETA {sum(budgets[i:]) * spent_seconds / spent_steps / 3600:.1f} h" if spent_steps else ""
            log(f"cell {k}/{len(plans)}: {algo} on {scenario}, {seeds} seed(s) x {steps:,} env steps{eta}")
            run = out / "runs" / scenario / algo
            if plan.status == "restart":
                log(f"{run} holds a run with other settings: moved to {set_aside(run)}")
            resume = plan.status != "restart" and Run.holds_run(run)
            clock = WallClock(run, resume, jax.devices()[0].device_kind)

            def chunk_saved(update):
                clock.save()
                if on_chunk is not None:
                    on_chunk(update)

            train_run(scenario, algo, steps, seeds, run, env_overrides=env_settings, hp=hp, seed=seed,
                      test_episodes=test_episodes, resume=resume, on_chunk=chunk_saved, log=log, eval_episodes=0,
                      checkpoint_every=max(1, plan.updates // eval_points), progress=progress)
            greedy = registry.get(algo).greedy_policy
            runs = cell_runs(run, env, lambda p: greedy(env, cfg, p), seeds, absolute_factor * test_episodes,
                             jax.random.PRNGKey(seed + 2024), plan.digest)
            seconds = clock.save()
            for entry in runs.values():
                entry[ABSOLUTE]["wall_seconds"] = [round(seconds, 1)]
                entry[ABSOLUTE]["device"] = [clock.device()]
            results = add_cell(path, scenario, algo, runs)
            publish_policy(run, out / POLICIES / f"{scenario}-{algo}")
            spent_steps += steps * seeds
            spent_seconds += seconds
            best = max(runs.values(), key=lambda r: r[ABSOLUTE]["best_test_return"][0])[ABSOLUTE]["reward"]
            log(f"cell {k}/{len(plans)} done in {seconds / 60:.1f} min: best seed's reward {np.mean(best):.2f} "
                f"over {len(best)} episodes -> {path}")
        return results


__all__ = ["run_benchmark", "publish_policy", "POLICIES", "plan_cells", "describe_plan", "measured_rates", "CellPlan",
           "CELL_STATUSES", "load_results", "add_cell", "finished_cells", "grid", "results_name", "PAPER_ALGOS", "PAPER_SCENARIOS", "JAXROBOTARIUM_SCENARIOS",
           "ENV_NAME"]
