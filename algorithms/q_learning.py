"""Value-decomposed deep Q-learning over episodes: the loop shared by VDN and QMIX.

VDN (:mod:`marbler_jax_rl.vdn`) and QMIX (:mod:`marbler_jax_rl.qmix`) differ only in the *mixer* that turns
the agents' chosen Q-values ``[..., N]`` and the global state into the team value ``Q_tot``; this
module is everything else, as in EPyMARL:

* **Acting.** Each update resets ``num_envs`` envs and runs them for ``num_steps`` steps (default:
  the episode length, so every sequence starts at an episode start; envs auto-reset, and an episode
  that ends early is followed by the next one in the same sequence). With ``persistent_envs`` the
  envs are not reset between updates (PQN's way): each update's sequences continue where the last
  update's stopped, so every phase of an episode is collected as often as it occurs (a fresh reset per
  update collects the first steps of a second, truncated episode after every early end, and all
  envs start in step), and each sequence stores the agents' hidden state at its first step, as the
  collecting network had it (R2D2's stored state). Agents act epsilon-greedily on
  :class:`~marbler_jax_rl.networks.QAgent` Q-values (GRU, minimal GRU or feed-forward; one parameter set
  + agent-ID one-hot, or per-agent parameters). With ``last_action`` every agent also sees the
  one-hot of its own previous action (EPyMARL's ``obs_last_action``; zeros at an episode's first
  step), appended after the observation and before the agent ID. Epsilon falls linearly from ``eps_start`` to ``eps_finish``
  over ``eps_decay_steps`` env steps; with ``eps_spread = a > 0`` env ``i`` of ``n`` explores with
  ``epsilon ** (1 + a * i / (n - 1))`` instead (Ape-X's spread of exploration rates: env 0 at the
  schedule, the others ever closer to greedy).
* **Replay.** The sequences go into an :mod:`marbler_jax_rl.buffer` episode buffer of ``buffer_size``
  sequences.
* **Learning.** ``train_steps`` gradient steps per update, each on ``batch_size`` sampled
  sequences: the recurrent agents are unrolled from the sequence's stored hidden state (zero at an
  episode start; reset again after every ``done``), ``Q_tot`` of the taken actions is regressed on
  ``r + gamma * (1 - done) * Q_tot_target(next)`` (or its TD(lambda) return along the sequence,
  ``td_lambda > 0``, as pymarl2 does) with double-Q action selection (``double_q``),
  the team reward (the scenario's reported reward) and the target networks' mixer. Target networks
  are copied every ``target_update_interval`` gradient steps (``tau = 1``) or Polyak-averaged with
  ``tau`` after every step. Learning starts once the buffer holds ``learning_starts`` env steps.
  ``learner_devices > 1`` splits each gradient step's batch over that many devices
  (:mod:`marbler_jax_rl.data_parallel`).
* **Targets once per update** (``cache_targets``, on by default). When the target network cannot change
  within an update (hard copies at update boundaries: ``tau = 1`` and ``target_update_interval`` a
  multiple of ``train_steps``), the targets do not need the online network (``double_q`` off), and
  the buffer holds no more sequences than the update's gradient steps sample (``buffer_size <=
  train_steps * batch_size``), the targets of every buffered sequence are computed once at the start of
  the update and each gradient step runs the online network only. The result is the same as computing
  them per batch (up to float rounding), and each target is computed once instead of once per sampling.

Choices (documented where EPyMARL differs): the end of an episode by MARBLER's step limit is
treated as terminal (the observations carry no time, and MARBLER returns ``done`` there);
``target_update_interval`` counts gradient steps (EPyMARL counts episodes, one gradient step per
episode, so the numbers agree at EPyMARL's settings); env steps are counted for every simulated
step.

``make_train(env, cfg, mixer) -> train``: ``train(key) -> (params, metrics)``, with
``train.init`` / ``train.run`` for chunked runs (same contract as :mod:`marbler_jax_rl.ippo`).
"""
from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import buffer as episode_buffer
from .algorithm import trainer
from .common import episode_info, float32_tensors, rollout_metrics
from .data_parallel import split_batch, split_rows, whole_on
from .common import global_state
from .networks import QAgent, apply_agents, init_agents, with_agent_ids
from marbler_jax.numpy_policy import CELLS
from marbler_jax.rollout import StatefulPolicy


