"""Benchmark the barrier certificates and the integrator; writes JSON and a Markdown table.

    python scripts/bench_cbf.py --out bench_out/cbf.json [--quick]

Measures, on whatever JAX backend is active:
* team-solves/s of ``cbf.make_barrier(kind)`` (default sweeps) for N in {2, 4, 8, 20, 50} and batch
  in {1, 256, 4096} (float32, jit, random well-spread configurations, compile excluded);
* robot-ticks/s of ``physics.integrate`` for the same grid (29 ticks per call, as one MARBLER step);
* solve accuracy: the share of rps tight-QP golden cases matched (if ``../shared/golden`` exists).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from datetime import date
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from marbler_jax_rl.checkpoints import atomic_write  # noqa: E402
from marbler_jax import cbf, physics  # noqa: E402


def timed(fn, *args, min_time=1.0):
    """Median seconds per call of a jitted ``fn`` (compile excluded) and the compile time."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    times = []
    t_start = time.perf_counter()
    while time.perf_counter() - t_start < min_time or len(times) < 3:
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times)), compile_s


def problem(n, batch, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform([-1.5, -0.9], [1.5, 0.9], size=(batch, n, 2))
    u = rng.normal(size=(batch, n, 2)) * 0.15
    return jnp.asarray(x, jnp.float32), jnp.asarray(u, jnp.float32)


def bench_cbf(kinds, ns, batches, min_time):
    rows = []
    bar = tqdm(total=len(kinds) * len(ns) * len(batches), desc="barrier benchmarks", unit="config")
    for kind in kinds:
        barrier = cbf.make_barrier(kind, **({"safety_radius": 0.2} if kind == "si2" else {}))
        for n in ns:
            for batch in batches:
                x, u = problem(n, batch)
                if kind in cbf.UNI_KINDS:
                    x = jnp.concatenate([x, jnp.zeros(x.shape[:-1] + (1,), x.dtype)], axis=-1)
                fn = jax.jit(barrier)
                sec, compile_s = timed(fn, u, x, min_time=min_time)
                rows.append(dict(kind=kind, n=n, batch=batch, sweeps=barrier.sweeps(n),
                                 team_solves_per_s=batch / sec, compile_s=compile_s))
                bar.update()
                tqdm.write(f"cbf {kind:12s} N={n:2d} batch={batch:5d} sweeps={barrier.sweeps(n):3d} "
                           f"{batch / sec:14,.0f} team-solves/s")
    bar.close()
    return rows


def bench_integrate(ns, batches, min_time, ticks=29):
    rows = []
    params = physics.PRESETS["robotarium"]
    for n in ns:
        for batch in batches:
            rng = np.random.default_rng(0)
            poses = jnp.asarray(rng.uniform(-1, 1, size=(batch, n, 3)), jnp.float32)
            vel = jnp.asarray(rng.uniform(-0.3, 0.3, size=(batch, n, 2)), jnp.float32)
            fn = jax.jit(lambda p, v: physics.integrate(params, p, v, ticks))
            sec, _ = timed(fn, poses, vel, min_time=min_time)
            rate = batch * n * ticks / sec
            rows.append(dict(n=n, batch=batch, ticks_per_call=ticks, robot_ticks_per_s=rate))
            print(f"integrate N={n:2d} batch={batch:5d} {rate:16,.0f} robot-ticks/s", flush=True)
    return rows


def accuracy():
    """Share of golden tight-QP cases matched per kind (skipped without ../shared/golden)."""
    if golden_case("si_cert_default", 4) is None:
        return []
    files = {
        "si_cert2_marbler_safe": ("si2", dict(safety_radius=0.2)), "si_cert_default": ("si", {}),
        "si_cert_boundary_default": ("si_boundary", {}), "uni_cert_default": ("uni", {}),
        "uni_cert2_default": ("uni2", {}), "uni_cert_boundary_default": ("uni_boundary", {}),
    }
    rows = []
    for fname, (kind, kwargs) in files.items():
        barrier = cbf.make_barrier(kind, **kwargs)
        for n in (4, 20):
            x, u_nom, ref, ok = golden_case(fname, n)
            u = np.asarray(jax.jit(barrier)(jnp.asarray(u_nom, jnp.float32), jnp.asarray(x, jnp.float32)))
            err = np.abs(u - ref).max(axis=(1, 2))[ok]
            rows.append(dict(kind=kind, n=n, cases=int(ok.sum()), worst_abs_err=float(err.max()),
                             p99_abs_err=float(np.percentile(err, 99)), median_abs_err=float(np.median(err))))
            print(f"accuracy {kind:12s} N={n:2d} worst {err.max():.2e} p99 {np.percentile(err, 99):.2e}", flush=True)
    return rows


def golden_case(fname: str, n: int):
    """``(x, u_nom, u_out_tight, ok)`` of one golden CBF file at team size ``n`` (robot-major),
    or ``None`` when ``../shared/golden`` is absent."""
    path = Path(__file__).resolve().parents[2] / "shared" / "golden" / "cbf" / f"{fname}.npz"
    if not path.exists():
        return None
    data = np.load(path)
    g = {k[len(f"N{n}_"):]: v for k, v in data.items() if k.startswith(f"N{n}_")}
    swap = lambda a: np.swapaxes(a, -1, -2)  # noqa: E731
    return swap(g["x"]), swap(g["u_nom"]), swap(g["u_out_tight"]), g["status_tight"] == 1


def sweep_study(n=20, batch=4096, sweeps=(16, 24, 48, 100), min_time=1.0):
    """Speed and golden accuracy of ``si2`` (radius 0.2) at one N for several sweep budgets."""
    case = golden_case("si_cert2_marbler_safe", n)
    rows = []
    for iters in sweeps:
        barrier = cbf.make_barrier("si2", safety_radius=0.2, iterations=iters)
        x, u = problem(n, batch)
        sec, _ = timed(jax.jit(barrier), u, x, min_time=min_time)
        row = dict(n=n, batch=batch, sweeps=iters, team_solves_per_s=batch / sec)
        if case is not None:
            x, u_nom, ref, ok = case
            with jax.enable_x64(True):
                out = np.asarray(jax.jit(barrier)(jnp.asarray(u_nom), jnp.asarray(x)))
            err = np.abs(out - ref).max(axis=(1, 2))
            tol = 5e-4 + 1e-3 * np.abs(ref).max(axis=(1, 2))
            row["golden_match"] = float((err <= tol)[ok].mean())
        rows.append(row)
        print(f"sweep study si2 N={n} sweeps={iters:3d}: {row['team_solves_per_s']:10,.0f} team-solves/s, "
              f"golden match {row.get('golden_match', float('nan')):.1%}", flush=True)
    return rows


def markdown(result):
    lines = [f"Machine: {result['machine']}; backend {result['backend']}; jax {result['jax']}; {result['date']}", "",
             "| kind | N | batch | sweeps | team-solves/s |", "|---|---:|---:|---:|---:|"]
    for r in result["cbf"]:
        lines.append(f"| {r['kind']} | {r['n']} | {r['batch']} | {r['sweeps']} | {r['team_solves_per_s']:,.0f} |")
    lines += ["", "| integrate N | batch | robot-ticks/s |", "|---:|---:|---:|"]
    for r in result["integrate"]:
        lines.append(f"| {r['n']} | {r['batch']} | {r['robot_ticks_per_s']:,.0f} |")
    if result.get("sweep_study"):
        lines += ["", "| si2 sweep study: N | batch | sweeps | team-solves/s | golden match |", "|---:|---:|---:|---:|---:|"]
        for r in result["sweep_study"]:
            lines.append(f"| {r['n']} | {r['batch']} | {r['sweeps']} | {r['team_solves_per_s']:,.0f} | "
                         f"{r.get('golden_match', float('nan')):.1%} |")
    if result["accuracy"]:
        lines += ["", "| accuracy kind | N | cases | worst abs err | p99 abs err |", "|---|---:|---:|---:|---:|"]
        for r in result["accuracy"]:
            lines.append(f"| {r['kind']} | {r['n']} | {r['cases']} | {r['worst_abs_err']:.2e} | {r['p99_abs_err']:.2e} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench_out/cbf.json", help="JSON output path")
    parser.add_argument("--quick", action="store_true", help="small grid, short timings (smoke test)")
    parser.add_argument("--kinds", default="si2,si,si_boundary,uni,uni2,uni_boundary,uni_dd,uni_dd_boundary")
    parser.add_argument("--sweep-study-only", action="store_true", help="only the si2 N=20 sweep study")
    args = parser.parse_args(argv)
    if args.sweep_study_only:
        rows = sweep_study()
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(dict(date=str(date.today()), jax=jax.__version__, sweep_study=rows), indent=2))
        return rows
    kinds = args.kinds.split(",")
    ns = [2, 4] if args.quick else [2, 4, 8, 20, 50]
    batches = [1, 64] if args.quick else [1, 256, 4096]
    min_time = 0.05 if args.quick else 1.0
    result = dict(
        date=str(date.today()), machine=f"{platform.processor() or platform.machine()}, {jax.device_count()} "
        f"{jax.default_backend()} device(s), {__import__('os').cpu_count()} CPU cores",
        backend=jax.default_backend(), jax=jax.__version__,
        cbf=bench_cbf(kinds if not args.quick else kinds[:2], ns, batches, min_time),
        integrate=bench_integrate(ns, batches, min_time),
        accuracy=[] if args.quick else accuracy(),
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, json.dumps(result, indent=2))
    table = markdown(result)
    atomic_write(out.with_suffix(".md"), table + "\n")
    print(table)
    return result


if __name__ == "__main__":
    main()
