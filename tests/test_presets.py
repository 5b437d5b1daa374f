"""Training presets: ``paper`` holds the settings of MARBLER's EPyMARL model files (spec E.2)."""
from __future__ import annotations

import pytest

from algorithms.driver import build_config
from algorithms.presets import PRESET_NAMES, preset


def paper(algo: str):
    env, hp, steps = preset("paper", "predator_capture_prey", algo)
    return env, build_config(algo, hp), steps


def test_paper_value_based_presets_are_epymarls_model_files():
    env, vdn, steps = paper("vdn")
    assert env == {"control_period": 15} and steps == 5_000_000
    assert (vdn.hidden, vdn.lr, vdn.target_update_interval, vdn.tau) == (128, 3e-4, 200, 1.0)
    _, qmix, _ = paper("qmix")
    assert (qmix.hidden, qmix.lr, qmix.tau, qmix.mixer_embed, qmix.hypernet_hidden) == (128, 1e-4, 0.01, 32, 64)
    _, qmix_ns, _ = paper("qmix_ns")
    assert (qmix_ns.hidden, qmix_ns.lr, qmix_ns.target_update_interval, qmix_ns.shared) == (64, 5e-4, 200, False)
    for cfg in (vdn, qmix, qmix_ns):
        # EPyMARL: buffer 5000 episodes, batch 32, one gradient step per collected episode, epsilon 1 -> 0.05
        # over 50k env steps, gamma 0.99, clip 10, double Q, raw rewards, and Adam (its QLearner builds
        # torch.optim.Adam; the model files' optim_alpha/optim_eps are unused RMSprop leftovers)
        assert (cfg.buffer_size, cfg.batch_size, cfg.train_steps, cfg.num_envs) == (5000, 32, 8, 8)
        assert (cfg.eps_start, cfg.eps_finish, cfg.eps_decay_steps) == (1.0, 0.05, 50_000)
        assert (cfg.gamma, cfg.max_grad_norm, cfg.double_q, cfg.reward_norm) == (0.99, 10.0, True, "none")
        assert cfg.optimizer == "adam" and cfg.recurrent and cfg.cell == "gru" and cfg.td_lambda == 0.0
    assert vdn.agent_ids and qmix.agent_ids      # obs_agent_id: True for the shared models


def test_paper_mappo_preset_and_unknown_names():
    _, mappo, steps = paper("mappo")
    assert (mappo.hidden, mappo.lr, mappo.update_epochs, mappo.clip_eps, mappo.ent_coef) == (128, 2e-4, 4, 0.2, 0.01)
    assert steps == 25_000_000
    assert preset("none", "warehouse", "vdn") == ({}, {}, 1_000_000)
    assert set(PRESET_NAMES) == {"fast", "parallel", "paper", "none"}
    with pytest.raises(ValueError, match=r"unknown preset 'epymarl'; available: \['fast', 'parallel', 'paper', 'none'\]"):
        preset("epymarl", "warehouse", "vdn")


@pytest.mark.parametrize("algo", ["vdn", "qmix", "qmix_ns"])
def test_parallel_preset_trains_on_fresh_episodes_only(algo):
    """``parallel``: PQN-style -- the buffer holds only the update's own episodes, each used 4 times,
    TD(lambda) targets from the network that collected them (target copied once per update)."""
    env, hp, steps = preset("parallel", "predator_capture_prey", algo)
    cfg = build_config(algo, hp)
    assert env == {"control_period": 15} and steps == {"vdn": 36_000_000, "qmix_ns": 28_000_000}.get(algo, 50_000_000)
    assert cfg.buffer_size == cfg.num_envs == 256 and cfg.learning_starts == 0
    assert cfg.train_steps * cfg.batch_size == 4 * cfg.num_envs
    assert cfg.target_update_interval == cfg.train_steps and cfg.tau == 1.0
    assert cfg.td_lambda > 0 and not cfg.double_q and cfg.lr_decay and cfg.cell == "mingru"
    assert cfg.last_action == (algo != "qmix")        # VDN's and QMIX_NS's agents see their previous action
    assert preset("parallel", "simple_navigation", algo)[2] == 5_000_000
    assert preset("parallel", "predator_capture_prey", "mappo") == preset("fast", "predator_capture_prey", "mappo")


def test_parallel_preset_is_tuned_on_pcp_only():
    """QMIX_NS and VDN on PCP: GRU 32 + LayerNorm, gamma 0.95, lr 1.5e-3 (VDN: per-robot networks, 36M steps;
    QMIX_NS: 28M); elsewhere the general settings (GRU 64, gamma 0.99, lr 5e-4; VDN shares one network)."""
    tuned = dict(hidden=32, layer_norm=True, gamma=0.95, lr=1.5e-3)
    for algo, pcp_steps, other_steps in (("qmix_ns", 28_000_000, 45_000_000), ("vdn", 36_000_000, 50_000_000)):
        _, pcp, steps = preset("parallel", "predator_capture_prey", algo)
        _, warehouse, warehouse_steps = preset("parallel", "warehouse", algo)
        assert {k: pcp[k] for k in tuned} == tuned and steps == pcp_steps
        assert warehouse_steps == other_steps and warehouse["hidden"] == 64 and warehouse["lr"] == 5e-4
        assert not {"layer_norm", "gamma", "shared", "agent_ids"} & set(warehouse)   # the algorithm's defaults
        cfg = build_config(algo, pcp)
        assert cfg.hidden == 32 and cfg.layer_norm and cfg.gamma == 0.95 and cfg.lr == 1.5e-3
        assert cfg.td_lambda == 0.8 and cfg.eps_finish == 0.01 and cfg.last_action
        assert not cfg.shared and not cfg.agent_ids                   # per-robot networks on PCP
    assert build_config("vdn", preset("parallel", "warehouse", "vdn")[1]).shared   # VDN shares one network elsewhere
