"""Agent networks shared by the algorithms (flax.linen).

* :class:`MLP` -- a plain ReLU/tanh MLP.
* :class:`ActorCritic` -- separate policy and value MLPs (IPPO: the critic sees the agent's own
  observation; MAPPO: the global state); :class:`RecurrentActorCritic` -- the same with a recurrent actor.
* :class:`QAgent` -- the Q-network of the value-based learners (VDN, QMIX): EPyMARL's RNN agent
  (``fc -> ReLU -> GRU cell -> fc``) or a feed-forward variant, stepped one env step at a time with
  an explicit hidden state (reset to zeros at episode starts).

Per-agent parameters (no sharing) are obtained by ``jax.vmap``-ing ``init``/``apply`` over agents
(:func:`init_agents`, :func:`apply_agents`); with sharing one parameter set serves every agent and
an agent-ID one-hot (:func:`with_agent_ids`) tells the agents apart.
"""
from __future__ import annotations

import functools
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from marbler_jax.numpy_policy import CELLS


# PyTorch's ``nn.Linear`` default kernel init, U(-1/sqrt(fan_in), 1/sqrt(fan_in)): a third of flax's
# default (lecun_normal) variance. EPyMARL's QMIX mixer is initialised this way (see marbler_jax_rl.qmix).
TORCH_LINEAR_INIT = nn.initializers.variance_scaling(1 / 3, "fan_in", "uniform")


def orthogonal(scale: float = 1.0):
    """flax's orthogonal initializer, made safe to ``vmap`` on the CPU (same values).

    Orthogonal draws take a QR decomposition. With jaxlib 0.10.2 the CPU QR (LAPACK ``geqrf`` FFI)
    splits a *batch* of matrices -- what ``vmap`` over seeds or agents makes of it -- over XLA's
    intra-op thread pool and waits for the parts on a pool thread; two such calls at once fill a
    2-thread pool with waiters and the program hangs forever. A custom vmap rule therefore draws a batch
    one matrix after another (``lax.map``), so no batched QR ever reaches LAPACK.
    """
    base = nn.initializers.orthogonal(scale)

    def init(key, shape, dtype=jnp.float32):
        @jax.custom_batching.custom_vmap
        def draw(k):
            return base(k, shape, dtype)

        @draw.def_vmap
        def _one_at_a_time(axis_size, in_batched, k):
            return jax.lax.map(draw, k), True

        return draw(key)

    return init


class MLP(nn.Module):
    """``features[-1]`` outputs after hidden layers ``features[:-1]`` (orthogonal init)."""

    features: Sequence[int]
    activation: str = "tanh"
    final_scale: float = 1.0

    @nn.compact
    def __call__(self, x):
        act = {"tanh": nn.tanh, "relu": nn.relu}[self.activation]
        for width in self.features[:-1]:
            x = act(nn.Dense(width, kernel_init=orthogonal(np.sqrt(2)))(x))
        return nn.Dense(self.features[-1], kernel_init=orthogonal(self.final_scale))(x)


class ActorCritic(nn.Module):
    """Policy logits ``[..., num_actions]`` and state value ``[...]`` from one observation."""

    num_actions: int
    hidden: int = 128
    layers: int = 2
    activation: str = "tanh"

    @nn.compact
    def __call__(self, obs, critic_obs=None):
        """``critic_obs`` (default ``obs``) is the critic's input: MAPPO passes the global state."""
        widths = [self.hidden] * self.layers
        logits = MLP(widths + [self.num_actions], self.activation, final_scale=0.01, name="actor")(obs)
        critic_in = obs if critic_obs is None else critic_obs
        value = MLP(widths + [1], self.activation, final_scale=1.0, name="critic")(critic_in)[..., 0]
        return logits, value


