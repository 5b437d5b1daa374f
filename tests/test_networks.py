"""Networks: the vmap-safe orthogonal initializer (jaxlib 0.10.2 CPU QR hang) and the Q-agents'
whole-sequence path (equal to stepping them)."""
from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl import registry
from marbler_jax_rl.driver import build_config
from marbler_jax_rl.networks import QAgent, apply_agents, init_agents, orthogonal


def _qr_operand_shapes(jaxpr, found):
    """Shapes of every ``qr`` operand in ``jaxpr`` and all its sub-jaxprs (scan, cond, custom_vmap...)."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "qr":
            found.append(tuple(eqn.invars[0].aval.shape))
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    _qr_operand_shapes(inner, found)
    return found


def test_same_values_as_flax_orthogonal_batched_or_not():
    keys = jax.random.split(jax.random.PRNGKey(0), 6).reshape(2, 3, -1)
    ref = np.stack([[np.asarray(nn.initializers.orthogonal(2.0)(k, (8, 5))) for k in row] for row in keys])
    single = orthogonal(2.0)(keys[0, 0], (8, 5))
    nested = jax.jit(jax.vmap(jax.vmap(lambda k: orthogonal(2.0)(k, (8, 5)))))(keys)
    np.testing.assert_array_equal(single, ref[0, 0])
    np.testing.assert_allclose(nested, ref, rtol=0, atol=1e-6)
    gram = np.einsum("...ij,...ik->...jk", nested, nested)
    np.testing.assert_allclose(gram, np.broadcast_to(4 * np.eye(5), gram.shape), atol=1e-5)


def test_vmapped_inits_never_hand_lapack_a_batch_of_matrices():
    """Seeds x agents vmapped inits (IPPO without sharing, QMIX_NS, VDN's GRU) only take 2-D QRs:
    batched CPU QRs can deadlock XLA's 2-thread pool."""
    env = marbler_jax.make("predator_capture_prey")
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    for algo, hp in [("ippo", dict(shared=False)), ("qmix_ns", {}), ("vdn", {})]:
        trainer = registry.get(algo).make_train(env, build_config(algo, dict(hp, total_timesteps=10**5)))
        shapes = _qr_operand_shapes(jax.make_jaxpr(jax.vmap(trainer.init))(keys).jaxpr, [])
        assert shapes, f"{algo}: no QR found -- is the orthogonal initializer still used?"
        assert all(len(s) == 2 for s in shapes), f"{algo}: batched QR operands {sorted(set(shapes))}"
    unsafe = jax.make_jaxpr(jax.vmap(lambda k: nn.initializers.orthogonal()(k, (4, 4))))(keys).jaxpr
    assert _qr_operand_shapes(unsafe, []) == [(3, 4, 4)]   # the walker does see batched QRs


@pytest.mark.parametrize("cell", ["mingru", "none"])
@pytest.mark.parametrize("shared,layer_norm", [(True, False), (False, False), (True, True)])
def test_q_agent_sequence_equals_stepping_with_resets(cell, shared, layer_norm):
    """``QAgent.sequence`` (one matmul per layer for all steps + an elementwise scan) gives the
    Q-values of stepping ``__call__`` one step at a time, memory zeroed where ``reset``."""
    agent = QAgent(num_actions=5, hidden=16, cell=cell, layer_norm=layer_norm)
    n, d, steps, batch = 3, 7, 12, 4
    sample = (agent.initial_hidden((1,))[0], jnp.zeros((d,)), jnp.zeros((1,), bool))
    params = init_agents(agent, jax.random.PRNGKey(0), sample, n, shared)
    obs = jax.random.normal(jax.random.PRNGKey(1), (steps, batch, n, d))
    reset = jax.random.uniform(jax.random.PRNGKey(2), (steps, batch, n, 1)) < 0.2
    whole = apply_agents(agent, params, obs, reset, shared=shared, method=QAgent.sequence)
    hidden, stepped = agent.initial_hidden((batch, n)), []
    for t in range(steps):
        hidden, q = apply_agents(agent, params, hidden, obs[t], reset[t], shared=shared)
        stepped.append(q)
    np.testing.assert_allclose(whole, np.stack(stepped), rtol=1e-5, atol=1e-5)
    if cell == "mingru":     # the memory matters: without the resets the values differ
        no_reset = apply_agents(agent, params, obs, jnp.zeros_like(reset), shared=shared, method=QAgent.sequence)
        assert np.abs(np.asarray(no_reset) - np.asarray(whole)).max() > 1e-3


def test_unknown_q_agent_cell_is_reported():
    with pytest.raises(ValueError, match=r"cell must be one of \['gru', 'mingru', 'none'\], got 'lstm'"):
        QAgent(num_actions=5, cell="lstm").init(jax.random.PRNGKey(0), jnp.zeros((4,)), jnp.zeros((3,)),
                                                 jnp.zeros((1,), bool))
    with pytest.raises(ValueError, match="QAgent.sequence is for cell='mingru' or 'none'"):
        QAgent(num_actions=5).init(jax.random.PRNGKey(0), jnp.zeros((2, 3)), jnp.zeros((2, 1), bool),
                                   method=QAgent.sequence)
