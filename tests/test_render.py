"""Rendering: vmapped episodes recorded and tiled into GIF frames; the ``render`` CLI for scenarios."""
from __future__ import annotations

import warnings

import imageio.v2 as imageio
import jax
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl.cli import main
from marbler_jax.render import FrameDrawer, record_episodes, render_frame, render_grid_episode


def test_recorded_episodes_freeze_when_done_and_tile_into_a_grid():
    env = marbler_jax.make("predator_capture_prey", max_episode_steps=6, control_period=15)
    states, returns, lengths = record_episodes(env, None, jax.random.PRNGKey(0), num_envs=3)
    steps = np.asarray(states.step)
    assert steps.shape == (env.max_steps + 1, 3) and returns.shape == steps.shape
    assert np.all(np.diff(steps, axis=0) >= 0) and np.all(steps[-1] == lengths) and np.all(lengths >= 1)
    for k in range(3):   # after its last step an env's state no longer changes
        after = slice(int(lengths[k]), None)
        assert np.all(np.asarray(states.poses)[after, k] == np.asarray(states.poses)[int(lengths[k]), k])
    frames = render_grid_episode(env, states)
    assert len(frames) == int(lengths.max()) + 1
    tile = render_frame(env, jax.tree_util.tree_map(lambda x: x[0, 0], states), dpi=60)
    assert frames[0].shape == (2 * tile.shape[0], 2 * tile.shape[1], 3)        # 3 envs -> 2 x 2 grid
    h, w = tile.shape[:2]
    first, second, empty = frames[0][:h, :w], frames[0][:h, w:], frames[0][h:, w:]
    assert first.std() > 20 and not np.array_equal(first, second)              # drawn, and different envs
    assert np.all(empty == 255)                                                # the unused cell stays blank
    assert not np.array_equal(frames[0], frames[-1])                           # robots moved


@pytest.mark.parametrize("scenario", ["arctic_transport", "predator_capture_prey"])
def test_a_reused_drawer_draws_each_state_like_a_fresh_figure(scenario):
    """``FrameDrawer`` keeps one figure and its background: a frame carries nothing over from the one
    before, and equals a fresh figure's (Arctic Transport: an image layer under the arena's outlines)."""
    env = marbler_jax.make(scenario, max_episode_steps=4)
    states, returns, _ = record_episodes(env, None, jax.random.PRNGKey(1), num_envs=1)
    draw = FrameDrawer(env, dpi=50)
    frames = []
    for t in (0, 4, 0):
        one = jax.tree_util.tree_map(lambda x: x[t, 0], states)
        frame = draw(one, step=t, reward=float(returns[t, 0]))
        np.testing.assert_array_equal(frame, render_frame(env, one, step=t, reward=float(returns[t, 0]), dpi=50))
        frames.append(frame)
    np.testing.assert_array_equal(frames[0], frames[2])
    assert not np.array_equal(frames[0], frames[1])
    assert len(draw._ax.get_children()) == len(FrameDrawer(env, dpi=50)._ax.get_children())   # nothing piles up


def test_render_cli_writes_a_gif_of_a_scenario_grid(tmp_path, capsys):
    gif = tmp_path / "warehouse.gif"
    assert main(["render", "warehouse", "--out", str(gif), "--envs", "2", "--no-progress",
                 "--set", "max_episode_steps=4"]) == 0
    frames = imageio.mimread(gif)
    assert 2 <= len(frames) <= 6 and frames[0].shape[1] > frames[0].shape[0]
    assert f"-> {gif}" in capsys.readouterr().out
    from PIL import Image

    assert Image.open(gif).info["duration"] == 160            # the default 6 fps, in GIF's 10 ms steps
    assert main(["render", "warehouse", "--out", str(gif), "--fps", "2", "--no-progress",
                 "--set", "max_episode_steps=2"]) == 0
    assert Image.open(gif).info["duration"] == 500


def test_render_cli_writes_an_mp4_without_warnings(tmp_path):
    mp4 = tmp_path / "pcp.mp4"                                     # imageio-ffmpeg is in the test extra
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["render", "predator_capture_prey", "--out", str(mp4), "--no-progress",
                     "--set", "max_episode_steps=5", "--set", "penalize_violations=false"]) == 0
    # e.g. JAX's fork warning when ffmpeg's process starts
    assert not [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        frames = imageio.mimread(mp4, format="FFMPEG")
    assert len(frames) == 7 and frames[0].std() > 20


@pytest.mark.parametrize("argv, message", [
    (["render", "no_such_scenario", "--out", "x.gif"], "neither a run folder"),
    (["render", "warehouse", "--out", "x.avi"], ".gif or .mp4"),
    (["render", "warehouse", "--out", "x.gif", "--envs", "0"], "--envs"),
    (["render", "warehouse", "--out", "x.gif", "--fps", "0"], "fps must be a number in (0, 100]"),
])
def test_render_cli_rejects_bad_input(argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if argv[-1] != "0":
        argv = argv + ["--set", "max_episode_steps=1"] if argv[1] == "warehouse" else argv
    assert main(argv + ["--no-progress"]) == 2
    assert message in capsys.readouterr().err
