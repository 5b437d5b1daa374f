"""The ``marbler-jax`` command line (also ``python -m marbler_jax_rl``).

Subcommands:
    demo     -- batched swap rollout of Robotarium robots under a barrier certificate: prints
                collisions, closest approach and throughput, saves a trajectory plot.
    rollout  -- batched random-policy rollout of a scenario: episode metrics, env-steps/s and
                an optional GIF of the first env.
    list     -- scenarios with their robots, observation/action sizes and default config.
    train    -- train IPPO, MAPPO, VDN, QMIX or QMIX_NS on a scenario (its recipe by default) and
                write a run folder.
    evaluate -- MARBLER's Table II metrics of a run's best checkpoint (JSON + Markdown).
    render   -- GIF/MP4 of a run's greedy policy or a scenario with random actions (``--envs K``: a grid).
    export   -- a run's policy as numpy ``.npy`` files, and (``--bundle``) a flat Robotarium submission.
    benchmark -- MARBLER's Table II grid: every cell's seeds trained with the recipes, one results file.
    report   -- the benchmark's tables (IQM, CIs, best seed, the paper), curves, probability of improvement.
    quickstart -- the main job: train IPPO on simple_navigation, evaluate, plot, render a GIF.
    bench    -- run ``scripts/bench_cbf.py`` (barrier + integrator throughput).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def _demo(args) -> int:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from marbler_jax import cbf, controllers, physics

    params = physics.get_params(args.preset)
    physics.check_num_robots(params, args.robots)
    barrier = cbf.make_barrier(args.barrier, **({"safety_radius": 0.2} if args.barrier == "si2" else {}))
    n, teams, ticks = args.robots, args.teams, args.ticks
    key = jax.random.PRNGKey(args.seed)
    angles = jnp.linspace(0, 2 * jnp.pi, n, endpoint=False)
    jitter = 0.3 * jax.random.normal(key, (teams, n))
    ring = jnp.broadcast_to(jnp.stack([1.1 * jnp.cos(angles), 0.75 * jnp.sin(angles)], -1), (teams, n, 2))
    start = jnp.concatenate([ring, (angles + jnp.pi + jitter)[..., None]], axis=-1)
    goals = -start[..., :2]

    def tick(poses, _):
        xi = controllers.uni_to_si_states(poses)
        dxi = controllers.si_position_controller(xi, goals)
        if barrier.is_unicycle:
            dxu = barrier(controllers.si_to_uni_mapping(dxi, poses), poses)
        else:
            dxu = controllers.si_to_uni_mapping(barrier(dxi, xi), poses)
        hits = physics.collisions(params, poses).any(-1)
        return physics.integrate(params, poses, dxu), (poses[0], hits, jnp.min(
            physics.pair_distances(poses[..., :2]), axis=(-1, -2)))

    rollout = jax.jit(lambda p: jax.lax.scan(tick, p, None, length=ticks))
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(start))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    final, (trace, hits, closest) = jax.block_until_ready(rollout(start))
    run_s = time.perf_counter() - t0
    err = np.linalg.norm(np.asarray(final[..., :2] - goals), axis=-1)
    print(f"{teams} teams x {n} robots x {ticks} ticks, barrier {barrier.kind!r}, physics {args.preset!r}")
    print(f"  compile {compile_s:.1f} s, run {run_s:.2f} s = {teams * ticks / run_s:,.0f} team-ticks/s "
          f"({teams * n * ticks / run_s:,.0f} robot-ticks/s with controller + certificate)")
    print(f"  collision ticks (rps test): {int(np.asarray(hits).sum())}; closest centre distance "
          f"{float(np.min(closest)):.3f} m; median final distance to goal {np.median(err):.3f} m")
    if args.plot:
        _plot(np.asarray(trace), np.asarray(goals[0]), params, args.plot)
        print(f"  trajectory plot of team 0: {args.plot}")
    return 0 if int(np.asarray(hits).sum()) == 0 else 1


def _plot(trace, goals, params, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x_min, x_max, y_min, y_max = params.arena
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.add_patch(plt.Rectangle((x_min, y_min), x_max - x_min, y_max - y_min, fill=False, lw=1.5))
    for i in range(trace.shape[1]):
        ax.plot(trace[:, i, 0], trace[:, i, 1], lw=0.8)
        ax.plot(*goals[i], "x", color="k", ms=4)
    ax.set_aspect("equal")
    ax.set_xlim(x_min - 0.05, x_max + 0.05)
    ax.set_ylim(y_min - 0.05, y_max + 0.05)
    ax.set_title("robots swap places under the barrier certificate")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def parse_overrides(pairs: list[str], flag: str = "--set") -> dict:
    """``["key=value", ...]`` (the values of option ``flag``) -> dict; values parsed as JSON when possible
    (numbers, true/false)."""
    import json

    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            raise ValueError(f"{flag} expects key=value, got {pair!r}")
        key, value = pair.split("=", 1)
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _rollout(args) -> int:
    import jax

    import marbler_jax
    from marbler_jax.rollout import episode_stats, make_rollout

    env = marbler_jax.make(args.scenario, **parse_overrides(args.set))
    rollout = make_rollout(env, args.envs, args.steps)
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(jax.random.PRNGKey(args.seed)))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    state, traj = jax.block_until_ready(rollout(jax.random.PRNGKey(args.seed + 1)))
    run_s = time.perf_counter() - t0
    stats = episode_stats(traj)
    print(f"{env!r}: {args.envs} envs x {args.steps} steps, random policy")
    print(f"  compile {compile_s:.1f} s, run {run_s:.2f} s = {args.envs * args.steps / run_s:,.0f} env-steps/s")
    print("  finished episodes: " + ", ".join(f"{k} {v:.3f}" for k, v in stats.items()))
    if args.gif:
        from marbler_jax.render import episode_frames, save_movie

        frames = episode_frames(env, None, jax.random.PRNGKey(args.seed + 2))
        save_movie(frames, args.gif, fps=4)
        print(f"  GIF of one episode ({len(frames)} frames): {args.gif}")
    return 0


def _list(args) -> int:
    import dataclasses
    import importlib
    import re
    import textwrap

    import marbler_jax
    from . import registry
    from .recipes import recipe
    from marbler_jax.registry import scenario_class
    from marbler_jax.scenarios.base import field_docs

    def plain(text: str) -> str:       # reST markup -> terminal text
        return re.sub(r"``([^`]+)``", r"\1", re.sub(r":\w+:`([^`]+)`", r"\1", text))

    def first_line(text: str | None) -> str:
        return plain(text.strip().splitlines()[0]) if text else ""

    def print_fields(config, indent=6, skip=()):
        docs = field_docs(type(config))
        for field in dataclasses.fields(config):
            if field.name in skip:
                continue
            print(f"{' ' * indent}{field.name} = {getattr(config, field.name)!r}")
            print(textwrap.fill(plain(docs.get(field.name, "")), width=110, initial_indent=" " * (indent + 4),
                                subsequent_indent=" " * (indent + 4)))

    from marbler_jax.registry import canonical_name

    if args.scenario is not None:            # one scenario: its config, every key with its meaning
        scenario_class(args.scenario)       # an unknown name is one clear error
        names, args.verbose = [canonical_name(args.scenario)], True
    else:
        names = marbler_jax.registered()
    print("scenarios:")
    for name in names:
        env = marbler_jax.make(name)
        print(f"  {name}: {env.num_agents} robots, obs_dim {env.obs_dim}, {env.num_actions} actions, "
              f"{env.max_steps} steps per episode -- "
              f"{first_line(importlib.import_module(scenario_class(name).__module__).__doc__)}")
        if args.verbose:
            print_fields(env.config)
    if args.scenario is not None:
        return 0
    print("algorithms (marbler-jax train --algo" + (", with the settings of each one's recipe):" if args.verbose else "):"))
    for algo in registry.names():
        print(f"  {algo}: {registry.get(algo).summary}")
        if args.verbose:
            chosen = recipe(algo)
            budgets = ", ".join(f"{name} {steps:,}" for name, steps in chosen.steps.items())
            print(f"      env steps per seed: {budgets}; elsewhere {chosen.default_steps:,}")
            print_fields(chosen.config, skip=("total_timesteps",))
    return 0


def _train(args) -> int:
    from .driver import train_run
    from .recipes import settings
    from marbler_jax.registry import canonical_name

    from marbler_jax.scenarios.base import merge_settings

    saved = _saved_run(args)
    if saved is not None:                          # --resume: the run's own settings, the options given on top
        env_overrides, hp, steps = saved
    else:
        env_overrides, hp, steps = settings(args.recipe, canonical_name(args.scenario), args.algo)
    env_overrides = merge_settings(env_overrides, _env_settings(args))
    hp.update(parse_overrides(args.hp, "--hp"))
    from .data_parallel import use_cpu_devices

    # before JAX first runs: a CPU split into the devices the run is spread over
    if args.seed_batching == "devices":
        use_cpu_devices(os.cpu_count() or 1)
    elif isinstance(hp.get("learner_devices"), int):
        use_cpu_devices(hp["learner_devices"])
    train_run(args.scenario, args.algo, args.total_steps or steps, args.seeds, args.out, env_overrides=env_overrides,
              hp=hp, seed=args.seed, test_episodes=args.test_episodes, resume=args.resume,
              checkpoint_every=args.checkpoint_every, eval_episodes=args.eval_episodes,
              seed_batching=args.seed_batching, progress=not args.no_progress)
    print(f"run folder: {args.out}")
    return 0


def _given(args, *flags) -> bool:
    """Whether the command line named one of ``flags`` (``--x V`` or ``--x=V``)."""
    return any(arg == flag or arg.startswith(flag + "=") for arg in args.argv for flag in flags)


def _saved_run(args):
    """For ``train --resume`` of a run folder with a ``config.json``: ``(env settings, hyperparameters, env
    steps)`` as the run saved them, with ``args``' scenario, algorithm, seeds, seed and test episodes set from
    the run unless the command line gives them (what it gives must match the run: the driver checks). ``None``
    for a fresh run, or where ``--recipe`` asks for a recipe's settings."""
    from marbler_jax.scenarios.base import renamed_keys
    from .checkpoints import read_json

    path = Path(args.out) / "config.json"
    if not args.resume or not path.exists() or _given(args, "--recipe", "--preset"):
        return None
    try:
        saved = read_json(path)
        for flag, name, key in (("--scenario", "scenario", "scenario"), ("--algo", "algo", "algo"),
                                ("--seeds", "seeds", "seeds"), ("--seed", "seed", "seed"),
                                ("--test-episodes", "test_episodes", "test_episodes")):
            if not _given(args, flag):
                setattr(args, name, saved.get(key, 0) if key == "test_episodes" else saved[key])
        algorithm = dict(saved["algorithm"])
        steps = int(algorithm.pop("total_timesteps"))
        env = renamed_keys(saved["env"])
    except (KeyError, TypeError, AttributeError) as err:
        raise ValueError(f"--resume: {path} is not a run's config.json ({type(err).__name__}: {err})") from None
    return env, algorithm, steps


