"""Benchmark the renderer: frames/s of ``render_grid_episode`` (one reused ``FrameDrawer``).

    python scripts/bench_render.py --out bench_out/render.json [--frames 40]

For each scenario, one env (dpi 80) and a 2 x 2 grid of four envs (dpi 60) of a random-action
episode: frames per second and milliseconds per env tile, the drawing only (the states are
recorded first). Writes JSON and a Markdown table next to it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import marbler_jax  # noqa: E402
from marbler_jax_rl.checkpoints import atomic_write  # noqa: E402
from marbler_jax.render import record_episodes, render_grid_episode  # noqa: E402


def measure(env, num_envs: int, frames: int) -> float:
    """Seconds per frame of a ``num_envs`` grid over the first ``frames`` steps of one episode."""
    states, _, _ = record_episodes(env, None, jax.random.PRNGKey(0), num_envs=num_envs)
    states = jax.tree_util.tree_map(lambda x: x[:frames], states)
    render_grid_episode(env, jax.tree_util.tree_map(lambda x: x[:2], states))       # fonts, caches
    t0 = time.perf_counter()
    drawn = render_grid_episode(env, states)
    return (time.perf_counter() - t0) / len(drawn)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench_out/render.json")
    parser.add_argument("--frames", type=int, default=40, help="frames per measurement (at most an episode's)")
    parser.add_argument("--scenarios", default=",".join(marbler_jax.registered()))
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error(f"--frames must be >= 2, got {args.frames}")
    rows = []
    for name in args.scenarios.split(","):
        env = marbler_jax.make(name)
        for num_envs in (1, 4):
            seconds = measure(env, num_envs, args.frames)
            rows.append(dict(scenario=name, envs=num_envs, frames_per_s=1 / seconds,
                             ms_per_tile=1000 * seconds / num_envs))
            print(f"{name:22s} envs {num_envs}: {1 / seconds:6.1f} frames/s "
                  f"({1000 * seconds / num_envs:.0f} ms per env tile)", flush=True)
    result = dict(date=str(date.today()), machine=f"{platform.machine()}, {os.cpu_count()} CPU cores", rows=rows)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, json.dumps(result, indent=2))
    lines = [f"Machine: {result['machine']}; {result['date']}", "",
             "| scenario | envs | frames/s | ms per env tile |", "|---|---:|---:|---:|"]
    lines += [f"| {r['scenario']} | {r['envs']} | {r['frames_per_s']:.1f} | {r['ms_per_tile']:.0f} |" for r in rows]
    atomic_write(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return result


if __name__ == "__main__":
    main()
