"""Robotarium submission bundles: flat, JAX-free, and running in the real simulator exactly like the env.

The real-simulator test installs ``robotarium-python-simulator`` from PyPI (it imports as ``rps``)
into a separate virtualenv without JAX (``.rps-venv/``, kept between runs; numpy 1.24, the oldest
numpy we support) and runs each bundle's ``main.py`` there headless. Set ``MARBLER_JAX_SKIP_RPS=1``
to skip it on a machine without PyPI access.
"""
from __future__ import annotations

import ast
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
from marbler_jax_rl import ippo, mappo, qmix, vdn
from marbler_jax_rl.export import export_params
from marbler_jax_rl.cli import main as cli
from marbler_jax.deploy.bundle import write_bundle
from marbler_jax.deploy import flatten
from marbler_jax.deploy.flatten import CORE_MODULES, check_bundle_folder, flatten_module, flatten_modules
from marbler_jax.deploy.replay import replay_trace
from tests.conftest import build_once
from tests.helpers import initial_params, slow_unless

REPO = Path(__file__).resolve().parents[1]
RPS_VENV = REPO / ".rps-venv"
RPS_V2_VENV = REPO / ".rps-v2-venv"
RPS_V2_DIR = REPO.parent / "shared" / "robotarium"   # rps v2 wheel + the server's library list
SERVER_VERSIONS = ("numpy==2.2.6", "scipy==1.15.3", "matplotlib==3.10.8", "cvxopt==1.3.2")

# scenario -> (algorithm module, config, algo name, env overrides): every architecture we train
UNTRAINED = {
    "predator_capture_prey": (vdn, vdn.VDNConfig(hidden=16), "vdn", {"control_period": 15}),
    "warehouse": (qmix, qmix.QMIXNSConfig(hidden=16), "qmix_ns", {}),
    "material_transport": (mappo, mappo.MAPPOConfig(hidden=16, shared=False), "mappo", {}),
    "arctic_transport": (qmix, qmix.QMIXConfig(hidden=16, recurrent=False), "qmix", {}),
    "discovery": (vdn, vdn.VDNConfig(hidden=16, recurrent=False), "vdn", {}),
    "foraging": (ippo, ippo.IPPOConfig(hidden=16), "ippo", {}),
    "rware": (qmix, qmix.QMIXConfig(hidden=16), "qmix", {}),
}
SHORT = {"max_episode_steps": 25}   # untrained bundles: shorter episodes keep the test quick
HEADING_OBS = {"discovery", "foraging", "rware"}
FLOAT32_REPLAY = {"simple_navigation", "predator_capture_prey", "rware"}   # all bundles are replayed in float64


@pytest.fixture(scope="session")
def bundles(tmp_path_factory, ippo_simple_nav_run):
    """A trained IPPO Simple Navigation bundle (via the CLI) and untrained bundles of the other scenarios,
    built once per session and shared by the xdist workers (``build_once``)."""
    def build(root):
        assert cli(["export", str(ippo_simple_nav_run), "--out", str(root / "sn-policy"), "--bundle",
                    str(root / "simple_navigation"), "--checkpoint", "final", "--episodes", "2"]) == 0
        for name, (module, cfg, algo, overrides) in UNTRAINED.items():
            env = marbler_jax.make(name, **overrides, **SHORT)
            params = initial_params(module, env, cfg, seed=1)
            export_params(algo, cfg, params, env, root / f"{name}-policy")
            write_bundle(env, root / f"{name}-policy", root / name, algo, episodes=1, seed=3)

    root = build_once(tmp_path_factory, "bundles", build)
    return {name: root / name for name in ("simple_navigation", *UNTRAINED)}