def _env_settings(args) -> dict:
    """Env settings of ``--set KEY=VALUE`` options and ``--protocol``."""
    settings = parse_overrides(args.set)
    if getattr(args, "protocol", None):
        if settings.get("protocol", args.protocol) != args.protocol:
            raise ValueError(f"--protocol {args.protocol} and --set protocol={settings['protocol']} disagree; drop one")
        settings["protocol"] = args.protocol
    return settings


def _benchmark(args) -> int:
    shard = _parse_shard(args.shard)
    env_overrides, hp_overrides = _env_settings(args), parse_overrides(args.hp, "--hp")
    if args.out is None:
        from .benchmark import DEFAULT_RESULTS

        args.out = DEFAULT_RESULTS.get(env_overrides.get("protocol"), DEFAULT_RESULTS[None])
    if args.dry_run:
        if args.coordinator:
            raise ValueError("--dry-run shows one process's cells: give --shard I/N instead of --coordinator")
        from .benchmark import DEFAULT_RESULTS, describe_plan, load_results, measured_rates, plan_cells, results_name

        plans = plan_cells(args.out, args.algos, args.scenarios, args.seeds, args.total_steps, args.test_episodes,
                           args.seed, *shard, env_overrides=env_overrides, hp_overrides=hp_overrides)
        # the rates of the folder's own earlier cells, else those of the recipes' table
        sources = [Path(args.out), Path(DEFAULT_RESULTS[None])]
        source = next((p for p in sources if p.is_dir() and list(p.glob("results*.json"))), None)
        import jax

        rates = measured_rates(load_results(source), jax.devices()[0].device_kind) if source else {}
        print(describe_plan(plans, args.seeds, str(Path(args.out) / results_name(*shard)), rates, str(source)))
        return 0
    if args.coordinator:
        if args.shard:
            raise ValueError("--coordinator assigns the shard itself; drop --shard")
        return _benchmark_distributed(args)
    if args.devices > 1:
        from .data_parallel import use_cpu_devices

        use_cpu_devices(args.devices)        # before JAX first runs
    from .benchmark import run_benchmark

    run_benchmark(args.out, args.algos, args.scenarios, args.seeds, args.total_steps, args.eval_points,
                  args.test_episodes, args.absolute_factor, args.devices, args.seed, progress=not args.no_progress,
                  process_index=shard[0], process_count=shard[1], env_overrides=env_overrides,
                  hp_overrides=hp_overrides, force=args.force)
    print(f"results: {args.out}; tables and curves: marbler-jax report {args.out}")
    return 0


