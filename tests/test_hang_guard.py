"""The hang watcher: fires on an idle call, not on a busy one; the CLI restarts with --resume."""
from __future__ import annotations

import sys
import time

import pytest

from marbler_jax_rl.hang_guard import HangGuard, resume_argv
from marbler_jax_rl import cli


def test_fires_once_when_the_process_stays_idle():
    calls = []
    with HangGuard(calls.append, idle_seconds=0.4, poll_seconds=0.05) as guard:
        time.sleep(1.2)
    assert guard.fired and len(calls) == 1 and calls[0] >= 0.4


def test_quiet_while_the_process_computes():
    calls = []
    with HangGuard(calls.append, idle_seconds=0.4, poll_seconds=0.05, min_busy=0.05) as guard:
        end = time.monotonic() + 1.2
        x = 0
        while time.monotonic() < end:
            x += sum(range(1000))
    assert not guard.fired and calls == []


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="idle_seconds and poll_seconds must be > 0, got 0"):
        HangGuard(print, idle_seconds=0)


def test_cli_restarts_the_same_command_with_resume(monkeypatch):
    assert resume_argv(["train", "--out", "r"]) == ["train", "--out", "r", "--resume"]
    assert resume_argv(["train", "--resume"]) == ["train", "--resume"]
    seen = []
    monkeypatch.setattr(cli.os, "execv", lambda exe, argv: seen.append((exe, argv)))
    cli._restart_resumed(["train", "--algo", "vdn", "--out", "runs/x"], 130.0)
    assert seen == [(sys.executable, [sys.executable, "-m", "marbler_jax_rl", "train", "--algo", "vdn", "--out",
                                      "runs/x", "--resume"])]
    assert cli.main(["train", "--hang-seconds", "-1", "--out", "unused"]) == 2
