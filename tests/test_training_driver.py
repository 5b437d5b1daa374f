"""Training driver: chunked == one-shot, interrupted + --resume == uninterrupted (bit-exact),
checkpoint round trip, and refusal to mix runs."""
from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

import marbler_jax
from tests.helpers import compile_marks, interrupt_at, tensorboard_steps
from marbler_jax_rl import registry
from marbler_jax_rl.driver import SEED_BATCHING, build_config, default_seed_batching, make_tester, train_run
from marbler_jax_rl.run import Run, load_params, load_run, seed_best_scores
from marbler_jax_rl.run_writer import keep_improved
from marbler_jax_rl.ippo import IPPOConfig, make_train

HP = dict(num_envs=8, num_steps=8, num_minibatches=2, update_epochs=1, hidden=16)
STEPS = 4 * 8 * 8  # 4 updates


@pytest.mark.parametrize("cell", ["none", "gru"])
def test_chunked_run_matches_one_shot(cell):
    """Same keys and schedule; different chunkings compile differently, so equal to float rounding (recurrent
    actors too: their hidden state and episode starts are runner state)."""
    env = marbler_jax.make("simple_navigation")
    trainer = make_train(env, IPPOConfig(total_timesteps=STEPS, cell=cell, **HP))
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
    train_run(out=tmp_path / "full", **common)

    with pytest.raises(KeyboardInterrupt):
        train_run(out=tmp_path / "cut", on_chunk=interrupt_at(2), **common)
    with pytest.raises(ValueError, match=r"already holds a run \(.*config.json.*\); pass --resume"):
        train_run(out=tmp_path / "cut", **common)
    with pytest.raises(ValueError, match=r"settings differ from the saved run in \['seeds'\]"):
        train_run(out=tmp_path / "cut", resume=True, **dict(common, seeds=3))
    # a run saved before an env setting existed resumes when that setting is at its default, not otherwise
    saved = json.loads((tmp_path / "cut" / "config.json").read_text())
    del saved["env"]["cbf_safety_radius"]
    (tmp_path / "cut" / "config.json").write_text(json.dumps(saved))
    with pytest.raises(ValueError, match=r"settings differ from the saved run in \['env'\]"):
        train_run(out=tmp_path / "cut", resume=True, **dict(common, env_overrides={"cbf_safety_radius": 0.3}))
    train_run(out=tmp_path / "cut", resume=True, **common)

    full, cut = np.load(tmp_path / "full" / "params.npz"), np.load(tmp_path / "cut" / "params.npz")
    assert sorted(full) == sorted(cut)
    for name in full:
        np.testing.assert_array_equal(full[name], cut[name], err_msg=name)
    assert (tmp_path / "cut" / "metrics.jsonl").read_text().count("\n") == 4
    # TensorBoard holds every update once, also those whose events the interrupted writer never flushed
    assert tensorboard_steps(tmp_path / "cut" / "tensorboard")["train/sps"] == [64, 128, 192, 256]
    # the greedy test after every chunk picks each seed's best checkpoint, also across the interruption
    rows = [json.loads(line) for line in (tmp_path / "full" / "metrics.jsonl").read_text().splitlines()]
    tests = [r["test_return_mean"] for r in rows]
    per_seed = np.array([r["test_returns"] for r in rows])                  # [chunks, seeds]
    assert all(np.isfinite(tests)) and len(set(tests)) > 1
    np.testing.assert_allclose(per_seed.mean(axis=1), tests, rtol=1e-5)
    last_improvement = max(rows[int(np.argmax(per_seed[:, s]))]["update"] for s in range(2))
    for run in ("full", "cut"):
        assert ocp.CheckpointManager(tmp_path / run / "best").latest_step() == last_improvement
    evaluation = json.loads((tmp_path / "full" / "evaluation.json").read_text())
    assert evaluation["best_by"] == "greedy test return"
    np.testing.assert_allclose(evaluation["best_return_per_seed"], per_seed.max(axis=0), rtol=1e-6)
    assert evaluation["best_return"] == pytest.approx(per_seed.max(axis=0).mean(), rel=1e-6)

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