def test_bundles_are_flat_jax_free_and_carry_the_training_config(bundles):
    for name, folder in bundles.items():
        files = check_bundle_folder(folder)
        assert {"main.py", "robotarium_loop.py", "cbf.py", "physics.py", "policy_spec.npy", "bundle_config.npy",
                "initial_poses.npy", f"{name}.py"} <= set(files)
        config = json.loads(str(np.load(folder / "bundle_config.npy", allow_pickle=False)))
        assert config["scenario"] == name
        assert config["config"]["control_period"] == (15 if name == "predator_capture_prey" else 1)
        for source in folder.glob("*.py"):
            imports = [line for line in source.read_text().splitlines() if line.lstrip().startswith(("import", "from"))]
            assert not [line for line in imports if "marbler_jax" in line or "jax" in line.split()], source.name
    scenario = (bundles["predator_capture_prey"] / "predator_capture_prey.py").read_text()
    assert "def reset" not in scenario and "def observe" in scenario and "@frozen_state" in scenario


@pytest.mark.parametrize("bad", ["folder", "json", "import_jax", "from_flax"])
def test_bundle_check_rejects_what_the_robotarium_cannot_run(bundles, tmp_path, bad):
    folder = tmp_path / "b"
    shutil.copytree(bundles["predator_capture_prey"], folder)
    if bad == "folder":
        (folder / "models").mkdir()
    elif bad == "json":
        (folder / "config.json").write_text("{}")
    elif bad == "import_jax":
        (folder / "extra.py").write_text("import numpy as np\nimport jax.numpy as jnp\n")
    else:
        (folder / "main.py").write_text((folder / "main.py").read_text() + "\nfrom flax import struct\n")
    with pytest.raises(ValueError):
        check_bundle_folder(folder)


def test_flattening_refuses_jax_in_the_shared_step_logic(tmp_path, monkeypatch):
    (tmp_path / "my_scenario.py").write_text(
        "import jax.numpy as jnp\n\n"
        "def reset(key):\n    return jnp.zeros(3)\n\n"
        "def observe(poses):\n    return jnp.asarray(poses)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match="observe"):
        flatten_module("my_scenario", {"my_scenario": "my_scenario"})


def test_flat_sources_format_without_f_strings(tmp_path, monkeypatch):
    """Python >= 3.12 unparses f-strings with nested quotes that Python 3.11 and older cannot parse: the
    flat sources use str.format instead, with the same results."""
    (tmp_path / "fstrings.py").write_text(
        "def message(spec, width):\n"
        "    name = 'x'\n"
        "    return (f\"format {spec.get('format')!r}; {{braces}} {name:>{width}}|{f'{width:03d}'} \"\n"
        "            f\"{3.14159:.{width - 3}f} {name!s:^{width}.1} {'=' * 2}\")\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    source, _ = flatten_module("fstrings", {"fstrings": "fstrings"})
    flat = {}
    exec(compile(source, "flat_fstrings.py", "exec"), flat)
    import fstrings

    assert flat["message"]({"format": "v1"}, 5) == fstrings.message({"format": "v1"}, 5) == (
        "format 'v1'; {braces}     x|005 3.14   x   ==")
    for name, text in dict(flatten_modules(CORE_MODULES), fstrings=source).items():
        assert not any(isinstance(node, ast.JoinedStr) for node in ast.walk(ast.parse(text))), name


def _two_passes(names):
    """The reference: every module flattened once to learn what it drops, then again without those imports."""
    dropped = {module: flatten_module(module, names)[1] for module in names}
    return {names[module]: flatten_module(module, names, dropped)[0] for module in names}


def test_one_pass_in_import_order_flattens_like_two_passes(tmp_path, monkeypatch):
    names = dict(CORE_MODULES, **{"marbler_jax.scenarios.predator_capture_prey": "predator_capture_prey"})
    reference = _two_passes(names)
    assert flatten_modules(names) == reference
    # the scenario imports a JAX-only sampler from the base module, which its flat imports must lose
    assert reference["predator_capture_prey"] != flatten_module("marbler_jax.scenarios.predator_capture_prey", names)[0]
    # package modules that import from each other (a cycle) are flattened in two passes
    package = tmp_path / "cycpkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("import jax\nfrom cycpkg.b import g, spawn_band\n\ndef f():\n    return g()\n\n"
                                  "def reset(key):\n    return jax.random.normal(key)\n")
    (package / "b.py").write_text("import jax\nfrom cycpkg.a import f, reset\n\ndef g():\n    return 1\n\n"
                                  "def spawn_band(key):\n    return jax.random.normal(key)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(flatten, "PACKAGE", "cycpkg")
    cycle = {"cycpkg.a": "cyc_a", "cycpkg.b": "cyc_b"}
    flat = flatten_modules(cycle)
    assert flat == _two_passes(cycle)
    assert "from cyc_b import g\n" in flat["cyc_a"] and "from cyc_a import f\n" in flat["cyc_b"]


def _rps_python() -> Path:
    """Python of a virtualenv with the PyPI Robotarium simulator and numpy 1.24, without JAX."""
    if os.environ.get("MARBLER_JAX_SKIP_RPS") == "1":
        pytest.skip("MARBLER_JAX_SKIP_RPS=1")
    python = RPS_VENV / "bin" / "python"
    ready = python.exists() and subprocess.run([python, "-c", "import rps.robotarium, numpy"],
                                               capture_output=True).returncode == 0
    if not ready:
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(RPS_VENV)], check=True)
        subprocess.run([python, "-m", "pip", "install", "-q", "--no-compile", "--disable-pip-version-check",
                        "robotarium-python-simulator", "numpy>=1.24,<1.25"], check=True, timeout=900)
    assert subprocess.run([python, "-c", "import jax"], capture_output=True).returncode != 0, "rps venv has JAX"
    return python


