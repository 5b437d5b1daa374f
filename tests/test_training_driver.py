"""Training driver: chunked == one-shot, interrupted + --resume == uninterrupted (bit-exact),
checkpoint round trip, and refusal to mix runs."""
from __future__ import annotations

import json

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

import marbler_jax
from tests.helpers import interrupt_at
from algorithms.driver import ALGORITHMS, SEED_BATCHING, load_params, load_run, make_tester, train
from algorithms.ippo import IPPOConfig, make_train

HP = dict(num_envs=8, num_steps=8, num_minibatches=2, update_epochs=1, hidden=16)
STEPS = 4 * 8 * 8  # 4 updates


def test_chunked_run_matches_one_shot():
    """Same keys and schedule; different chunkings compile differently, so equal to float rounding."""
    env = marbler_jax.make("simple_navigation")
    trainer = make_train(env, IPPOConfig(total_timesteps=STEPS, **HP))
    one_shot, _ = jax.jit(trainer)(jax.random.PRNGKey(3))
    runner = trainer.init(jax.random.PRNGKey(3))
    run = jax.jit(trainer.run, static_argnums=1)
    runner, _ = run(runner, 1)
    runner, _ = run(runner, 3)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-8),
                           one_shot, runner["params"])


def test_interrupted_run_resumes_bit_exactly(tmp_path):
    common = dict(scenario="warehouse", algo="ippo", total_steps=STEPS, seeds=2, hp=HP, eval_episodes=0,
                  checkpoint_every=1, progress=False, log=lambda *a: None, test_episodes=16)
    train(out=tmp_path / "full", **common)

    with pytest.raises(KeyboardInterrupt):
        train(out=tmp_path / "cut", on_chunk=interrupt_at(2), **common)
    with pytest.raises(ValueError, match="already holds checkpoints; pass --resume"):
        train(out=tmp_path / "cut", **common)
    with pytest.raises(ValueError, match=r"settings differ from the saved run in \['seeds'\]"):
        train(out=tmp_path / "cut", resume=True, **dict(common, seeds=3))
    train(out=tmp_path / "cut", resume=True, **common)

    full, cut = np.load(tmp_path / "full" / "params.npz"), np.load(tmp_path / "cut" / "params.npz")
    assert sorted(full) == sorted(cut)
    for name in full:
        np.testing.assert_array_equal(full[name], cut[name], err_msg=name)
    assert (tmp_path / "cut" / "metrics.jsonl").read_text().count("\n") == 4
    # the greedy test after every chunk picks the best checkpoint, also across the interruption
    rows = [json.loads(line) for line in (tmp_path / "full" / "metrics.jsonl").read_text().splitlines()]
    tests = [r["test_return_mean"] for r in rows]
    assert all(np.isfinite(tests)) and len(set(tests)) > 1
    best_step = rows[int(np.argmax(tests))]["update"]
    for run in ("full", "cut"):
        assert ocp.CheckpointManager(tmp_path / run / "best").latest_step() == best_step
    evaluation = json.loads((tmp_path / "full" / "evaluation.json").read_text())
    assert evaluation["best_by"] == "greedy test return" and evaluation["best_return"] == max(tests)

    # checkpoint round trip: the latest checkpoint restores the final parameters exactly
    manager = ocp.CheckpointManager(tmp_path / "full" / "checkpoints")
    assert manager.latest_step() == 4 and len(manager.all_steps()) == 3  # keep the last 3
    restored = manager.restore(4)
    kernel = restored["params"]["params"]["actor"]["Dense_0"]["kernel"]
    np.testing.assert_array_equal(kernel, full["params/actor/Dense_0/kernel"])
    loaded = load_params(tmp_path / "full" / "params.npz")
    np.testing.assert_array_equal(loaded["params"]["actor"]["Dense_0"]["kernel"], kernel)
    env, policy = load_run(tmp_path / "full")
    assert env.name == "warehouse" and policy(None, np.zeros((env.num_agents, env.obs_dim), np.float32)).shape == (env.num_agents,)


