"""``scripts/bench_train.py`` times its configurations in turns (no JAX work here: fake chunks)."""
from __future__ import annotations

import pytest

from tests.helpers import load_script


@pytest.fixture(scope="module")
def bench_train():
    return load_script("bench_train")


def test_configurations_take_turns_and_report_best_and_median(bench_train, monkeypatch):
    now, calls = [0.0], []
    monkeypatch.setattr(bench_train.time, "perf_counter", lambda: now[0])

    def fake(name, steps, durations):
        def run():
            calls.append(name)
            now[0] += durations[sum(c == name for c in calls) - 1]     # this call's duration
        return dict(row=dict(name=name, env_steps=steps), run=run)

    rows = bench_train.time_in_turns([fake("a", 10, [1, 4, 2]), fake("b", 20, [5, 5, 5]), fake("c", 30, [3, 1, 9])],
                                     repeats=3)
    # each round runs every configuration once, starting one further along each time
    assert calls == ["a", "b", "c", "b", "c", "a", "c", "a", "b"]
    assert [r["name"] for r in rows] == ["a", "b", "c"]
    assert [r["all_seconds"] for r in rows] == [[1, 4, 2], [5, 5, 5], [3, 1, 9]]
    assert [(r["seconds"], r["median_seconds"]) for r in rows] == [(1, 2), (5, 5), (1, 3)]
    assert [(r["env_steps_per_s"], r["median_env_steps_per_s"]) for r in rows] == [(10, 5), (4, 4), (30, 10)]


def test_variants_parse_into_overrides(bench_train):
    assert bench_train.parse_variant("") == {}
    assert bench_train.parse_variant("last_action=true,hidden=32") == {"last_action": True, "hidden": 32}
    with pytest.raises(ValueError, match="key=value"):
        bench_train.parse_variant("last_action")


def test_the_profile_splits_an_update_by_difference():
    """``scripts/profile_train.py``: parts from programs that differ in one setting (no JAX work here)."""
    profile = load_script("profile_train")
    value = dict(train_steps=32)
    assert set(profile.variants(value)) == {"whole", "no learning", "half the gradient steps"}
    parts = profile.parts(value, {"whole": 10.0, "no learning": 2.0, "half the gradient steps": 6.0}, 1.5)
    # 16 fewer steps saved 4 s: 32 steps take 8 s, leaving 0 s of the 8 s of learning for the targets
    assert parts == {"env step": 1.5, "action selection and buffer": 0.5, "gradient steps (32)": 8.0,
                     "targets and the rest of learning": 0.0}
    ppo = dict(update_epochs=4, num_minibatches=4)
    assert set(profile.variants(ppo)) == {"whole", "one epoch"}
    parts = profile.parts(ppo, {"whole": 5.0, "one epoch": 2.0}, 0.5)
    # three epochs more cost 3 s: four take 4 s, the rollout the remaining 1 s, of which 0.5 s is the env
    assert parts == {"env step": 0.5, "action selection and advantages": 0.5, "epochs (4 x 4 minibatches)": 4.0}
