"""Bad training input gets one clear error naming the setting, the value and what is allowed -- before
anything is created."""
from __future__ import annotations

import pytest

from marbler_jax_rl.driver import build_config, train
from marbler_jax_rl.cli import main


@pytest.mark.parametrize("algo, overrides, message", [
    ("vdn", {"lr": -1.0}, "lr must be > 0, got -1.0"),
    ("vdn", {"lr": float("inf")}, "lr=inf is not valid: expected a finite number"),
    ("vdn", {"lr": "abc"}, "lr='abc' is not valid: expected a finite number"),
    ("qmix", {"gamma": 1.5}, r"gamma must be in \(0, 1\], got 1.5"),
    ("qmix_ns", {"eps_start": 5}, r"eps_start must be in \[0, 1\], got 5"),
    ("vdn", {"max_grad_norm": -1}, "max_grad_norm must be > 0, got -1"),
    ("vdn", {"hidden": 32.5}, "hidden=32.5 is not valid: expected an integer"),
    ("vdn", {"shared": 1}, "shared=1 is not valid: expected true or false"),
    ("ippo", {"lr": 0}, "lr must be > 0, got 0"),
    ("mappo", {"gae_lambda": 2.0}, r"gae_lambda must be in \[0, 1\], got 2.0"),
    ("ippo", {"ent_coef": float("nan")}, "ent_coef=nan is not valid"),
])
def test_training_settings_are_checked_when_the_config_is_built(algo, overrides, message):
    with pytest.raises(ValueError, match=message):
        build_config(algo, overrides)


def test_cli_rejects_bad_input_with_exit_2_and_creates_nothing(tmp_path, capsys):
    out = tmp_path / "run"
    for args in (["--hp", "lr=Infinity"], ["--hp", "lr=abc"], ["--hp", "gamma=1.5"], ["--checkpoint-every", "-3"],
                 ["--checkpoint-every", "0"]):
        assert main(["train", "--algo", "ippo", "--out", str(out), "--no-progress", *args]) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("marbler-jax: error: ") and err.count("\n") == 1, err
    assert not out.exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    assert main(["train", "--algo", "ippo", "--out", str(notes), "--no-progress"]) == 2
    assert "is a file" in capsys.readouterr().err and notes.read_text() == "mine"


def test_driver_checks_checkpoint_every(tmp_path):
    with pytest.raises(ValueError, match="checkpoint_every must be an integer >= 1"):
        train("simple_navigation", "ippo", 1000, 1, tmp_path / "x", checkpoint_every=0, progress=False)
    assert not (tmp_path / "x").exists()
