"""IPPO written against JaxMARL's API alone, trained on a marbler-jax scenario through ``JaxMARLEnv``.

Nothing here uses marbler-jax beyond the one line that makes the env: the loop is a JaxMARL user's script
(dict observations batched over agents, JaxMARL's ``LogWrapper`` for the returns), so it shows what a JaxMARL
user changes to train on marbler-jax. Shared feed-forward actor-critic, GAE, clipped PPO.

    python examples/jaxmarl_ippo.py --scenario predator_capture_prey --updates 300
"""
from __future__ import annotations

import argparse

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from jaxmarl.wrappers.baselines import LogWrapper

import marbler_jax
from marbler_jax.adapters import JaxMARLEnv


class ActorCritic(nn.Module):
    num_actions: int

    @nn.compact
    def __call__(self, x):
        actor = nn.Dense(self.num_actions)(nn.tanh(nn.Dense(64)(nn.tanh(nn.Dense(64)(x)))))
        critic = nn.Dense(1)(nn.tanh(nn.Dense(64)(nn.tanh(nn.Dense(64)(x)))))
        return actor, critic[..., 0]


def batchify(x: dict, agents):
    return jnp.stack([x[a] for a in agents])              # [N, E, ...]


def make_train(env, num_envs=32, num_steps=64, updates=300, lr=1e-3, gamma=0.99, lam=0.95, clip=0.2, epochs=4):
    env = LogWrapper(env)
    agents, num_actions = env.agents, env.action_space(env.agents[0]).n
    net, tx = ActorCritic(num_actions), optax.chain(optax.clip_by_global_norm(0.5), optax.adam(lr))

    def train(key):
        key, k_init, k_reset = jax.random.split(key, 3)
        obs, state = jax.vmap(env.reset)(jax.random.split(k_reset, num_envs))
        params = net.init(k_init, batchify(obs, agents))
        carry = (params, tx.init(params), obs, state, key)

        def update(carry, _):
            params, opt_state, obs, state, key = carry

            def step(c, key):
                obs, state = c
                k_act, k_env = jax.random.split(key)
                x = batchify(obs, agents)                                   # [N, E, D]
                logits, value = net.apply(params, x)
                action = jax.random.categorical(k_act, logits)
                logp = jax.nn.log_softmax(logits)[jnp.arange(len(agents))[:, None], jnp.arange(num_envs), action]
                obs, state, reward, done, info = jax.vmap(env.step)(
                    jax.random.split(k_env, num_envs), state, {a: action[i] for i, a in enumerate(agents)})
                out = (x, action, logp, value, batchify(reward, agents), done["__all__"],
                       info["returned_episode_returns"].mean(-1), info["returned_episode"].all(-1))
                return (obs, state), out

            key, k_run, k_perm = jax.random.split(key, 3)
            (obs, state), (x, action, logp, value, reward, done, ret, ended) = jax.lax.scan(
                step, (obs, state), jax.random.split(k_run, num_steps))
            _, last = net.apply(params, batchify(obs, agents))

            def gae(c, t):
                adv, next_value = c
                r, v, d = t
                delta = r + gamma * next_value * (1 - d) - v
                adv = delta + gamma * lam * (1 - d) * adv
                return (adv, v), adv

            done_n = jnp.broadcast_to(done[:, None], reward.shape).astype(jnp.float32)
            _, adv = jax.lax.scan(gae, (jnp.zeros_like(last), last), (reward, value, done_n), reverse=True)
            target = adv + value

            def loss_fn(params):
                logits, v = net.apply(params, x)
                new_logp = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
                ratio = jnp.exp(new_logp - logp)
                a = (adv - adv.mean()) / (adv.std() + 1e-8)
                actor = -jnp.minimum(ratio * a, jnp.clip(ratio, 1 - clip, 1 + clip) * a).mean()
                entropy = -(jax.nn.softmax(logits) * jax.nn.log_softmax(logits)).sum(-1).mean()
                return actor + 0.5 * ((v - target) ** 2).mean() - 0.01 * entropy

            def epoch(c, _):
                params, opt_state = c
                grads = jax.grad(loss_fn)(params)
                updates_, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates_), opt_state), None

            (params, opt_state), _ = jax.lax.scan(epoch, (params, opt_state), None, length=epochs)
            finished = jnp.maximum(ended.sum(), 1)
            mean_return = jnp.where(ended.any(), (ret * ended).sum() / finished, jnp.nan)
            return (params, opt_state, obs, state, key), mean_return

        carry, returns = jax.lax.scan(update, carry, None, length=updates)
        return carry[0], returns

    return train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="predator_capture_prey")
    parser.add_argument("--updates", type=int, default=300)
    args = parser.parse_args()
    env = JaxMARLEnv(marbler_jax.make(args.scenario))            # the one marbler-jax line
    _, returns = jax.jit(make_train(env, updates=args.updates))(jax.random.PRNGKey(0))
    print(f"mean episode return per robot: first updates {jnp.nanmean(returns[:10]):.2f}, "
          f"last updates {jnp.nanmean(returns[-10:]):.2f}")


if __name__ == "__main__":
    main()
