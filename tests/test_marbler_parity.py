"""Parity with MARBLER's own code, step by step, in the ``marbler`` protocol.

MARBLER's code (``../shared/marbler``, run by ``scripts/marbler_oracle.py`` in a venv of its own without JAX)
plays whole episodes with random actions and with a paper model (imported with ``marbler-jax import``), and
records every simulator tick. marbler-jax then replays each episode from the same initial state with the same
actions, MARBLER's commands at each control refresh (MARBLER's barrier QP is solved loosely by cvxopt, so the
commands, not the barrier, are shared), and must give the same poses, observations, rewards, dones and
violations at every step (float64, 1e-9). The default suite plays a few episodes per scenario; the ``slow``
version plays 100 (half random, half the model). Skips where ``../shared/marbler`` is absent.
"""
from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl.epymarl import import_model
from marbler_jax_rl.marbler_starts import SCENARIOS as SCENARIO_FILES
from tests.golden_rollouts import assert_matches_marbler, episodes_from, initial_state, replay_recorded

REPO = Path(__file__).resolve().parents[1]
MARBLER = REPO.parent / "shared" / "marbler"
MODELS = MARBLER / "robotarium_gym" / "scenarios"
VENV = REPO / ".marbler-venv"
# MARBLER's stack, as ../shared/marbler/MARBLER-README-for-tests.md gives it (the oracle puts MARBLER on the path)
PACKAGES = ["numpy==1.24.4", "cvxopt", "scipy", "matplotlib<3.9", "pyyaml", "imageio", "gym==0.26.2",
            "robotarium-python-simulator"]
MODEL = {"Simple": "qmix", "PredatorCapturePrey": "vdn", "Warehouse": "vdn", "MaterialTransport": "vdn",
         "ArcticTransport": "vdn"}


def marbler_python() -> Path:
    """Python of a venv with MARBLER's stack and without JAX (made once, shared by the xdist workers)."""
    if not MARBLER.is_dir():
        pytest.skip(f"MARBLER's code is not at {MARBLER}")
    if os.environ.get("MARBLER_JAX_SKIP_RPS") == "1":
        pytest.skip("MARBLER_JAX_SKIP_RPS=1")
    python = VENV / "bin" / "python"
    probe = "import rps.robotarium, gym, cvxopt, yaml, numpy; assert numpy.__version__ == '1.24.4'"
    with open(REPO / ".marbler-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (python.exists() and subprocess.run([python, "-c", probe], capture_output=True).returncode == 0):
            subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)
            subprocess.run([python, "-m", "pip", "install", "-q", "--no-compile", "--disable-pip-version-check",
                            *PACKAGES], check=True, timeout=900)
    assert subprocess.run([python, "-c", "import jax"], capture_output=True).returncode != 0, "MARBLER venv has JAX"
    return python


def trace(python: Path, scenario: str, episodes: int, seed: int, out: Path, policy: Path | None = None,
          tight_qp: bool = False) -> list:
    command = [python, REPO / "scripts" / "marbler_oracle.py", "trace", "--scenario", scenario, "--episodes",
               str(episodes), "--seed", str(seed), "--out", out] + (["--tight-qp"] if tight_qp else [])
    if policy is not None:
        command += ["--policy", policy]
    result = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=1800,
                            env=dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1"))
    assert result.returncode == 0, result.stderr[-3000:]
    return episodes_from(np.load(out))


def check_scenario(fname: str, episodes: int, tmp_path: Path) -> int:
    """``episodes`` random and ``episodes`` model episodes of MARBLER's ``fname``, replayed; returns the
    number of steps compared."""
    python = marbler_python()
    name = SCENARIO_FILES[fname][0]
    model = MODELS / fname / "models" / MODEL[fname]
    policy = tmp_path / "policy"
    import_model(model.with_suffix(".th"), model.with_suffix(".json"), name, policy)
    played = (trace(python, fname, episodes, 7, tmp_path / "random.npz")
              + trace(python, fname, episodes, 8, tmp_path / "model.npz", policy))
    # the oracle's `starts` (resets alone) gives the starts of the episodes a policy plays from the same seed
    command = [python, REPO / "scripts" / "marbler_oracle.py", "starts", "--scenario", fname, "--episodes",
               str(episodes), "--seed", "8", "--out", tmp_path / "starts.json"]
    subprocess.run([str(c) for c in command], check=True, capture_output=True, timeout=600)
    starts = json.loads((tmp_path / "starts.json").read_text())["starts"]
    for start, ep in zip(starts, played[episodes:], strict=True):
        np.testing.assert_array_equal(start["reset_poses"], ep.data["reset_poses"], err_msg=ep.tag)
        assert start["reset_state"] == ep.meta["reset_state"] and start["reset_agents"] == ep.meta["reset_agents"]
    compared = 0
    with jax.enable_x64(True):
        env = marbler_jax.make(name, protocol="marbler")
        for ep in played:
            out = replay_recorded(env, initial_state(env, fname, ep), ep)
            assert_matches_marbler(env, out, ep)
            compared += ep.steps
    return compared


@pytest.mark.parametrize("fname", sorted(SCENARIO_FILES))
def test_marbler_and_marbler_jax_agree_step_by_step(fname, tmp_path):
    assert check_scenario(fname, 2, tmp_path) > 0


@pytest.mark.slow
@pytest.mark.parametrize("fname", sorted(SCENARIO_FILES))
def test_marbler_and_marbler_jax_agree_over_100_episodes(fname, tmp_path):
    steps = check_scenario(fname, 50, tmp_path)
    print(f"{fname}: 100 episodes, {steps} steps identical")


def test_with_a_tight_barrier_solve_marblers_commands_are_ours(tmp_path):
    """MARBLER's code with its barrier QP solved near-exactly (``--tight-qp``) sends, at every control refresh of a
    paper model's Material Transport episodes, the commands marbler-jax computes from the same poses and goals:
    the loose-QP gap (up to ~1 rad/s in omega with rps's solve) is all there is between the two controllers."""
    python = marbler_python()
    policy = tmp_path / "policy"
    model = MODELS / "MaterialTransport" / "models" / "mappo"
    import_model(model.with_suffix(".th"), model.with_suffix(".json"), "material_transport", policy)
    played = trace(python, "MaterialTransport", 2, 3, tmp_path / "tight.npz", policy, tight_qp=True)
    from marbler_jax import physics

    with jax.enable_x64(True):
        env = marbler_jax.make("material_transport", protocol="marbler")
        command = jax.jit(lambda p, g: physics.threshold(env.params, env.velocities(p, g)))
        goals_of = jax.jit(env.scenario.goals)
        gaps, refreshes = [], 0
        for ep in played:
            poses, sent = (np.swapaxes(ep.data[k], -1, -2) for k in ("iter_poses", "iter_vels"))
            index = ep.data["iter_index"]
            state = initial_state(env, "MaterialTransport", ep)
            for t in range(ep.steps):
                goals = goals_of(poses[index[t] - 1], state.scenario, ep.data["actions"][t].astype(np.int32))
                for j in range(index[t], index[t + 1], env.config.control_period):
                    gaps.append(np.abs(np.asarray(command(poses[j - 1], goals)) - sent[j]).max(axis=0))
                    refreshes += 1
        gaps = np.array(gaps)
    assert refreshes > 100 and gaps[:, 0].max() < 1e-3 and gaps[:, 1].max() < 1e-2, gaps.max(axis=0)