@dataclasses.dataclass(frozen=True)
class QConfig:
    """Settings shared by VDN and QMIX (the benchmark's settings: ``marbler_jax_rl.recipes``).

    Attributes:
        total_timesteps: env steps per seed (one env step moves every robot).
        num_envs: sequences collected per update (one per parallel env).
        num_steps: sequence length; 0 = the env's episode length.
        buffer_size: sequences the replay buffer holds.
        batch_size: sequences per gradient step.
        train_steps: gradient steps per update.
        learning_starts: env steps collected before the first gradient step.
        lr: learning rate.
        lr_decay: decay the learning rate linearly to 0 over the run.
        optimizer: "adam", "radam" or "rmsprop".
        max_grad_norm: global gradient-norm clip.
        gamma: discount factor.
        eps_start: exploration epsilon at the start.
        eps_finish: exploration epsilon after ``eps_decay_steps``.
        eps_decay_steps: env steps of the linear epsilon decay.
        eps_spread: > 0 gives env ``i`` the epsilon ``eps ** (1 + eps_spread * i / (num_envs - 1))``; 0: one
            epsilon for all envs.
        persistent_envs: envs continue across updates (sequences may start mid-episode); else every update
            collects fresh episodes.
        target_update_interval: gradient steps between hard copies to the target network (``tau = 1``).
        tau: < 1: Polyak averaging of the target network after every gradient step instead.
        double_q: the online network picks the target's next action (double Q-learning).
        td_lambda: > 0: TD(lambda) targets along each sequence; 0: one-step targets.
        reward_norm: "none", "scale" (r / running std) or "standardise" ((r - mean) / std, EPyMARL's).
        hidden: units of the agent network's hidden layers (and recurrent cell).
        recurrent: False: feed-forward agents (the same as ``cell="none"``).
        cell: recurrent cell of the agents, "gru", "mingru" or "none" (:class:`marbler_jax_rl.networks.QAgent`).
        layer_norm: LayerNorm before the agents' hidden ReLUs (PQN's stabiliser).
        shared: one agent network for every robot (else one per robot).
        agent_ids: append a one-hot robot ID to each robot's input.
        last_action: append the one-hot of each robot's previous action to its input.
        learner_devices: > 1: each gradient step's batch is split over this many devices.
        cache_targets: compute the TD targets once per update where that is exact and no dearer
            (:attr:`targets_per_update`).
    """

    total_timesteps: int = 1_000_000
    num_envs: int = 16
    num_steps: int = 0
    buffer_size: int = 5000
    batch_size: int = 32
    train_steps: int = 1
    learning_starts: int = 10_000
    lr: float = 3e-4
    lr_decay: bool = False
    optimizer: str = "adam"
    max_grad_norm: float = 10.0
    gamma: float = 0.99
    eps_start: float = 1.0
    eps_finish: float = 0.05
    eps_decay_steps: int = 50_000
    eps_spread: float = 0.0
    persistent_envs: bool = False
    target_update_interval: int = 200
    tau: float = 1.0
    double_q: bool = True
    td_lambda: float = 0.0
    reward_norm: str = "none"
    hidden: int = 128
    recurrent: bool = True
    cell: str = "gru"
    layer_norm: bool = False
    shared: bool = True
    agent_ids: bool = True
    last_action: bool = False
    learner_devices: int = 1
    cache_targets: bool = True

    @property
    def targets_per_update(self) -> bool:
        """Whether the learner computes the TD targets once per update (``cache_targets`` and it is exact
        and no dearer than per batch: fixed target network within an update, no double-Q, and no more
        buffered sequences than the update's gradient steps sample)."""
        return (self.cache_targets and self.tau == 1.0 and not self.double_q
                and self.target_update_interval % self.train_steps == 0
                and self.buffer_size <= self.train_steps * self.batch_size)

    def validate(self) -> None:
        for name in ("total_timesteps", "num_envs", "buffer_size", "batch_size", "train_steps", "hidden",
                     "eps_decay_steps", "target_update_interval", "learner_devices"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.learning_starts < 2**31:
            raise ValueError(f"learning_starts must be in [0, 2**31) env steps, got {self.learning_starts}")
        if self.num_steps < 0:
            raise ValueError(f"num_steps must be >= 0 (0 = episode length), got {self.num_steps}")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {sorted(OPTIMIZERS)}, got {self.optimizer!r}")
        if not 0.0 <= self.eps_spread <= 16.0:
            raise ValueError(f"eps_spread must be in [0, 16] (0 = one epsilon for all envs), got {self.eps_spread}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        for name in ("eps_start", "eps_finish"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not self.max_grad_norm > 0:
            raise ValueError(f"max_grad_norm must be > 0, got {self.max_grad_norm}")
        if not 0.0 <= self.td_lambda <= 1.0:
            raise ValueError(f"td_lambda must be in [0, 1], got {self.td_lambda}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {self.tau}")
        if self.cell not in CELLS:
            raise ValueError(f"cell must be one of {list(CELLS)}, got {self.cell!r}")
        if self.reward_norm not in REWARD_NORMS:
            raise ValueError(f"reward_norm must be one of {list(REWARD_NORMS)}, got {self.reward_norm!r}")
        if self.batch_size % self.learner_devices:
            raise ValueError(f"batch_size ({self.batch_size}) must be divisible by learner_devices ({self.learner_devices})")
        if self.last_action and self.persistent_envs:
            raise ValueError("last_action is not supported with persistent_envs (sequences would have to store "
                             "each agent's action before their first step); turn one of them off")
        if self.num_envs > self.buffer_size:
            raise ValueError(f"num_envs ({self.num_envs}) must not exceed buffer_size ({self.buffer_size})")


REWARD_NORMS = ("none", "scale", "standardise")


def update_moments(moments, x):
    """Running ``(count, mean, M2)`` of every reward seen so far, updated with the batch ``x``
    (Chan et al.'s parallel combination, so the order of batches does not matter)."""
    count, mean, m2 = moments
    n = jnp.float32(x.size)
    batch_mean = jnp.mean(x)
    delta = batch_mean - mean
    total = count + n
    mean = mean + delta * n / total
    m2 = m2 + jnp.sum((x - batch_mean) ** 2) + delta ** 2 * count * n / total
    return total, mean, m2


def normalise_rewards(cfg: QConfig, moments, reward):
    """Rewards as the learner sees them under ``cfg.reward_norm``. ``"scale"`` divides by the running
    standard deviation (the optimal policy is unchanged); ``"standardise"`` also subtracts the running
    mean, as EPyMARL's ``standardise_rewards`` does (which, with early termination, changes what the
    optimal policy is: a negative shifted reward makes ending an episode early attractive)."""
    if cfg.reward_norm == "none":
        return reward
    count, mean, m2 = moments
    std = jnp.sqrt(jnp.maximum(m2 / jnp.maximum(count, 1.0), 1e-8))
    if cfg.reward_norm == "standardise":
        reward = reward - mean
    return reward / std


OPTIMIZERS = {"adam": optax.adam, "radam": optax.radam,
              "rmsprop": lambda lr: optax.rmsprop(lr, decay=0.99, eps=1e-5)}


def lambda_returns(reward, done, next_value, gamma: float, lam: float):
    """TD(lambda) targets ``[T, ...]`` along time-major sequences: ``G_t = r_t + gamma (1 - done_t)
    ((1 - lam) V_{t+1} + lam G_{t+1})`` with ``V_{t+1} = next_value[t]`` and the last step
    bootstrapped on ``next_value[-1]``. ``lam = 0`` is the one-step target; a ``done`` cuts both terms,
    so a sequence that holds several episodes never bootstraps across an episode boundary."""
    live = gamma * (1.0 - done.astype(jnp.float32))
    if lam == 0.0:
        return reward + live * next_value

    def back(g_next, inputs):
        r, live_t, v_next = inputs
        g = r + live_t * ((1.0 - lam) * v_next + lam * g_next)
        return g, g

    return jax.lax.scan(back, next_value[-1], (reward, live, next_value), reverse=True)[1]


def env_epsilons(eps, num_envs: int, spread: float):
    """Exploration rate of each of ``num_envs`` envs ``[num_envs]`` from the schedule's ``eps``:
    ``eps ** (1 + spread * i / (num_envs - 1))`` (all ``eps`` for ``spread = 0``)."""
    eps = jnp.asarray(eps, jnp.float32)
    if spread == 0.0:
        return jnp.broadcast_to(eps, (num_envs,))
    position = jnp.arange(num_envs, dtype=jnp.float32) / max(num_envs - 1, 1)
    return jnp.power(eps, 1.0 + spread * position)


def sequence_length(env, cfg: QConfig) -> int:
    return cfg.num_steps or env.max_steps


def agent_module(env, cfg: QConfig) -> QAgent:
    return QAgent(env.num_actions, cfg.hidden, cfg.recurrent, cfg.cell, cfg.layer_norm)


def agent_inputs(cfg: QConfig, obs, last=None):
    """The agents' network inputs ``[..., N, D']`` from observations ``obs [..., N, D]``: with
    ``cfg.last_action`` followed by ``last [..., N, A]``, the one-hot of each agent's previous action
    (zeros at an episode start), then with shared parameters and ``cfg.agent_ids`` the agent-ID
    one-hot (EPyMARL's order)."""
    if cfg.last_action:
        obs = jnp.concatenate([obs, last], -1)
    return with_agent_ids(obs) if cfg.agent_ids and cfg.shared else obs


def previous_actions(actions, resets, num_actions: int):
    """One-hot of every agent's previous action ``[T+1, B, N, A]`` at each step of time-major
    sequences (``actions [T, B, N]`` taken at steps ``0..T-1``; ``resets [T+1, B]`` marks episode
    starts, where it is zero; step 0 of a sequence has no previous action in it, so also zero)."""
    taken = jax.nn.one_hot(actions, num_actions, dtype=jnp.float32)
    last = jnp.concatenate([jnp.zeros_like(taken[:1]), taken], 0)
    return jnp.where(resets[..., None, None], 0.0, last)


def make_train(env, cfg: QConfig, mixer: nn.Module):
    """``train(key) -> (params, metrics)`` for ``env`` with the team-value ``mixer``
    (``mixer.apply(params, q_chosen [..., N], state [..., S]) -> [...]``)."""
    cfg.validate()
    agent = agent_module(env, cfg)
    n_agents, seq_len = env.num_agents, sequence_length(env, cfg)
    steps_per_update = cfg.num_envs * seq_len
    num_updates = max(1, cfg.total_timesteps // steps_per_update)
    total_grad_steps = num_updates * cfg.train_steps
    lr = optax.linear_schedule(cfg.lr, 0.0, total_grad_steps) if cfg.lr_decay else cfg.lr
    tx = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), OPTIMIZERS[cfg.optimizer](lr))

    def q_values(agent_params, hidden, inputs, reset):
        """One step: ``hidden [..., N, H]``, ``inputs [..., N, D']`` (:func:`agent_inputs`), ``reset [..., N, 1]``."""
        return apply_agents(agent, agent_params, hidden, inputs, reset, shared=cfg.shared)

    def sequence_inputs(obs, actions, resets):
        """Agent inputs ``[T', B, N, D']`` along time-major sequences (``obs [T', B, N, D]``, the
        ``actions [T, B, N]`` taken, ``resets [T+1, B]``; ``T'`` = T or T + 1)."""
        last = previous_actions(actions, resets, env.num_actions)[:obs.shape[0]] if cfg.last_action else None
        return agent_inputs(cfg, obs, last)

    def agent_resets(resets):
        return jnp.broadcast_to(resets[..., None, None], resets.shape + (n_agents, 1))

    def q_sequence(agent_params, inputs, resets, hidden=None):
        """Q-values ``[T, B, N, A]`` of one network along sequences of agent inputs ``inputs [T, B, N, D']``
        (``resets [T, B]``) from the hidden state ``hidden [B, N, H]`` (``None``: zero)."""
        reset = agent_resets(resets)
        if agent.memory != "gru":      # minimal-GRU and feed-forward agents take the whole sequence at once
            start = () if hidden is None else (hidden,)       # feed-forward agents ignore it
            return apply_agents(agent, agent_params, inputs, reset, *start, shared=cfg.shared,
                                method=QAgent.sequence)

        def step(hidden, inputs):
            return q_values(agent_params, hidden, *inputs)

        start = agent.initial_hidden(inputs.shape[1:3]) if hidden is None else hidden
        return jax.lax.scan(step, start, (inputs, reset))[1]

    def q_sequences(agent_params, target_params, inputs, resets, hidden=None):
        """Online and target Q-values, each ``[T, B, N, A]``. GRU agents: both networks advance in one
        scan (half the loop steps of two unrolls; each step's two small GRU matmuls run back to back)."""
        if agent.memory != "gru":
            return tuple(q_sequence(p, inputs, resets, hidden) for p in (agent_params, target_params))
        reset = agent_resets(resets)
        if hidden is None:
            hidden = agent.initial_hidden(inputs.shape[1:3])

        def step(hiddens, inputs):
            h_online, q_online = q_values(agent_params, hiddens[0], *inputs)
            h_target, q_target = q_values(target_params, hiddens[1], *inputs)
            return (h_online, h_target), (q_online, q_target)

        return jax.lax.scan(step, (hidden, hidden), (inputs, reset))[1]

    def epsilon(env_steps):
        frac = jnp.clip(env_steps / cfg.eps_decay_steps, 0.0, 1.0)
        return cfg.eps_start + frac * (cfg.eps_finish - cfg.eps_start)

    def init(key):
        """Runner state of a fresh run: parameters, target copy, optimiser, empty buffer, key."""
        key, k_agent, k_mixer, k_reset = jax.random.split(key, 4)
        obs, _ = env.reset(k_reset)
        hidden = agent.initial_hidden((n_agents,))
        no_action = jnp.zeros((n_agents, env.num_actions), jnp.float32)
        sample = (hidden[0], agent_inputs(cfg, obs, no_action)[0], jnp.zeros((1,), bool))
        params = dict(agent=init_agents(agent, k_agent, sample, n_agents, cfg.shared),
                      mixer=mixer.init(k_mixer, jnp.zeros((n_agents,)), global_state(obs)))
        example = dict(obs=jnp.zeros((seq_len + 1,) + obs.shape, jnp.float32),
                       actions=jnp.zeros((seq_len, n_agents), jnp.int32),
                       reward=jnp.zeros((seq_len,), jnp.float32), done=jnp.zeros((seq_len,), bool))
        runner = dict(params=params, target=params, opt_state=tx.init(params), key=key, update=jnp.int32(0),
                      grad_steps=jnp.int32(0), reward_moments=(jnp.float32(0), jnp.float32(0), jnp.float32(0)))
        if cfg.persistent_envs:    # the envs the first update continues, and each sequence's stored start
            example.update(hidden=hidden, first=jnp.zeros((), bool))
            runner["envs"] = fresh_envs(jax.random.fold_in(k_reset, 1))
        # laid out as the split learner's updates return it, so its programs compile once
        return whole_on(cfg.learner_devices)(dict(runner, buffer=episode_buffer.init(example, cfg.buffer_size)))

    def fresh_envs(key):
        """``num_envs`` envs just reset: ``(obs, env state, agents' hidden state, reset flags)``."""
        obs, state = jax.vmap(env.reset)(jax.random.split(key, cfg.num_envs))
        return obs, state, agent.initial_hidden((cfg.num_envs, n_agents)), jnp.ones((cfg.num_envs,), bool)

    def collect(params, key, eps, envs=None):
        """``num_envs`` sequences of ``seq_len`` steps, env-major, the rollout metrics and the envs as
        they were left (``eps [num_envs]``: each env's exploration rate). ``envs`` (see
        :func:`fresh_envs`): continue those; ``None``: start from a fresh reset."""
        k_reset, k_run = jax.random.split(key)
        start = fresh_envs(k_reset) if envs is None else envs
        no_action = jnp.zeros((cfg.num_envs, n_agents, env.num_actions), jnp.float32)

        def step(carry, key):
            (obs, state, hidden, reset), last = carry
            k_explore, k_random, k_env = jax.random.split(key, 3)
            inputs = agent_inputs(cfg, obs, jnp.where(reset[:, None, None], 0.0, last))
            hidden, q = q_values(params["agent"], hidden, inputs, agent_resets(reset))
            explore = jax.random.uniform(k_explore, (cfg.num_envs, n_agents)) < eps[:, None]
            random = jax.random.randint(k_random, (cfg.num_envs, n_agents), 0, env.num_actions)
            actions = jnp.where(explore, random, jnp.argmax(q, -1)).astype(jnp.int32)
            next_obs, state, rewards, done, info = jax.vmap(env.step)(
                jax.random.split(k_env, cfg.num_envs), state, actions)
            out = dict(obs=obs, actions=actions, reward=jax.vmap(env.scenario.team_reward)(rewards),
                       done=done, info=episode_info(info))
            last = jax.nn.one_hot(actions, env.num_actions) if cfg.last_action else last    # off: stays zero
            return ((next_obs, state, hidden, done), last), out

        (left, _), traj = jax.lax.scan(step, (start, no_action), jax.random.split(k_run, seq_len))
        metrics = rollout_metrics(traj["done"], traj["info"])
        sequences = dict(obs=jnp.concatenate([traj["obs"], left[0][None]], 0), actions=traj["actions"],
                         reward=traj["reward"], done=traj["done"])
        sequences = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), sequences)
        if cfg.persistent_envs:    # hidden state (before the reset flag is applied) and flag at the start
            sequences.update(hidden=start[2], first=start[3])
        return sequences, metrics, left

    def time_major(batch):
        """``(data, resets [T+1, B], state [T+1, B, S], hidden [B, N, H] or None)`` of env-major ``batch``."""
        batch = dict(batch)
        hidden, first = batch.pop("hidden", None), batch.pop("first", None)
        data = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), batch)
        first = jnp.ones_like(data["done"][:1]) if first is None else first[None]
        resets = jnp.concatenate([first, data["done"]], 0)                              # [T+1, B]
        return data, resets, global_state(data["obs"]), hidden                          # state [T+1, B, S]

    def targets(data, state, next_q, target_mixer, moments):
        """TD(lambda) targets ``[T, B]`` from the next steps' agent values ``next_q [T, B, N]``."""
        next_tot = mixer.apply(target_mixer, next_q, state[1:])
        return lambda_returns(normalise_rewards(cfg, moments, data["reward"]), data["done"], next_tot,
                              cfg.gamma, cfg.td_lambda)

    def chosen_q(q, data):
        return jnp.take_along_axis(q, data["actions"][..., None], -1)[..., 0]

    def loss_fn(params, target, batch, moments):
        data, resets, state, hidden = time_major(batch)
        inputs = sequence_inputs(data["obs"], data["actions"], resets)
        q, q_target = q_sequences(params["agent"], target["agent"], inputs, resets, hidden)   # [T+1, B, N, A]
        if cfg.double_q:
            best = jnp.argmax(jax.lax.stop_gradient(q[1:]), -1)
            next_q = jnp.take_along_axis(q_target[1:], best[..., None], -1)[..., 0]
        else:
            next_q = q_target[1:].max(-1)
        y = targets(data, state, next_q, target["mixer"], moments)
        q_tot = mixer.apply(params["mixer"], chosen_q(q[:-1], data), state[:-1])
        return jnp.mean((q_tot - jax.lax.stop_gradient(y)) ** 2)

    def update_targets(target, sequences, moments):
        """Targets ``[B, T]`` of env-major ``sequences`` under the (fixed) target network (no double-Q)."""
        data, resets, state, hidden = time_major(sequences)
        inputs = sequence_inputs(data["obs"], data["actions"], resets)
        next_q = q_sequence(target["agent"], inputs, resets, hidden)[1:].max(-1)   # from the start
        return jnp.swapaxes(targets(data, state, next_q, target["mixer"], moments), 0, 1)

    def cached_loss_fn(params, target, batch, moments):
        """``loss_fn`` with the targets precomputed (``batch["target"] [B, T]``): online network only."""
        del target, moments
        data, resets, state, hidden = time_major(batch)
        inputs = sequence_inputs(data["obs"][:-1], data["actions"], resets)
        q = q_sequence(params["agent"], inputs, resets[:-1], hidden)                   # [T, B, N, A]
        q_tot = mixer.apply(params["mixer"], chosen_q(q, data), state[:-1])
        return jnp.mean((q_tot - data["target"]) ** 2)

    per_update = cfg.targets_per_update
    loss_and_grad = split_batch(jax.value_and_grad(cached_loss_fn if per_update else loss_fn),
                                cfg.learner_devices, batch_argnum=2)
    buffer_targets = split_rows(update_targets, cfg.learner_devices, batch_argnum=1)

    def learn(moments, buffer, carry, key):
        """One gradient step on a batch from ``buffer``; ``moments`` (the reward statistics) and the
        buffer stay fixed within an update."""
        params, target, opt_state, grad_steps = carry
        batch = episode_buffer.sample(buffer, key, cfg.batch_size)
        loss, grads = loss_and_grad(params, target, batch, moments)
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        grad_steps = grad_steps + 1
        if cfg.tau < 1.0:
            target = optax.incremental_update(params, target, cfg.tau)
        else:
            copy = grad_steps % cfg.target_update_interval == 0
            target = jax.tree_util.tree_map(lambda p, t: jnp.where(copy, p, t), params, target)
        return (params, target, opt_state, grad_steps), loss

    def update(runner, key):
        k_collect, k_learn = jax.random.split(key)
        env_steps = runner["update"] * steps_per_update
        eps = epsilon(env_steps)
        sequences, metrics, envs = collect(runner["params"], k_collect, env_epsilons(eps, cfg.num_envs, cfg.eps_spread),
                                           runner.get("envs"))
        buffer = episode_buffer.add(runner["buffer"], sequences)
        moments = update_moments(runner["reward_moments"], sequences["reward"])
        carry = (runner["params"], runner["target"], runner["opt_state"], runner["grad_steps"])
        ready = buffer.size * seq_len >= cfg.learning_starts

        def train(carry):
            sampled = buffer
            if per_update:      # targets of every buffered sequence, sampled alongside them
                target = carry[1]
                sampled = buffer.replace(data=dict(buffer.data, target=buffer_targets(target, buffer.data, moments)))
            carry, losses = jax.lax.scan(functools.partial(learn, moments, sampled), carry,
                                         jax.random.split(k_learn, cfg.train_steps))
            return carry, losses.mean()

        carry, loss = jax.lax.cond(ready, train, lambda c: (c, jnp.float32(jnp.nan)), carry)
        params, target, opt_state, grad_steps = carry
        runner = dict(runner, params=params, target=target, opt_state=opt_state, buffer=buffer,
                      update=runner["update"] + 1, grad_steps=grad_steps, reward_moments=moments)
        if cfg.persistent_envs:
            runner["envs"] = envs
        return runner, dict(metrics, loss=loss, epsilon=eps)

    def run(runner, num_updates: int):
        """Advance a runner state by ``num_updates`` updates (static): ``(runner, metrics)``."""
        def one(runner, _):
            key, sub = jax.random.split(runner["key"])
            return update(dict(runner, key=key), sub)

        return jax.lax.scan(one, runner, None, length=num_updates)

    return trainer(init, run, num_updates, steps_per_update)


