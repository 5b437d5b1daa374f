"""The command line: subcommands run end to end and bad input gets a clear error."""
from __future__ import annotations

import json

import imageio.v2 as imageio
import jax
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl.cli import main, parse_overrides
from marbler_jax_rl.evaluate import greedy_episodes
from marbler_jax_rl.run import load_run
from tests.helpers import load_script


def test_list(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "predator_capture_prey: 4 robots, obs_dim 16, 5 actions, 81 steps per episode" in out


def test_rollout_writes_gif(tmp_path, capsys):
    gif = tmp_path / "ep.gif"
    code = main(["rollout", "simple_navigation", "--envs", "8", "--steps", "5", "--gif", str(gif),
                 "--set", "max_episode_steps=3"])
    assert code == 0
    frames = imageio.mimread(gif)
    assert len(frames) == 5 and frames[0].std() > 0  # reset frame + 4 steps
    assert "env-steps/s" in capsys.readouterr().out


def test_demo_runs_without_collisions(tmp_path):
    plot = tmp_path / "swap.png"
    assert main(["demo", "--robots", "6", "--teams", "4", "--ticks", "200", "--plot", str(plot)]) == 0
    assert plot.stat().st_size > 10_000


def test_bad_input_is_reported(capsys):
    assert main(["rollout", "simple_navigation", "--set", "no_such_key=1", "--envs", "2", "--steps", "2"]) == 2
    err = capsys.readouterr().err
    assert "unknown config key(s) ['no_such_key']" in err and "valid keys" in err
    assert main(["rollout", "pacman"]) == 2
    assert parse_overrides(["a=1", "b=true", "c=safe"]) == {"a": 1, "b": True, "c": "safe"}


def test_an_os_error_is_one_line_naming_the_path_and_debug_shows_the_traceback(tmp_path, capsys, monkeypatch):
    """``--out`` under a file gave a NotADirectoryError traceback, a full disk an OSError traceback."""
    import errno

    import marbler_jax_rl.run_writer as run_writer

    (tmp_path / "notes").write_text("a file")
    argv = ["train", "--total-steps", "64", "--hp", "num_envs=8", "--hp", "num_steps=8", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "notes" / "run")]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"marbler-jax: error: Not a directory: {tmp_path / 'notes' / 'run'}"]

    def disk_full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(run_writer, "atomic_write", disk_full)
    assert main([*argv, "--out", str(tmp_path / "full")]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"marbler-jax: error: No space left on device: {tmp_path / 'full' / 'config.json'}"]
    with pytest.raises(OSError, match="No space left"):
        main(["--debug", *argv, "--out", str(tmp_path / "full2")])


