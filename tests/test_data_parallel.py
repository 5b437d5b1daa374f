"""Data-parallel value-based learning (``learner_devices``): the same gradient steps as one device
(targets once per update with the buffer's rows split over the devices, and targets per batch), and an
interrupted VDN run (GRU agents, two seeds, its replay buffer, envs and hidden states in the checkpoint)
resumes bit-exactly. JAX picks its CPU device count when it first runs, so
the two-device checks run in a fresh interpreter."""
from __future__ import annotations

import textwrap

import jax
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl import ippo, vdn
from tests.helpers import run_with_two_devices

PRELUDE = """
import sys
from marbler_jax_rl.data_parallel import use_cpu_devices
use_cpu_devices(2)
import jax, numpy as np, pytest
import marbler_jax
assert len(jax.devices()) == 2
"""

MATCH_ONE_DEVICE = PRELUDE + textwrap.dedent("""
    from marbler_jax_rl import qmix

    # 1 vs 2 devices: the same updates up to float rounding. "per_update" (the recipes' path): QMIX, whose
    # mixer's gradients are split too, with targets once per update (minimal GRU) and the buffer's rows
    # split over the devices; "per_batch": QMIX_NS (a network per robot) with targets per sampled batch
    env = marbler_jax.make("predator_capture_prey", control_period=15)
    hp = dict(total_timesteps=3 * 4 * 8, num_envs=4, num_steps=8, buffer_size=16, batch_size=4, learning_starts=0,
              hidden=16, train_steps=3, target_update_interval=2, mixer_embed=8, hypernet_hidden=8)
    per_update = dict(hp, buffer_size=12, target_update_interval=3, double_q=False, td_lambda=0.65, cell="mingru")
    cases = {"per_update": (qmix.QMIXConfig, per_update, True), "per_batch": (qmix.QMIXNSConfig, hp, False)}
    for config, hp, targets_per_update in [cases[name] for name in sys.argv[1:]]:
        assert config(**hp).targets_per_update == targets_per_update
        out = {}
        for devices in (1, 2):
            trainer = qmix.make_train(env, config(learner_devices=devices, **hp))
            out[devices] = jax.jit(trainer)(jax.random.PRNGKey(0))
        losses = [np.asarray(out[d][1]["loss"]) for d in (1, 2)]
        assert np.all(np.isfinite(losses[0])), losses
        np.testing.assert_allclose(losses[0], losses[1], rtol=1e-4)
        jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), out[1][0], out[2][0])
    print("ok")
""")

RESUME = PRELUDE + textwrap.dedent("""
    from marbler_jax_rl.driver import train_run
    from tests.helpers import compile_marks, interrupt_at

    # interrupted + resumed == uninterrupted, bit for bit, with two seeds and two devices; with persistent envs
    # the checkpoint holds the replay buffer, the envs in mid-episode and the agents' hidden states. Neither
    # the fresh nor the resumed run compiles after its "compiled in" line: the state enters the split program
    # laid out as the program returns it (whole on each device)
    root = sys.argv[1]
    hp = dict(num_envs=4, num_steps=8, buffer_size=16, batch_size=4, learning_starts=0, hidden=16, train_steps=2,
              target_update_interval=3, learner_devices=2, persistent_envs=True)
    common = dict(scenario="predator_capture_prey", algo="vdn", total_steps=4 * 4 * 8, seeds=2, hp=hp,
                  eval_episodes=0, checkpoint_every=1, progress=False, test_episodes=2)
    marks = compile_marks(train_run, out=root + "/full", **common)
    assert len(marks) == 5 and marks[0] > 0 and marks[-1] == marks[0], f"compilations inside the loop: {marks}"
    with pytest.raises(KeyboardInterrupt):
        train_run(out=root + "/cut", on_chunk=interrupt_at(2), log=lambda *a: None, **common)
    marks = compile_marks(train_run, out=root + "/cut", resume=True, **common)
    assert len(marks) == 3 and marks[-1] == marks[0], f"compilations inside the resumed loop: {marks}"
    full, cut = np.load(root + "/full/params.npz"), np.load(root + "/cut/params.npz")
    assert sorted(full) == sorted(cut) and any("gru" in name for name in full)
    for name in full:
        np.testing.assert_array_equal(full[name], cut[name], err_msg=name)
    print("ok")
""")

