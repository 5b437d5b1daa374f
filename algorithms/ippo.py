"""IPPO: independent PPO, one actor-critic per agent on its own observation (decentralised critic).

With ``critic_input="global"`` the critic sees the global state instead (every agent's observation
concatenated, as MARBLER's EPyMARL runs did): that is MAPPO (:mod:`marbler_jax_rl.mappo`).

The whole training run is one jitted function ``train(key) -> (params, metrics)`` built by
:func:`make_train`; ``jax.vmap(train)(keys)`` trains several seeds in one program (the driver's
default, see ``algorithms/driver.py``). Each update
rolls out ``num_steps`` steps of ``num_envs`` auto-resetting envs, computes per-agent GAE, then runs
``update_epochs`` epochs of clipped-surrogate SGD over ``num_minibatches`` minibatches (Adam,
global-norm clipping, linear learning-rate annealing). Agents share parameters (with an agent-ID
one-hot appended to each observation) unless ``shared=False``, in which case every agent has its own
network, vmapped over agents. ``learner_devices > 1`` splits each rollout's envs and each minibatch's
samples over that many devices of this host (:func:`marbler_jax_rl.data_parallel.rows_over`).

``cell="gru"`` (or ``"mingru"``) makes the actors recurrent (:class:`marbler_jax_rl.networks.RecurrentActorCritic`,
the form of MARBLER's MAPPO actors; the critic stays feed-forward): the rollout carries each robot's hidden
state, zeroed at episode starts, and each minibatch is a set of whole env sequences of the rollout, unrolled
from the hidden state they started the rollout with.

Metrics per update (arrays ``[num_updates]``): ``return`` (mean team return of the episodes that
finished during the rollout; NaN if none did), ``length``, ``collision_rate``, ``out_of_bounds_rate``,
``episodes``, ``loss``, ``entropy``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .algorithm import trainer
from .common import episode_info, float32_tensors, global_state, rollout_metrics
from .data_parallel import rows_over
from marbler_jax.numpy_policy import CELLS
from marbler_jax.rollout import StatefulPolicy

from .networks import ActorCritic, RecurrentActorCritic, apply_agents, init_agents, with_agent_ids


@dataclasses.dataclass(frozen=True)
class IPPOConfig:
    """IPPO settings (MAPPO's too, with a centralised critic).

    Attributes:
        total_timesteps: env steps per seed (one env step moves every robot).
        num_envs: parallel envs collecting each update's rollout.
        num_steps: rollout length per env per update.
        update_epochs: passes over each rollout.
        num_minibatches: minibatches per pass.
        gamma: discount factor.
        gae_lambda: GAE lambda of the advantages.
        clip_eps: PPO's clip range of the probability ratio (and of the value update).
        ent_coef: weight of the entropy bonus.
        vf_coef: weight of the value loss.
        max_grad_norm: global gradient-norm clip.
        lr: Adam learning rate.
        anneal_lr: decay the learning rate linearly to 0 over the run.
        hidden: units per hidden layer of actor and critic (and of the actor's recurrent cell).
        layers: hidden layers of actor and critic (of the critic alone with a recurrent actor).
        activation: hidden activation, "tanh" or "relu" (of the critic alone with a recurrent actor).
        cell: "none": feed-forward actors; "gru" or "mingru": recurrent actors (``Dense(hidden) -> ReLU ->
            cell -> Dense(actions)``) trained on whole env sequences (``num_envs / num_minibatches`` per
            minibatch).
        shared: one network for every robot (else one per robot).
        agent_ids: append a one-hot robot ID to each robot's input.
        critic_input: "local": the critic sees the robot's own observation (IPPO); "global": every
            robot's observation (MAPPO).
        learner_devices: > 1: the rollout's envs and each minibatch's samples are split over this many
            devices (the same updates as one device, up to float rounding).
    """

    total_timesteps: int = 500_000
    num_envs: int = 64
    num_steps: int = 64
    update_epochs: int = 4
    num_minibatches: int = 4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    lr: float = 3e-4
    anneal_lr: bool = True
    hidden: int = 128
    layers: int = 2
    activation: str = "tanh"
    cell: str = "none"
    shared: bool = True
    agent_ids: bool = True
    critic_input: str = "local"
    learner_devices: int = 1

    @property
    def recurrent(self) -> bool:
        return self.cell != "none"

    @property
    def num_updates(self) -> int:
        return max(1, self.total_timesteps // (self.num_envs * self.num_steps))

    def validate(self) -> None:
        for name in ("total_timesteps", "num_envs", "num_steps", "update_epochs", "num_minibatches", "hidden", "layers",
                     "learner_devices"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("lr", "clip_eps", "max_grad_norm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("ent_coef", "vf_coef"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        if not 0.0 <= self.gae_lambda <= 1.0:
            raise ValueError(f"gae_lambda must be in [0, 1], got {self.gae_lambda}")
        if self.cell not in CELLS:
            raise ValueError(f"cell must be one of {list(CELLS)}, got {self.cell!r}")
        if self.critic_input not in ("local", "global"):
            raise ValueError(f"critic_input must be 'local' or 'global', got {self.critic_input!r}")
        if (self.num_envs * self.num_steps) % self.num_minibatches:
            raise ValueError(f"num_envs * num_steps = {self.num_envs * self.num_steps} must be divisible by "
                             f"num_minibatches = {self.num_minibatches}")
        if self.recurrent and self.num_envs % self.num_minibatches:
            raise ValueError(f"num_envs = {self.num_envs} must be divisible by num_minibatches = "
                             f"{self.num_minibatches} with a recurrent cell ({self.cell!r}): a minibatch is whole env "
                             "sequences")
        minibatch = self.num_envs * self.num_steps // self.num_minibatches
        rows = (("num_envs", self.num_envs), ("the minibatch (num_envs * num_steps / num_minibatches)", minibatch))
        if self.recurrent:
            rows = (("num_envs", self.num_envs), ("the minibatch's envs (num_envs / num_minibatches)",
                                                  self.num_envs // self.num_minibatches))
        for name, rows in rows:
            if rows % self.learner_devices:
                raise ValueError(f"{name} = {rows} must be divisible by learner_devices = {self.learner_devices}")


def policy_inputs(cfg: IPPOConfig, obs):
    return with_agent_ids(obs) if cfg.agent_ids and cfg.shared else obs


def critic_inputs(cfg: IPPOConfig, obs):
    """The critic's input per agent ``[..., N, F]``: the policy input (``"local"``) or the global
    state broadcast to every agent, with the agent-ID one-hot when parameters are shared."""
    if cfg.critic_input == "local":
        return policy_inputs(cfg, obs)
    state = jnp.broadcast_to(global_state(obs)[..., None, :], obs.shape[:-1] + (obs.shape[-2] * obs.shape[-1],))
    return with_agent_ids(state) if cfg.shared else state


def make_train(env, cfg: IPPOConfig):
    """``train(key) -> (params, metrics)`` for ``env`` (a :class:`marbler_jax.env.MarblerEnv`).

    ``train.init(key) -> runner`` and ``train.run(runner, n) -> (runner, metrics)`` expose the same
    run in chunks (for checkpointing and progress reporting).
    """
    cfg.validate()
    spread = rows_over(cfg.learner_devices)       # envs and minibatch samples over the learner's devices
    network = make_network(env, cfg)
    n_agents = env.num_agents
    batch = cfg.num_envs * cfg.num_steps
    minibatch = batch // cfg.num_minibatches
    envs_per_minibatch = cfg.num_envs // cfg.num_minibatches

    def schedule(count):
        frac = 1.0 - (count // (cfg.num_minibatches * cfg.update_epochs)) / cfg.num_updates
        return cfg.lr * (frac if cfg.anneal_lr else 1.0)

    tx = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(schedule, eps=1e-5))

    def forward(params, obs):
        return apply_agents(network, params, policy_inputs(cfg, obs), critic_inputs(cfg, obs), shared=cfg.shared)

    def value(params, obs):
        return apply_agents(network, params, critic_inputs(cfg, obs), shared=cfg.shared,
                            method=RecurrentActorCritic.value)

    def init(key):
        """Runner state ``(params, opt_state, obs, env_state, key, update)`` of a fresh run (and with
        recurrent actors ``hidden [E, N, H]`` and ``reset [E]``, True where an episode starts)."""
        key, k_init, k_reset = jax.random.split(key, 3)
        obs, state = spread(jax.vmap(env.reset)(jax.random.split(k_reset, cfg.num_envs)))
        sample = (policy_inputs(cfg, obs[0])[0], critic_inputs(cfg, obs[0])[0])
        if cfg.recurrent:
            sample = (jnp.zeros(cfg.hidden), sample[0], jnp.ones(1, bool), sample[1])
        params = init_agents(network, k_init, sample, n_agents, cfg.shared)
        runner = dict(params=params, opt_state=tx.init(params), obs=obs, env_state=state, key=key,
                      update=jnp.int32(0))
        if cfg.recurrent:
            runner.update(spread(dict(hidden=jnp.zeros((cfg.num_envs, n_agents, cfg.hidden)),
                                      reset=jnp.ones(cfg.num_envs, bool))))
        return runner

    def env_step(carry, key):
        params, obs, state, memory = carry
        k_act, k_env = jax.random.split(key)
        if cfg.recurrent:
            hidden, reset = memory
            hidden, logits = recurrent_act(network, cfg, params, hidden, obs, reset)   # [E, N, H], [E, N, A]
            value_now = value(params, obs)
        else:
            logits, value_now = forward(params, obs)                      # [E, N, A], [E, N]
        actions = jax.random.categorical(k_act, logits)          # [E, N]
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], -1)[..., 0]
        next_obs, state, rewards, done, info = jax.vmap(env.step)(
            jax.random.split(k_env, cfg.num_envs), state, actions)
        next_obs, state = spread((next_obs, state))
        transition = dict(obs=obs, actions=actions, logp=logp, value=value_now, rewards=rewards, done=done,
                          info=episode_info(info))
        if cfg.recurrent:
            transition["reset"] = reset
            memory = (hidden, done)            # the envs auto-reset: a done step's next obs starts an episode
        return (params, next_obs, state, memory), transition

    def gae(traj, last_value):
        def backward(carry, t):
            next_value, next_adv = carry
            not_done = 1.0 - t["done"][:, None].astype(jnp.float32)
            delta = t["rewards"] + cfg.gamma * next_value * not_done - t["value"]
            adv = delta + cfg.gamma * cfg.gae_lambda * not_done * next_adv
            return (t["value"], adv), adv

        _, adv = jax.lax.scan(backward, (last_value, jnp.zeros_like(last_value)), traj, reverse=True)
        return adv, adv + traj["value"]

    def ppo_loss(logits, value_new, mb):
        logp_all = jax.nn.log_softmax(logits)
        logp = jnp.take_along_axis(logp_all, mb["actions"][..., None], -1)[..., 0]
        ratio = jnp.exp(logp - mb["logp"])
        adv = (mb["adv"] - mb["adv"].mean()) / (mb["adv"].std() + 1e-8)
        actor = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps) * adv).mean()
        v_clipped = mb["value"] + jnp.clip(value_new - mb["value"], -cfg.clip_eps, cfg.clip_eps)
        critic = 0.5 * jnp.maximum((value_new - mb["target"]) ** 2, (v_clipped - mb["target"]) ** 2).mean()
        entropy = -(jnp.exp(logp_all) * logp_all).sum(-1).mean()
        return actor + cfg.vf_coef * critic - cfg.ent_coef * entropy, entropy

    def loss_fn(params, mb):
        if not cfg.recurrent:
            return ppo_loss(*forward(params, mb["obs"]), mb)
        # a minibatch of whole env sequences ``[Em, T, ...]``, unrolled time-major from their start hidden state
        seq = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), {k: v for k, v in mb.items() if k != "hidden"})

        logits = actor_sequence(network, cfg, params, mb["hidden"], seq["obs"], seq["reset"])
        return ppo_loss(logits, value(params, seq["obs"]), seq)

    def minibatches(data, hidden, key):
        """One epoch's minibatches ``[M, ...]``: shuffled samples, or with recurrent actors shuffled whole
        env sequences ``[M, Em, T, ...]`` with the hidden state each began the rollout with."""
        if not cfg.recurrent:
            flat = jax.tree_util.tree_map(lambda x: x.reshape((batch,) + x.shape[2:]), data)
            perm = jax.random.permutation(key, batch)
            return jax.tree_util.tree_map(lambda x: x[perm].reshape((cfg.num_minibatches, minibatch) + x.shape[1:]),
                                          flat)
        perm = jax.random.permutation(key, cfg.num_envs)
        by_env = dict(jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), data), hidden=hidden)
        return jax.tree_util.tree_map(
            lambda x: x[perm].reshape((cfg.num_minibatches, envs_per_minibatch) + x.shape[1:]), by_env)

    def update(carry, key):
        params, opt_state, obs, state, memory = carry
        k_roll, k_perm = jax.random.split(key)
        start_hidden = memory[0] if cfg.recurrent else None
        (params, obs, state, memory), traj = jax.lax.scan(env_step, (params, obs, state, memory),
                                                          jax.random.split(k_roll, cfg.num_steps))
        last_value = value(params, obs) if cfg.recurrent else forward(params, obs)[1]
        adv, target = gae(traj, last_value)
        data = dict(obs=traj["obs"], actions=traj["actions"], logp=traj["logp"], value=traj["value"],
                    adv=adv, target=target)
        if cfg.recurrent:
            data["reset"] = traj["reset"]

        def epoch(carry, key):
            params, opt_state = carry

            def sgd(carry, mb):
                params, opt_state = carry
                (loss, entropy), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, spread(mb))
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), (loss, entropy)

            (params, opt_state), stats = jax.lax.scan(sgd, (params, opt_state), minibatches(data, start_hidden, key))
            return (params, opt_state), stats

        (params, opt_state), (loss, entropy) = jax.lax.scan(
            epoch, (params, opt_state), jax.random.split(k_perm, cfg.update_epochs))
        metrics = dict(rollout_metrics(traj["done"], traj["info"]), loss=loss.mean(), entropy=entropy.mean())
        return (params, opt_state, obs, state, memory), metrics

    def run(runner, num_updates: int):
        """Advance a runner state by ``num_updates`` updates (static): ``(runner, metrics)``.

        The key and the learning-rate schedule's count live in the runner state, so a run cut into
        chunks follows the same trajectory as one long run: bit-identical for a fixed chunk size
        (what the driver's resume relies on), equal to float rounding across chunkings.
        """
        def one(runner, _):
            key, sub = jax.random.split(runner["key"])
            memory = (runner["hidden"], runner["reset"]) if cfg.recurrent else ()
            carry = (runner["params"], runner["opt_state"], runner["obs"], runner["env_state"], memory)
            (params, opt_state, obs, env_state, memory), metrics = update(carry, sub)
            new = dict(params=params, opt_state=opt_state, obs=obs, env_state=env_state, key=key,
                       update=runner["update"] + 1)
            if cfg.recurrent:
                new.update(hidden=memory[0], reset=memory[1])
            return new, metrics

        return jax.lax.scan(one, runner, None, length=num_updates)

    return trainer(init, run, cfg.num_updates, batch)


def make_network(env, cfg: IPPOConfig):
    """The actor-critic module of ``cfg``: feed-forward, or with recurrent actors (``cfg.cell``)."""
    if cfg.recurrent:
        return RecurrentActorCritic(env.num_actions, cfg.hidden, cfg.layers, cfg.activation, cfg.cell)
    return ActorCritic(env.num_actions, cfg.hidden, cfg.layers, cfg.activation)


def recurrent_act(network, cfg: IPPOConfig, params, hidden, obs, reset):
    """Recurrent actors' ``(hidden [..., N, H], logits [..., N, A])`` for ``obs [..., N, D]``, with the hidden
    state zeroed where ``reset [...]`` (an episode's first step)."""
    reset = jnp.broadcast_to(reset[..., None, None], obs.shape[:-1] + (1,))
    return apply_agents(network, params, hidden, policy_inputs(cfg, obs), reset, shared=cfg.shared,
                        method=RecurrentActorCritic.act)


def actor_sequence(network, cfg: IPPOConfig, params, hidden, obs, reset):
    """Recurrent actors' logits ``[T, E, N, A]`` along ``obs [T, E, N, D]`` from the hidden state ``hidden
    [E, N, H]``, zeroed before the steps where ``reset [T, E]``: the logits the rollout's steps had."""
    def step(hidden, inputs):
        return recurrent_act(network, cfg, params, hidden, *inputs)

    return jax.lax.scan(step, hidden, (obs, reset))[1]


def policy_tensors(cfg: IPPOConfig, params) -> tuple[dict, dict]:
    """What an export keeps of one seed's ``params``: the actor (the critic is training-only), as
    :class:`marbler_jax.numpy_policy.NumpyPolicy` spec fields and ``float32`` tensors by name. A recurrent
    actor has the Q-agent network's layout (``kind="q_agent"``; its outputs are logits, whose argmax acts)."""
    actor = jax.tree_util.tree_map(np.asarray, params)["params"]["actor"]
    if cfg.recurrent:
        fields = dict(kind="q_agent", recurrent=True, cell=cfg.cell, layer_norm=False, last_action=False,
                      hidden=cfg.hidden, activation="relu", layers=[], shared=bool(cfg.shared),
                      agent_ids=bool(cfg.agent_ids))
        return fields, float32_tensors(actor)
    layers = sorted(actor, key=lambda name: int(name.split("_")[-1]))
    fields = dict(kind="actor", recurrent=False, cell="none", hidden=cfg.hidden, activation=cfg.activation,
                  layers=[f"actor.{name}" for name in layers], shared=bool(cfg.shared), agent_ids=bool(cfg.agent_ids))
    return fields, float32_tensors({"actor": actor})


def greedy_policy(env, cfg: IPPOConfig, params):
    """The argmax of the trained policy: ``(key, obs [..., N, D]) -> actions [..., N]``, or with recurrent
    actors a :class:`marbler_jax.rollout.StatefulPolicy` whose carry is the hidden state ``[..., N, H]``."""
    network = make_network(env, cfg)
    if cfg.recurrent:
        def step(key, obs, hidden, reset):
            del key
            hidden, logits = recurrent_act(network, cfg, params, hidden, obs, reset)
            return jnp.argmax(logits, axis=-1).astype(jnp.int32), hidden

        return StatefulPolicy(initial_carry=lambda batch_shape: jnp.zeros(
            tuple(batch_shape) + (env.num_agents, cfg.hidden), jnp.float32), step=step)

    def act(key, obs):
        del key
        logits, _ = apply_agents(network, params, policy_inputs(cfg, obs), critic_inputs(cfg, obs),
                                 shared=cfg.shared)
        return jnp.argmax(logits, axis=-1).astype(jnp.int32)

    return act