class RecurrentActorCritic(nn.Module):
    """A recurrent policy beside a feed-forward critic: the actor is :class:`QAgent`'s network (``Dense(H) ->
    ReLU -> cell -> Dense(A)``, EPyMARL's ``RNNAgent``, the form of MARBLER's MAPPO actors) giving logits, the
    critic :class:`ActorCritic`'s MLP.

    ``act(hidden [..., H], obs [..., D], reset [..., 1]) -> (hidden, logits [..., A])`` steps the actor
    (``reset`` zeroes the incoming hidden state); ``value(critic_obs [..., F]) -> [...]``.
    """

    num_actions: int
    hidden: int = 128
    layers: int = 2
    activation: str = "tanh"
    cell: str = "gru"

    def setup(self):
        self.actor = QAgent(self.num_actions, self.hidden, cell=self.cell)
        self.critic = MLP([self.hidden] * self.layers + [1], self.activation, final_scale=1.0)

    def __call__(self, hidden, obs, reset, critic_obs):
        hidden, logits = self.act(hidden, obs, reset)
        return hidden, logits, self.value(critic_obs)

    def act(self, hidden, obs, reset):
        return self.actor(hidden, obs, reset)

    def value(self, critic_obs):
        return self.critic(critic_obs)[..., 0]


class QAgent(nn.Module):
    """Per-agent Q-values ``[..., num_actions]`` from one observation ``[..., D]``.

    ``__call__(hidden [..., H], obs [..., D], reset [..., 1] bool) -> (hidden, q)``: ``reset`` zeroes
    the incoming hidden state (episode start). ``cell`` picks the memory between ``fc1`` and ``fc2``:

    * ``"gru"`` -- EPyMARL's ``RNNAgent`` (``Dense(H) -> ReLU -> GRUCell(H) -> Dense(A)``, flax's GRU
      gate layout);
    * ``"mingru"`` -- a minimal GRU (Feng et al. 2024, "Were RNNs all we needed?"): the update gate
      and the candidate depend on the input only, ``z = sigmoid(x W_z + b_z)``, ``c = x W_c + b_c``,
      ``h = (1 - z) * h_prev + z * c``, then ``Dense(H) -> ReLU -> Dense(A)`` on ``h``. The
      recurrence is linear in ``h``, so a whole sequence costs one batched matmul per layer plus an
      elementwise scan (:meth:`sequence`), not a matmul per time step;
    * ``"none"`` -- feed-forward: ``Dense(H) -> ReLU`` instead of the cell; ``hidden`` passes
      through unchanged.

    ``layer_norm=True`` puts a ``LayerNorm`` (learned scale and bias, epsilon 1e-6) between every
    hidden ``Dense`` and its ReLU (``fc1``, and ``fc_out`` / ``fc_hidden``), as PQN (Gallici et al.
    2024) does to keep Q-learning without a replay buffer stable. ``recurrent=False`` is the older
    spelling of ``cell="none"``.
    """

    num_actions: int
    hidden: int = 128
    recurrent: bool = True
    cell: str = "gru"
    layer_norm: bool = False

    def setup(self):
        if self.memory not in CELLS:
            raise ValueError(f"cell must be one of {list(CELLS)}, got {self.cell!r}")
        self.fc1 = nn.Dense(self.hidden)
        if self.layer_norm:
            self.ln1 = nn.LayerNorm()
            if self.memory != "gru":
                self.ln_out = nn.LayerNorm()
        if self.memory == "gru":
            self.gru = nn.GRUCell(self.hidden, recurrent_kernel_init=orthogonal())
        elif self.memory == "mingru":
            self.mingru = nn.Dense(2 * self.hidden)
            self.fc_out = nn.Dense(self.hidden)
        else:
            self.fc_hidden = nn.Dense(self.hidden)
        self.fc2 = nn.Dense(self.num_actions)

    @property
    def memory(self) -> str:
        return self.cell if self.recurrent else "none"

    def _mingru_gates(self, x):
        gates = self.mingru(x)
        z = nn.sigmoid(gates[..., :self.hidden])
        return 1.0 - z, z * gates[..., self.hidden:]

    def _norm(self, name, x):
        return getattr(self, name)(x) if self.layer_norm else x

    def _input_layer(self, obs):
        return nn.relu(self._norm("ln1", self.fc1(obs)))

    def _mingru_head(self, hidden):
        return self.fc2(nn.relu(self._norm("ln_out", self.fc_out(hidden))))

    def _feed_forward_head(self, x):
        return self.fc2(nn.relu(self._norm("ln_out", self.fc_hidden(x))))

    def __call__(self, hidden, obs, reset):
        x = self._input_layer(obs)
        if self.memory == "gru":
            hidden = jnp.where(reset, 0.0, hidden)
            hidden, x = self.gru(hidden, x)
            return hidden, self.fc2(x)
        if self.memory == "mingru":
            keep, write = self._mingru_gates(x)
            hidden = keep * jnp.where(reset, 0.0, hidden) + write
            return hidden, self._mingru_head(hidden)
        return hidden, self._feed_forward_head(x)

    def sequence(self, obs, reset, hidden=None):
        """Q-values ``[T, ..., A]`` along sequences ``obs [T, ..., D]`` from the hidden state ``hidden
        [..., H]`` (default zero; ``reset [T, ..., 1]`` zeroes it before a step). Equal to stepping
        :meth:`__call__`; for ``"mingru"`` and ``"none"``, whose whole sequence needs no per-step
        matmul (a GRU is stepped by the caller's own scan)."""
        if self.memory == "gru":
            raise ValueError("QAgent.sequence is for cell='mingru' or 'none'; step a GRU with __call__")
        x = self._input_layer(obs)
        if self.memory == "none":
            return self._feed_forward_head(x)
        keep, write = self._mingru_gates(x)
        keep = jnp.where(reset, 0.0, keep)

        def step(hidden, inputs):
            hidden = inputs[0] * hidden + inputs[1]
            return hidden, hidden

        start = jnp.zeros(keep.shape[1:], keep.dtype) if hidden is None else hidden
        hidden = jax.lax.scan(step, start, (keep, write))[1]
        return self._mingru_head(hidden)

    def initial_hidden(self, batch_shape=()):
        """Zero hidden state ``[*batch_shape, H]`` (``[*batch_shape, 1]`` for feed-forward agents)."""
        width = 1 if self.memory == "none" else self.hidden
        return jnp.zeros(tuple(batch_shape) + (width,), jnp.float32)


