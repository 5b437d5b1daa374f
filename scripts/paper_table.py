"""Run MARBLER's Table II with our algorithms: train + evaluate every (scenario, algorithm) cell.

    python scripts/paper_table.py --total-steps 2e6 --seeds 1 --runs runs/table --out bench_out/paper_table.json
    python scripts/paper_table.py --algos qmix_ns --learner-devices 2 --runs runs/table-v2 --out bench_out/t.json

For every cell it runs ``marbler-jax train --scenario S --algo A --preset P`` into ``RUNS/S-A`` and
``marbler-jax evaluate RUNS/S-A --episodes 100`` (greedy, best checkpoint; ``--best-seed``: only the seed
with the highest greedy test return, the paper's protocol -- its Table II reports the best of five seeds'
models), each in its own process, then writes JSON and a Markdown table with the paper's simulated numbers
beside ours. Cells that
already have an evaluation are skipped and an interrupted training run is resumed, so the script can
be stopped and restarted at any time.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from algorithms.driver import has_setting  # noqa: E402
from algorithms.evaluate import PAPER  # noqa: E402

SCENARIOS = ("predator_capture_prey", "warehouse", "material_transport", "arctic_transport")
ALGOS = ("mappo", "vdn", "qmix", "qmix_ns")
ROWS = ("reward", "steps", "prey_left", "material_left", "collisions", "out_of_bounds")


def run_cell(scenario: str, algo: str, args) -> dict:
    """Train (or resume) and evaluate one cell; returns the evaluation JSON plus timings."""
    run = Path(args.runs) / f"{scenario}-{algo}"
    evaluation = run / ("eval_best_best_seed.json" if args.best_seed else "eval_best.json")
    if evaluation.exists():
        return json.loads(evaluation.read_text())
    cli = [sys.executable, "-m", "marbler_jax"]
    train = cli + ["train", "--scenario", scenario, "--algo", algo, "--preset", args.preset,
                   "--total-steps", str(args.total_steps), "--seeds", str(args.seeds), "--out", str(run),
                   "--no-progress"]
    if args.learner_devices > 1 and has_setting(algo, "learner_devices"):
        train += ["--hp", f"learner_devices={args.learner_devices}"]
    if (run / "config.json").exists() and not (run / "params.npz").exists():
        train.append("--resume")
    t0 = time.perf_counter()
    if not (run / "params.npz").exists():
        subprocess.run(train, check=True)
    train_s = time.perf_counter() - t0
    subprocess.run(cli + ["evaluate", str(run), "--episodes", str(args.episodes), "--no-progress"]
                   + (["--best-seed"] if args.best_seed else []), check=True, stdout=subprocess.DEVNULL)
    result = json.loads(evaluation.read_text())
    summary = json.loads((run / "evaluation.json").read_text())
    result["train_seconds"] = summary.get("train_seconds", train_s)
    result["env_steps_per_s"] = summary.get("env_steps_per_s")
    evaluation.write_text(json.dumps(result, indent=2))
    return result


def cell_text(value: dict | None, key: str) -> str:
    if value is None:
        return "—"
    if key in ("collisions", "out_of_bounds"):
        return f"{value['mean']:.0f} %"
    return f"{value['mean']:.2f} ± {value['std']:.2f}"


def paper_text(scenario: str, algo: str, key: str) -> str:
    ref = PAPER.get(scenario, {}).get(algo, {}).get(key)
    if ref is not None:
        return f"{ref[0]:g} ± {ref[1]:g}"
    return "0 %" if key in ("collisions", "out_of_bounds") else "—"


def markdown(results: dict, args) -> str:
    evaluated = "the best seed's" if args.best_seed else "each seed's"
    lines = [f"Cells: `--preset {args.preset}`, {args.total_steps:.3g} env steps x {args.seeds} seed(s), "
             f"{args.episodes} greedy episodes of {evaluated} best checkpoint; paper: MARBLER Table II "
             "(simulated: the best model of 5 seeds, 100 episodes; 5M steps for VDN/QMIX, 25M for MAPPO).", ""]
    for scenario in SCENARIOS:
        done = [a for a in ALGOS if (scenario, a) in results]
        if not done:
            continue
        lines += [f"### {scenario}", "", "| metric | " + " | ".join(f"{a} (ours) | {a} (paper)" for a in done) + " |",
                  "|---|" + "---|---|" * len(done)]
        for key in ROWS:
            if not any(key in results[(scenario, a)]["pooled"] for a in done):
                continue
            cells = []
            for a in done:
                cells += [cell_text(results[(scenario, a)]["pooled"].get(key), key), paper_text(scenario, a, key)]
            lines.append(f"| {key.replace('_', ' ')} | " + " | ".join(cells) + " |")
        times = ", ".join(f"{a} {results[(scenario, a)].get('train_seconds', float('nan')):.0f} s" for a in done)
        lines += ["", f"Training wall time: {times}.", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    parser.add_argument("--algos", nargs="+", default=["vdn", "qmix", "mappo", "qmix_ns"], choices=ALGOS)
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--total-steps", type=float, default=2e6)
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--best-seed", action="store_true",
                        help="evaluate only each cell's best seed (the paper's protocol; use with --seeds 5)")
    parser.add_argument("--learner-devices", type=int, default=1,
                        help="VDN/QMIX/QMIX_NS: split each gradient step over this many CPU devices")
    parser.add_argument("--runs", default="runs/table")
    parser.add_argument("--out", default="bench_out/paper_table.json")
    args = parser.parse_args()
    results = {}
    for algo in args.algos:
        for scenario in args.scenarios:
            t0 = time.perf_counter()
            results[(scenario, algo)] = run_cell(scenario, algo, args)
            reward = results[(scenario, algo)]["pooled"]["reward"]
            print(f"{scenario:22s} {algo:8s} reward {reward['mean']:7.2f} ± {reward['std']:.2f} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({f"{s}/{a}": r for (s, a), r in results.items()}, indent=2))
    out.with_suffix(".md").write_text(markdown(results, args))
    print(out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