def _rps_v2_python() -> Path:
    """Python of a virtualenv with the Robotarium's rps v2 simulator and the server's library
    versions, without JAX; skips where ``../shared/robotarium`` is absent."""
    if os.environ.get("MARBLER_JAX_SKIP_RPS") == "1":
        pytest.skip("MARBLER_JAX_SKIP_RPS=1")
    wheels = sorted(RPS_V2_DIR.glob("robotarium_python_simulator-*.whl"))
    if not wheels:
        pytest.skip(f"no rps v2 wheel in {RPS_V2_DIR}")
    python = RPS_V2_VENV / "bin" / "python"
    probe = "import rps.robotarium, numpy; assert numpy.__version__ == '2.2.6'; assert hasattr(rps.robotarium.Robotarium, 'debug')"
    if not (python.exists() and subprocess.run([python, "-c", probe], capture_output=True).returncode == 0):
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(RPS_V2_VENV)], check=True)
        subprocess.run([python, "-m", "pip", "install", "-q", "--no-compile", "--disable-pip-version-check", *SERVER_VERSIONS,
                        str(wheels[-1])], check=True, timeout=900)
    assert subprocess.run([python, "-c", "import jax"], capture_output=True).returncode != 0, "rps v2 venv has JAX"
    return python


def _run_bundle(python, folder, trace, extra_env=None, prelude=None):
    """``main.py`` of the bundle ``folder`` run headless by ``python`` (or ``prelude``, Python source that runs
    it); returns its stdout. A run that drives in under rps v2: :func:`_run_on_rps_v2`."""
    result = _bundle_process(python, folder, trace, extra_env, prelude)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


def _bundle_process(python, folder, trace, extra_env=None, prelude=None, args=()):
    env = dict(os.environ, MARBLER_JAX_HEADLESS="1", MARBLER_JAX_TRACE=str(trace), **(extra_env or {}))
    env.pop("PYTHONPATH", None)
    # the rps venvs are installed without bytecode: the first run writes it for what it imports, into a cache
    # outside the bundle folders (a bundle must stay flat), and later runs load it
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["PYTHONPYCACHEPREFIX"] = str(REPO / ".pytest_cache" / "pycache-bundles")
    command = [str(python), "main.py"] if prelude is None else [str(python), "-c", prelude, *args]
    return subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True, timeout=600)


