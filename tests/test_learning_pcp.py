"""Longer learning checks on Predator Capture Prey (``-m slow``; 12-30 minutes each on 2 cores).

VDN and QMIX train through the CLI with the ``fast`` preset (MARBLER's training control loop, safe
CBF, penalties; one gradient step per collected episode) for 2M env steps, one seed, and assert the
greedy return of the driver's evaluation. The thresholds sit below what this code reaches
(RESULTS.md, greedy after 2M steps: VDN 24.0-28.9, QMIX 24.1; random actions -4.8) and below the
paper's simulated rewards (VDN 33.25, QMIX 30.02 after 5M steps).

VDN and QMIX_NS also train with the ``parallel`` preset (on PCP: per-robot GRU 32 with LayerNorm, gamma 0.95,
lr 1.5e-3; VDN 36M env steps, QMIX_NS 28M; two learner devices: 13-15 minutes per seed on the slower development
VMs) and must reach the paper's reward for that algorithm over 500 greedy episodes, within the paper's spread.
VDN: at least 32.8 (the paper: 33.25 ± 0.46, less that spread) for the better of two seeds trained in one
program, the paper's protocol (it reports the best of 5 seeds' models; ``evaluate --best-seed``). Single seeds
of the recipe gave 33.14, 33.47, 33.37 and 33.46 (RESULTS.md) and, under this suite's XLA flags (``-O2``: other
float rounding, other samples), 32.67 alone and 33.57 / 33.42 as this check's two seeds (23 minutes on the slower
VM): mean 33.30, sd 0.31, so one seed would miss 32.8 about one time in twenty, the better of two far more
rarely. QMIX_NS: one seed, at least 31.5 (the paper: 31.76 ± 2.7; this command 33.46 / 33.61 for seeds 0 / 1,
the general settings 31.90-33.40 over thirteen runs). The paper's VDN shares one
network over the robots; ours levels off at 31.4-31.8 that way (32.9 at GRU 64, at half the speed; RESULTS.md), so
the preset gives each robot its own.

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
@pytest.mark.parametrize("algo, seeds, floor", [("qmix_ns", 1, 31.5), ("vdn", 2, 32.8)])
def test_parallel_preset_reaches_the_papers_reward(tmp_path, algo, seeds, floor):
    from algorithms.evaluate import PAPER, evaluate_run

    out = tmp_path / algo
    # a fresh interpreter: two learner devices must be set before JAX starts
    subprocess.run([sys.executable, "-m", "marbler_jax.cli", "train", "--scenario", "predator_capture_prey",
                    "--algo", algo, "--preset", "parallel", "--hp", "learner_devices=2", "--seeds", str(seeds),
                    "--out", str(out), "--no-progress"], check=True, timeout=3600)
    # the paper's protocol with several seeds: the model of the seed with the best greedy test return
    result = evaluate_run(out, episodes=500, seed_selection="best")["pooled"]
    paper_reward, paper_std = PAPER["predator_capture_prey"][algo]["reward"]
    assert (paper_reward, paper_std) == {"qmix_ns": (31.76, 2.7), "vdn": (33.25, 0.46)}[algo]
    assert result["reward"]["mean"] >= floor >= paper_reward - paper_std, result
    assert result["prey_left"]["mean"] < 0.5, result
