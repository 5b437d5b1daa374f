"""PQN, VDN form: parallel Q-learning with lambda-returns and LayerNorm, no replay buffer, no target network.

Gallici et al. 2024, "Simplifying Deep Temporal Difference Learning". Each update steps ``num_envs`` envs
``num_steps`` times (the envs run on across updates; an episode that ends resets its env), acting
epsilon-greedily on a shared feed-forward Q-network with LayerNorm (:class:`~marbler_jax_rl.networks.QAgent`,
``cell="none"``, agent-ID one-hot in). The team value is the sum of the robots' chosen Q-values (VDN), its
target the TD(lambda) return of the team reward along the collected steps, bootstrapped on the sum of the
robots' greedy Q-values of the network that collected them (computed while acting: no second pass, no target
network). The collected steps are then learned from for ``num_epochs`` epochs of ``num_minibatches``
minibatches and dropped. Written against marbler-jax's public interface only, like an outside algorithm.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .algorithm import Algorithm, trainer
from .common import episode_info, float32_tensors, rollout_metrics
from .networks import QAgent, with_agent_ids
from .q_learning import lambda_returns


@dataclasses.dataclass(frozen=True)
class PQNConfig:
    """PQN's settings (``--hp key=value``).

    Attributes:
        total_timesteps: env steps per seed.
        num_envs: envs stepped in parallel (they run on across updates).
        num_steps: steps of each env per update.
        num_epochs: passes over an update's ``num_envs * num_steps`` samples.
        num_minibatches: minibatches of each pass (must divide ``num_envs * num_steps``).
        lr: Adam's step size.
        lr_decay: the step size falls linearly to 0 over training.
        gamma: discount.
        td_lambda: the lambda of the targets' TD(lambda) returns (0: one-step targets).
        eps_start: exploration rate at the start.
        eps_finish: exploration rate after ``eps_decay_steps``.
        eps_decay_steps: env steps of each seed over which epsilon falls linearly.
        max_grad_norm: gradients are clipped to this global norm.
        hidden: units of the Q-network's two hidden layers.
    """

    total_timesteps: int = 10_000_000
    num_envs: int = 128
    num_steps: int = 32
    num_epochs: int = 2
    num_minibatches: int = 4
    lr: float = 5e-4
    lr_decay: bool = True
    gamma: float = 0.95
    td_lambda: float = 0.8
    eps_start: float = 1.0
    eps_finish: float = 0.01
    eps_decay_steps: int = 1_000_000
    max_grad_norm: float = 10.0
    hidden: int = 128

    def validate(self) -> None:
        for name in ("total_timesteps", "num_envs", "num_steps", "num_epochs", "num_minibatches", "hidden"):
            value = getattr(self, name)
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if self.eps_decay_steps < 0:
            raise ValueError(f"eps_decay_steps must be >= 0, got {self.eps_decay_steps}")
        if (self.num_envs * self.num_steps) % self.num_minibatches:
            raise ValueError(f"num_minibatches={self.num_minibatches} must divide num_envs * num_steps = "
                             f"{self.num_envs * self.num_steps}")
        for name, high, open_low in (("lr", 1.0, True), ("gamma", 1.0, True), ("max_grad_norm", 1e6, True),
                                     ("td_lambda", 1.0, False), ("eps_start", 1.0, False), ("eps_finish", 1.0, False)):
            value = getattr(self, name)
            if not ((value > 0.0 if open_low else value >= 0.0) and value <= high):
                raise ValueError(f"{name} must be in {'(' if open_low else '['}0, {high:g}], got {value}")


def q_network(env, cfg: PQNConfig) -> QAgent:
    return QAgent(env.num_actions, cfg.hidden, cell="none", layer_norm=True)


def q_values(network: QAgent, params, obs):
    """Q-values ``[..., N, A]`` of observations ``obs [..., N, D]`` (shared network, agent IDs in)."""
    inputs = with_agent_ids(obs)
    return network.apply(params, inputs, jnp.zeros(inputs.shape[:-1] + (1,), bool), method=QAgent.sequence)


def make_train(env, cfg: PQNConfig):
    cfg.validate()
    network = q_network(env, cfg)
    batch = cfg.num_envs * cfg.num_steps            # env steps per update, each one sample
    num_updates = max(1, cfg.total_timesteps // batch)
    lr = (optax.linear_schedule(cfg.lr, 0.0, num_updates * cfg.num_epochs * cfg.num_minibatches)
          if cfg.lr_decay else cfg.lr)
    tx = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(lr))

    def init(key):
        k_net, k_reset, key = jax.random.split(key, 3)
        sample = jnp.zeros((env.num_agents, env.obs_dim + env.num_agents))
        params = {"agent": network.init(k_net, sample, jnp.zeros((env.num_agents, 1), bool),
                                        method=QAgent.sequence)}
        obs, state = jax.vmap(env.reset)(jax.random.split(k_reset, cfg.num_envs))
        return dict(params=params, opt_state=tx.init(params), obs=obs, env_state=state, key=key,
                    steps=jnp.zeros((), jnp.int32))

    def epsilon(steps):
        fraction = jnp.clip(steps / max(cfg.eps_decay_steps, 1), 0.0, 1.0)
        return cfg.eps_start + fraction * (cfg.eps_finish - cfg.eps_start)

    def collect(runner, key):
        eps = epsilon(runner["steps"])

        def step(carry, key):
            obs, state = carry
            k_explore, k_random, k_env = jax.random.split(key, 3)
            q = q_values(network, runner["params"]["agent"], obs)                    # [E, N, A]
            greedy = jnp.argmax(q, -1)
            explore = jax.random.uniform(k_explore, greedy.shape) < eps
            actions = jnp.where(explore, jax.random.randint(k_random, greedy.shape, 0, env.num_actions), greedy)
            next_obs, state, rewards, done, info = jax.vmap(env.step)(
                jax.random.split(k_env, cfg.num_envs), state, actions.astype(jnp.int32))
            out = dict(obs=obs, actions=actions, reward=jax.vmap(env.scenario.team_reward)(rewards),
                       done=done, value=q.max(-1).sum(-1), info=episode_info(info))
            return (next_obs, state), out

        (obs, state), traj = jax.lax.scan(step, (runner["obs"], runner["env_state"]),
                                          jax.random.split(key, cfg.num_steps))
        last_value = q_values(network, runner["params"]["agent"], obs).max(-1).sum(-1)       # [E]
        next_value = jnp.concatenate([traj["value"][1:], last_value[None]], 0)
        targets = lambda_returns(traj["reward"], traj["done"], next_value, cfg.gamma, cfg.td_lambda)
        return obs, state, traj, jax.lax.stop_gradient(targets)

    def loss_fn(params, obs, actions, targets):
        q = q_values(network, params["agent"], obs)                                    # [B, N, A]
        chosen = jnp.take_along_axis(q, actions[..., None], -1)[..., 0].sum(-1)         # [B]
        return 0.5 * jnp.mean((chosen - targets) ** 2)

    def learn(params, opt_state, samples, key):
        def epoch(carry, key):
            def minibatch(carry, part):
                params, opt_state = carry
                loss, grads = jax.value_and_grad(loss_fn)(params, *part)
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), loss

            order = jax.random.permutation(key, batch)
            parts = jax.tree_util.tree_map(
                lambda x: x[order].reshape((cfg.num_minibatches, batch // cfg.num_minibatches) + x.shape[1:]), samples)
            return jax.lax.scan(minibatch, carry, parts)

        (params, opt_state), losses = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, cfg.num_epochs))
        return params, opt_state, losses.mean()

    def run(runner, n: int):
        def update(runner, _):
            key, k_collect, k_learn = jax.random.split(runner["key"], 3)
            obs, state, traj, targets = collect(runner, k_collect)
            samples = tuple(x.reshape((batch,) + x.shape[2:]) for x in (traj["obs"], traj["actions"], targets))
            params, opt_state, loss = learn(runner["params"], runner["opt_state"], samples, k_learn)
            runner = dict(params=params, opt_state=opt_state, obs=obs, env_state=state, key=key,
                          steps=runner["steps"] + batch)
            return runner, dict(rollout_metrics(traj["done"], traj["info"]), loss=loss)

        return jax.lax.scan(update, runner, None, length=n)

    return trainer(init, run, num_updates, batch)


def greedy_policy(env, cfg: PQNConfig, params):
    """Argmax-Q actions ``[..., N]`` of observations ``[..., N, D]`` (a feed-forward network: no memory)."""
    network = q_network(env, cfg)
    return lambda key, obs: jnp.argmax(q_values(network, params["agent"], obs), -1).astype(jnp.int32)


def policy_tensors(cfg: PQNConfig, params):
    """The Q-network as a numpy ``q_agent`` policy (feed-forward, LayerNorm, shared, agent IDs)."""
    agent = jax.tree_util.tree_map(np.asarray, params)["agent"]["params"]
    fields = dict(kind="q_agent", recurrent=False, cell="none", layer_norm=True, last_action=False,
                  hidden=cfg.hidden, activation="relu", layers=[], shared=True, agent_ids=True)
    return fields, float32_tensors(agent)


PQN = Algorithm(
    name="pqn", summary="PQN (VDN form): parallel Q-learning with lambda-returns and LayerNorm, no replay buffer "
    "or target network", config=PQNConfig, make_train=make_train, greedy_policy=greedy_policy,
    policy_tensors=policy_tensors)

__all__ = ["PQN", "PQNConfig", "make_train", "greedy_policy", "policy_tensors"]
