"""A plain, single-file PureJaxRL-style PPO: the reference amjax's PPO is timed against.

Written for the throughput benchmark, independent of amjax's agent code (it uses amjax only for the environment
and to read the hyperparameters). `make_train(config)` does the Python-side work and returns `train(key, cost)`, a
pure function built from `lax.scan`s: rollout -> GAE -> `update_epochs` x `num_minibatches` clipped-objective
steps, exactly as PureJaxRL's `ppo.py`, with these deliberate choices:

- Same algorithm and hyperparameters as `amjax.agents.ppo.PPOConfig`: the config object is read field by field
  (pass `PPOConfig()` for the defaults), so the two cannot drift. Hyperparameters are Python constants here (plain
  PureJaxRL style); only the key and the measurement cost are arguments, so `jax.vmap(train)` sweeps seeds x costs.
- Same environment: `amjax.make(env_id)` (the active-measure CartPole, reward = raw reward - cost * measured) or,
  with `vanilla=True`, the plain gymnax environment (`amjax.make_env(env_id)`, no wrapper at all).
- Truncation bootstraps from the value of the pre-reset observation (`info["final_observation"]`, gymnax 1.0 API)
  like amjax does; PureJaxRL treats truncation as termination. Same cost either way but one forward pass.
- Network initialisation is QR-free: a truncated normal with the orthogonal initialiser's variance (gain^2 /
  fan_in) instead of PureJaxRL's `orthogonal`. Orthogonal init vmapped over many seeds inside one jitted program
  (batched QR) deadlocks jaxlib 0.10.2's CPU thread pool on 2 cores (shared/research/reference-systems.md).
- Metrics: no per-step metrics (PureJaxRL keeps them for every run; memory grows with steps x runs). With
  `evaluate=True` (the default) it does the same periodic greedy evaluation as amjax (`eval_episodes` test episodes
  every `eval_every` env steps) and returns the mean costed test return per evaluation; with `evaluate=False` it
  returns the mean loss per update.
- The learning rate anneals linearly per update, as in PureJaxRL (amjax anneals per gradient step).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

from amjax.agents.ppo import PPOConfig  # noqa: E402

ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu, "elu": nn.elu}


def qr_free_init(gain: float) -> nn.initializers.Initializer:
    """Truncated normal with variance gain^2 / fan_in: the variance of `orthogonal(gain)`, without a QR."""
    return nn.initializers.variance_scaling(gain**2, "fan_in", "truncated_normal")


class ActorCritic(nn.Module):
    """Separate actor and critic MLPs (PureJaxRL's CartPole network)."""

    action_dim: int
    hidden: Sequence[int] = (64, 64)
    activation: str = "tanh"

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        act = ACTIVATIONS[self.activation]
        actor = x
        for width in self.hidden:
            actor = act(nn.Dense(width, kernel_init=qr_free_init(2**0.5))(actor))
        logits = nn.Dense(self.action_dim, kernel_init=qr_free_init(0.01))(actor)
        critic = x
        for width in self.hidden:
            critic = act(nn.Dense(width, kernel_init=qr_free_init(2**0.5))(critic))
        value = nn.Dense(1, kernel_init=qr_free_init(1.0))(critic)
        return logits, jnp.squeeze(value, -1)


class Transition(NamedTuple):
    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    terminated: jax.Array
    done: jax.Array
    log_prob: jax.Array
    value: jax.Array
    next_obs: jax.Array  # pre-reset observation (for the truncation bootstrap)


def make_env(env_id: str, vanilla: bool) -> tuple[Any, Any, Callable[[Any, jax.Array], Any], int]:
    """(env, default params, with_cost(params, cost) -> params, episode step limit)."""
    if vanilla:
        env, params = amjax.make_env(env_id)
        return env, params, lambda p, cost: p, int(params.max_steps_in_episode)
    env, params = amjax.make(env_id)
    return (
        env,
        params,
        lambda p, cost: p.replace(cost=jnp.asarray(cost, jnp.float32)),
        int(params.env_params.max_steps_in_episode),
    )


def make_train(
    config: PPOConfig, vanilla: bool = False, evaluate: bool = True
) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """`train(key, cost)`: a whole PPO run as one pure function (jit / vmap it)."""
    if config.shared_network:
        raise ValueError("the reference PPO has separate actor and critic networks only")
    env, base_params, with_cost, max_steps = make_env(config.env_id, vanilla)
    num_actions = env.action_space(base_params).n
    obs_shape = env.observation_space(base_params).shape
    network = ActorCritic(num_actions, tuple(config.hidden), config.activation)

    num_envs, num_steps = config.num_envs, config.num_steps
    batch_size = num_envs * num_steps
    minibatch_size = batch_size // config.num_minibatches
    num_updates = config.total_timesteps // batch_size
    num_evals = config.total_timesteps // config.eval_every
    updates_per_eval = config.eval_every // batch_size
    lr, clip_eps = float(config.learning_rate), float(config.clip_eps)
    gamma, gae_lambda = float(config.gamma), float(config.gae_lambda)
    ent_coef, vf_coef = float(config.ent_coef), float(config.vf_coef)

    def linear_schedule(count):
        frac = 1.0 - (count // (config.num_minibatches * config.update_epochs)) / num_updates
        return lr * frac

    tx = optax.chain(
        optax.clip_by_global_norm(float(config.max_grad_norm)),
        optax.adam(linear_schedule if config.anneal_lr else lr, eps=1e-5),
    )

    def train(key: jax.Array, cost: jax.Array) -> jax.Array:
        env_params = with_cost(base_params, cost)
        key, init_key, reset_key, eval_key = jax.random.split(key, 4)
        params = network.init(init_key, jnp.zeros((1, *obs_shape)))
        opt_state = tx.init(params)
        obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, num_envs), env_params)

        def update_step(runner_state, _):
            # 1. Rollout.
            def env_step(carry, _):
                params, opt_state, env_state, last_obs, key = carry
                key, act_key, step_key = jax.random.split(key, 3)
                logits, value = network.apply(params, last_obs)
                action = jax.random.categorical(act_key, logits)
                log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[:, None], -1)[:, 0]
                obs, env_state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                    jax.random.split(step_key, num_envs), env_state, action, env_params
                )
                transition = Transition(
                    last_obs,
                    action,
                    reward,
                    terminated,
                    terminated | truncated,
                    log_prob,
                    value,
                    info["final_observation"],
                )
                return (params, opt_state, env_state, obs, key), transition

            runner_state, traj = jax.lax.scan(env_step, runner_state, None, num_steps)
            params, opt_state, env_state, last_obs, key = runner_state

            # 2. GAE; V(pre-reset next observation) bootstraps truncated episodes.
            _, next_values = network.apply(params, traj.next_obs)
            deltas = traj.reward + gamma * (1.0 - traj.terminated) * next_values - traj.value

            def gae_step(gae, step):
                delta, done = step
                gae = delta + gamma * gae_lambda * (1.0 - done) * gae
                return gae, gae

            _, advantages = jax.lax.scan(
                gae_step, jnp.zeros_like(deltas[0]), (deltas, traj.done.astype(jnp.float32)), reverse=True
            )
            targets = advantages + traj.value

            # 3. Epochs of minibatch updates.
            def update_epoch(update_state, _):
                def update_minibatch(train_state, minibatch):
                    params, opt_state = train_state
                    traj, advantages, targets = minibatch

                    def loss_fn(params):
                        logits, value = network.apply(params, traj.obs)
                        log_softmax = jax.nn.log_softmax(logits)
                        log_prob = jnp.take_along_axis(log_softmax, traj.action[:, None], -1)[:, 0]
                        value_clipped = traj.value + jnp.clip(value - traj.value, -clip_eps, clip_eps)
                        value_loss = (
                            0.5 * jnp.maximum(jnp.square(value - targets), jnp.square(value_clipped - targets)).mean()
                        )
                        ratio = jnp.exp(log_prob - traj.log_prob)
                        gae = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
                        actor_loss = -jnp.minimum(
                            ratio * gae, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * gae
                        ).mean()
                        entropy = -(jnp.exp(log_softmax) * log_softmax).sum(-1).mean()
                        return actor_loss + vf_coef * value_loss - ent_coef * entropy

                    loss, grads = jax.value_and_grad(loss_fn)(params)
                    updates, opt_state = tx.update(grads, opt_state, params)
                    return (optax.apply_updates(params, updates), opt_state), loss

                params, opt_state, traj, advantages, targets, key = update_state
                key, perm_key = jax.random.split(key)
                permutation = jax.random.permutation(perm_key, batch_size)
                batch = jax.tree.map(lambda x: x.reshape(batch_size, *x.shape[2:]), (traj, advantages, targets))
                minibatches = jax.tree.map(
                    lambda x: x[permutation].reshape(config.num_minibatches, minibatch_size, *x.shape[1:]), batch
                )
                (params, opt_state), losses = jax.lax.scan(update_minibatch, (params, opt_state), minibatches)
                return (params, opt_state, traj, advantages, targets, key), losses

            update_state = (params, opt_state, traj, advantages, targets, key)
            update_state, losses = jax.lax.scan(update_epoch, update_state, None, config.update_epochs)
            params, opt_state, _, _, _, key = update_state
            return (params, opt_state, env_state, last_obs, key), losses.mean()

        def greedy_return(params, key):
            """Mean costed return of `eval_episodes` greedy episodes (each counted up to its first end)."""
            reset_key, run_key = jax.random.split(key)
            obs, state = jax.vmap(env.reset, in_axes=(0, None))(
                jax.random.split(reset_key, config.eval_episodes), env_params
            )

            def step(carry, step_key):
                obs, state, finished, total = carry
                action = jnp.argmax(network.apply(params, obs)[0], -1)
                obs, state, reward, terminated, truncated, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                    jax.random.split(step_key, config.eval_episodes), state, action, env_params
                )
                total = total + jnp.where(finished, 0.0, reward)
                return (obs, state, finished | terminated | truncated, total), None

            zeros = jnp.zeros(config.eval_episodes)
            (_, _, _, total), _ = jax.lax.scan(
                step, (obs, state, zeros.astype(bool), zeros), jax.random.split(run_key, max_steps)
            )
            return total.mean()

        runner_state = (params, opt_state, env_state, obs, key)
        if not evaluate:
            _, losses = jax.lax.scan(update_step, runner_state, None, num_updates)
            return losses

        def eval_period(runner_state, index):
            runner_state, _ = jax.lax.scan(update_step, runner_state, None, updates_per_eval)
            return runner_state, greedy_return(runner_state[0], jax.random.fold_in(eval_key, index))

        _, returns = jax.lax.scan(eval_period, runner_state, jnp.arange(num_evals))
        return returns

    return train


if __name__ == "__main__":
    # A short learning check: 8 seeds at cost 0.1 on the active-measure CartPole-v0.
    import time

    config = PPOConfig(total_timesteps=102_400, eval_every=10_240)
    train = jax.jit(jax.vmap(make_train(config)))
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    start = time.perf_counter()
    returns = jax.block_until_ready(train(keys, jnp.full(8, 0.1)))
    print(f"{time.perf_counter() - start:.1f} s (with compile); greedy costed return per evaluation (median):")
    print(jnp.median(returns, axis=0))
