"""Shared fixtures: golden traces are read from ``../shared/golden`` (never copied here)."""
from __future__ import annotations

import json
import os
from pathlib import Path

# One BLAS thread per process: the suite runs two xdist workers on two cores, and the worker's numpy and the
# Robotarium simulators it starts (cvxopt's QP solver) would otherwise spin thread pools against each other,
# which makes a bundle episode in the rps venvs tens of times slower. Set before numpy loads its BLAS.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

# Many tests build the same training programs again (a run, then its interrupted twin and the resume;
# the CLI and the API on the same settings): a persistent compilation cache shared by the xdist workers
# (and the CLIs they start) compiles each program once per machine. Cached executables are keyed by the
# program, JAX version and flags, so they never change a result. Set JAX_COMPILATION_CACHE_DIR to move it.
_CACHE = os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax-compilation"))
# Cache every program, not only those that took over a second to compile (JAX's default): much of the
# suite's time is compilation, and the many sub-second programs that several workers and CLI subprocesses
# build add up too (BENCHMARKS.md has the suite's time in a fresh clone).
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# The suite is compile-bound, so it compiles for speed of compilation (a setting already in XLA_FLAGS is kept):
# LLVM at -O0 instead of -O3 (a training program compiles about three times faster and runs about twice as
# slowly) and XLA's CPU fusion emitters off.
# Tests compare programs built under the same flags, so neither changes what they check.
# Each of the two xdist workers has one core: a program is compiled as one LLVM module and run without Eigen's
# thread pool, instead of splitting both over threads that would only contend with the other worker.
_FAST_COMPILE = ("--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false "
                 "--xla_cpu_parallel_codegen_split_count=1 --xla_cpu_multi_thread_eigen=false")


def _supported(flags: str) -> bool:
    """Whether this jaxlib's XLA knows ``flags`` (an unknown flag aborts the process at backend start)."""
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    return subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env,
                          capture_output=True).returncode == 0


# set once in the controller; the xdist workers and the CLIs the tests start inherit XLA_FLAGS
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    _flags = _FAST_COMPILE if _supported(_FAST_COMPILE) else "--xla_backend_optimization_level=0"
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flags).strip()

import jax  # noqa: E402  (after the cache and XLA settings, which jax reads at import)

jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))

GOLDEN = Path(os.environ.get("MARBLER_JAX_GOLDEN", Path(__file__).resolve().parents[2] / "shared" / "golden"))


def golden_path(name: str) -> Path:
    path = GOLDEN / name
    if not GOLDEN.is_dir():
        pytest.skip(f"golden folder {GOLDEN} is absent")
    if not path.exists():
        raise FileNotFoundError(f"golden file {path} is missing although {GOLDEN} exists")
    return path


class Golden:
    """A golden ``.npz`` file with per-N views: ``g[N]['poses0']`` is ``N{N}_poses0``."""

    def __init__(self, name: str):
        self.data = dict(np.load(golden_path(name)))
        self.meta = json.loads(str(self.data["meta"]))

    def __getitem__(self, n: int) -> dict[str, np.ndarray]:
        prefix = f"N{n}_"
        return {k[len(prefix):]: v for k, v in self.data.items() if k.startswith(prefix)}


def robot_major(a: np.ndarray) -> np.ndarray:
    """rps ``(..., C, N)`` -> ours ``(..., N, C)``."""
    return np.swapaxes(a, -1, -2)


def angle_diff(a, b):
    d = np.asarray(a) - np.asarray(b)
    return np.abs(np.arctan2(np.sin(d), np.cos(d)))


@pytest.fixture(scope="session")
def golden():
    cache: dict[str, Golden] = {}

    def load(name: str) -> Golden:
        if name not in cache:
            cache[name] = Golden(name)
        return cache[name]

    return load


_CBF_REPORT: list[tuple] = []


@pytest.fixture(scope="session")
def cbf_report():
    """Rows (file, N, cases, match rate, worst abs error, p99 abs error, feasible rate)."""
    return _CBF_REPORT


def pytest_terminal_summary(terminalreporter):
    if not _CBF_REPORT:
        return
    tr = terminalreporter
    tr.section("CBF accuracy vs rps tight QP (cases with status_tight == 1)")
    tr.write_line(f"{'file':28s} {'N':>3s} {'cases':>5s} {'match':>6s} {'worst':>9s} {'p99':>9s} {'feasible':>8s}")
    for name, n, cases, match, worst, p99, feas in sorted(_CBF_REPORT):
        tr.write_line(f"{name:28s} {n:3d} {cases:5d} {match:6.1%} {worst:9.2e} {p99:9.2e} {feas:8.1%}")


def build_once(tmp_path_factory, name: str, build) -> Path:
    """``build(folder)`` once per test session, shared by the xdist workers: the first worker to need
    ``name`` builds it under a file lock in the session's common temp folder (a ``.done`` marker is
    written last); the others wait for the lock and reuse the finished folder. (pytest-xdist's
    ``loadgroup`` cannot keep a module's tests on one worker under pytest 9, so a session fixture
    would otherwise be built once per worker.)"""
    import fcntl
    import shutil

    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent          # common to every worker of this session
    folder = shared / name
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / ".done").exists():
            shutil.rmtree(folder, ignore_errors=True)     # what a failed attempt left
            folder.mkdir()
            build(folder)
            (folder / ".done").touch()
    return folder


@pytest.fixture(scope="session")
def ippo_simple_nav_run(tmp_path_factory):
    """One IPPO run on Simple Navigation (the recipe's settings for 150k steps; default env: safe CBF, control
    every tick), trained once per session (:func:`build_once`) through the training driver; used by the
    learning test and the Robotarium bundle test."""
    from marbler_jax_rl import recipes
    from marbler_jax_rl.driver import train_run

    def build(folder):
        hp = recipes.settings("recipe", "simple_navigation", "ippo")[1]
        train_run("simple_navigation", "ippo", 150_000, 1, folder / "run", hp=hp,
              eval_episodes=256, test_episodes=16, progress=False, log=lambda *a, **k: None)

    return build_once(tmp_path_factory, "ippo-sn", build) / "run"


# Modules whose tests train or compile whole programs (the suite's longest tests), in the
# order to start them. pytest-xdist hands the tests out in collection order, so running these first
# and the many short tests after them keeps both workers busy to the end instead of leaving one long
# test alone on one worker. test_ippo's first test starts the session's IPPO run at once, so that it is
# trained before the other worker reaches test_bundle, whose tests wait for it.
LONG_FIRST = ("test_ippo", "test_data_parallel", "test_value_based", "test_training_driver", "test_cli",
              "test_examples", "test_bundle")


def pytest_collection_modifyitems(config, items):
    def rank(item):
        module = item.path.stem
        return LONG_FIRST.index(module) if module in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)    # stable: the order within a module is kept
