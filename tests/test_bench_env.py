"""``scripts/bench_env.py`` parses its grid options (no JAX work here)."""
from __future__ import annotations

import argparse
import json

import pytest

from tests.helpers import load_script


@pytest.fixture(scope="module")
def bench_env():
    return load_script("bench_env")


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


def test_devices_must_divide_every_batch(bench_env, capsys):
    with pytest.raises(SystemExit):
        bench_env.main(["--batches", "256", "100", "--devices", "3"])
    assert "--devices must be >= 1 and divide every batch, got 3" in capsys.readouterr().err


def test_more_devices_than_jax_has_is_a_usage_error(bench_env, capsys):
    import jax

    jax.devices()            # the backend runs: the script cannot add CPU devices to this process any more
    with pytest.raises(SystemExit):
        bench_env.main(["--batches", "256", "--devices", "64", "--scenarios", "simple_navigation"])
    assert "--devices 64: JAX has" in capsys.readouterr().err


def test_each_measurement_is_written_before_the_next_one(bench_env, tmp_path, monkeypatch):
    calls = []

    def fake_measure(env, batch, steps, repeats=3, devices=1):
        calls.append(batch)
        if len(calls) == 3:
            raise KeyboardInterrupt          # interrupted during the third configuration
        return 1000.0 * batch, 0.5

    monkeypatch.setattr(bench_env, "measure", fake_measure)
    out = tmp_path / "env.json"
    with pytest.raises(KeyboardInterrupt):
        bench_env.main(["--scenarios", "simple_navigation", "--batches", "2", "8", "--settings", "safe:15", "none:1",
                        "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(r["barrier"], r["control_period"], r["batch"], r["env_steps_per_s"]) for r in rows] == [
        ("safe", 15, 2, 2000.0), ("safe", 15, 8, 8000.0)]
    assert "| simple_navigation | safe | 15 | 8 | 8,000 |" in out.with_suffix(".md").read_text()