def with_agent_ids(obs):
    """Append a one-hot agent ID: ``[..., N, D] -> [..., N, D + N]``."""
    n = obs.shape[-2]
    ids = jnp.broadcast_to(jnp.eye(n, dtype=obs.dtype), obs.shape[:-2] + (n, n))
    return jnp.concatenate([obs, ids], axis=-1)


def init_agents(module: nn.Module, key, sample_inputs, num_agents: int, shared: bool):
    """Parameters for ``num_agents`` agents: one set if ``shared`` else a stack (leading axis N).

    ``sample_inputs`` is one agent's input (a tuple of arrays for multi-input modules).
    """
    sample = sample_inputs if isinstance(sample_inputs, tuple) else (sample_inputs,)
    if shared:
        return module.init(key, *sample)
    return jax.vmap(lambda k: module.init(k, *sample))(jax.random.split(key, num_agents))


def apply_agents(module: nn.Module, params, *inputs, shared: bool, method=None):
    """Apply to inputs ``[..., N, F]`` (agent axis second to last): the same parameters for all
    agents, or agent i's to agent i. Outputs keep the agent axis in the same place. ``method``
    (default ``__call__``) is the module's method to apply."""
    apply = functools.partial(module.apply, method=method)
    if shared:
        return apply(params, *inputs)
    agent_axis = inputs[0].ndim - 2
    return jax.vmap(apply, in_axes=(0,) + tuple(x.ndim - 2 for x in inputs),
                    out_axes=agent_axis)(params, *inputs)