@pytest.mark.parametrize("argv, message", [
    (["train", "--seeds", "x"], "marbler-jax train: error: argument --seeds: invalid int value: 'x'"),
    (["trian"], "marbler-jax: error: argument command: invalid choice: 'trian'"),
    (["benchmark", "--protocol", "foo"], "marbler-jax benchmark: error: argument --protocol: invalid choice: 'foo'"),
])
def test_a_flag_argparse_refuses_is_one_line_naming_it(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and err.startswith(message), err
    assert err.rstrip().endswith("-h)")


def test_benchmark_dry_run_lists_the_cells_and_trains_nothing(tmp_path, capsys):
    out = tmp_path / "bench"
    args = ["benchmark", "--dry-run", "--algos", "vdn", "mappo", "--scenarios", "simple", "warehouse", "--out", str(out)]
    assert main(args + ["--total-steps", "2e4", "--seeds", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{out / 'results.json'}: 4 cell(s), 4 new; 240,000 env steps to train (3 seed(s) per cell)"
    assert "warehouse" in lines[4] and "mappo" in lines[4] and "20,000 steps/seed  new" in lines[4]
    # then, where results/marbler-table2 holds cells trained on this kind of device, the estimated time
    assert len(lines) == 5 or (len(lines) == 6 and lines[5].startswith("estimated "))
    assert not out.exists()
    assert main(args + ["--shard", "1/2"]) == 0            # the recipes' budgets, this process's share
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{out / 'results-p1.json'}: 2 cell(s)") and "mappo" in lines[1]
    assert main(args + ["--hp", "hidden=32", "--hp", "td_lambda=0.5"]) == 0          # VDN has both, MAPPO hidden
    assert "4 new" in capsys.readouterr().out
    assert main(args + ["--hp", "no_such=1"]) == 2
    assert "--hp no_such: none of the algorithms ['mappo', 'vdn'] has this setting" in capsys.readouterr().err
    assert main(args + ["--hp", "hidden"]) == 2 and "--hp expects key=value, got 'hidden'" in capsys.readouterr().err
    for bad in ("abc", "1.5", "0", "inf"):
        with pytest.raises(SystemExit) as exit_:
            main(args + ["--total-steps", bad])
        assert exit_.value.code == 2
        assert f"--total-steps: must be a whole number of env steps >= 1 (e.g. 5e6), got '{bad}'" in capsys.readouterr().err


def test_output_into_a_closed_pipe_ends_quietly(tmp_path, monkeypatch, capsys):
    """``marbler-jax list | head -1``: the reader leaves early, which is no error and prints no traceback."""
    class ClosedPipe:
        def __init__(self):
            self.file = open(tmp_path / "stdout", "w")

        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

        def fileno(self):
            return self.file.fileno()

    pipe = ClosedPipe()
    monkeypatch.setattr("sys.stdout", pipe)
    assert main(["list"]) == 0
    pipe.file.close()
    assert capsys.readouterr().err == ""


def test_train_writes_a_complete_run_folder(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--scenario", "Warehouse", "--total-steps", "2100", "--seeds", "2", "--out", str(out),
            "--hp", "num_envs=16", "--hp", "num_steps=16", "--hp", "hidden=32", "--test-episodes", "8",
            "--eval-episodes", "16"]
    code = main(args + ["--seed", "7"])
    assert code == 0
    printed = capsys.readouterr().out          # the budget is whole updates of 16 x 16 env steps, and says so
    assert "(--total-steps 2,100 rounded to whole updates: 2,048 per seed)" in printed
    assert "s of it compiling;" in printed and "after compilation)" in printed
    for name in ("config.json", "metrics.jsonl", "learning_curve.png", "params.npz", "evaluation.json"):
        assert (out / name).exists(), name
    assert not list(out.glob("*.tmp*"))  # atomic writes leave no temporaries
    events = list((out / "tensorboard").glob("events.out.tfevents.*"))   # tensorboardX is in the test extra
    assert events and b"train/return_mean" in events[0].read_bytes() and b"train/sps" in events[0].read_bytes()
    config = json.loads((out / "config.json").read_text())
    assert config["algo"] == "ippo" and config["algorithm"]["total_timesteps"] == 2100 and config["seed"] == 7
    assert config["scenario"] == "warehouse"     # MARBLER's name, stored canonical (evaluate's paper column finds it)
    assert main(args + ["--seed", "8", "--resume"]) == 2      # a resume must keep the run's seed
    # a resume needs no more than the folder: scenario, algorithm, seeds and settings come from config.json
    saved = (out / "config.json").read_text()
    assert main(["train", "--out", str(out), "--resume", "--no-progress", "--eval-episodes", "16"]) == 0
    assert (out / "config.json").read_text() == saved
    assert main(["train", "--out", str(out), "--resume", "--algo", "mappo", "--no-progress"]) == 2
    lines = (out / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 2048 // (16 * 16)
    evaluation = json.loads((out / "evaluation.json").read_text())
    assert set(evaluation) >= {"trained", "random", "train_seconds"}
    assert np.isfinite(evaluation["trained"]["return"]) and np.isfinite(evaluation["random"]["return"])
    assert main(["train", "--hp", "no_such=1", "--total-steps", "100", "--out", str(out)]) == 2


# two recurrent VDN seeds on Predator Capture Prey's recipe, a few updates
TINY_PCP_VDN = ["train", "--scenario", "predator_capture_prey", "--algo", "vdn", "--total-steps", "1296", "--seeds", "2",
                "--no-progress", "--hp", "num_envs=8", "--hp", "hidden=16", "--hp", "learning_starts=0",
                "--hp", "buffer_size=32", "--hp", "batch_size=4", "--checkpoint-every", "1", "--test-episodes", "8",
                "--eval-episodes", "0"]


def test_train_vdn_then_evaluate_best_checkpoint(tmp_path, capsys, monkeypatch):
    out = tmp_path / "vdn"
    code = main(TINY_PCP_VDN + ["--out", str(out)])
    assert code == 0
    config = json.loads((out / "config.json").read_text())
    assert config["env"]["control_period"] == 1 and config["algorithm"]["train_steps"] == 32    # the recipe
    assert main(["evaluate", str(out), "--episodes", "6", "--no-progress"]) == 0
    result = json.loads((out / "eval_best.json").read_text())
    assert result["seeds"] == 2 and len(result["per_seed"]) == 2
    pooled = result["pooled"]
    assert set(pooled) == {"reward", "steps", "prey_left", "collisions", "out_of_bounds"}
    assert 1 <= pooled["steps"]["mean"] <= 81 and 0 <= pooled["prey_left"]["mean"] <= 6
    assert result["paper"]["reward"] == [33.25, 0.46]
    table = (out / "eval_best.md").read_text()
    assert "| reward |" in table and "33.25 ± 0.46" in table
    assert "33.25 ± 0.46" in capsys.readouterr().out
    # --best-seed: the paper's protocol, only the seed with the highest greedy test, in its own files
    assert main(["evaluate", str(out), "--episodes", "6", "--no-progress", "--best-seed"]) == 0
    best = json.loads((out / "eval_best_best_seed.json").read_text())
    assert best["seed_selection"] == "best" and best["pooled"] == result["per_seed"][best["seed_indices"][0]]
    assert "the best of 2 by greedy test return" in (out / "eval_best_best_seed.md").read_text()
    assert json.loads((out / "eval_best.json").read_text()) == result          # the all-seeds evaluation is kept
    assert main(["evaluate", str(tmp_path / "missing")]) == 2
    assert "is not a run folder" in capsys.readouterr().err
    # the recurrent greedy policy of the best checkpoint, two episodes side by side
    gif = tmp_path / "vdn.gif"
    assert main(["render", str(out), "--out", str(gif), "--checkpoint", "best", "--envs", "2", "--no-progress"]) == 0
    frames = imageio.mimread(gif)
    assert 2 <= len(frames) <= 82 and frames[0].shape[1] > 1.5 * frames[0].shape[0]
    assert f"seed {best['seed_indices'][0]})" in capsys.readouterr().out     # the seed evaluate --best-seed reports
    assert main(["render", str(out), "--out", str(gif), "--seed-index", "5", "--no-progress"]) == 2
    assert "out of range" in capsys.readouterr().err
    # export's default is that seed too (here made seed 1, which index 0 would not find by chance)
    from marbler_jax.numpy_policy import load_policy
    from marbler_jax_rl.run import Run

    monkeypatch.setattr(Run, "best_seed", lambda self: (1, 0.0))
    assert main(["export", str(out), "--out", str(tmp_path / "policy")]) == 0
    assert load_policy(tmp_path / "policy").spec["seed_index"] == 1
    assert main(["export", str(out), "--out", str(tmp_path / "policy"), "--seed-index", "0"]) == 0
    assert load_policy(tmp_path / "policy").spec["seed_index"] == 0


@pytest.mark.slow     # a diagnostic script of one scenario, on a run trained like the test above
def test_pcp_failures_script_breaks_down_the_greedy_episodes(tmp_path):
    out = tmp_path / "vdn"
    assert main(TINY_PCP_VDN + ["--out", str(out)]) == 0
    # scripts/pcp_failures.py: every episode is a success, a violation or a timeout with prey left
    failures = load_script("pcp_failures")
    assert failures.main([str(out), "--episodes", "6", "--eps", "0.5", "--out", str(tmp_path / "f.json")]) == 0
    rows = json.loads((tmp_path / "f.json").read_text())
    assert set(rows) == {"eps=0", "eps=0.5"}
    for row in rows.values():
        assert row["success"] + row["violation"] + row["timeout"] == pytest.approx(1.0)
        assert 0 <= row["sensed_share_of_left"] <= 1
    # the breakdown plays the same greedy episodes as evaluate does from the same key
    env, policy = load_run(out, checkpoint="best")
    played = failures.make_play(env, policy, 6)(jax.random.PRNGKey(5))
    reference = greedy_episodes(env, policy, 6, jax.random.PRNGKey(5))
    np.testing.assert_allclose(played["ret"], reference["reward"], rtol=1e-6)
    # where the capture robots were: counted over each first episode's own steps only
    np.testing.assert_array_equal(played["live_steps"], played["steps"])
    assert np.all(played["range_idle_steps"] <= played["range_steps"])
    assert np.all(played["range_steps"] <= played["live_steps"])
    assert rows["eps=0"]["return_mean"] == pytest.approx(float(reference["reward"].mean()), rel=1e-5)


def test_version_list_and_help_defaults(capsys):
    from marbler_jax import __version__

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"marbler-jax {__version__}"
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "predator_capture_prey: 4 robots" in out and "Predator Capture Prey (MARBLER" in out
    assert "qmix_ns: QMIX with one network per robot" in out
    with pytest.raises(SystemExit):
        main(["benchmark", "--help"])
    assert "(default: 5)" in capsys.readouterr().out


def test_train_names_its_starting_settings_recipe_and_keeps_preset_as_the_older_name():
    from marbler_jax_rl.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["train"]).recipe == "recipe"
    assert parser.parse_args(["train", "--recipe", "paper"]).recipe == "paper"
    assert parser.parse_args(["train", "--preset", "none"]).recipe == "none"


def test_list_verbose_explains_every_config_key(capsys):
    """Every field of every registered scenario's config has a documented meaning, and ``list -v``
    prints it under the key."""
    import dataclasses

    from marbler_jax.registry import scenario_class
    from marbler_jax.scenarios.base import field_docs

    for name in marbler_jax.registered():
        config_cls = scenario_class(name).Config
        docs = field_docs(config_cls)
        undocumented = [f.name for f in dataclasses.fields(config_cls) if not docs.get(f.name)]
        assert not undocumented, f"{name}: add these to an Attributes: section: {undocumented}"
    from marbler_jax_rl.recipes import RECIPES

    for algo, chosen in RECIPES.items():
        docs = field_docs(type(chosen.config))
        undocumented = [f.name for f in dataclasses.fields(chosen.config) if not docs.get(f.name)]
        assert not undocumented, f"{algo}: add these to an Attributes: section: {undocumented}"
    assert main(["list", "-v"]) == 0
    out = capsys.readouterr().out
    assert "      mixer_embed = 32\n          width of the mixing network's hidden layer.\n" in out
    assert "      num_prey = 6\n          prey per episode.\n" in out
    assert "      y_min = -0.9\n          smallest waypoint y [m]" in out
    assert "``" not in out and ":func:" not in out
    # list SCENARIO: that scenario alone, every key explained (MARBLER's names accepted)
    assert main(["list", "pcp"]) == 0
    one = capsys.readouterr().out
    assert "      num_prey = 6\n          prey per episode.\n" in one
    assert "warehouse" not in one and "algorithms" not in one
    assert main(["list", "no_such"]) == 2 and "unknown scenario 'no_such'" in capsys.readouterr().err


def test_every_command_that_reads_a_run_defaults_to_the_same_checkpoint(tmp_path):
    """evaluate, export and render (and the Python API behind them) read the run's parameters from one
    default checkpoint, so a user's evaluated, exported and rendered policy is the same one."""
    import inspect

    from marbler_jax_rl.cli import build_parser
    from marbler_jax_rl.evaluate import evaluate_run
    from marbler_jax_rl.export import export_policy
    from marbler_jax_rl.run import DEFAULT_CHECKPOINT, Run

    parser = build_parser()
    defaults = {cmd: parser.parse_args([cmd, "RUN", "--out", "X"] if cmd != "evaluate" else [cmd, "RUN"]).checkpoint
                for cmd in ("evaluate", "export", "render")}
    assert defaults == dict.fromkeys(defaults, DEFAULT_CHECKPOINT)
    for cmd in ("export", "render"):      # the seed evaluate --best-seed reports, by default and by name
        assert parser.parse_args([cmd, "RUN", "--out", "X"]).seed_index == "best"
        assert parser.parse_args([cmd, "RUN", "--out", "X", "--seed-index", "1", "--best-seed"]).seed_index == "best"
        assert parser.parse_args([cmd, "RUN", "--out", "X", "--seed-index", "1"]).seed_index == 1
    for fn in (evaluate_run, export_policy, load_run, Run.params, Run.seed_params, Run.policy):
        assert inspect.signature(fn).parameters["checkpoint"].default == DEFAULT_CHECKPOINT, fn
    with pytest.raises(ValueError, match="is not a run folder"):
        Run.open(tmp_path)
    (tmp_path / "config.json").write_text('{"scenario": "warehouse", "algo": "vdn", "seeds": 1, "env": {}}')
    with pytest.raises(ValueError, match=r"checkpoint must be one of \['best', 'final'\], got 'last'"):
        Run.open(tmp_path).params("last")
    with pytest.raises(ValueError, match="has no best checkpoint"):
        Run.open(tmp_path).params()


def test_ctrl_c_ends_with_one_line_and_exit_code_130(monkeypatch, capsys, tmp_path):
    import marbler_jax_rl.cli as cli_module

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_module, "_train", interrupted)
    argv = ["train", "--scenario", "simple_navigation", "--algo", "ippo", "--out", str(tmp_path / "run")]
    assert cli_module.main(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["marbler-jax: interrupted; the last checkpoint is kept, resume with: marbler-jax "
                   + " ".join(argv + ["--resume"])]


def test_the_program_ends_without_the_interpreters_teardown_after_ctrl_c(monkeypatch):
    """``marbler-jax`` (``cli.console``) leaves through ``os._exit(130)`` after Ctrl-C: the teardown crashed with
    SIGSEGV while an interrupted XLA compilation unwound (the slow test below sends the signal)."""
    import marbler_jax_rl.cli as cli_module

    ended = []
    monkeypatch.setattr(cli_module.os, "_exit", lambda code: ended.append(code))
    for code in (130, 0, 2):
        monkeypatch.setattr(cli_module, "main", lambda code=code: code)
        ended.clear()
        with pytest.raises(SystemExit) as exit_:         # (os._exit is recorded here, and the program goes on)
            cli_module.console()
        assert exit_.value.code == code and ended == ([130] if code == 130 else [])


@pytest.mark.slow
@pytest.mark.parametrize("delay", [9.0, 11.0, 13.0, 15.0])
def test_ctrl_c_during_compilation_ends_with_130_not_a_crash(tmp_path, delay):
    """SIGINT ``delay`` seconds after the start, while XLA compiles the training programs, printed the resume
    line and then died with SIGSEGV (exit 139) in the interpreter's teardown."""
    import os
    import signal
    import subprocess
    import sys
    import time

    argv = [sys.executable, "-m", "marbler_jax_rl", "train", "--scenario", "pcp", "--algo", "vdn", "--total-steps",
            "100000", "--out", str(tmp_path / "run"), "--no-progress"]
    # compiled for real, as a user's first run is (not loaded from the suite's compilation cache), with XLA's
    # own flags and threads
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_"))}
    with open(tmp_path / "out.log", "w") as out, open(tmp_path / "err.log", "w") as err:
        process = subprocess.Popen(argv, stdout=out, stderr=err, env=env)
        time.sleep(delay)
        process.send_signal(signal.SIGINT)
        process.wait(timeout=300)
    said = (tmp_path / "err.log").read_text()
    assert process.returncode in (0, 130), said        # 0: it had finished before the signal came
    assert process.returncode == 0 or "marbler-jax: interrupted; the last checkpoint is kept" in said


def test_quickstart_replaces_only_its_own_earlier_run(monkeypatch, tmp_path, capsys):
    import marbler_jax_rl.cli as cli_module
    import marbler_jax_rl.driver as driver

    from marbler_jax_rl.recipes import settings

    real, asked = driver.train_run, []

    def tiny(scenario, algo, total_steps, seeds, out, env_overrides, hp):     # the quickstart's job at a test's size
        asked.append((scenario, algo, env_overrides, hp, total_steps))
        return real(scenario, algo, 4 * 8 * 8, 1, out, env_overrides=env_overrides,
                    hp=dict(hp, num_envs=8, num_steps=8, hidden=16), eval_episodes=8, test_episodes=4,
                    progress=False, log=lambda *a, **k: None)

    monkeypatch.setattr(driver, "train_run", tiny)
    monkeypatch.setattr(cli_module, "_episode_gif", lambda run, gif: gif.write_bytes(b"GIF89a"))
    out = tmp_path / "qs"
    (tmp_path / "qs.new").mkdir()                       # a user's folder of that name is left alone
    (tmp_path / "qs.new" / "notes.txt").write_text("mine")
    assert cli_module.main(["quickstart", "--out", str(out)]) in (0, 1)
    assert (tmp_path / "qs.new" / "notes.txt").read_text() == "mine"
    # the IPPO recipe, as `marbler-jax train --scenario simple_navigation --algo ippo` trains it
    assert asked == [("simple_navigation", "ippo", *settings("recipe", "simple_navigation", "ippo"))]
    first = (out / "config.json").stat().st_mtime_ns
    assert cli_module.main(["quickstart", "--out", str(out)]) in (0, 1)       # its own run: replaced whole
    assert (out / "config.json").stat().st_mtime_ns != first and (out / "robotarium" / "main.py").exists()
    assert "replacing the earlier run" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["qs", "qs.new"]          # no staging folder left
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert cli_module.main(["quickstart", "--out", str(mine)]) == 2
    assert (mine / "notes.txt").read_text() == "keep me"


def test_a_second_writer_gets_one_line_naming_the_first_and_touches_nothing(tmp_path, capsys):
    """While one process holds a run folder's (or a results file's) writer lock, ``train`` (``benchmark``)
    into it exits 1 with one line naming the holder, and writes nothing."""
    import subprocess
    import sys

    out, bench = tmp_path / "run", tmp_path / "bench"
    out.mkdir()
    bench.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from marbler_jax_rl.writer_lock import writer_lock\n"
        f"with writer_lock({str(out / '.lock')!r}, 'run'), writer_lock({str(bench / 'results.json.lock')!r}, 'b'):\n"
        "    print('held', flush=True)\n"
        "    time.sleep(10)\n")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(["train", "--total-steps", "512", "--out", str(out), "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"run folder {out} is being written by pid {holder.pid} (-c)" in err
        assert sorted(p.name for p in out.iterdir()) == [".lock"]          # no config.json, no checkpoint
        assert main(["benchmark", "--algos", "ippo", "--scenarios", "simple", "--seeds", "1", "--total-steps", "512",
                     "--out", str(bench), "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert f"results file {bench / 'results.json'} is being written by pid {holder.pid}" in err
        assert sorted(p.name for p in bench.iterdir()) == ["results.json.lock"]
    finally:
        holder.kill()
        holder.wait()


def test_damaged_json_files_are_one_line_naming_the_file(tmp_path, capsys):
    """A truncated results.json or config.json, or valid JSON of the wrong shape, is reported by name and place
    in one line (exit 2), not as a parser traceback."""
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "results.json").write_text('{"marbler": {"warehouse": ')
    assert main(["report", str(bench)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bench / 'results.json'} is not valid JSON (line 1, column 27" in err
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("[1, 2]")
    assert main(["evaluate", str(run)]) == 2
    assert f"{run / 'config.json'} holds a JSON list, expected an object" in capsys.readouterr().err
    from marbler_jax_rl.checkpoints import read_json_lines

    (run / "metrics.jsonl").write_text('{"update": 1}\n{"upd')
    with pytest.raises(ValueError, match=r"metrics.jsonl line 2 is not valid JSON"):
        read_json_lines(run / "metrics.jsonl")
