"""``scripts/bench_env.py`` parses its grid options (no JAX work here)."""
from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_env.py"


@pytest.fixture(scope="module")
def bench_env():
    spec = importlib.util.spec_from_file_location("bench_env", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_settings_parse_into_barrier_and_period(bench_env):
    parser = argparse.ArgumentParser()
    assert bench_env.parse_setting(parser, "safe:15") == ("safe", 15)
    assert bench_env.parse_setting(parser, "none:1") == ("none", 1)


@pytest.mark.parametrize("text", ["safe", "safe:", ":15", "safe:0", "safe:fast"])
def test_malformed_settings_are_usage_errors_naming_them(bench_env, text, capsys):
    with pytest.raises(SystemExit):
        bench_env.parse_setting(argparse.ArgumentParser(), text)
    assert repr(text) in capsys.readouterr().err


def test_batches_must_be_positive(bench_env, capsys):
    with pytest.raises(SystemExit):
        bench_env.main(["--batches", "4096", "0"])
    assert "--batches must be positive" in capsys.readouterr().err
