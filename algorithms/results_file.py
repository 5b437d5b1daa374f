"""A benchmark's results file: the one reader and writer of ``results*.json``, with a schema check.

The layout is marl-eval's: ``{env: {scenario: {algo: {"run_<k>": {"step_<i>": {"step_count": n, metric:
[per episode]}, "absolute_metrics": {metric: [per episode], ...}}}}}}``. Every read checks it, so a damaged or
hand-edited file is one ``ValueError`` naming the file and the entry, not a traceback deep in ``report``.
"""
from __future__ import annotations

import fcntl
import json
import numbers
import os
from pathlib import Path

from .checkpoints import atomic_write, read_json

ENV_NAME = "marbler"
ABSOLUTE = "absolute_metrics"


def results_name(process_index: int = 0, process_count: int = 1) -> str:
    """The results file one process writes (``results.json`` alone, ``results-p<i>.json`` among several)."""
    return "results.json" if process_count == 1 else f"results-p{process_index}.json"


def _numbers(value) -> bool:
    return isinstance(value, list) and all(v is None or (isinstance(v, numbers.Real) and not isinstance(v, bool))
                                           for v in value)


def _run_problem(run) -> str | None:
    """What is wrong with one ``run_<k>`` entry (``None``: nothing)."""
    if not isinstance(run, dict):
        return f"is a {type(run).__name__}, expected an object"
    if not isinstance(run.get(ABSOLUTE), dict):
        return f"has no {ABSOLUTE!r} object"
    if not _numbers(run[ABSOLUTE].get("reward")):
        return f"{ABSOLUTE}/reward is not a list of numbers"
    for name, step in run.items():
        if name == ABSOLUTE:
            continue
        if not (name.startswith("step_") and name[5:].isdigit()):
            return f"has an entry {name!r} (expected step_<i> and {ABSOLUTE})"
        if not isinstance(step, dict) or not isinstance(step.get("step_count"), numbers.Real):
            return f"{name} has no step_count"
        if not _numbers(step.get("reward")):
            return f"{name}/reward is not a list of numbers"
    return None


def check_results(results, path) -> dict:
    """``results`` (the parsed file ``path``) if it has the layout above, else a ``ValueError`` naming the
    file and the first bad entry."""
    def fail(where: str, what: str):
        raise ValueError(f"{path}: {where} {what}; not a marbler-jax results file (rerun the cell, or move the "
                         "file aside)")

    if not isinstance(results, dict):
        fail("the file", f"holds a {type(results).__name__}, expected an object")
    for env_name, tasks in results.items():
        if not isinstance(tasks, dict):
            fail(env_name, "is not an object of scenarios")
        for scenario, algos in tasks.items():
            if not isinstance(algos, dict):
                fail(f"{env_name}/{scenario}", "is not an object of algorithms")
            for algo, runs in algos.items():
                where = f"{env_name}/{scenario}/{algo}"
                if not isinstance(runs, dict) or not runs:
                    fail(where, "is not a non-empty object of runs")
                for name, run in runs.items():
                    if not (name.startswith("run_") and name[4:].isdigit()):
                        fail(where, f"has an entry {name!r} (expected run_<k>)")
                    problem = _run_problem(run)
                    if problem:
                        fail(f"{where}/{name}", problem)
    return results


def read_results(path) -> dict:
    """The checked contents of one results file (``{}`` where it does not exist yet)."""
    return check_results(read_json(path, {}), path)


def load_results(folder) -> dict:
    """Every ``results*.json`` of ``folder``, checked and merged into one marl-eval dict."""
    merged: dict = {}
    for path in sorted(Path(folder).glob("results*.json")):
        for env_name, tasks in read_results(path).items():
            for task, algos in tasks.items():
                merged.setdefault(env_name, {}).setdefault(task, {}).update(algos)
    return merged


def add_cell(path, scenario: str, algo: str, runs: dict) -> dict:
    """Write one cell's ``runs`` into the results file ``path``; returns the file's new contents.

    The file is read again under an exclusive lock on its folder and the cell merged in, so cells
    that other processes wrote into the same file since this one started are kept."""
    path = Path(path)
    problem = _run_problem(next(iter(runs.values()), None)) if runs else "no runs"
    if problem:
        raise ValueError(f"cell {scenario}/{algo}: {problem}")
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        fcntl.flock(folder, fcntl.LOCK_EX)
        results = read_results(path)
        results.setdefault(ENV_NAME, {}).setdefault(scenario, {})[algo] = runs
        atomic_write(path, json.dumps(results))
        return results
    finally:
        os.close(folder)         # closing the descriptor releases the lock


__all__ = ["ENV_NAME", "ABSOLUTE", "results_name", "check_results", "read_results", "load_results", "add_cell"]