def test_a_fresh_run_never_writes_into_a_folder_that_holds_files(tmp_path):
    """Another run's folder without its checkpoints, or a folder of a user's files: a fresh run is refused
    before anything is written (it overwrote the other run's config.json, leaving a folder that said IPPO
    with VDN's parameters)."""
    other = tmp_path / "vdn-run"
    other.mkdir()
    (other / "config.json").write_text('{"algo": "vdn"}')
    (other / "params.npz").write_bytes(b"vdn's")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    common = dict(scenario="simple_navigation", algo="ippo", total_steps=STEPS, seeds=1, hp=HP, progress=False,
                  log=lambda *a: None)
    with pytest.raises(ValueError, match=r"vdn-run already holds a run \(config.json, params.npz\); pass --resume"):
        train_run(out=other, **common)
    with pytest.raises(ValueError, match=r"mine already holds files \(notes.txt\)"):
        train_run(out=mine, **common)
    assert sorted(p.name for p in other.iterdir()) == ["config.json", "params.npz"]
    assert (other / "config.json").read_text() == '{"algo": "vdn"}' and sorted(mine.iterdir()) == [mine / "notes.txt"]
    with pytest.raises(ValueError, match="the settings differ from the saved run"):
        train_run(out=other, resume=True, **common)


def test_changed_settings_name_what_differs_and_ignore_the_learners_device_count(tmp_path):
    from marbler_jax_rl.run_writer import changed_settings, run_config

    env = marbler_jax.make("predator_capture_prey", control_period=15)
    config = run_config("predator_capture_prey", "vdn", 2, 0, env, build_config("vdn", dict(learner_devices=2)), 64)
    (tmp_path / "config.json").write_text(json.dumps(config))
    assert changed_settings(tmp_path, config, env) == []
    one_device = run_config("predator_capture_prey", "vdn", 2, 0, env, build_config("vdn", {}), 64)
    assert changed_settings(tmp_path, one_device, env) == []
    robots_loop = marbler_jax.make("predator_capture_prey", control_period=1)
    other = run_config("predator_capture_prey", "vdn", 3, 0, robots_loop, build_config("vdn", dict(lr=1e-4)), 64)
    assert changed_settings(tmp_path, other, robots_loop) == ["algorithm", "env", "seeds"]


def test_settings_added_since_a_run_was_saved_compare_equal_at_their_defaults(tmp_path):
    """A MAPPO run saved before ``cell`` existed resumes with the feed-forward default, not with another."""
    from marbler_jax_rl.run_writer import changed_settings, run_config

    env = marbler_jax.make("warehouse")
    config = run_config("warehouse", "mappo", 2, 0, env, build_config("mappo", {}), 64)
    old = json.loads(json.dumps(config))
    del old["algorithm"]["cell"]
    (tmp_path / "config.json").write_text(json.dumps(old))
    assert changed_settings(tmp_path, config, env) == []
    recurrent = run_config("warehouse", "mappo", 2, 0, env, build_config("mappo", dict(cell="gru")), 64)
    assert changed_settings(tmp_path, recurrent, env) == ["algorithm"]


@pytest.mark.parametrize("algo", ["ippo", "vdn"])
def test_vmapped_seeds_match_mapped_seeds(tmp_path, algo):
    """The driver's ``seed_batching="vmap"`` and ``"map"`` train the same seeds (vmap == loop); for VDN with
    learning starting in the second update, a branch that ``map`` takes and ``vmap`` computes both sides of."""
    env = marbler_jax.make("simple_navigation")
    if algo == "ippo":
        trainer = make_train(env, IPPOConfig(total_timesteps=STEPS, **HP))
    else:
        cfg = build_config("vdn", dict(num_envs=4, buffer_size=8, batch_size=4, train_steps=2, hidden=8, cell="mingru",
                                       num_steps=10, learning_starts=41, total_timesteps=10**6))
        trainer = registry.get("vdn").make_train(env, cfg)
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    out = {}
    for name in ("vmap", "map"):          # "devices": tests/test_data_parallel.py, in a two-device interpreter
        over_seeds = SEED_BATCHING[name]
        runner = jax.jit(lambda k: over_seeds(trainer.init, k))(keys)
        runner, metrics = jax.jit(lambda r: over_seeds(lambda s: trainer.run(s, 2), r))(runner)
        out[name] = runner["params"]
        if algo == "vdn":                 # no loss before learning starts, one after
            assert np.isnan(metrics["loss"][:, 0]).all() and np.isfinite(metrics["loss"][:, 1]).all()
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6), out["vmap"], out["map"])
    first = jax.tree_util.tree_leaves(out["vmap"])[0]
    assert first.shape[0] == 2 and not np.allclose(first[0], first[1])
    with pytest.raises(ValueError, match=r"seed_batching must be one of \['vmap', 'map', 'devices'\], got 'pmap'"):
        train_run("simple_navigation", algo, STEPS, 2, tmp_path / "bad", hp=HP if algo == "ippo" else {},
              seed_batching="pmap", progress=False)