# rps v2 drives the robots in from chargers it picks at random and breaks barrier deadlocks with random
# waypoints (Python's and numpy's global generators, unseeded), until every robot is at its initial pose: for
# some layouts a deadlock now and then never breaks (Predator Capture Prey's: about one drive-in in 300), and the
# run hangs. The v2 runs seed both generators and end with DRIVE_IN_STUCK where the drive-in has not arrived
# after DRIVE_IN_STEPS iterations (typical: 500-5,000); _run_on_rps_v2 then runs again with the next seed.
DRIVE_IN_STEPS = 20_000
DRIVE_IN_STUCK = 75          # exit status
V2_DRIVE_IN = """
import random, sys
import numpy
from rps import robotarium
random.seed(int(sys.argv[1]))
numpy.random.seed(int(sys.argv[1]))
_drive_in = robotarium.Robotarium.initialize
def _capped_drive_in(self, conditions):
    step, count = self.step, [0]
    def counted():
        count[0] += 1
        if count[0] > {steps}:
            sys.exit({stuck})
        step()
    self.step = counted
    try:
        _drive_in(self, conditions)
    finally:
        del self.step
robotarium.Robotarium.initialize = _capped_drive_in
"""
RUN_MAIN = "import runpy; sys.argv = ['main.py']; runpy.run_path('main.py', run_name='__main__')"


def _run_on_rps_v2(python, folder, trace, extra_env=None, steps=DRIVE_IN_STEPS):
    """Like :func:`_run_bundle` under rps v2, with the drive-in seeded and capped at ``steps`` iterations
    (``V2_DRIVE_IN``): a drive-in that does not arrive is run again with the next seed, up to 3 seeds."""
    prelude = V2_DRIVE_IN.format(steps=steps, stuck=DRIVE_IN_STUCK) + RUN_MAIN
    for seed in range(3):
        result = _bundle_process(python, folder, trace, extra_env, prelude, [str(seed)])
        if result.returncode != DRIVE_IN_STUCK:
            assert result.returncode == 0, result.stdout + result.stderr
            return result.stdout
    pytest.fail(f"{folder.name}: rps v2's drive-in did not reach the initial poses within {steps} "
                "iterations with seeds 0, 1 and 2")


def test_bundles_run_in_the_real_rps_simulator_like_the_env(bundles, tmp_path):
    python = _rps_python()
    report = {}
    pairs = []
    for name, folder in bundles.items():
        trace = tmp_path / f"trace-{name}"
        stdout = _run_bundle(python, folder, trace)
        episodes = 2 if name == "simple_navigation" else 1
        assert stdout.count("episode ") == episodes and "##### DEBUG OUTPUT #####" in stdout, stdout
        if name == "simple_navigation":   # the trained policy: rps recorded no collision, no boundary violation
            assert "collided" not in stdout and "outside the boundaries" not in stdout, stdout
            assert "violation=False" in stdout
        else:                              # untrained policies may violate: the bundle saw what rps saw
            assert ("outside the boundaries" not in stdout) or "out_of_bounds=True" in stdout, stdout
            assert ("collided" not in stdout) or "collisions=True" in stdout, stdout
        # every command is clipped to the motors' limits before set_velocities: rps counts no actuator error
        assert "actuator limits were exceeded" not in stdout, stdout
        pairs += [str(folder), str(trace)]
        if name not in FLOAT32_REPLAY:
            continue
        # float32 (training precision): every step from the logged pose agrees to float32 rounding. (Greedy
        # actions are compared in float64 below: JaxRobotarium's scenarios observe raw headings, which a
        # float32 rounding can flip from +pi to -pi.)
        for result in replay_trace(folder, trace):
            assert result["env_done"], (name, result)
            assert result["actions_agree"] or name in HEADING_OBS, (name, result)
            assert result["max_step_deviation"] <= 1e-5, (name, result)
            assert result["max_reward_deviation"] <= 1e-4, (name, result)
            report[(name, result["episode"])] = result["max_pose_deviation"]
    # float64: the bundle and the env run the same logic, so whole episodes agree to rounding
    replay = subprocess.run([sys.executable, "-m", "marbler_jax.deploy.replay", *pairs], capture_output=True,
                            text=True, env=dict(os.environ, JAX_ENABLE_X64="1"), timeout=600)
    assert replay.returncode == 0, replay.stderr
    results = [json.loads(line) for line in replay.stdout.splitlines()]
    assert len(results) == len(bundles) + 1                    # the trained bundle runs two episodes
    for result in results:
        assert result["max_pose_deviation"] <= 1e-6, result
        assert result["max_step_deviation"] <= 1e-9 and result["max_reward_deviation"] <= 1e-9, result
        assert result["actions_agree"] and abs(result["bundle_return"] - result["env_return"]) <= 1e-6, result
    print("largest pose deviation per episode, float64 / float32 replay [m]:")
    for r in results:
        name = Path(r["bundle"]).name
        dev32 = report.get((name, r["episode"]))
        print(f"  {name} episode {r['episode']}: {r['max_pose_deviation']:.2e} / "
              + (f"{dev32:.2e}" if dev32 is not None else "-"))


