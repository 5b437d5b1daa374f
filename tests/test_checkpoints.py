"""Checkpoint integrity: a damaged checkpoint is found by its manifest (or by orbax), skipped with one
warning line, and the run resumes from the newest intact one and ends bit-exactly as an uninterrupted
run; damaged final parameters and best checkpoints are refused with the file named."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from marbler_jax_rl import checkpoints
from marbler_jax_rl.driver import train_run
from marbler_jax_rl.run import load_params
from marbler_jax_rl.run import Run

from tests.test_training_driver import TWO_SEEDS

# the driver tests' settings, so their compiled programs are shared through the persistent cache
RUN = {k: v for k, v in TWO_SEEDS.items() if k != "log"}


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    """An uninterrupted 4-update run (a checkpoint after every update)."""
    out = tmp_path_factory.mktemp("full") / "run"
    train_run(out=out, log=lambda *a: None, **RUN)
    return out


def flip_bytes(path: Path, count: int = 16) -> None:
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    for i in range(middle, min(middle + count, len(data))):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def largest_file(folder: Path) -> Path:
    return max((p for p in folder.rglob("*") if p.is_file() and p.name != checkpoints.MANIFEST),
               key=lambda p: p.stat().st_size)


def cut_run(tmp_path: Path, full: Path, stop_at: int) -> Path:
    """A copy of ``full`` as an interrupted run would have left it after ``stop_at`` updates."""
    import shutil

    out = tmp_path / "cut"
    shutil.copytree(full, out)
    for step in (out / "checkpoints").iterdir():
        if int(step.name) > stop_at:
            shutil.rmtree(step)
    (out / "params.npz").unlink()
    return out


def final_params(run: Path) -> dict:
    with np.load(run / "params.npz") as f:
        return {k: f[k] for k in f.files}


def assert_same_params(a: Path, b: Path) -> None:
    pa, pb = final_params(a), final_params(b)
    assert pa.keys() == pb.keys()
    for name in pa:
        np.testing.assert_array_equal(pa[name], pb[name], err_msg=name)


def test_every_checkpoint_has_a_matching_manifest(full):
    steps = sorted((full / "checkpoints").iterdir(), key=lambda p: int(p.name))
    assert [p.name for p in steps] == ["1", "2", "3", "4"]
    for folder in steps + list((full / "best").iterdir()):
        assert (folder / checkpoints.MANIFEST).exists() and checkpoints.manifest_problem(folder) is None
    checkpoints.check_file(full / "params.npz")


@pytest.mark.parametrize("damage", ["flip", "empty_metadata", "empty_step"])
def test_a_damaged_latest_checkpoint_is_skipped_and_the_run_ends_as_if_uninterrupted(tmp_path, full, damage):
    out = cut_run(tmp_path, full, stop_at=3)
    latest = out / "checkpoints" / "3"
    if damage == "flip":                  # silent before: orbax restored other numbers
        flip_bytes(largest_file(latest))
    elif damage == "empty_metadata":
        (latest / "default" / "_METADATA").write_text("")
    else:
        for item in latest.iterdir():
            if item.is_dir():
                import shutil

                shutil.rmtree(item)
    said = []
    train_run(out=out, resume=True, log=said.append, **RUN)
    warnings = [line for line in said if line.startswith("warning:")]
    assert len(warnings) == 1 and f"{latest}" in warnings[0], said
    assert "resuming from update 2 of 4" in said
    assert (out / "checkpoints.damaged" / "3").is_dir()          # kept aside, not deleted
    assert_same_params(out, full)
    lines = [json.loads(line)["update"] for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert lines == [1, 2, 3, 4]


def test_a_checkpoint_interrupted_before_its_manifest_is_not_trusted(tmp_path, full):
    out = cut_run(tmp_path, full, stop_at=3)
    (out / "checkpoints" / "3" / checkpoints.MANIFEST).unlink()
    said = []
    train_run(out=out, resume=True, log=said.append, **RUN)
    assert any("has no manifest" in line for line in said) and "resuming from update 2 of 4" in said
    assert_same_params(out, full)


def test_every_manifest_is_required_in_a_folder_that_writes_them(tmp_path, full):
    """With every manifest of checkpoints/ deleted and a byte flipped, a resume restored the flipped bytes
    without a word; a best/ step without its manifest was never checked, so export shipped it. A folder
    written with manifests (config.json says so) treats a step without one as damaged."""
    import shutil

    out = cut_run(tmp_path, full, stop_at=2)
    for step in (out / "checkpoints").iterdir():
        (step / checkpoints.MANIFEST).unlink()
    flip_bytes(largest_file(out / "checkpoints" / "2"))
    said = []
    with pytest.raises(ValueError, match="no intact checkpoint left"):
        train_run(out=out, resume=True, log=said.append, **RUN)
    assert sum("has no manifest" in line for line in said) == 2
    run = tmp_path / "best-run"
    shutil.copytree(full, run)
    best = next((run / "best").iterdir())
    (best / checkpoints.MANIFEST).unlink()
    flip_bytes(largest_file(best))
    with pytest.raises(ValueError, match=f"the best checkpoint {best} is damaged: it has no manifest"):
        Run.open(run).params("best")
    # a folder from before manifests (its config.json does not say it writes them) is trusted on orbax's restore
    old = cut_run(tmp_path / "old", full, stop_at=2)
    config = json.loads((old / "config.json").read_text())
    del config["manifests"]
    (old / "config.json").write_text(json.dumps(config))
    for step in (*(old / "checkpoints").iterdir(), *(old / "best").iterdir()):
        (step / checkpoints.MANIFEST).unlink()
    train_run(out=old, resume=True, log=lambda *a: None, **RUN)
    assert_same_params(old, full)


def test_no_intact_checkpoint_is_one_clear_error(tmp_path, full):
    out = cut_run(tmp_path, full, stop_at=2)
    for step in (out / "checkpoints").iterdir():
        flip_bytes(largest_file(step))
    with pytest.raises(ValueError, match=f"no intact checkpoint left in {out / 'checkpoints'}"):
        train_run(out=out, resume=True, log=lambda *a: None, **RUN)


def test_damaged_final_parameters_and_best_checkpoint_are_refused_by_name(tmp_path, full):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(full, out)
    flip_bytes(out / "params.npz")
    with pytest.raises(ValueError, match=r"params.npz changed after it was written \(checksum mismatch"):
        load_params(out / "params.npz")
    best = next((out / "best").iterdir())
    flip_bytes(largest_file(best))
    with pytest.raises(ValueError, match=f"the best checkpoint {best} is damaged: .*checksum mismatch"):
        Run.open(out).params("best")
    (out / "params.npz").write_bytes(b"")
    (out / "params.npz.sha256").unlink()
    with pytest.raises(ValueError, match="cannot read .*params.npz"):
        load_params(out / "params.npz")


def test_a_run_saved_with_marblers_key_names_opens_and_resumes(tmp_path, full):
    """Run folders written before the waypoint-box and spawn-band keys were renamed (``LEFT``, ``UP``,
    ``ROBOT_INIT_RIGHT_THRESH``, ...) still open and resume: their saved names are read as the current ones."""
    import shutil

    out = tmp_path / "old"
    shutil.copytree(full, out)
    config = json.loads((out / "config.json").read_text())
    old_names = {"x_min": "LEFT", "x_max": "RIGHT", "y_min": "UP", "y_max": "DOWN",
                 "robot_band_right": "ROBOT_INIT_RIGHT_THRESH", "goal_band_left": "PREY_INIT_LEFT_THRESH"}
    config["env"] = {old_names.get(k, k): v for k, v in config["env"].items()}
    (out / "config.json").write_text(json.dumps(config))
    run = Run.open(out)
    assert run.env().config.y_min == -0.9 and run.env().config.robot_band_right == -0.5
    train_run(out=out, resume=True, log=lambda *a: None, **RUN)        # finished already: nothing to redo
    assert_same_params(out, full)
    assert json.loads((out / "evaluation.json").read_text())["env_steps_per_s"] == 0   # none trained now
    assert "y_min" in json.loads((out / "config.json").read_text())["env"]