SEEDS_OVER_DEVICES = PRELUDE + textwrap.dedent("""
    import json

    from marbler_jax_rl.driver import train_run
    from tests.helpers import compile_marks, interrupt_at

    # Three IPPO seeds on two devices train as vmapped on one device up to float rounding, greedy tests
    # included, either way of splitting them: seed_batching="devices" (2 + 1 seeds, the last padded) or
    # learner_devices=2 (each seed's envs and minibatches split), whichever argv[2] names. Neither compiles after
    # its "compiled in" line, and each resumes bit for bit: interrupted + resumed == uninterrupted, the resumed
    # run compiling nothing more either (the state enters every chunk laid out over the devices as the chunk
    # returns it)
    root, splits = sys.argv[1], sys.argv[2].split(",")
    hp = dict(num_envs=8, num_steps=8, num_minibatches=2, update_epochs=1, hidden=16)
    common = dict(scenario="simple_navigation", algo="ippo", total_steps=6 * 8 * 8, seeds=3, eval_episodes=0,
                  checkpoint_every=2, progress=False, test_episodes=4)
    quiet = lambda *a: None

    def chunks(**kw):
        marks = compile_marks(train_run, **kw)
        assert marks[0] > 0 and marks[-1] == marks[0], f"compilations inside the loop: {marks}"
        return len(marks) - 1

    train_run(out=root + "/vmap", hp=hp, log=quiet, **common)
    vmap = np.load(f"{root}/vmap/params.npz")
    vmap_tests = [json.loads(line) for line in open(f"{root}/vmap/tests.jsonl")]
    every = {"seeds": dict(seed_batching="devices", hp=hp), "envs": dict(hp=dict(hp, learner_devices=2))}
    for name in splits:
        split = every[name]
        assert chunks(out=f"{root}/{name}", **split, **common) == 3
        full = np.load(f"{root}/{name}/params.npz")
        with pytest.raises(KeyboardInterrupt):
            train_run(out=f"{root}/{name}-cut", on_chunk=interrupt_at(2), log=quiet, **split, **common)
        assert chunks(out=f"{root}/{name}-cut", resume=True, **split, **common) == 2
        cut = np.load(f"{root}/{name}-cut/params.npz")
        assert sorted(cut) == sorted(full)
        for key in full:
            np.testing.assert_array_equal(full[key], cut[key], err_msg=f"{name}: {key}")
        assert sorted(full) == sorted(vmap)
        for key in full:
            assert full[key].shape[0] == 3 and not np.allclose(full[key][1], full[key][2]), (name, key)
            np.testing.assert_allclose(full[key], vmap[key], rtol=2e-4, atol=1e-6, err_msg=f"{name}: {key}")
        tests = [json.loads(line) for line in open(f"{root}/{name}/tests.jsonl")]
        np.testing.assert_allclose(tests[-1]["episodes"]["reward"], vmap_tests[-1]["episodes"]["reward"],
                                   rtol=1e-3, atol=1e-3)
    print("ok")
""")


def test_envs_over_devices_match_one_device_and_resume_bit_exactly(tmp_path):
    run_with_two_devices(SEEDS_OVER_DEVICES, str(tmp_path), "envs")        # the split the benchmark's PPO cells use


@pytest.mark.slow     # seed_batching="devices", an option no recipe uses
def test_seeds_over_devices_match_one_device_and_resume_bit_exactly(tmp_path):
    run_with_two_devices(SEEDS_OVER_DEVICES, str(tmp_path), "seeds")


def test_seeds_over_devices_with_a_split_learner_is_refused(tmp_path):
    from marbler_jax_rl.driver import train_run

    with pytest.raises(ValueError, match=r"seed_batching='devices' splits the seeds .* \(learner_devices=2\)"):
        train_run("simple_navigation", "vdn", 64, 2, tmp_path / "run", hp=dict(learner_devices=2, batch_size=8),
              seed_batching="devices", progress=False)
    assert not (tmp_path / "run").exists()


def test_two_devices_match_one():
    run_with_two_devices(MATCH_ONE_DEVICE, "per_update")


@pytest.mark.slow     # the recipes compute targets once per update, the case above
def test_two_devices_match_one_with_targets_per_batch():
    run_with_two_devices(MATCH_ONE_DEVICE, "per_batch")


# the benchmark's value-based cells resume this way: the restored state must enter programs split over devices
def test_two_devices_resume_bit_exactly(tmp_path):
    run_with_two_devices(RESUME, str(tmp_path))
    # this process has one device: the two-device run's checkpoints still restore (no device layout saved)
    import orbax.checkpoint as ocp

    from marbler_jax_rl.run import load_run

    restored = ocp.CheckpointManager(tmp_path / "full" / "checkpoints").restore(4)
    kernel = np.load(tmp_path / "full" / "params.npz")["agent/params/fc1/kernel"]
    np.testing.assert_array_equal(restored["params"]["agent"]["params"]["fc1"]["kernel"], kernel)
    env, policy = load_run(tmp_path / "full", checkpoint="final")    # the parameters compared above
    actions, _ = policy.step(None, np.zeros((env.num_agents, env.obs_dim), np.float32),
                             policy.initial_carry(()), np.bool_(True))
    assert env.name == "predator_capture_prey" and actions.shape == (env.num_agents,)


def test_more_learner_devices_than_jax_has_is_a_clear_error():
    env = marbler_jax.make("simple_navigation")
    too_many = len(jax.devices()) + 1
    with pytest.raises(ValueError, match=rf"learner_devices={too_many} needs {too_many} devices but JAX has"):
        vdn.make_train(env, vdn.VDNConfig(learner_devices=too_many, batch_size=too_many * 4))
    with pytest.raises(ValueError, match=r"batch_size \(32\) must be divisible by learner_devices \(3\)"):
        vdn.VDNConfig(batch_size=32, learner_devices=3).validate()
    with pytest.raises(ValueError, match=rf"learner_devices={too_many} needs {too_many} devices but JAX has"):
        ippo.make_train(env, ippo.IPPOConfig(num_envs=too_many * 4, num_minibatches=1, learner_devices=too_many))
    with pytest.raises(ValueError, match="num_envs = 64 must be divisible by learner_devices = 3"):
        ippo.IPPOConfig(learner_devices=3).validate()
    with pytest.raises(ValueError, match=r"the minibatch \(num_envs \* num_steps / num_minibatches\) = 6 must be "
                                         r"divisible by learner_devices = 4"):
        ippo.IPPOConfig(num_envs=4, num_steps=3, num_minibatches=2, learner_devices=4).validate()
