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