def test_bundle_runs_with_numpy_2_and_jax_blocked(bundles, tmp_path):
    """The server has numpy 2.x: run the trained bundle in this interpreter with JAX made unimportable."""
    python = _rps_python()
    site = subprocess.run([python, "-c", "import rps, os; print(os.path.dirname(os.path.dirname(rps.__file__)))"],
                          capture_output=True, text=True, check=True).stdout.strip()
    shutil.copytree(Path(site) / "rps", tmp_path / "rps_only" / "rps")
    prelude = (f"import sys; sys.modules.update(jax=None, jaxlib=None, flax=None); "
               f"sys.path[:0] = ['.', {str(tmp_path / 'rps_only')!r}]; import numpy; "
               "assert numpy.__version__ >= '2', numpy.__version__; "
               "import runpy; runpy.run_path('main.py', run_name='__main__')")
    stdout = _run_bundle(sys.executable, bundles["simple_navigation"], tmp_path / "trace", {"MARBLER_JAX_EPISODES": "1"},
                         prelude=prelude)
    assert "episode 1/1" in stdout and "collided" not in stdout


def test_end_of_script_call_supports_old_and_new_rps():
    from marbler_jax.deploy.main import end_of_script

    calls = []

    class Rps2024:
        def call_at_scripts_end(self):
            calls.append("call_at_scripts_end")

    class RpsV2:
        def debug(self):
            calls.append("debug")

    end_of_script(Rps2024())
    end_of_script(RpsV2())
    assert calls == ["call_at_scripts_end", "debug"]
    with pytest.raises(AttributeError, match="neither"):
        end_of_script(object())


def test_export_deploys_the_robots_loop_unless_told_otherwise(ippo_simple_nav_run, tmp_path):
    from marbler_jax_rl.export import export_policy

    def bundle_period(**kw):
        out = tmp_path / f"bundle-{len(list(tmp_path.iterdir()))}"
        export_policy(ippo_simple_nav_run, tmp_path / "policy", checkpoint="final", bundle=out, **kw)
        return json.loads(str(np.load(out / "bundle_config.npy", allow_pickle=False)))["config"]["control_period"]

    trained = json.loads((ippo_simple_nav_run / "config.json").read_text())["env"]["control_period"]
    assert bundle_period() == 1                                 # the default: controller + barrier every iteration
    assert bundle_period(control_period=15) == 15               # an explicit choice
    assert bundle_period(control_period=None) == trained        # the training period as it is
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="control_period must be an integer >= 1"):
            export_policy(ippo_simple_nav_run, tmp_path / "policy", bundle=tmp_path / "x", control_period=bad)
    assert cli(["export", str(ippo_simple_nav_run), "--out", str(tmp_path / "p2"), "--bundle", str(tmp_path / "b2"),
                "--control-period", "train"]) == 0
    with pytest.raises(SystemExit):
        cli(["export", str(ippo_simple_nav_run), "--out", str(tmp_path / "p3"), "--control-period", "0"])