def env_steps(text: str) -> int:
    """``--total-steps``: a whole number of env steps >= 1, written as ``20000``, ``2e4`` or ``5_000_000``."""
    try:
        value = float(text.replace("_", ""))
    except ValueError:
        value = float("nan")
    if not (1 <= value < float("inf") and value.is_integer()):
        raise argparse.ArgumentTypeError(f"must be a whole number of env steps >= 1 (e.g. 5e6), got {text!r}")
    return int(value)


def _parse_shard(text: str | None) -> tuple[int, int]:
    """``"I/N"`` -> ``(I, N)`` with ``0 <= I < N``; None -> ``(0, 1)``."""
    if not text:
        return 0, 1
    try:
        index, count = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard must be I/N (e.g. 0/2), got {text!r}") from None
    if not 0 <= index < count:
        raise ValueError(f"--shard I/N needs 0 <= I < N, got {text!r}")
    return index, count


def _without_options(argv: list[str], names: set[str]) -> list[str]:
    """``argv`` without the options ``names`` and their values (``--name value`` or ``--name=value``)."""
    out, skip_value = [], False
    for arg in argv:
        if skip_value:
            skip_value = False
        elif arg in names:
            skip_value = True
        elif arg.split("=", 1)[0] not in names:
            out.append(arg)
    return out


def _benchmark_distributed(args) -> int:
    """Join JAX's distributed runtime (``--coordinator HOST:PORT`` with ``--num-processes`` and
    ``--process-id``, or ``auto`` where JAX detects the cluster, e.g. under SLURM) to learn this process's
    shard, train it in a child process of its own (its checkpoints stay single-process), then wait for
    every process at a barrier."""
    import subprocess

    import jax

    if args.coordinator == "auto":
        jax.distributed.initialize()
    else:
        jax.distributed.initialize(args.coordinator, num_processes=args.num_processes, process_id=args.process_id)
    index, count = jax.process_index(), jax.process_count()
    child = _without_options(args.argv, {"--coordinator", "--num-processes", "--process-id"})
    code = subprocess.run([sys.executable, "-m", "marbler_jax_rl", *child, "--shard", f"{index}/{count}"]).returncode
    from jax.experimental import multihost_utils

    multihost_utils.sync_global_devices("marbler-jax benchmark done")
    return code


def _report(args) -> int:
    from .report import write_report

    written = write_report(args.results, args.out, reps=args.reps, results_md=args.results_md, readme=args.readme,
                           progress=not args.no_progress, paper_models=args.paper_models)
    print("\n".join(f"written: {p}" for p in written))
    return 0