def test_seeds_are_mapped_for_value_based_learners_on_a_cpu_and_vmapped_otherwise():
    assert [default_seed_batching(a, "cpu") for a in ("vdn", "qmix", "qmix_ns", "mappo", "ippo")] == \
        ["map", "map", "map", "vmap", "vmap"]
    assert {default_seed_batching(a, "gpu") for a in registry.names()} == {"vmap"}
    assert default_seed_batching("vdn") == ("map" if jax.default_backend() == "cpu" else "vmap")


def test_greedy_tests_do_not_change_training(tmp_path):
    """The per-chunk greedy test (``test_episodes``) draws no training randomness: same parameters with
    and without it; it reports the mean return of each seed's greedy episodes; bad counts are refused."""
    common = dict(scenario="simple_navigation", algo="ippo", total_steps=STEPS, seeds=2, hp=HP,
                  checkpoint_every=2, progress=False, log=lambda *a: None)
    train_run(out=tmp_path / "test", test_episodes=8, eval_episodes=8, **common)
    train_run(out=tmp_path / "none", test_episodes=0, eval_episodes=0, **common)
    evaluations = [json.loads((tmp_path / run / "evaluation.json").read_text()) for run in ("test", "none")]
    assert evaluations[0]["trained"]["episodes"] >= 8 and evaluations[1]["trained"] is None   # 0: no evaluation
    with_test, without = np.load(tmp_path / "test" / "params.npz"), np.load(tmp_path / "none" / "params.npz")
    for name in with_test:
        np.testing.assert_array_equal(with_test[name], without[name], err_msg=name)
    rows = [json.loads(line) for line in (tmp_path / "test" / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows if "test_return_mean" in r] == [2, 4]
    no_test = [json.loads(line) for line in (tmp_path / "none" / "metrics.jsonl").read_text().splitlines()]
    assert not any("test_return_mean" in r for r in no_test)
    # without tests each chunk's last line scores every seed by its mean training return over the chunk
    # (none here: no episode ends in these few steps, so no seed has a score and none is "best" yet)
    chunk_lines = [r for r in no_test if "chunk_returns" in r]
    assert [r["update"] for r in chunk_lines] == [2, 4] and all(r["chunk_returns"] == [None, None] for r in chunk_lines)
    assert not (tmp_path / "none" / "best").exists() or ocp.CheckpointManager(tmp_path / "none" / "best").latest_step() is None
    # the final test equals a direct greedy rollout of each seed's final parameters
    env = marbler_jax.make("simple_navigation")
    cfg = IPPOConfig(total_timesteps=STEPS, **HP)
    greedy = registry.get("ippo").greedy_policy
    params = load_params(tmp_path / "test" / "params.npz")
    keys = jax.random.split(jax.random.PRNGKey(0 + 7919), 2)
    episodes = make_tester(env, lambda p: greedy(env, cfg, p), 8)(params, keys)
    assert set(episodes) == {"reward", "steps", "collisions", "out_of_bounds"} and episodes["reward"].shape == (2, 8)
    per_seed = np.asarray(episodes["reward"]).mean(-1)
    # tests.jsonl holds those per-episode metrics of every seed at every test
    tests = [json.loads(line) for line in (tmp_path / "test" / "tests.jsonl").read_text().splitlines()]
    assert [t["update"] for t in tests] == [2, 4] and not (tmp_path / "none" / "tests.jsonl").exists()
    for name, values in episodes.items():
        np.testing.assert_allclose(tests[-1]["episodes"][name], np.asarray(values), rtol=1e-4, atol=1e-4)
    assert rows[-1]["test_return_mean"] == pytest.approx(float(per_seed.mean()), rel=1e-5)
    np.testing.assert_allclose(rows[-1]["test_returns"], per_seed, rtol=1e-5)
    assert rows[-1]["test_return_std"] == pytest.approx(float(per_seed.std()), rel=1e-4, abs=1e-5)
    from marbler_jax.rollout import batched_rollout
    seed0 = jax.tree_util.tree_map(lambda x: x[0], params)
    _, (_, done, info) = batched_rollout(env, keys[0], 8, env.max_steps, greedy(env, cfg, seed0))
    done, returns = np.asarray(done), np.asarray(info["episode_return"])
    first = done.argmax(0)
    assert done.any(0).all()
    assert per_seed[0] == pytest.approx(returns[first, np.arange(8)].mean(), rel=1e-5)
    with pytest.raises(ValueError, match="test_episodes must be >= 0"):
        train_run(out=tmp_path / "bad", test_episodes=-1, **common)
    with pytest.raises(ValueError, match="eval_episodes must be >= 0"):
        train_run(out=tmp_path / "bad", eval_episodes=-1, **common)


def test_seed_best_scores_read_per_seed_scores_and_older_lines():
    """Each seed's best chunk score from ``metrics.jsonl`` lines: per-seed test returns (None = no score),
    chunk training returns for untested runs, and the mean over seeds for lines from before per-seed logs."""
    lines = [json.dumps(row) for row in (
        dict(update=1, return_mean=0.0),                                         # not a chunk's last line
        dict(update=2, test_return_mean=1.5),                                    # older run: the mean only
        dict(update=3, test_return_mean=2.0, test_returns=[3.0, None], chunk_returns=[9.0, 9.0]),
        dict(update=4, test_return_mean=1.0, test_returns=[-1.0, 1.0]))]
    np.testing.assert_array_equal(seed_best_scores(lines, 2, tested=True), [3.0, 1.5])
    np.testing.assert_array_equal(seed_best_scores(lines, 2, tested=False), [9.0, 9.0])
    np.testing.assert_array_equal(seed_best_scores([], 3, tested=True), [-np.inf] * 3)
    # keep_improved: the new parameters of the improved seeds, the kept ones of the others
    new, old = {"w": np.ones((2, 3))}, {"w": np.zeros((2, 3))}
    np.testing.assert_array_equal(keep_improved(np.array([False, True]), new, old)["w"], [[0, 0, 0], [1, 1, 1]])
    assert keep_improved(np.array([False, True]), new, None) is new


TWO_SEEDS = dict(scenario="simple_navigation", algo="ippo", total_steps=STEPS, seeds=2, hp=HP, eval_episodes=0,
                 checkpoint_every=1, keep=4, progress=False, log=lambda *a: None, test_episodes=16, seed=1)


def test_best_checkpoint_keeps_each_seeds_best_and_evaluate_can_pick_the_best_seed(tmp_path):
    """``best/`` holds, per seed, the parameters of that seed's best greedy test (each seed an independent
    run); ``evaluate --best-seed`` plays only the seed with the highest one, as the paper's Table II does."""
    from marbler_jax_rl.evaluate import evaluate_run, markdown_table

    run = tmp_path / "run"
    train_run(out=run, **TWO_SEEDS)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    per_seed = np.array([r["test_returns"] for r in rows])                  # [4 chunks, 2 seeds]
    best_chunk = per_seed.argmax(axis=0)
    assert best_chunk[0] != best_chunk[1], best_chunk       # (seed=1 chosen so: a mean-over-seeds pick differs)
    best = ocp.CheckpointManager(run / "best").restore(ocp.CheckpointManager(run / "best").latest_step())
    checkpoints = ocp.CheckpointManager(run / "checkpoints")
    for s in range(2):
        at_best = checkpoints.restore(rows[best_chunk[s]]["update"])["params"]
        jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(a[s], b[s]), best, at_best)

    winner = int(per_seed.max(axis=0).argmax())
    index, score = Run.open(run).best_seed()
    assert (index, score) == (winner, pytest.approx(per_seed.max()))
    every = evaluate_run(run, episodes=4)
    only = evaluate_run(run, episodes=4, seed_selection="best")
    assert only["seed_indices"] == [winner] and every["seed_indices"] == [0, 1]
    assert "deployed" not in every       # trained in the robots' loop already: one column
    assert only["pooled"] == every["per_seed"][winner]          # the same seed, key and episodes
    assert f"seed {winner}, the best of 2 by greedy test return" in markdown_table(only)
    with pytest.raises(ValueError, match="seed_selection must be 'all' or 'best', got 'worst'"):
        evaluate_run(run, episodes=4, seed_selection="worst")
    # a multi-seed run from before the per-seed scores were logged cannot name its best seed
    old = [json.dumps({k: v for k, v in r.items() if k != "test_returns"}) for r in rows]
    (run / "metrics.jsonl").write_text("\n".join(old) + "\n")
    with pytest.raises(ValueError, match="logs no per-seed scores"):
        Run.open(run).best_seed()


