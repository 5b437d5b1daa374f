"""Longer learning checks on Predator Capture Prey (``-m slow``: each trains a recipe's full budget).

Each value-based algorithm trains with its recipe through the CLI (``marbler-jax train``, the command a user
types; two learner devices, set in a fresh interpreter before JAX starts) for 10M env steps, one seed, and its
best checkpoint must clearly learn the task over 200 greedy episodes: a reward far above random actions
(-4.8) and most of the six prey captured. Whether a recipe reaches the paper's Table II is the benchmark's
question (``marbler-jax benchmark``, RESULTS.md), with five seeds per cell.

    python -m pytest -m slow tests/test_learning_pcp.py
"""
from __future__ import annotations

import subprocess
import sys

import pytest

RANDOM_RETURN = -4.8


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["vdn", "qmix", "qmix_ns"])
def test_recipe_captures_prey(tmp_path, algo):
    from marbler_jax_rl.evaluate import evaluate_run

    out = tmp_path / algo
    subprocess.run([sys.executable, "-m", "marbler_jax_rl.cli", "train", "--scenario", "pcp", "--algo", algo,
                    "--hp", "learner_devices=2", "--total-steps", "1e7", "--out", str(out), "--no-progress",
                    "--eval-episodes", "0"], check=True, timeout=3600)
    result = evaluate_run(out, episodes=200)["pooled"]
    assert result["reward"]["mean"] >= RANDOM_RETURN + 25, result
    assert result["prey_left"]["mean"] < 2.0, result