def policy_tensors(cfg: QConfig, params) -> tuple[dict, dict]:
    """What an export keeps of one seed's ``params``: the agent network (the mixer is training-only), as
    :class:`marbler_jax.numpy_policy.NumpyPolicy` spec fields and ``float32`` tensors by name."""
    agent = jax.tree_util.tree_map(np.asarray, params)["agent"]["params"]
    memory = QAgent(1, cfg.hidden, cfg.recurrent, cfg.cell).memory
    fields = dict(kind="q_agent", recurrent=memory != "none", cell=memory, layer_norm=bool(cfg.layer_norm),
                  last_action=bool(cfg.last_action), hidden=cfg.hidden, activation="relu", layers=[],
                  shared=bool(cfg.shared), agent_ids=bool(cfg.agent_ids))
    return fields, float32_tensors(agent)


def greedy_policy(env, cfg: QConfig, params) -> StatefulPolicy:
    """Greedy (argmax-Q) policy of trained ``params``. Its carry is the agents' memory ``[..., N, M]``:
    the hidden state, followed with ``cfg.last_action`` by the one-hot of each agent's last action
    (the layout of :class:`marbler_jax.numpy_policy.NumpyPolicy`'s memory)."""
    agent = agent_module(env, cfg)
    width = agent.initial_hidden().shape[-1]

    def step(key, obs, memory, reset):
        del key
        reset = jnp.broadcast_to(reset[..., None, None], obs.shape[:-1] + (1,))
        hidden, last = memory[..., :width], jnp.where(reset, 0.0, memory[..., width:])
        hidden, q = apply_agents(agent, params["agent"], hidden, agent_inputs(cfg, obs, last), reset, shared=cfg.shared)
        actions = jnp.argmax(q, -1).astype(jnp.int32)
        if cfg.last_action:
            hidden = jnp.concatenate([hidden, jax.nn.one_hot(actions, env.num_actions, dtype=hidden.dtype)], -1)
        return actions, hidden

    def initial_carry(batch_shape):
        memory = agent.initial_hidden(tuple(batch_shape) + (env.num_agents,))
        if cfg.last_action:
            memory = jnp.concatenate([memory, jnp.zeros(memory.shape[:-1] + (env.num_actions,), memory.dtype)], -1)
        return memory

    return StatefulPolicy(initial_carry=initial_carry, step=step)


__all__ = ["QConfig", "make_train", "greedy_policy", "policy_tensors", "sequence_length", "lambda_returns", "env_epsilons",
           "agent_inputs", "previous_actions", "OPTIMIZERS"]