def test_a_kill_before_the_checkpoint_commits_repeats_the_chunk(tmp_path, monkeypatch):
    """The runner checkpoint is written last in a chunk: killed after the metrics and ``best/`` were
    written but before it, a resumed run repeats that chunk and ends with the same parameters,
    metrics lines and best checkpoint as an uninterrupted one."""
    train_run(out=tmp_path / "full", **TWO_SEEDS)
    save = ocp.CheckpointManager.save
    killed = []

    def save_or_die(self, step, *args, **kwargs):
        if Path(self.directory).name == "checkpoints" and step == 2 and not killed:
            killed.append(step)
            raise KeyboardInterrupt
        return save(self, step, *args, **kwargs)

    monkeypatch.setattr(ocp.CheckpointManager, "save", save_or_die)
    with pytest.raises(KeyboardInterrupt):
        train_run(out=tmp_path / "cut", **TWO_SEEDS)
    assert ocp.CheckpointManager(tmp_path / "cut" / "checkpoints").latest_step() == 1
    assert (tmp_path / "cut" / "metrics.jsonl").read_text().count("\n") == 2       # chunk 2 written, not committed
    train_run(out=tmp_path / "cut", resume=True, **TWO_SEEDS)

    def lines(run):   # without the timings
        return [{k: v for k, v in json.loads(line).items() if k != "sps"}
                for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]
    assert lines("cut") == lines("full")
    # TensorBoard: every update once, chunk 2 (logged before the kill, then repeated) not doubled
    steps = tensorboard_steps(tmp_path / "cut" / "tensorboard")["train/sps"]
    assert steps == tensorboard_steps(tmp_path / "full" / "tensorboard")["train/sps"] == [64, 128, 192, 256]
    # the test log too: chunk 2's line, written before the kill, is not doubled by the repeat
    assert (tmp_path / "cut" / "tests.jsonl").read_text() == (tmp_path / "full" / "tests.jsonl").read_text()
    full, cut = np.load(tmp_path / "full" / "params.npz"), np.load(tmp_path / "cut" / "params.npz")
    for name in full:
        np.testing.assert_array_equal(full[name], cut[name], err_msg=name)
    bests = [ocp.CheckpointManager(tmp_path / run / "best") for run in ("full", "cut")]
    assert bests[0].latest_step() == bests[1].latest_step()
    jax.tree_util.tree_map(np.testing.assert_array_equal, *(b.restore(b.latest_step()) for b in bests))