_MEMORY_NAMES = {"gru": "GRU", "mingru": "minimal GRU", "none": "feed-forward"}


def _export(args) -> int:
    from .export import export_policy

    if (Path(args.run) / "policy_spec.npy").exists():
        return _bundle_policy_folder(args)
    if args.out is None:
        raise ValueError("--out is required to export a run (the policy folder to write)")

    from .run import Run

    seed_index = Run.open(args.run).seed_index(args.seed_index)
    spec = export_policy(args.run, args.out, seed_index=seed_index, checkpoint=args.checkpoint,
                         bundle=args.bundle, episodes=args.episodes, bundle_seed=args.bundle_seed,
                         control_period=None if args.control_period == "train" else args.control_period,
                         force=args.force)
    from marbler_jax.deploy.bundle import folder_size

    files = sorted(p.name for p in Path(args.out).iterdir())
    size = folder_size(args.out)
    print(f"exported {spec['algo']} ({spec['kind']}, {_MEMORY_NAMES[spec['cell']]}, "
          f"{'shared' if spec['shared'] else 'per-agent'} parameters) for {spec['scenario']} to {args.out}: "
          f"{len(files)} files, {size / 1024:.1f} KiB")
    print("load with numpy only: from marbler_jax.numpy_policy import load_policy; "
          f"load_policy({str(args.out)!r}).act(obs)")
    if args.bundle:
        _print_bundle(Path(args.bundle))
        period = "the training period" if args.control_period == "train" else f"every {args.control_period} iteration(s)"
        print(f"the bundle recomputes controller and barrier {period} and clips commands to the motor limits")
    return 0


def _bundle_policy_folder(args) -> int:
    """``export POLICY --bundle B``: a policy folder (exported or imported) as a Robotarium bundle."""
    from .evaluate import open_policy
    from marbler_jax.deploy.bundle import write_bundle

    if args.bundle is None:
        raise ValueError(f"{args.run} is already a policy folder: give --bundle B to write its Robotarium bundle")
    if args.out is not None:
        raise ValueError(f"{args.run} is already a policy folder: drop --out (or export a run folder)")
    from marbler_jax.deploy.bundle import deployment_settings

    env, policy = open_policy(args.run, deployment_settings(None if args.control_period == "train"
                                                            else args.control_period))
    spec = policy.spec
    write_bundle(env, args.run, args.bundle, spec.get("algo", "policy"), episodes=args.episodes, seed=args.bundle_seed,
                 force=args.force)
    _print_bundle(Path(args.bundle))
    return 0


def _number_or_word(text: str, word: str, minimum: int, what: str):
    """An argparse type: ``word`` itself, or an integer >= ``minimum``."""
    if text == word:
        return text
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{text!r} is not {what} or {word!r}")
    return value


def _seed_choice(text: str):
    """``--seed-index``: ``best`` or an index >= 0."""
    return _number_or_word(text, "best", 0, "a seed index >= 0")


def _period(text: str):
    """``--control-period``: a positive integer, or ``train`` (kept as the string)."""
    return _number_or_word(text, "train", 1, "a positive integer")


def _print_bundle(folder: Path) -> None:
    from marbler_jax.deploy.bundle import folder_size

    files = sorted(p.name for p in folder.iterdir())
    print(f"Robotarium bundle: {folder} ({len(files)} flat files, {folder_size(folder) / 1024:.1f} KiB). Upload every "
          "file and mark main.py as the main file. Try it first in the simulator: cd into the folder and run "
          "`MARBLER_JAX_HEADLESS=1 python main.py` where `pip install robotarium-python-simulator` is installed.")


def _evaluate(args) -> int:
    import json

    from .checkpoints import atomic_write
    from .evaluate import evaluate_policy, evaluate_run, markdown_table
    from marbler_jax.numpy_policy import SPEC_FILE

    overrides = {"protocol": args.protocol} if args.protocol else {}
    run = Path(args.run)
    suffix = f"_{args.protocol}" if args.protocol else ""
    if (run / SPEC_FILE).exists():                  # a policy folder: its files stay as they are
        result = evaluate_policy(run, args.episodes, seed=args.seed, env_overrides=overrides)
        print(markdown_table(dict(result, seeds=1, episodes_per_seed=args.episodes, checkpoint="policy folder's")))
        if args.json:
            atomic_write(Path(args.json), json.dumps(result, indent=2))
            print(f"written: {args.json}")
        return 0
    result = evaluate_run(args.run, args.episodes, args.checkpoint, seed=args.seed, progress=not args.no_progress,
                          seed_selection="best" if args.best_seed else "all", env_overrides=overrides)
    table = markdown_table(result)
    stem = f"eval_{args.checkpoint}" + ("_best_seed" if args.best_seed else "") + suffix
    json_path = Path(args.json) if args.json else run / f"{stem}.json"
    atomic_write(json_path, json.dumps(result, indent=2))
    atomic_write(run / f"{stem}.md", table)
    print(table)
    print(f"written: {json_path}, {run / f'{stem}.md'}")
    return 0


