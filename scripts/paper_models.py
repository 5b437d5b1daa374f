"""MARBLER's paper models (its Table II) in marbler-jax and in MARBLER's own code, side by side.

The 16 EPyMARL models that MARBLER ships (MAPPO, QMIX, QMIX_NS, VDN on Predator Capture Prey, Warehouse,
Material Transport and Arctic Transport) are imported with ``marbler-jax import`` and evaluated

(a) in marbler-jax's ``marbler`` protocol (MARBLER's simulator, loop and first observation),
(b) in MARBLER's own code (``scripts/marbler_oracle.py``, run by a Python with MARBLER's stack),
(c) -- the paper's Table II value --,
(d) in marbler-jax's robots' loop (today's robots: what a bundle deploys),
(e) as a Robotarium bundle run by today's Robotarium simulator (rps v2),
and in marbler-jax with MARBLER's settings but its ``robotarium: True`` loop (controller every iteration),

each over ``--episodes`` episodes, and written as one JSON file per model and loop under ``--out``;
``table`` turns them into the Markdown table that RESULTS.md holds. marbler-jax plays the episodes from the
very start states MARBLER's code plays with ``--seed`` (``starts``: MARBLER's robots' poses and task state,
e.g. Material Transport's zone loads), so (a) and (b) are compared episode by episode and share every start's
luck; (a) also runs from ``--fresh-episodes`` of marbler-jax's own start draws (``marbler-jax-fresh/``, its
population mean). Steps (each skips what is done):

    python scripts/paper_models.py import                       # policies/ from ../shared/marbler
    python scripts/paper_models.py starts                       # starts/ in .marbler-venv (seconds)
    python scripts/paper_models.py marbler --workers 2           # (b) in .marbler-venv, ~1 episode/s a process
    python scripts/paper_models.py evaluate                     # (a), (d), robotarium: True, fresh (a)
    python scripts/paper_models.py robotarium --episodes 30 --workers 2   # (e) in .rps-v2-venv
    python scripts/paper_models.py table --results-md RESULTS.md --readme README.md
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from marbler_jax_rl.report import mean_ci

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO.parent / "shared" / "marbler" / "robotarium_gym" / "scenarios"
SCENARIOS = {"predator_capture_prey": "PredatorCapturePrey", "warehouse": "Warehouse",
             "material_transport": "MaterialTransport", "arctic_transport": "ArcticTransport"}
ALGOS = ("mappo", "qmix", "qmix_ns", "vdn")
OUT = REPO / "results" / "paper-models"


def models():
    """``(scenario, algo, model .th, config .json)`` of the paper's 16 models."""
    for scenario, folder in SCENARIOS.items():
        for algo in ALGOS:
            yield scenario, algo, MODELS / folder / "models" / f"{algo}.th", MODELS / folder / "models" / f"{algo}.json"


def policy_dir(out: Path, scenario: str, algo: str) -> Path:
    return out / "policies" / f"{scenario}-{algo}"


def _import(args) -> None:
    sys.path.insert(0, str(REPO))
    from marbler_jax_rl.epymarl import import_model

    if not MODELS.is_dir():
        raise SystemExit(f"MARBLER's models are not at {MODELS}")
    for scenario, algo, model, config in models():
        spec = import_model(model, config, scenario, policy_dir(args.out, scenario, algo), force=True)
        print(f"imported {model.relative_to(MODELS)} -> {policy_dir(args.out, scenario, algo)} ({spec['algo']})")


