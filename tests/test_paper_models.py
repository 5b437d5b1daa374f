"""``scripts/paper_models.py``: the bundle's episode lines parse as the env counts them, and the paper-models
table reads the per-episode files and says where marbler-jax and MARBLER's code agree."""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.helpers import load_script


@pytest.fixture(scope="module")
def paper_models():
    return load_script("paper_models")


def test_bundle_lines_count_violations_as_the_env_does(paper_models):
    stdout = "\n".join([
        "marbler-jax bundle: predator_capture_prey with 4 robots, vdn policy, 2 episode(s), control period 1",
        "episode 1/2: return=33.250 steps=55 violation=False collisions=False out_of_bounds=False prey_left=0 "
        "compute_ms_mean=1.77 compute_ms_max=6.00",
        "Your simulation took approximately 52.64 real seconds to execute.",
        "episode 2/2: return=-2.150 steps=12 violation=True collisions=True out_of_bounds=False prey_left=4 "
        "compute_ms_mean=1.71 compute_ms_max=7.63",
    ])
    rows = paper_models.parse_bundle_output(stdout, 81, ("prey_left",))
    assert rows == {"reward": [33.25, -2.15], "steps": [55.0, 81.0], "collisions": [0.0, 100.0],
                    "out_of_bounds": [0.0, 0.0], "prey_left": [0.0, 4.0]}


def test_the_table_reads_every_loop_and_judges_agreement(paper_models, tmp_path):
    rng = np.random.default_rng(0)

    def write(loop, scenario, algo, shift):
        rewards = (30 + shift + rng.normal(size=500)).tolist()
        metrics = {"reward": rewards, "steps": [60.0] * 500, "collisions": [0.0] * 500, "out_of_bounds": [0.0] * 500,
                   "prey_left": [0.0] * 500}
        (tmp_path / loop).mkdir(exist_ok=True)
        (tmp_path / loop / f"{scenario}-{algo}.json").write_text(json.dumps({"episodes_metrics": metrics}))

    write("marbler-jax", "predator_capture_prey", "vdn", 0.0)
    write("marbler", "predator_capture_prey", "vdn", 0.02)            # the same within the CI
    write("marbler-jax", "predator_capture_prey", "qmix", 0.0)
    write("marbler", "predator_capture_prey", "qmix", 1.0)             # one reward apart: not the same
    text = paper_models.table_markdown(tmp_path)
    vdn = next(line for line in text.splitlines() if line.startswith("| predator_capture_prey | vdn |"))
    qmix = next(line for line in text.splitlines() if line.startswith("| predator_capture_prey | qmix |"))
    assert "| yes |" in vdn and "33.25 ± 0.46" in vdn and "| **no** |" in qmix
    assert "(a) and (b) agree on 1 of 2 models." in text
    low, high = paper_models.difference_ci([1.0, 2.0, 3.0] * 50, [1.0, 2.0, 3.0] * 50)[1:]
    assert low < 0 < high


def test_the_difference_is_paired_when_both_sides_played_the_same_starts(paper_models, tmp_path):
    """Each start's luck (e.g. Material Transport's zone loads) is shared: the episode-by-episode difference
    sees through it where two independent means would not."""
    rng = np.random.default_rng(1)
    luck = rng.normal(scale=3.0, size=500)
    a, b = 30 + luck + rng.normal(scale=0.3, size=500), 30.1 + luck + rng.normal(scale=0.3, size=500)
    paired = paper_models.difference_ci(a, b, paired=True)
    welch = paper_models.difference_ci(a, b)
    assert paired[2] < 0 < welch[2] and paired[2] - paired[1] < (welch[2] - welch[1]) / 5

    def write(loop, rewards, starts):
        metrics = {"reward": list(rewards), "steps": [60.0] * 500, "collisions": [0.0] * 500,
                   "out_of_bounds": [0.0] * 500, "prey_left": [0.0] * 500}
        (tmp_path / loop).mkdir(exist_ok=True)
        (tmp_path / loop / "predator_capture_prey-vdn.json").write_text(
            json.dumps({"episodes_metrics": metrics, **({"marbler_starts": True} if starts else {})}))

    write("marbler", b, False)
    write("marbler-jax", a, True)
    row = next(line for line in paper_models.table_markdown(tmp_path).splitlines()
               if line.startswith("| predator_capture_prey | vdn |"))
    assert "| **no** |" in row and f"{paired[0]:+.2f} [{paired[1]:+.2f}, {paired[2]:+.2f}]" in row
    write("marbler-jax", a, False)                    # fresh starts: the difference of two independent means
    row = next(line for line in paper_models.table_markdown(tmp_path).splitlines()
               if line.startswith("| predator_capture_prey | vdn |"))
    assert "| yes |" in row


def test_episodes_begin_at_marbler_starts():
    """A Material Transport start with both zones empty ends at its first step; MARBLER's usual start does not,
    and the robots begin at its poses."""
    import jax

    import marbler_jax
    from marbler_jax_rl.evaluate import greedy_episodes
    from marbler_jax_rl.marbler_starts import batched_starts

    env = marbler_jax.make("material_transport", protocol="marbler")
    poses = [[-1.4, -1.4, -1.1, -1.1], [-0.6, 0.3, -0.3, 0.6], [0.0] * 4]
    agents = [{"load": 0}] * 4

    def start(zone1, zone2):
        return {"reset_poses": poses, "reset_state": {"zone1_load": zone1, "zone2_load": zone2, "messages": [0] * 4},
                "reset_agents": agents}

    obs, state = batched_starts(env, "MaterialTransport", [start(0, 0), start(100, 20)])
    np.testing.assert_allclose(state.poses[1], np.transpose(poses), atol=1e-6)
    assert not np.asarray(obs).any()                                    # MARBLER's all-zero first observation
    values = greedy_episodes(env, None, 2, jax.random.PRNGKey(0), (obs, state))
    assert values["steps"][0] == 1 and values["material_left"][0] == 0
    assert values["steps"][1] > 1 and values["material_left"][1] > 0


def test_a_start_of_another_scenario_is_one_clear_error():
    import marbler_jax
    from marbler_jax_rl.marbler_starts import env_state

    env = marbler_jax.make("predator_capture_prey", protocol="marbler")
    mt_start = {"zone1_load": 100, "zone2_load": 20, "messages": [0] * 4}
    with pytest.raises(ValueError, match="a PredatorCapturePrey start needs 'prey_loc'"):
        env_state(env, "PredatorCapturePrey", np.zeros((3, 4)), mt_start, [{"load": 0}] * 4)
    with pytest.raises(ValueError, match=r"reset_poses must be \[3, 4\] \(rps's layout\), got \(4, 3\)"):
        env_state(env, "PredatorCapturePrey", np.zeros((4, 3)), {"prey_loc": np.zeros((6, 2)).tolist(),
                  "prey_sensed": [False] * 6, "prey_captured": [False] * 6}, [{}] * 4)