# The default run drives in the trained bundle, Predator Capture Prey's (a control period of 15) and RWARE's (a
# JaxRobotarium scenario): every bundle shares main.py and the robots' loop, and each drive-in takes ~5 s.
# The others run under -m slow (all of them run under the 2023 rps above).
V2_DEFAULT_RUN = {"simple_navigation", "predator_capture_prey", "rware"}


@pytest.mark.parametrize("name", slow_unless(("simple_navigation", *UNTRAINED), V2_DEFAULT_RUN))
def test_bundles_run_on_rps_v2(bundles, tmp_path, name):
    """A bundle under rps v2 (the Robotarium's simulator, with the server's numpy 2.2.6 / scipy /
    matplotlib / cvxopt and no JAX), through v2's drive-in phase from the chargers: ``debug()`` passes the
    trained policy without an error or a warning, counts no actuator error for any bundle, and every hard
    error it reports the bundle saw too."""
    python = _rps_v2_python()
    # one episode: every episode drives the robots in from the chargers again (most of a run's time); the
    # trained bundle's second episode runs under the 2023 rps above
    stdout = _run_on_rps_v2(python, bundles[name], tmp_path / "trace", {"MARBLER_JAX_EPISODES": "1"})
    assert stdout.count("episode ") == 1 and "real seconds to execute" in stdout, stdout
    assert "exceed actuator limits" not in stdout, (name, stdout)
    if name == "simple_navigation":
        assert stdout.count("No errors or warnings in your simulation!") == 1, stdout
    else:
        assert ("robots were too close" not in stdout) or "collisions=True" in stdout, (name, stdout)
        assert ("outside boundaries" not in stdout) or "out_of_bounds=True" in stdout, (name, stdout)


def test_a_drive_in_that_never_arrives_fails_the_v2_run_instead_of_hanging(bundles, tmp_path):
    """Two robots 0.2 m apart facing each other: a start the bundle's main.py accepts (no collision), but one
    rps v2's drive-in seldom reaches (its barrier keeps the points 5 cm ahead of the robots 0.25 m apart), and
    not within the 300 iterations allowed here (a drive-in from the chargers takes 500 or more). The seeded,
    capped v2 run fails after three seeds with a message instead of hanging until the subprocess timeout."""
    python = _rps_v2_python()
    folder = tmp_path / "unreachable"
    shutil.copytree(bundles["simple_navigation"], folder)
    poses = np.load(folder / "initial_poses.npy")
    poses[:, 0], poses[:, 1] = [-0.1, 0.0, 0.0], [0.1, 0.0, np.pi]
    np.save(folder / "initial_poses.npy", poses)
    with pytest.raises(pytest.fail.Exception, match="did not reach the initial poses within 300 iterations"):
        _run_on_rps_v2(python, folder, tmp_path / "trace", {"MARBLER_JAX_EPISODES": "1"}, steps=300)