def _import(args) -> int:
    from .epymarl import import_model

    from marbler_jax.deploy.main import CONFIG_FILE
    from marbler_jax.deploy.bundle import check_target, write_bundle

    if args.bundle is not None:
        check_target(args.bundle, CONFIG_FILE, "bundle", args.force)
    spec = import_model(args.model, args.config, args.scenario, args.out, {"protocol": args.protocol},
                        force=args.force)
    origin = spec["origin"]
    print(f"imported {args.model} (EPyMARL {origin['agent']}, {spec['algo']}, GRU {spec['hidden']}, "
          f"{'shared' if spec['shared'] else 'per-robot'} parameters) for {spec['scenario']} to {args.out}")
    print(f"evaluate it: marbler-jax evaluate {args.out} (protocol {args.protocol}; --protocol robots for the "
          "robots' loop)")
    if args.bundle is not None:
        from .evaluate import open_policy
        from marbler_jax.deploy.bundle import deployment_settings

        env, _ = open_policy(args.out, deployment_settings())
        write_bundle(env, args.out, args.bundle, spec["algo"], episodes=args.episodes, force=args.force)
        _print_bundle(Path(args.bundle))
    return 0


def _quickstart(args) -> int:
    from .driver import train_run

    from marbler_jax.deploy.bundle import building, check_target

    from .export import export_policy
    from .recipes import settings
    from .run import Run

    final = Path(args.out)
    check_target(final, "config.json", "quickstart run", args.force)
    if final.exists() and any(final.iterdir()):
        print(f"replacing the earlier run in {final} once this one has finished")
    with building(final) as out:                   # built beside it under a name of its own, swapped in at the end
        env_overrides, hp, steps = settings("recipe", "simple_navigation", "ippo")    # what `train` would run
        result = train_run("simple_navigation", "ippo", steps, 2, out, env_overrides=env_overrides, hp=hp)
        _episode_gif(out, out / "episode.gif")
        export_policy(out, out / "policy", seed_index=Run.open(out).seed_index("best"), bundle=out / "robotarium")
    out = final
    better = result["trained"]["return"] > result["random"]["return"]
    print("\nquickstart outputs:")
    for name in ("config.json", "metrics.jsonl", "learning_curve.png", "params.npz", "evaluation.json", "episode.gif",
                 "policy/ (numpy policy files: marbler_jax.numpy_policy.load_policy)",
                 "robotarium/ (flat Robotarium submission bundle: upload all files, main.py is the main file)"):
        print(f"  {out / name}")
    return 0 if better else 1


def _episode_gif(run: Path, gif: Path) -> None:
    """GIF of one greedy episode of the run's first seed."""
    import jax

    from .run import load_run
    from marbler_jax.render import episode_frames, save_movie

    env, policy = load_run(run)
    save_movie(episode_frames(env, policy, jax.random.PRNGKey(1)), gif)


def _render(args) -> int:
    import jax

    import marbler_jax
    from marbler_jax.render import episode_frames, save_movie

    if args.envs < 1:
        raise ValueError(f"--envs must be >= 1, got {args.envs}")
    target = Path(args.target)
    if (target / "config.json").exists():
        from .run import load_run

        if args.set:
            raise ValueError("--set applies to a scenario name; a run renders with the settings it was trained with")
        from .run import Run

        seed_index = Run.open(target).seed_index(args.seed_index)
        env, policy = load_run(target, seed_index=seed_index, checkpoint=args.checkpoint)
        what = f"greedy policy of {target} ({args.checkpoint} parameters, seed {seed_index})"
    elif (target / "policy_spec.npy").exists():
        from .evaluate import open_policy
        from marbler_jax.rollout import numpy_policy_greedy

        if args.set:
            raise ValueError("--set applies to a scenario name; a policy folder renders with the settings it records")
        env, numpy_policy = open_policy(target)
        policy = numpy_policy_greedy(numpy_policy)
        what = f"greedy policy in {target}"
    elif args.target in marbler_jax.registered():
        env, policy = marbler_jax.make(args.target, **parse_overrides(args.set)), None
        what = "random actions"
    else:
        raise ValueError(f"{args.target!r} is neither a run folder (no config.json), a policy folder (no "
                         f"policy_spec.npy) nor a scenario; scenarios: "
                         f"{sorted(marbler_jax.registered())}")
    frames = episode_frames(env, policy, jax.random.PRNGKey(args.seed), args.envs, progress=not args.no_progress)
    save_movie(frames, args.out, fps=args.fps)
    print(f"{env.name}: {args.envs} episode(s) of {what}, {len(frames)} frames -> {args.out}")
    return 0


def _bench(args) -> int:
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_cbf.py"
    if not script.exists():
        print(f"benchmark script not found at {script} (install from a source checkout)", file=sys.stderr)
        return 2
    import runpy

    sys.argv = [str(script), "--out", args.out] + (["--quick"] if args.quick else [])
    runpy.run_path(str(script), run_name="__main__")
    return 0


