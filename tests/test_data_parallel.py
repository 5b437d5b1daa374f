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
from marbler_jax_rl import vdn
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
    from marbler_jax_rl.driver import train
    from tests.helpers import interrupt_at

    # interrupted + resumed == uninterrupted, bit for bit, with two seeds and two devices; with persistent envs
    # the checkpoint holds the replay buffer, the envs in mid-episode and the agents' hidden states. Neither
    # the fresh nor the resumed run compiles after its "compiled in" line: the state enters the split program
    # laid out as the program returns it (whole on each device)
    root = sys.argv[1]
    hp = dict(num_envs=4, num_steps=8, buffer_size=16, batch_size=4, learning_starts=0, hidden=16, train_steps=2,
              target_update_interval=3, learner_devices=2, persistent_envs=True)
    common = dict(scenario="predator_capture_prey", algo="vdn", total_steps=4 * 4 * 8, seeds=2, hp=hp,
                  eval_episodes=0, checkpoint_every=1, progress=False, test_episodes=2)
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, seconds, **kw: compiles.append(name) if name == "/jax/core/compile/backend_compile_duration" else None)

    def counted(**kw):
        marks = []
        train(on_chunk=lambda done: marks.append(len(compiles)),
              log=lambda message: marks.append(len(compiles)) if message.startswith("compiled in") else None, **kw)
        return marks

    marks = counted(out=root + "/full", **common)
    assert len(marks) == 5 and marks[0] > 0 and marks[-1] == marks[0], f"compilations inside the loop: {marks}"
    with pytest.raises(KeyboardInterrupt):
        train(out=root + "/cut", on_chunk=interrupt_at(2), log=lambda *a: None, **common)
    marks = counted(out=root + "/cut", resume=True, **common)
    assert len(marks) == 3 and marks[-1] == marks[0], f"compilations inside the resumed loop: {marks}"
    full, cut = np.load(root + "/full/params.npz"), np.load(root + "/cut/params.npz")
    assert sorted(full) == sorted(cut) and any("gru" in name for name in full)
    for name in full:
        np.testing.assert_array_equal(full[name], cut[name], err_msg=name)
    print("ok")
""")

SEEDS_OVER_DEVICES = PRELUDE + textwrap.dedent("""
    import json

    from marbler_jax_rl.driver import train
    from tests.helpers import interrupt_at

    # seed_batching="devices": three IPPO seeds on two devices (2 + 1, the last padded) train as vmapped on one
    # device up to float rounding, greedy tests included; interrupted + resumed == uninterrupted, bit for bit,
    # and the resumed run compiles nothing after its "compiled in" line (the restored state is laid out over
    # the devices like a fresh one, so every chunk runs the program compiled up front)
    root = sys.argv[1]
    hp = dict(num_envs=8, num_steps=8, num_minibatches=2, update_epochs=1, hidden=16)
    common = dict(scenario="simple_navigation", algo="ippo", total_steps=6 * 8 * 8, seeds=3, hp=hp, eval_episodes=0,
                  checkpoint_every=2, progress=False, test_episodes=4)
    quiet = lambda *a: None
    train(out=root + "/vmap", log=quiet, **common)
    train(out=root + "/full", seed_batching="devices", log=quiet, **common)
    with pytest.raises(KeyboardInterrupt):
        train(out=root + "/cut", seed_batching="devices", on_chunk=interrupt_at(2), log=quiet, **common)
    compiles, marks = [], []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, seconds, **kw: compiles.append(name) if name == "/jax/core/compile/backend_compile_duration" else None)
    train(out=root + "/cut", seed_batching="devices", resume=True, on_chunk=lambda done: marks.append(len(compiles)),
          log=lambda message: marks.append(len(compiles)) if message.startswith("compiled in") else None, **common)
    assert len(marks) == 3 and marks[0] > 0 and marks[-1] == marks[0], f"compilations inside the loop: {marks}"
    vmap, full, cut = (np.load(f"{root}/{name}/params.npz") for name in ("vmap", "full", "cut"))
    assert sorted(full) == sorted(vmap) == sorted(cut)
    for name in full:
        assert full[name].shape[0] == 3 and not np.allclose(full[name][1], full[name][2]), name
        np.testing.assert_array_equal(full[name], cut[name], err_msg=name)
        np.testing.assert_allclose(full[name], vmap[name], rtol=2e-4, atol=1e-6, err_msg=name)
    tests = {name: [json.loads(line) for line in open(f"{root}/{name}/tests.jsonl")] for name in ("vmap", "full")}
    np.testing.assert_allclose(tests["full"][-1]["episodes"]["reward"], tests["vmap"][-1]["episodes"]["reward"],
                               rtol=1e-3, atol=1e-3)
    print("ok")
""")


def test_seeds_over_devices_match_vmapped_seeds_and_resume_bit_exactly(tmp_path):
    run_with_two_devices(SEEDS_OVER_DEVICES, str(tmp_path))


def test_seeds_over_devices_with_a_split_learner_is_refused(tmp_path):
    from marbler_jax_rl.driver import train

    with pytest.raises(ValueError, match=r"seed_batching='devices' splits the seeds .* \(learner_devices=2\)"):
        train("simple_navigation", "vdn", 64, 2, tmp_path / "run", hp=dict(learner_devices=2, batch_size=8),
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
