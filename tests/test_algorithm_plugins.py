"""Algorithms from outside marbler-jax: ``examples/reinforce`` (written against the public interface only) by
``MODULE:NAME`` and installed as a package through the ``marbler_jax.algorithms`` entry points."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import marbler_jax
from marbler_jax.numpy_policy import NumpyPolicy
from marbler_jax_rl import registry
from marbler_jax_rl.driver import build_config
from marbler_jax_rl.recipes import PAPER_RECIPES, RECIPES, recipe

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "reinforce"
REFERENCE = "marbler_reinforce:REINFORCE"


@pytest.fixture
def example_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    yield
    sys.modules.pop("marbler_reinforce", None)


def test_the_built_ins_are_registered_once_with_everything_the_commands_use():
    assert registry.names()[:5] == ["vdn", "qmix", "qmix_ns", "mappo", "ippo"]
    for name in registry.names()[:5]:
        algorithm = registry.get(name)
        assert algorithm.name == name and algorithm.summary
        assert recipe(name) is RECIPES[name] and recipe(name, "paper") is PAPER_RECIPES[name]
    assert [registry.get(a).map_seeds_on_cpu for a in ("vdn", "mappo")] == [True, False]
    with pytest.raises(ValueError, match=r"an algorithm named 'vdn' is already registered"):
        registry.register(registry.Algorithm("vdn", "another", **{k: getattr(registry.get("ippo"), k) for k in (
            "config", "make_train", "greedy_policy", "policy_tensors")}))


@pytest.mark.parametrize("name, message", [
    ("nope", r"unknown algorithm 'nope'; available: \['vdn', 'qmix', 'qmix_ns', 'mappo', 'ippo'.*MODULE:NAME"),
    ("no_such_module:X", r"algorithm 'no_such_module:X': cannot import 'no_such_module'"),
    ("json:dumps", r"json:dumps is function, not a marbler_jax_rl.registry.Algorithm"),
    ("json:missing", r"algorithm 'json:missing': module 'json' has no 'missing'"),
])
def test_an_unknown_algorithm_is_one_clear_error(name, message):
    with pytest.raises(ValueError, match=message):
        registry.get(name)


def test_an_outside_algorithm_trains_acts_and_exports_through_the_interface(example_on_path):
    """MODULE:NAME finds the example; its trainer, greedy policy and exported numpy policy agree (the default
    suite's short version of the installed package's benchmark -> report -> export run below)."""
    algorithm = registry.get(REFERENCE)
    assert algorithm.name == REFERENCE and REFERENCE in registry.names()
    assert recipe(REFERENCE).config == algorithm.config()            # no recipe of its own: its defaults
    env = marbler_jax.make("simple_navigation")
    cfg = build_config(REFERENCE, dict(total_timesteps=2 * 8 * env.max_steps, num_envs=8, hidden=16))
    with pytest.raises(ValueError, match=r"unknown marbler_reinforce:REINFORCE setting\(s\) \['hiden'\]"):
        build_config(REFERENCE, dict(hiden=16))
    train = algorithm.make_train(env, cfg)
    params, metrics = jax.jit(train)(jax.random.PRNGKey(0))
    assert metrics["return"].shape == (2,) and np.isfinite(np.asarray(metrics["return"])).all()
    fields, tensors = algorithm.policy_tensors(cfg, params)
    policy = NumpyPolicy(dict(format="marbler-jax-policy/1", algo=REFERENCE, scenario=env.name,
                              num_agents=env.num_agents, obs_dim=env.obs_dim, num_actions=env.num_actions, **fields),
                         tensors)
    obs, _ = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), 16))
    greedy = algorithm.greedy_policy(env, cfg, params)(None, obs)
    numpy_actions = np.stack([policy.act(np.asarray(o))[0] for o in obs])
    np.testing.assert_array_equal(numpy_actions, np.asarray(greedy))


def _cli(args, pythonpath: Path, cwd: Path) -> str:
    env = dict(os.environ, PYTHONPATH=str(pythonpath), MPLBACKEND="Agg")
    done = subprocess.run([sys.executable, "-m", "marbler_jax_rl", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done.stdout


@pytest.mark.slow
def test_an_installed_algorithm_package_runs_through_benchmark_report_and_export(tmp_path):
    """``pip install examples/reinforce`` (into a folder of its own), then the benchmark, the report and a
    Robotarium bundle by the name its entry point declares, with nothing of marbler-jax changed."""
    site, source = tmp_path / "site", tmp_path / "reinforce"
    shutil.copytree(EXAMPLE, source)                 # the build writes next to the sources, not into the repo
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(site), str(source)], check=True, capture_output=True, timeout=600)
    bench = tmp_path / "bench"
    _cli(["benchmark", "--algos", "reinforce", "--scenarios", "simple_navigation", "--seeds", "2", "--total-steps",
          "20000", "--eval-points", "2", "--test-episodes", "4", "--absolute-factor", "2", "--no-progress",
          "--out", str(bench)], site, tmp_path)
    results = json.loads((bench / "results.json").read_text())
    assert list(results["marbler"]["simple_navigation"]) == ["reinforce"]
    _cli(["report", str(bench), "--reps", "50"], site, tmp_path)
    assert "reinforce" in (bench / "report.md").read_text()
    run = bench / "runs" / "simple_navigation" / "reinforce"
    _cli(["export", str(run), "--out", str(tmp_path / "policy"), "--bundle", str(tmp_path / "bundle")], site, tmp_path)
    spec = json.loads(str(np.load(tmp_path / "bundle" / "policy_spec.npy")))
    assert spec["algo"] == "reinforce" and spec["kind"] == "actor"
    assert (tmp_path / "bundle" / "main.py").exists()