def _marbler(args) -> None:
    """(b): every model (of ``--scenarios``) in MARBLER's own code, one process per model (``--workers`` at a
    time), skipping finished files; with ``--tight-qp`` the barrier's QP solved near-exactly (folder
    ``marbler-tight-qp/``), to measure the loose solve's share of a difference between (a) and (b)."""
    from concurrent.futures import ThreadPoolExecutor

    folder = args.out / ("marbler-tight-qp" if args.tight_qp else "marbler")

    def run(item):
        scenario, algo = item
        target = folder / f"{scenario}-{algo}.json"
        tmp = target.with_suffix(".json.part")
        subprocess.run([args.python, str(REPO / "scripts" / "marbler_oracle.py"), "evaluate", "--scenario",
                        SCENARIOS[scenario], "--policy", str(policy_dir(args.out, scenario, algo)),
                        "--episodes", str(args.episodes), "--seed", str(args.seed), "--out", str(tmp)]
                       + (["--tight-qp"] if args.tight_qp else []),
                       check=True, stderr=subprocess.DEVNULL,
                       env=dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1"))   # a core per process
        tmp.rename(target)

    folder.mkdir(parents=True, exist_ok=True)
    todo = [(scenario, algo) for scenario, algo, _, _ in models()
            if (args.scenarios is None or scenario in args.scenarios)
            and not (folder / f"{scenario}-{algo}.json").exists()]
    with ThreadPoolExecutor(args.workers) as pool:
        list(pool.map(run, todo))


def starts_file(out: Path, scenario: str) -> Path:
    return out / "starts" / f"{scenario}.json"


def _starts(args) -> None:
    """The start states of the ``--episodes`` episodes MARBLER's code plays with ``--seed`` (each scenario)."""
    for scenario, marbler_class in SCENARIOS.items():
        target = starts_file(args.out, scenario)
        if target.exists():
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([args.python, str(REPO / "scripts" / "marbler_oracle.py"), "starts", "--scenario", marbler_class,
                        "--episodes", str(args.episodes), "--seed", str(args.seed), "--out", str(target)],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        print(f"{scenario}: {args.episodes} starts of seed {args.seed} -> {target}")


FRESH = "marbler-jax-fresh"   # (a) from marbler-jax's own draws of the start states, --fresh-episodes of them


def _evaluate(args) -> None:
    """(a) and (d): every model in marbler-jax, in MARBLER's protocol and in the robots' loop, from MARBLER's
    starts where ``starts`` wrote them (else from fresh resets); and (a) from ``--fresh-episodes`` fresh starts,
    its population mean."""
    sys.path.insert(0, str(REPO))
    from marbler_jax_rl.evaluate import evaluate_policy

    # MARBLER's protocol; the robots' loop; MARBLER's own settings with its robots' loop (`robotarium: True` in
    # a scenario's config.yaml: the controller every iteration, rps 6bb184e, the zero first observation)
    loops = {"marbler-jax": {"protocol": "marbler"}, "robots-loop": {"protocol": "robots"},
             "marbler-robotarium-true": {"control_period": 1}, FRESH: {"protocol": "marbler"}}
    for scenario, algo, _, _ in models():
        for loop, env in loops.items():
            target = args.out / loop / f"{scenario}-{algo}.json"
            if target.exists():
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            starts, episodes = None, args.fresh_episodes if loop == FRESH else args.episodes
            if loop != FRESH and starts_file(args.out, scenario).exists():
                starts = json.loads(starts_file(args.out, scenario).read_text())["starts"][:episodes]
            start = time.perf_counter()
            result = evaluate_policy(policy_dir(args.out, scenario, algo), episodes, seed=args.seed,
                                     env_overrides=env, per_episode=True, marbler_starts=starts)
            result["marbler_starts"] = starts is not None
            result["seconds"] = round(time.perf_counter() - start, 1)
            target.write_text(json.dumps(result))
            print(f"{loop} {scenario} {algo}: reward {result['pooled']['reward']['mean']:.2f} "
                  f"({result['seconds']:.0f} s)")


# rps v2 runs the bundle as the Robotarium would, except the drive-in from the chargers to each episode's initial
# poses (thousands of iterations of its own barrier, per episode): skipped, so the robots start exactly there.
RPS_V2_PRELUDE = """
import runpy, sys
from rps import robotarium
_init = robotarium.Robotarium.__init__
def _no_drive_in(self, *args, **kwargs):
    kwargs["skip_initialization"] = True
    _init(self, *args, **kwargs)
robotarium.Robotarium.__init__ = _no_drive_in
sys.argv = ["main.py"]
runpy.run_path("main.py", run_name="__main__")
"""


def parse_bundle_output(stdout: str, max_steps: int, metric_names) -> dict:
    """Per-episode metrics from a bundle's ``episode k/K: return=... steps=...`` lines, counted as
    :func:`marbler_jax.rollout.first_episode_metrics` counts them."""
    rows: dict[str, list] = {}
    for line in stdout.splitlines():
        if not line.startswith("episode "):
            continue
        fields = dict(item.split("=", 1) for item in line.split(": ", 1)[1].split() if "=" in item)
        violated = fields["violation"] == "True"
        row = {"reward": float(fields["return"]), "steps": float(max_steps if violated else int(fields["steps"])),
               "collisions": 100.0 * (fields["collisions"] == "True"),
               "out_of_bounds": 100.0 * (fields["out_of_bounds"] == "True"),
               **{name: float(fields[name]) for name in metric_names if name in fields}}
        for key, value in row.items():
            rows.setdefault(key, []).append(value)
    return rows


def _robotarium(args) -> None:
    """(e): every model's Robotarium bundle (robots' loop) run by rps v2, ``--episodes`` start states each."""
    sys.path.insert(0, str(REPO))
    from marbler_jax.deploy.bundle import deployment_settings, write_bundle
    from marbler_jax_rl.evaluate import open_policy

    from concurrent.futures import ThreadPoolExecutor

    def run(item):
        scenario, algo = item
        target = args.out / "robotarium-v2" / f"{scenario}-{algo}.json"
        folder = args.out / "bundles" / f"{scenario}-{algo}"
        env, policy = open_policy(policy_dir(args.out, scenario, algo), deployment_settings())     # as (d)
        write_bundle(env, policy_dir(args.out, scenario, algo), folder, algo, episodes=args.episodes,
                     seed=args.seed, force=True)
        start = time.perf_counter()
        result = subprocess.run([args.python, "-c", RPS_V2_PRELUDE], cwd=folder, capture_output=True, text=True,
                                env=dict(os.environ, MARBLER_JAX_HEADLESS="1", OPENBLAS_NUM_THREADS="1"))
        if result.returncode != 0:
            raise SystemExit(f"{folder}: rps v2 failed\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}")
        metrics = parse_bundle_output(result.stdout, env.max_steps, env.metric_names)
        seconds = round(time.perf_counter() - start, 1)
        target.write_text(json.dumps(dict(scenario=scenario, algo=algo, loop="robots", simulator="rps v2",
                                          episodes=len(metrics["reward"]), seconds=seconds,
                                          episodes_metrics=metrics)))
        print(f"rps v2 {scenario} {algo}: reward {np.mean(metrics['reward']):.2f} ({seconds:.0f} s)", flush=True)

    (args.out / "robotarium-v2").mkdir(parents=True, exist_ok=True)
    todo = [(scenario, algo) for scenario, algo, _, _ in models()
            if not (args.out / "robotarium-v2" / f"{scenario}-{algo}.json").exists()
            and scenario in (args.scenarios or SCENARIOS)]
    with ThreadPoolExecutor(args.workers) as pool:
        list(pool.map(run, todo))


LOOPS = {"marbler-jax": "(a) marbler-jax, MARBLER's protocol", "marbler": "(b) MARBLER's code",
         "robots-loop": "(d) marbler-jax, robots' loop", "robotarium-v2": "(e) rps v2, the bundle"}
LEFT = {"predator_capture_prey": "prey_left", "material_transport": "material_left"}


def _episodes(out: Path, loop: str, scenario: str, algo: str) -> dict | None:
    path = out / loop / f"{scenario}-{algo}.json"
    return json.loads(path.read_text())["episodes_metrics"] if path.exists() else None


def difference_ci(a, b, paired: bool = False) -> tuple[float, float, float]:
    """``mean(a) - mean(b)`` with its 95 % CI (normal approximation): of the episode-by-episode differences where
    ``paired`` (the same starts, in order), else Welch's."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if paired:
        mean, half = mean_ci(a - b)
    else:
        mean = a.mean() - b.mean()
        half = 1.96 * np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return float(mean), float(mean - half), float(mean + half)


def paired(out: Path, loop: str, scenario: str, algo: str, other: list) -> bool:
    """Whether ``loop``'s episodes of a model began at MARBLER's starts, those ``other`` (MARBLER's code, seed
    ``--seed``) played, in the same order."""
    path = out / loop / f"{scenario}-{algo}.json"
    if not path.exists():
        return False
    result = json.loads(path.read_text())
    return result.get("marbler_starts", False) and len(result["episodes_metrics"]["reward"]) == len(other)


def _cell(values, digits: int = 2) -> str:
    if values is None:
        return "—"
    mean, half = mean_ci(values)
    return f"{mean:.{digits}f} ± {half:.{digits}f}"


def table_markdown(out: Path) -> str:
    """RESULTS.md's section on the paper's models: reward and task metrics in the four loops."""
    sys.path.insert(0, str(REPO))
    from marbler_jax_rl.evaluate import PAPER_TABLE2

    counts = {}                                     # episodes per model in each loop
    for loop in LOOPS:
        found = [e for s, a, _, _ in models() if (e := _episodes(out, loop, s, a))]
        if found:
            counts[loop] = len(found[0]["reward"])
    lines = [
        "## The paper's own models",
        "",
        "MARBLER ships the 16 models of its Table II (EPyMARL GRU agents). `marbler-jax import` converts each into a "
        "numpy policy (its forward pass equals MARBLER's torch agents: `tests/test_epymarl.py`), which then runs "
        "(a) in marbler-jax's `marbler` protocol, (b) in MARBLER's own code at the paper's commit "
        "(`scripts/marbler_oracle.py`), (d) in marbler-jax's robots' loop (today's robots: controller and "
        "barrier every iteration, rps v2 physics, the real first observation) and (e) as the Robotarium bundle "
        "that `marbler-jax export POLICY --bundle` writes, run by today's Robotarium simulator (rps v2, its "
        "drive-in to the start poses skipped); (c) is the paper's Table II (mean ± standard deviation over 100 "
        "episodes). Elsewhere mean ± 95 % CI half-width over "
        + ", ".join(f"{n} episodes for {LOOPS[loop][:3]}" for loop, n in counts.items())
        + ". marbler-jax plays its episodes from the start states MARBLER's code played (its robots' poses and "
        "task state, drawn by MARBLER's own reset), so (a) and (b) face the same episodes; *agree*: the 95 % "
        "CI of the episode-by-episode difference (a) − (b) contains 0. Made with:",
        "",
        "```bash",
        "python scripts/paper_models.py import && python scripts/paper_models.py starts   # starts in .marbler-venv",
        "python scripts/paper_models.py evaluate",
        "python scripts/paper_models.py marbler --workers 2          # in .marbler-venv (its README says how)",
        "python scripts/paper_models.py robotarium --episodes 30 --workers 2   # in the tests' .rps-v2-venv",
        "python scripts/paper_models.py table --results-md RESULTS.md --readme README.md",
        "```",
        "",
        "### Reward",
        "",
        "| scenario | algorithm | (a) marbler-jax, MARBLER's protocol | (b) MARBLER's code | (a) − (b) [95 % CI] "
        "| agree | (c) paper | (d) robots' loop | (e) rps v2, the bundle |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    agree, disagree = [], []
    for scenario, algo, _, _ in models():
        a, b, d, e = (_episodes(out, loop, scenario, algo) for loop in LOOPS)
        paper = PAPER_TABLE2.get(scenario, {}).get(algo, {}).get("reward")
        diff, verdict = "—", "—"
        if a is not None and b is not None:
            mean, low, high = difference_ci(a["reward"], b["reward"],
                                            paired(out, "marbler-jax", scenario, algo, b["reward"]))
            diff, ok = f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]", low <= 0 <= high
            verdict = "yes" if ok else "**no**"
            agree.append(ok)
            if not ok:
                disagree.append((scenario, algo))
        lines.append(f"| {scenario} | {algo} | {_cell(a and a['reward'])} | {_cell(b and b['reward'])} | {diff} | "
                     f"{verdict} | {f'{paper[0]:g} ± {paper[1]:g}' if paper else '—'} | {_cell(d and d['reward'])} | "
                     f"{_cell(e and e['reward'])} |")
    lines += ["", f"(a) and (b) agree on {sum(agree)} of {len(agree)} models."]
    if disagree:
        lines += ["", "Where they differ, (a) from marbler-jax's own draws of the start states (its population mean) "
                  "beside (b) (Welch):", "", "| scenario | algorithm | (a), fresh starts | (b) MARBLER's code | "
                  "difference [95 % CI] | agree |", "|---|---|---|---|---|---|"]
        for scenario, algo in disagree:
            fresh, b = _episodes(out, FRESH, scenario, algo), _episodes(out, "marbler", scenario, algo)
            if fresh is None:
                continue
            mean, low, high = difference_ci(fresh["reward"], b["reward"])
            lines.append(f"| {scenario} | {algo} | {_cell(fresh['reward'])} ({len(fresh['reward'])} episodes) | "
                         f"{_cell(b['reward'])} | {mean:+.2f} [{low:+.2f}, {high:+.2f}] | "
                         f"{'yes' if low <= 0 <= high else '**no**'} |")
        lines += ["", f"At 95 % each, one interval in twenty misses 0 by chance alone ({len(agree)} intervals here)."]
    lines += tight_qp_lines(out)
    lines += ["",
              "### Task metrics: (a) marbler-jax, MARBLER's protocol / (b) MARBLER's code", "",
              "| scenario | algorithm | steps | prey / material left | collisions % | out of bounds % |",
              "|---|---|---|---|---|---|"]
    for scenario, algo, _, _ in models():
        a, b = (_episodes(out, loop, scenario, algo) for loop in ("marbler-jax", "marbler"))
        cells = []
        for metric in ("steps", LEFT.get(scenario), "collisions", "out_of_bounds"):
            if metric is None:
                cells.append("—")
                continue
            digits = 1 if metric in ("collisions", "out_of_bounds", "steps") else 2
            cells.append(f"{_cell(a and a[metric], digits)} / {_cell(b and b[metric], digits)}")
        lines.append(f"| {scenario} | {algo} | " + " | ".join(cells) + " |")
    lines += ["", "### Which loop the paper's numbers come from", "",
              "MARBLER's `config.yaml` files switch the loop with `robotarium`: `False` (every 15 iterations, the "
              "simulation setting) or `True` (every iteration, for the robots). Each model's reward in both, "
              "emulated in marbler-jax with MARBLER's simulator and zero first observation, beside the paper's:", "",
              "| scenario | algorithm | (c) paper | `robotarium: False` = (a) | `robotarium: True` | closer to the paper |",
              "|---|---|---|---|---|---|"]
    apart = {"False": [], "True": []}       # models whose two loops' CIs do not overlap, by the closer loop
    for scenario, algo, _, _ in models():
        a, t = (_episodes(out, loop, scenario, algo) for loop in ("marbler-jax", "marbler-robotarium-true"))
        paper = PAPER_TABLE2.get(scenario, {}).get(algo, {}).get("reward")
        which = "—"
        if a is not None and t is not None and paper:
            gaps = {"False": abs(np.mean(a["reward"]) - paper[0]), "True": abs(np.mean(t["reward"]) - paper[0])}
            which = min(gaps, key=gaps.get)
            (mean_a, half_a), (mean_t, half_t) = mean_ci(a["reward"]), mean_ci(t["reward"])
            if abs(mean_a - mean_t) > half_a + half_t:
                apart[which].append(f"{scenario} {algo}")
                which = f"**{which}**"
        lines.append(f"| {scenario} | {algo} | {f'{paper[0]:g} ± {paper[1]:g}' if paper else '—'} | "
                     f"{_cell(a and a['reward'])} | {_cell(t and t['reward'])} | {which} |")
    if apart["True"] or apart["False"]:
        lines += ["", "Where the two loops' rewards are apart (CIs not overlapping; **bold**), the paper's value is "
                      f"the `robotarium: True` one for {len(apart['True'])} model(s) "
                      f"({', '.join(apart['True']) or 'none'}) and the `robotarium: False` one for "
                      f"{len(apart['False'])} ({', '.join(apart['False']) or 'none'}); elsewhere the two loops' CIs overlap."]
    lines += ["", "### Collisions and boundary violations on today's robots: (d) marbler-jax, robots' loop / (e) rps "
              "v2, the bundle", "", "| scenario | algorithm | collisions % | out of bounds % |", "|---|---|---|---|"]
    for scenario, algo, _, _ in models():
        d, e = (_episodes(out, loop, scenario, algo) for loop in ("robots-loop", "robotarium-v2"))
        cells = [f"{_cell(d and d[m], 1)} / {_cell(e and e[m], 1)}" for m in ("collisions", "out_of_bounds")]
        lines.append(f"| {scenario} | {algo} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def tight_qp_lines(out: Path) -> list[str]:
    """MARBLER's code with its barrier's QP solved near-exactly (b') beside rps's loose solve (b), where
    ``marbler --tight-qp`` ran: what the loose solve does to a model's score."""
    rows = [(s, a, _episodes(out, "marbler", s, a), _episodes(out, "marbler-tight-qp", s, a)) for s, a, _, _ in models()]
    rows = [row for row in rows if row[2] is not None and row[3] is not None]
    if not rows:
        return []
    scenarios = sorted({s for s, _, _, _ in rows})
    lines = ["", "### MARBLER's loose barrier solve", "",
             "MARBLER's controller (`robotarium_gym/utilities/controller.py`, line 14) solves the barrier QP with the "
             "cvxopt options rps sets when it is imported (`rps/utilities/barrier_certificates.py`, lines 18-20: "
             "`reltol` and `feastol` 1e-2, 50 iterations), which leave its commands off the exact solution near other "
             "robots (marbler-jax solves the QP exactly). The same models in MARBLER's code with a near-exact solve "
             f"(b', {len(rows[0][3]['reward'])} episodes each, the same starts as (b): `python "
             f"scripts/paper_models.py marbler --tight-qp --scenarios {' '.join(scenarios)}`, in .marbler-venv):", "",
             "| scenario | algorithm | (b) MARBLER, rps's QP | (b') MARBLER, tight QP | (b') − (b) [95 % CI] | "
             "collisions % (b) / (b') | out of bounds % (b) / (b') |", "|---|---|---|---|---|---|---|"]
    unchanged = 0
    for scenario, algo, loose, tight in rows:
        mean, low, high = difference_ci(tight["reward"], loose["reward"], len(tight["reward"]) == len(loose["reward"]))
        unchanged += low <= 0 <= high
        lines.append(f"| {scenario} | {algo} | {_cell(loose['reward'])} | {_cell(tight['reward'])} | "
                     f"{mean:+.2f} [{low:+.2f}, {high:+.2f}] | {_cell(loose['collisions'], 1)} / "
                     f"{_cell(tight['collisions'], 1)} | {_cell(loose['out_of_bounds'], 1)} / "
                     f"{_cell(tight['out_of_bounds'], 1)} |")
    return lines + ["", f"The tight solve leaves the score unchanged (the CI of (b') − (b) contains 0) for {unchanged} of "
                        f"{len(rows)} models."]


def summary_line(out: Path) -> str:
    """The README's sentence on the paper's models: how many agree between marbler-jax and MARBLER's code."""
    agree = total = 0
    for scenario, algo, _, _ in models():
        a, b = (_episodes(out, loop, scenario, algo) for loop in ("marbler-jax", "marbler"))
        if a is not None and b is not None:
            low, high = difference_ci(a["reward"], b["reward"], paired(out, "marbler-jax", scenario, algo,
                                                                       b["reward"]))[1:]
            agree, total = agree + (low <= 0 <= high), total + 1
    return (f"MARBLER's own 16 paper models, imported with `marbler-jax import`, score the same in marbler-jax's "
            f"`marbler` protocol as in MARBLER's code on {agree} of {total} models, playing the same start states "
            "(95 % CI of the episode-by-episode difference contains 0; RESULTS.md, *The paper's own models*, with "
            "the robots' loop and rps v2 beside them).")


def _table(args) -> None:
    sys.path.insert(0, str(REPO))
    from marbler_jax_rl.report import replace_block

    text = table_markdown(args.out)
    (args.out / "table.md").write_text(text)
    command = "scripts/paper_models.py table"
    if args.results_md:
        page = Path(args.results_md)
        page.write_text(replace_block(page.read_text(), "paper-models", command, text))
    if args.readme:
        page = Path(args.readme)
        if "<!-- begin paper-models-summary" not in page.read_text():
            raise SystemExit(f"{page} has no paper-models-summary block: put its begin and end lines where it goes")
        page.write_text(replace_block(page.read_text(), "paper-models-summary", command, summary_line(args.out)))
    print(text)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("command", choices=["import", "starts", "marbler", "evaluate", "robotarium", "table"])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fresh-episodes", type=int, default=5000,
                        help="`evaluate`: episodes of (a) from marbler-jax's own start draws (its population mean)")
    parser.add_argument("--workers", type=int, default=1, help="MARBLER processes at a time (for `marbler`)")
    parser.add_argument("--python", default=None,
                        help="a Python with MARBLER's stack (for `starts`, `marbler`; default .marbler-venv) or with rps v2 (for "
                             "`robotarium`; default .rps-v2-venv, the test suite's)")
    parser.add_argument("--scenarios", nargs="+", choices=list(SCENARIOS), default=None,
                        help="only these scenarios' models (for `marbler` and `robotarium`)")
    parser.add_argument("--tight-qp", action="store_true",
                        help="`marbler`: solve MARBLER's barrier QP near-exactly (writes marbler-tight-qp/)")
    parser.add_argument("--results-md", default=None, help="page whose paper-models block `table` rewrites")
    parser.add_argument("--readme", default=None, help="page whose paper-models-summary block `table` rewrites")
    args = parser.parse_args(argv)
    if args.python is None:
        args.python = str(REPO / (".rps-v2-venv" if args.command == "robotarium" else ".marbler-venv") / "bin" / "python")
    {"import": _import, "starts": _starts, "marbler": _marbler, "evaluate": _evaluate, "robotarium": _robotarium,
     "table": _table}[args.command](args)


if __name__ == "__main__":
    main()
