"""Longer learning checks on Predator Capture Prey (``-m slow``; 12-30 minutes each on 2 cores).

VDN and QMIX train through the CLI with the ``fast`` preset (MARBLER's training control loop, safe
CBF, penalties; one gradient step per collected episode) for 2M env steps, one seed, and assert the
greedy return of the driver's evaluation. The thresholds sit below what this code reaches
(RESULTS.md, greedy after 2M steps: VDN 24.0-28.9, QMIX 24.1; random actions -4.8) and below the
paper's simulated rewards (VDN 33.25, QMIX 30.02 after 5M steps). QMIX_NS trains with the
``parallel`` preset (on PCP since 2026-11-24: GRU 32 with LayerNorm, gamma 0.95, lr 1.5e-3, 28M env steps, two
learner devices: 13-15 minutes on the slower development VMs; before, 45M steps of GRU 64: 13-14 minutes on the
earlier host, 30 at half speed) and must reach the paper's QMIX_NS level over 500 greedy episodes:
at least 31.5 (the paper: 31.76 ± 2.7 over its 5 seeds; our seven runs of the preset and its
``eps_spread`` variant 31.90-33.23, mean 32.68, sd 0.45, so a run below 31.5 is ~0.5 % likely). Since
the preset gives each agent its previous action (``last_action``), this command gave 33.33 with the general settings
(seed 3 with the flag: 33.40; ``--seed 1``: 32.16) and gives 33.46 / 33.61 (seeds 0 / 1) with the PCP-tuned ones, so
the floor is now further below what it reaches.

    python -m pytest -m slow tests/test_learning_pcp.py
"""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from marbler_jax.cli import main as cli

RANDOM_RETURN = -4.8


@pytest.mark.slow
@pytest.mark.parametrize("algo, floor", [("vdn", 18.0), ("qmix", 16.0)])
def test_value_based_learners_capture_prey(tmp_path, algo, floor):
    out = tmp_path / algo
    assert cli(["train", "--scenario", "predator_capture_prey", "--algo", algo, "--total-steps", "2e6",
                "--seeds", "1", "--out", str(out), "--no-progress"]) == 0
    trained = json.loads((out / "evaluation.json").read_text())["trained"]
    assert trained["return"] >= floor > RANDOM_RETURN + 10, trained
    assert trained["prey_left"] < 3.0, trained      # of 6: most prey are found and captured


@pytest.mark.slow
def test_qmix_ns_parallel_preset_reaches_the_papers_qmix_ns_level(tmp_path):
    from algorithms.evaluate import PAPER, evaluate_run

    out = tmp_path / "qmix_ns"
    # a fresh interpreter: two learner devices must be set before JAX starts
    subprocess.run([sys.executable, "-m", "marbler_jax.cli", "train", "--scenario", "predator_capture_prey",
                    "--algo", "qmix_ns", "--preset", "parallel", "--hp", "learner_devices=2", "--out", str(out),
                    "--no-progress"], check=True, timeout=3600)
    result = evaluate_run(out, episodes=500)["pooled"]
    assert PAPER["predator_capture_prey"]["qmix_ns"]["reward"] == (31.76, 2.7)
    assert result["reward"]["mean"] >= 31.5, result
    assert result["prey_left"]["mean"] < 0.5, result