class _DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default, except where there is none to show."""

    def _get_help_string(self, action):
        if action.default in (None, False) or action.default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


PROGRESS_LEGEND = ("progress bar: updates done / all, elapsed < ETA and updates/s measured after compilation "
                   "(printed apart as 'compiled in'); ret: mean training return of the last update's episodes; "
                   "test: mean greedy test return of the last checkpoint (--test-episodes); sps: env steps per "
                   "second over all seeds in the last chunk")
CHECKPOINT_HELP = "which parameters of the run: each seed's best greedy test (best) or the end of training (final)"


PROTOCOL_HELP = ("marbler: MARBLER's shipped protocol, that of the paper's Table II (rps 6bb184e, controller and "
                 "barrier every 15 iterations, all-zero first observation); robots: the robots' loop (every "
                 "iteration); default: the recipe's / the run's settings")


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line naming the argument, the value and where the
    usage is (``-h``), instead of the usage block followed by the error."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (usage: {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    from .benchmark import PAPER_ALGOS, PAPER_SCENARIOS
    from .driver import SEED_BATCHING
    from .recipes import RECIPE_NAMES
    from .run import CHECKPOINTS, DEFAULT_CHECKPOINT
    from marbler_jax.scenarios.base import PROTOCOLS
    from marbler_jax import cbf, physics
    from marbler_jax.control_loop import ROBOTS_CONTROL_PERIOD

    from marbler_jax import __version__

    parser = OneLineParser(prog="marbler-jax", description="Batched Robotarium simulation and MARL in JAX.")
    parser.add_argument("--version", action="version", version=f"marbler-jax {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the whole traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="robots swap places under a barrier certificate (batched)")
    demo.add_argument("--robots", type=int, default=12, help="robots per team (1-50)")
    demo.add_argument("--teams", type=int, default=256, help="teams simulated in parallel")
    demo.add_argument("--ticks", type=int, default=1500, help="simulator ticks (0.033 s each)")
    demo.add_argument("--barrier", default="si2", choices=list(cbf.KINDS))
    demo.add_argument("--preset", default=physics.DEFAULT_PRESET, choices=sorted(physics.PRESETS))
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--plot", default="runs/demo/swap.png", help="trajectory PNG ('' to skip)")
    demo.set_defaults(func=_demo)
    roll = sub.add_parser("rollout", help="batched random-policy rollout of a scenario")
    roll.add_argument("scenario", help="scenario name (see `marbler-jax list`)")
    roll.add_argument("--envs", type=int, default=1024)
    roll.add_argument("--steps", type=int, default=200)
    roll.add_argument("--seed", type=int, default=0)
    roll.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    roll.add_argument("--gif", default="", help="write a GIF of env 0 to this path")
    roll.set_defaults(func=_rollout)
    lst = sub.add_parser("list", help="scenarios, sizes and default config")
    lst.add_argument("scenario", nargs="?", default=None,
                     help="only this scenario, with every config key, its default and its meaning")
    lst.add_argument("-v", "--verbose", action="store_true", help="print every config key, its default and its meaning")
    lst.set_defaults(func=_list)
    tr = sub.add_parser("train", help="train an algorithm on a scenario (writes a run folder)",
                        epilog=PROGRESS_LEGEND)
    tr.add_argument("--scenario", default="simple_navigation")
    tr.add_argument("--algo", default="ippo", metavar="ALGO",
                    help="an algorithm's name (`marbler-jax list` shows them) or MODULE:NAME of an Algorithm that is "
                         "not installed (docs/algorithms.md)")
    tr.add_argument("--recipe", "--preset", dest="recipe", default="recipe", choices=list(RECIPE_NAMES),
                    help="settings to start from (recipe: the algorithm's benchmark recipe, algorithms/recipes.py; "
                         "paper: MARBLER's EPyMARL settings; none: the algorithm's defaults); --preset is its "
                         "older name")
    tr.add_argument("--total-steps", type=env_steps, default=None,
                    help="env steps per seed (e.g. 5e6; default: the recipe's)")
    tr.add_argument("--seeds", type=int, default=1, help="seeds trained in one vmapped program")
    tr.add_argument("--seed", type=int, default=0,
                    help="base PRNG seed: the seeds' keys are split from PRNGKey(seed) (default 0)")
    tr.add_argument("--out", default="runs/train")
    tr.add_argument("--set", action="append", metavar="KEY=VALUE", help="env config override (repeatable)")
    tr.add_argument("--protocol", choices=list(PROTOCOLS), default=None, help=PROTOCOL_HELP)
    tr.add_argument("--hp", action="append", metavar="KEY=VALUE", help="algorithm setting (repeatable)")
    tr.add_argument("--checkpoint-every", type=int, default=None, help="updates per chunk/checkpoint (default: 1/10 of the run)")
    tr.add_argument("--test-episodes", type=int, default=64,
                    help="greedy test episodes per seed after every chunk; the best checkpoint is the one with "
                         "the best test return (0 = no test: best by training return)")
    tr.add_argument("--eval-episodes", type=int, default=256,
                    help="episodes of the final evaluation.json (the first seed's greedy policy and the random "
                         "policy; 0 = none)")
    tr.add_argument("--resume", action="store_true",
                    help="continue the run in --out from its latest checkpoint, with the settings its config.json "
                         "holds (options given must agree with them)")
    tr.add_argument("--no-progress", action="store_true", help="no progress bar")
    tr.add_argument("--seed-batching", choices=list(SEED_BATCHING), default=None,
                    help="vmap: seeds vectorized in one batch; map: one after another in the program; devices: the "
                         "seeds spread over the devices (on a CPU, one device per core); default: map for VDN, "
                         "QMIX and QMIX_NS on a CPU, else vmap (the faster there)")
    tr.set_defaults(func=_train)
    ev = sub.add_parser("evaluate", help="paper-style metrics (MARBLER Table II) of a run's best checkpoint "
                                         "or of a policy folder (exported or imported)")
    ev.add_argument("run", help="run folder written by `marbler-jax train`, or a policy folder written by "
                                "`marbler-jax export` or `marbler-jax import`")
    ev.add_argument("--episodes", type=int, default=100, help="greedy episodes per seed")
    ev.add_argument("--protocol", choices=list(PROTOCOLS), default=None,
                    help="evaluate in this protocol instead of the one the policy trained in: " + PROTOCOL_HELP)
    ev.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT, choices=CHECKPOINTS, help=CHECKPOINT_HELP)
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--best-seed", action="store_true",
                    help="only the seed with the highest greedy test return, as the paper's Table II reports the "
                         "best of five seeds' models (writes eval_<checkpoint>_best_seed.json/.md)")
    ev.add_argument("--json", default=None, metavar="FILE",
                    help="write the result here (default for a run: eval_<checkpoint>[_best_seed][_<protocol>].json "
                         "in the run folder; a policy folder is never written to)")
    ev.add_argument("--no-progress", action="store_true")
    ev.set_defaults(func=_evaluate)
    ex = sub.add_parser("export", help="write a run's policy as numpy .npy files (runs without JAX)")
    ex.add_argument("run", help="run folder written by `marbler-jax train`, or a policy folder (then only --bundle)")
    ex.add_argument("--out", default=None, help="policy folder to write (flat, .npy files only); required for a run")
    ex.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT, choices=CHECKPOINTS, help=CHECKPOINT_HELP)
    ex.add_argument("--seed-index", type=_seed_choice, default="best",
                    help="which of the run's seeds to export: an index, or best (the one `evaluate --best-seed` "
                         "reports)")
    ex.add_argument("--best-seed", dest="seed_index", action="store_const", const="best",
                    help="the seed `evaluate --best-seed` reports (the default; same as --seed-index best)")
    ex.add_argument("--bundle", default=None,
                    help="also write a flat Robotarium submission bundle (main.py + files) to this folder")
    ex.add_argument("--episodes", type=int, default=2, help="episodes the bundle runs (start states drawn now)")
    ex.add_argument("--bundle-seed", type=int, default=0, help="seed of the bundle's start states")
    ex.add_argument("--control-period", type=_period, default=ROBOTS_CONTROL_PERIOD, metavar="N|train",
                    help="Robotarium iterations between the bundle's controller and barrier refreshes: 1 is "
                         "the robots' loop; 'train' deploys the period the policy trained with")
    ex.add_argument("--force", action="store_true",
                    help="replace --out / --bundle folders even if they hold files export did not write")
    ex.set_defaults(func=_export)
    rd = sub.add_parser("render", help="GIF/MP4 of a run's greedy policy, or of a scenario with random actions")
    rd.add_argument("target", help="run folder or policy folder (greedy policy), or scenario name (random actions)")
    rd.add_argument("--out", required=True, help="movie file: .gif, or .mp4 with imageio-ffmpeg installed")
    rd.add_argument("--envs", type=int, default=1, help="episodes side by side in a grid (vmapped envs)")
    rd.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT, choices=CHECKPOINTS, help=CHECKPOINT_HELP)
    rd.add_argument("--seed-index", type=_seed_choice, default="best",
                    help="which of the run's seeds: an index, or best (the one `evaluate --best-seed` reports)")
    rd.add_argument("--best-seed", dest="seed_index", action="store_const", const="best",
                    help="the seed `evaluate --best-seed` reports (the default; same as --seed-index best)")
    rd.add_argument("--seed", type=int, default=0, help="episode randomness")
    rd.add_argument("--fps", type=float, default=6.0)
    rd.add_argument("--set", action="append", default=[], help="scenario config override key=value")
    rd.add_argument("--no-progress", action="store_true")
    rd.set_defaults(func=_render)
    bm = sub.add_parser("benchmark", help="MARBLER's Table II grid: every cell's seeds trained with the recipes, "
                        "tested during training, one marl-eval results file (resumable)", epilog=PROGRESS_LEGEND)
    bm.add_argument("--algos", nargs="+", default=list(PAPER_ALGOS), metavar="ALGO",
                    help="algorithms, as train's --algo takes them")
    bm.add_argument("--scenarios", nargs="+", default=list(PAPER_SCENARIOS))
    bm.add_argument("--seeds", type=int, default=5, help="seeds per cell, trained in one vmapped program")
    bm.add_argument("--out", default=None, help="results folder (results.json, runs/); default: "
                    "results/marbler-table2, with --protocol marbler results/marbler-table2-protocol")
    bm.add_argument("--protocol", choices=list(PROTOCOLS), default=None, help=PROTOCOL_HELP)
    bm.add_argument("--force", action="store_true",
                    help="replace finished cells of the results file that were made with other settings")
    bm.add_argument("--total-steps", type=env_steps, default=None,
                    help="env steps per seed for every cell (default: each recipe's)")
    bm.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="env config override for every cell, on top of the recipe's (repeatable), e.g. "
                         "control_period=15; the report marks such cells as trained off the recipe")
    bm.add_argument("--hp", action="append", metavar="KEY=VALUE",
                    help="algorithm setting on top of the recipe of every algorithm that has it (repeatable), e.g. "
                         "hidden=64; the report marks such cells as trained off the recipe")
    bm.add_argument("--eval-points", type=int, default=20, help="greedy tests during training")
    bm.add_argument("--test-episodes", type=int, default=64, help="episodes per seed at each test")
    bm.add_argument("--absolute-factor", type=int, default=10,
                    help="the absolute metric evaluates each seed's best checkpoint over this many times "
                         "--test-episodes episodes")
    bm.add_argument("--devices", "--learner-devices", dest="devices", type=int, default=1,
                    help="devices each cell is spread over (on a CPU, at most one per core): "
                         "value-based cells split each gradient step over them, PPO cells each rollout's envs and "
                         "each minibatch")
    bm.add_argument("--seed", type=int, default=0, help="base PRNG seed of every cell")
    bm.add_argument("--shard", default=None, metavar="I/N",
                    help="train only every N-th cell starting at cell I and write results-pI.json (report merges)")
    bm.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                    help="join JAX's distributed runtime (with --num-processes and --process-id; 'auto' where JAX "
                         "detects the cluster): each process trains its shard of the cells")
    bm.add_argument("--num-processes", type=int, default=None)
    bm.add_argument("--process-id", type=int, default=None)
    bm.add_argument("--no-progress", action="store_true")
    bm.add_argument("--dry-run", action="store_true",
                    help="list the cells and what a run would do with each (done, resume from update k, restart, "
                         "new) and the env steps left; train nothing")
    bm.set_defaults(func=_benchmark)
    im = sub.add_parser("import", help="convert an EPyMARL model (MARBLER's paper models) into a numpy policy folder")
    im.add_argument("model", help="EPyMARL agent state dict (.th; read without torch)")
    im.add_argument("--config", required=True, help="the model's EPyMARL config (.json)")
    im.add_argument("--scenario", required=True, help="scenario the model acts in (see `marbler-jax list`)")
    im.add_argument("--out", required=True, help="policy folder to write")
    im.add_argument("--protocol", choices=list(PROTOCOLS), default="marbler",
                    help="the env protocol the policy records (evaluate's default): MARBLER's models trained in "
                         "'marbler'")
    im.add_argument("--bundle", default=None, help="also write a Robotarium submission bundle to this folder")
    im.add_argument("--episodes", type=int, default=2, help="episodes the bundle runs")
    im.add_argument("--force", action="store_true", help="replace --out / --bundle even if they hold other files")
    im.set_defaults(func=_import)
    rp = sub.add_parser("report", help="tables (IQM, 95%% CI, best seed, paper), curves and probability of "
                        "improvement from a benchmark's results")
    rp.add_argument("results", help="benchmark folder (its results*.json are merged)")
    rp.add_argument("--out", default=None, help="report folder (default: the results folder)")
    rp.add_argument("--reps", type=int, default=2000, help="bootstrap resamples")
    rp.add_argument("--results-md", default=None, metavar="FILE",
                    help="also write the report as a results page (the project's RESULTS.md)")
    rp.add_argument("--readme", default=None, metavar="FILE",
                    help="also rewrite the reward summary of FILE (the project's README.md) between its markers")
    rp.add_argument("--paper-models", default=None, metavar="DIR",
                    help="show beside each cell the score of MARBLER's own paper model, from the `evaluate --json` "
                         "files <scenario>-<algo>.json in DIR (results/paper-models/marbler-jax-fresh: MARBLER's "
                         "protocol)")
    rp.add_argument("--no-progress", action="store_true", help="no progress bar")
    rp.set_defaults(func=_report)
    qs = sub.add_parser("quickstart", help="the main job: train, evaluate, plot and render (a few minutes)")
    qs.add_argument("--out", default="runs/quickstart")
    qs.add_argument("--force", action="store_true", help="replace --out even if it holds files quickstart did not write")
    qs.set_defaults(func=_quickstart)
    bench = sub.add_parser("bench", help="barrier certificate and integrator throughput")
    bench.add_argument("--out", default="bench_out/cbf.json")
    bench.add_argument("--quick", action="store_true")
    bench.set_defaults(func=_bench)
    for command in sub.choices.values():           # every option's default in its --help
        command.formatter_class = _DefaultsFormatter
    return parser


def main(argv=None) -> int:
    from .writer_lock import Busy

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    try:
        return args.func(args)
    except BrokenPipeError:
        # the reader of stdout left (e.g. `| head`): nothing more to say, and nothing to flush at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, TypeError, OSError) as err:
        if args.debug:
            raise
        if isinstance(err, OSError):            # disk full, a file where a folder should be, no permission
            where = f": {err.filename}" if err.filename else ""
            print(f"marbler-jax: error: {err.strerror or err}{where}", file=sys.stderr)
            return 1
        print(f"marbler-jax: error: {err}", file=sys.stderr)
        return 2
    except Busy as err:                     # another process writes the same run folder / results file
        print(f"marbler-jax: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"marbler-jax: interrupted{_resume_hint(args)}", file=sys.stderr)
        return 130


def console() -> None:
    """The ``marbler-jax`` program: :func:`main`, ending the process. After Ctrl-C it ends without the
    interpreter's teardown, which can crash in XLA's runtime while a compilation it interrupted is unwinding
    (the run's files are complete by then: the last chunk's checkpoint is committed and the lock goes with
    the process)."""
    code = main()
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def _resume_hint(args) -> str:
    """How to continue an interrupted command (every finished chunk and cell is saved)."""
    if args.command == "train":
        again = args.argv if "--resume" in args.argv else [*args.argv, "--resume"]
        return "; the last checkpoint is kept, resume with: marbler-jax " + " ".join(again)
    if args.command == "benchmark":
        return "; finished cells and checkpoints are kept, run the same command to resume: marbler-jax " + " ".join(args.argv)
    return ""


if __name__ == "__main__":
    sys.exit(main())