def test_export_never_deletes_what_a_user_made(ippo_simple_nav_run, tmp_path):
    notes = tmp_path / "mine"
    notes.mkdir()
    (notes / "notes.txt").write_text("keep me")
    args = ["export", str(ippo_simple_nav_run), "--checkpoint", "final"]
    assert cli([*args, "--out", str(notes)]) == 2                          # refused, one line, nothing touched
    assert cli([*args, "--out", str(tmp_path / "p"), "--bundle", str(notes)]) == 2
    assert (notes / "notes.txt").read_text() == "keep me" and not (tmp_path / "p").exists()
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert cli([*args, "--out", str(a_file)]) == 2 and a_file.read_text() == "x"
    assert not list(tmp_path.glob("*.old")) and not list(tmp_path.glob("*.tmp"))
    # our own earlier output is replaced; --force replaces a foreign folder on purpose
    assert cli([*args, "--out", str(tmp_path / "p")]) == 0 and cli([*args, "--out", str(tmp_path / "p")]) == 0
    assert cli([*args, "--out", str(notes), "--force"]) == 0 and not (notes / "notes.txt").exists()


def test_bundles_start_only_where_the_robotariums_drive_in_can_reach(monkeypatch):
    """rps v2's drive-in keeps the points 0.05 m ahead of every two robots 0.25 m apart: a start closer than
    that is never reached (the run hangs). Such starts are drawn again; starts that are all reachable stay
    exactly the env's resets from the bundle seed's keys."""
    from marbler_jax.deploy import bundle

    def pair(distance, heading_a, heading_b):
        return np.array([[-distance / 2, 0.0, heading_a], [distance / 2, 0.0, heading_b]])

    # facing each other 0.3 m apart: points 0.2 m apart; facing away: 0.4 m; side by side 0.25 / 0.24 m
    cases = [pair(0.3, 0.0, np.pi), pair(0.3, np.pi, 0.0), pair(0.25, np.pi / 2, np.pi / 2),
             pair(0.24, np.pi / 2, np.pi / 2)]
    assert bundle.drive_in_reachable(np.stack(cases)).tolist() == [False, True, True, False]
    # Discovery draws random headings on a 0.3 m grid: some of the seed's first resets are unreachable
    env = marbler_jax.make("discovery")
    _, raw = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), 24))
    reachable = bundle.drive_in_reachable(np.asarray(raw.poses))
    assert 0 < reachable.sum() < 24
    poses, fields, _ = bundle.initial_states(env, 24, seed=3)
    assert poses.shape == (24, 4, 3) and bundle.drive_in_reachable(poses).all()
    np.testing.assert_allclose(poses[:reachable.sum()], np.asarray(raw.poses)[reachable], atol=1e-6)
    assert set(fields) == {"landmarks", "sensed", "tagged"}
    for name, value in fields.items():              # each start's scenario state stays with its poses
        np.testing.assert_array_equal(value[:reachable.sum()], np.asarray(getattr(raw.scenario, name))[reachable])
    pcp = marbler_jax.make("predator_capture_prey")
    _, raw = jax.vmap(pcp.reset)(jax.random.split(jax.random.PRNGKey(0), 3))
    np.testing.assert_allclose(bundle.initial_states(pcp, 3)[0], np.asarray(raw.poses), atol=1e-6)
    monkeypatch.setattr(bundle, "DRIVE_IN_SPACING", 5.0)
    with pytest.raises(ValueError, match=r"discovery: fewer than 2 of 200 start states put every two robots' points"):
        bundle.initial_states(env, 2)


def test_bundle_refuses_initial_poses_that_cannot_start_an_episode():
    from marbler_jax.deploy.main import check_initial_poses

    scenario = marbler_jax.make("simple_navigation").scenario
    good = np.array([[[-1.0, y, 0.0] for y in (-0.6, -0.2, 0.2, 0.6)]])
    check_initial_poses(good, scenario)
    bad = {"non-finite": good.copy(), "outside the arena": good.copy(), "in collision": good.copy(),
           r"must be \[episodes, 4, 3\]": good[:, :3]}
    bad["non-finite"][0, 1, 0] = np.nan
    bad["outside the arena"][0, 2, 0] = -1.7
    bad["in collision"][0, 1, :2] = good[0, 0, :2] + 0.05
    for message, poses in bad.items():
        with pytest.raises(ValueError, match=message):
            check_initial_poses(poses, scenario)