def test_vmapped_seeds_match_mapped_seeds(tmp_path):
    """The driver's ``seed_batching="vmap"`` (default) and ``"map"`` train the same seeds (vmap == loop)."""
    env = marbler_jax.make("simple_navigation")
    trainer = make_train(env, IPPOConfig(total_timesteps=STEPS, **HP))
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    out = {}
    for name, over_seeds in SEED_BATCHING.items():
        runner = jax.jit(lambda k: over_seeds(trainer.init, k))(keys)
        runner, _ = jax.jit(lambda r: over_seeds(lambda s: trainer.run(s, 2), r))(runner)
        out[name] = runner["params"]
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6), out["vmap"], out["map"])
    kernel = out["vmap"]["params"]["actor"]["Dense_0"]["kernel"]
    assert kernel.shape[0] == 2 and not np.allclose(kernel[0], kernel[1])
    with pytest.raises(ValueError, match=r"seed_batching must be one of \['vmap', 'map'\], got 'pmap'"):
        train("simple_navigation", "ippo", STEPS, 2, tmp_path / "bad", hp=HP, seed_batching="pmap", progress=False)


def test_greedy_tests_do_not_change_training(tmp_path):
    """The per-chunk greedy test (``test_episodes``) draws no training randomness: same parameters with
    and without it; it reports the mean return of each seed's greedy episodes; bad counts are refused."""
    common = dict(scenario="simple_navigation", algo="ippo", total_steps=STEPS, seeds=2, hp=HP,
                  checkpoint_every=2, progress=False, log=lambda *a: None)
    train(out=tmp_path / "test", test_episodes=8, eval_episodes=8, **common)
    train(out=tmp_path / "none", test_episodes=0, eval_episodes=0, **common)
    evaluations = [json.loads((tmp_path / run / "evaluation.json").read_text()) for run in ("test", "none")]
    assert evaluations[0]["trained"]["episodes"] >= 8 and evaluations[1]["trained"] is None   # 0: no evaluation
    with_test, without = np.load(tmp_path / "test" / "params.npz"), np.load(tmp_path / "none" / "params.npz")
    for name in with_test:
        np.testing.assert_array_equal(with_test[name], without[name], err_msg=name)
    rows = [json.loads(line) for line in (tmp_path / "test" / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows if "test_return_mean" in r] == [2, 4]
    assert not any("test_return_mean" in line for line in (tmp_path / "none" / "metrics.jsonl").read_text().splitlines())
    # the final test equals a direct greedy rollout of each seed's final parameters
    env = marbler_jax.make("simple_navigation")
    cfg = IPPOConfig(total_timesteps=STEPS, **HP)
    greedy = ALGORITHMS["ippo"][2]
    params = load_params(tmp_path / "test" / "params.npz")
    keys = jax.random.split(jax.random.PRNGKey(0 + 7919), 2)
    per_seed = np.asarray(make_tester(env, lambda p: greedy(env, cfg, p), 8)(params, keys))
    assert rows[-1]["test_return_mean"] == pytest.approx(float(per_seed.mean()), rel=1e-5)
    assert rows[-1]["test_return_std"] == pytest.approx(float(per_seed.std()), rel=1e-4, abs=1e-5)
    from marbler_jax.rollout import batched_rollout
    seed0 = jax.tree_util.tree_map(lambda x: x[0], params)
    _, (_, done, info) = batched_rollout(env, keys[0], 8, env.max_steps, greedy(env, cfg, seed0))
    done, returns = np.asarray(done), np.asarray(info["episode_return"])
    first = done.argmax(0)
    assert done.any(0).all()
    assert per_seed[0] == pytest.approx(returns[first, np.arange(8)].mean(), rel=1e-5)
    with pytest.raises(ValueError, match="test_episodes must be >= 0"):
        train(out=tmp_path / "bad", test_episodes=-1, **common)
    with pytest.raises(ValueError, match="eval_episodes must be >= 0"):
        train(out=tmp_path / "bad", eval_episodes=-1, **common)
