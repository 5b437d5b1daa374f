"""Robotarium bundle cost: size on disk and compute time per Robotarium iteration of ``main.py``.

For every scenario it exports an (untrained) policy of the given architecture, writes the bundle,
runs ``main.py`` headless in a Python that has the Robotarium simulator (``--python``, e.g. the
test suite's ``.rps-venv/bin/python``; no JAX needed there) and reads the per-iteration compute
times (``get_poses()`` to ``set_velocities``) from the bundle's trace. Writes JSON and prints a
Markdown table.

    python scripts/bench_bundle.py --python .rps-venv/bin/python --out bench_out/bundle.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

import marbler_jax
from marbler_jax_rl import ippo, vdn
from marbler_jax_rl.checkpoints import atomic_write
from marbler_jax_rl.export import export_params
from marbler_jax.deploy.bundle import folder_size, write_bundle

ARCHITECTURES = {
    "vdn-gru128": (vdn, lambda: vdn.VDNConfig(hidden=128), "vdn"),
    "ippo-mlp128": (ippo, lambda: ippo.IPPOConfig(hidden=128), "ippo"),
}


def bench(python: str, scenario: str, arch: str, episodes: int, workdir: Path) -> dict:
    module, make_cfg, algo = ARCHITECTURES[arch]
    env = marbler_jax.make(scenario)
    cfg = make_cfg()
    params = module.make_train(env, cfg).init(jax.random.PRNGKey(0))["params"]
    policy, folder, trace = workdir / f"{scenario}-policy", workdir / scenario, workdir / f"{scenario}-trace"
    export_params(algo, cfg, params, env, policy)
    write_bundle(env, policy, folder, algo, episodes=episodes)
    run_env = dict(os.environ, MARBLER_JAX_HEADLESS="1", MARBLER_JAX_TRACE=str(trace))
    run_env.pop("PYTHONPATH", None)
    result = subprocess.run([python, "main.py"], cwd=folder, env=run_env, capture_output=True, text=True)
    if result.returncode:
        raise RuntimeError(result.stdout + result.stderr)
    compute = np.concatenate([np.load(trace / f"episode_{k}.npz")["compute_s"] for k in range(episodes)]) * 1e3
    return dict(scenario=scenario, arch=arch, robots=env.num_agents, files=len(list(folder.iterdir())),
                bundle_kib=folder_size(folder) / 1024, iterations=int(compute.size),
                compute_ms_mean=float(compute.mean()), compute_ms_p99=float(np.percentile(compute, 99)),
                compute_ms_max=float(compute.max()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", required=True, help="a Python with rps (robotarium-python-simulator)")
    parser.add_argument("--scenarios", nargs="+", default=sorted(marbler_jax.registered()))
    parser.add_argument("--archs", nargs="+", default=sorted(ARCHITECTURES), choices=sorted(ARCHITECTURES))
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--out", default="bench_out/bundle.json")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(s, a) for a in args.archs for s in args.scenarios]
        for scenario, arch in tqdm(jobs, desc="bundles"):
            workdir = Path(tmp) / arch
            workdir.mkdir(exist_ok=True)
            rows.append(bench(str(Path(args.python).absolute()), scenario, arch, args.episodes, workdir))
            tqdm.write(json.dumps(rows[-1]))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, json.dumps(dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(),
                                      rows=rows), indent=1))
    print("| scenario | policy | robots | files | bundle KiB | iterations | compute ms mean | p99 | max |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scenario']} | {r['arch']} | {r['robots']} | {r['files']} | {r['bundle_kib']:.0f} | "
              f"{r['iterations']} | {r['compute_ms_mean']:.2f} | {r['compute_ms_p99']:.2f} | {r['compute_ms_max']:.2f} |")


if __name__ == "__main__":
    main()