def test_evaluate_reports_the_training_loop_and_the_robots_loop_side_by_side(tmp_path):
    from marbler_jax_rl.evaluate import evaluate_run, greedy_episodes, markdown_table, summarize

    run = tmp_path / "run"
    train_run(out=run, **dict(TWO_SEEDS, seeds=1, checkpoint_every=None, env_overrides={"control_period": 15}))
    result = evaluate_run(run, episodes=8)
    assert result["control_period"] == 15 and result["deployed"]["control_period"] == 1
    # the deployed column is the same policy and start states in the every-tick env
    env1 = marbler_jax.make("simple_navigation", control_period=1)
    cfg = registry.get("ippo").config(**json.loads((run / "config.json").read_text())["algorithm"])
    params = jax.tree_util.tree_map(lambda x: x[0], Run.open(run).params("best"))
    direct = summarize(greedy_episodes(env1, registry.get("ippo").greedy_policy(env1, cfg, params), 8, jax.random.PRNGKey(0)))
    assert result["deployed"]["pooled"] == direct
    table = markdown_table(result)
    assert "| metric | training loop (period 15) | robots' loop (period 1, what a bundle deploys) |" in table


def test_every_training_program_is_compiled_before_the_first_chunk(tmp_path, monkeypatch):
    """The chunk programs (also a shorter last chunk) and the greedy test compile before the loop starts,
    so the progress bar's rate, ETA and sps measure the steady state: no compilation happens between the
    "compiled in" line and the last chunk. The learning curve is drawn after the first and the last chunk
    (and between them at most every ``PLOT_EVERY_S``), the last time from every update."""
    import marbler_jax_rl.run_writer as run_writer

    drawn = []
    monkeypatch.setattr(run_writer, "PLOT_EVERY_S", 1e9)
    monkeypatch.setattr(run_writer, "plot_learning_curve",
                        lambda metrics, png, title: drawn.append(len(metrics.read_text().splitlines())))
    # 5 updates in chunks of 2: programs of 2 and 1 updates
    settings = {k: v for k, v in TWO_SEEDS.items() if k != "log"}         # compile_marks reads the log
    marks = compile_marks(train_run, out=tmp_path / "run", **dict(settings, total_steps=5 * 8 * 8, checkpoint_every=2))
    assert len(marks) == 4 and marks[0] > 0, marks      # compiled; then 3 chunks: 2, 2, 1 updates
    assert marks[-1] == marks[0], f"compilations inside the training loop: {marks}"
    assert drawn == [2, 5]
