"""A plain, single-file PureJaxRL-style DQN: the reference amjax's DQN is timed against.

Written for the throughput benchmark, independent of amjax's agent code (it uses amjax only for the environment
and to read the hyperparameters). `make_train(config)` returns `train(key, cost)`, a pure function built from
`lax.scan`s over iterations of: `train_freq` epsilon-greedy steps of `num_envs` envs -> their `n_step`-step
transitions into a ring replay buffer -> (`lax.cond`, once `learning_starts` steps are stored) `gradient_steps`
Huber-loss steps -> a target update with rate `tau` each time `target_update_interval` env steps have passed.
Choices:

- Same algorithm and hyperparameters as the `amjax.agents.dqn.DQNConfig` passed in (read field by field; dueling
  and double-Q heads included, so `DQNConfig()` gives a Dueling Double DQN and `dueling=False, double_q=False` the
  plain DQN of Stable-Baselines3; `n_step=1, anneal_lr=False` its one-step targets and constant learning rate).
  n-step returns as amjax defines them: the last n-1 steps of each env wait until their window is complete, the
  window is primed with n-1 random steps (not counted), returns stop at an episode's end, and the bootstrap is
  discounted by gamma^m (1 - terminated). With `anneal_lr` the learning rate decays linearly to 0 over the run's
  optimiser steps. Hyperparameters are Python constants (plain PureJaxRL style); only the key and
  the measurement cost are arguments, so `jax.vmap(train)` sweeps seeds x costs.
- Same environment: `amjax.make(env_id)` (active-measure) or, with `vanilla=True`, the plain gymnax environment.
- The replay buffer is a dict of arrays written with `dynamic_update_slice` (PureJaxRL uses flashbax, which is not
  installed here and does the same); sampling is uniform with replacement over the filled slots.
- One scan iteration is `train_freq` env steps, not one: PureJaxRL scans single env steps and gates learning with a
  `lax.cond` on `step % train_freq`, but under `vmap` a `lax.cond` on a batched predicate becomes a select that
  computes the gradient step on every env step (train_freq times the work). That would be a strawman.
- The random seed is the caller's key (PureJaxRL's DQN replaced it with a constant: every vmapped seed was equal).
- Network initialisation is QR-free (see reference_ppo.py: batched QR deadlocks jaxlib 0.10.2 on 2 cores).
- Metrics: none per step. With `evaluate=True` (default) the same periodic greedy evaluation as amjax (returns the
  mean costed test return per evaluation); with `evaluate=False` it returns the mean loss per iteration.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

from amjax.agents.dqn import DQNConfig  # noqa: E402

if __package__:
    from .reference_ppo import ACTIVATIONS, make_env, qr_free_init
else:  # run as a script or imported with benchmarks/ on sys.path
    from reference_ppo import ACTIVATIONS, make_env, qr_free_init


class QNetwork(nn.Module):
    """MLP Q-network; with `dueling`, Q = V + A - mean(A)."""

    action_dim: int
    hidden: Sequence[int] = (64, 64)
    activation: str = "relu"
    dueling: bool = True

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = ACTIVATIONS[self.activation]
        for width in self.hidden:
            x = act(nn.Dense(width, kernel_init=qr_free_init(2**0.5))(x))
        if not self.dueling:
            return nn.Dense(self.action_dim, kernel_init=qr_free_init(1.0))(x)
        value = nn.Dense(1, kernel_init=qr_free_init(1.0))(x)
        advantage = nn.Dense(self.action_dim, kernel_init=qr_free_init(1.0))(x)
        return value + advantage - advantage.mean(-1, keepdims=True)


def make_train(
    config: DQNConfig, vanilla: bool = False, evaluate: bool = True
) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """`train(key, cost)`: a whole DQN run as one pure function (jit / vmap it)."""
    env, base_params, with_cost, max_steps = make_env(config.env_id, vanilla)
    num_actions = env.action_space(base_params).n
    obs_shape = env.observation_space(base_params).shape
    network = QNetwork(num_actions, tuple(config.hidden), config.activation, config.dueling)

    num_envs, train_freq = config.num_envs, config.train_freq
    steps_per_iter = num_envs * train_freq
    if config.buffer_size % steps_per_iter:
        raise ValueError("buffer_size must be a multiple of num_envs * train_freq")
    num_iters = config.total_timesteps // steps_per_iter
    num_evals = config.total_timesteps // config.eval_every
    iters_per_eval = config.eval_every // steps_per_iter
    gamma, tau = float(config.gamma), float(config.tau)
    eps_start, eps_end = float(config.epsilon_start), float(config.epsilon_end)
    decay_steps = max(float(config.exploration_fraction) * config.total_timesteps, 1.0)
    n_step = config.n_step
    lr, opt_steps = float(config.learning_rate), max(num_iters * config.gradient_steps, 1)
    schedule = (lambda count: lr * (1.0 - jnp.minimum(count, opt_steps) / opt_steps)) if config.anneal_lr else lr
    tx = optax.chain(optax.clip_by_global_norm(float(config.max_grad_norm)), optax.adam(schedule))

    def n_step_items(window):
        """n-step transitions for the first T steps of a [T + n - 1, num_envs] window of one-step steps."""
        T = window["reward"].shape[0] - (n_step - 1)
        reward, discount = jnp.zeros_like(window["reward"][:T]), jnp.zeros_like(window["reward"][:T])
        next_obs, alive, scale = window["next_obs"][:T], jnp.ones_like(reward), jnp.ones_like(reward)
        for k in range(n_step):
            reward = reward + alive * scale * window["reward"][k : k + T]
            scale = scale * gamma
            next_obs = jnp.where(alive[..., None] > 0, window["next_obs"][k : k + T], next_obs)
            discount = jnp.where(alive > 0, scale * (1.0 - window["terminated"][k : k + T]), discount)
            alive = alive * (1.0 - window["done"][k : k + T])
        return {
            "obs": window["obs"][:T],
            "action": window["action"][:T],
            "reward": reward,
            "next_obs": next_obs,
            "discount": discount,
        }

    def train(key: jax.Array, cost: jax.Array) -> jax.Array:
        env_params = with_cost(base_params, cost)
        key, init_key, reset_key, eval_key = jax.random.split(key, 4)
        params = network.init(init_key, jnp.zeros((1, *obs_shape)))
        opt_state = tx.init(params)
        obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, num_envs), env_params)
        buffer = {
            "obs": jnp.zeros((config.buffer_size, *obs_shape), jnp.float32),
            "action": jnp.zeros(config.buffer_size, jnp.int32),
            "reward": jnp.zeros(config.buffer_size, jnp.float32),
            "next_obs": jnp.zeros((config.buffer_size, *obs_shape), jnp.float32),
            "discount": jnp.zeros(config.buffer_size, jnp.float32),
        }

        def loss_fn(params, target_params, batch):
            q = network.apply(params, batch["obs"])
            q_taken = jnp.take_along_axis(q, batch["action"][:, None], -1)[:, 0]
            q_next_target = network.apply(target_params, batch["next_obs"])
            if config.double_q:
                best = jnp.argmax(network.apply(params, batch["next_obs"]), -1)
            else:
                best = jnp.argmax(q_next_target, -1)
            q_next = jnp.take_along_axis(q_next_target, best[:, None], -1)[:, 0]
            target = batch["reward"] + batch["discount"] * q_next
            return optax.huber_loss(q_taken, jax.lax.stop_gradient(target)).mean()

        def make_env_step(params, eps):
            def env_step(carry, step_key):
                env_state, obs = carry
                explore_key, random_key, env_key = jax.random.split(step_key, 3)
                greedy = jnp.argmax(network.apply(params, obs), -1)
                random = jax.random.randint(random_key, (num_envs,), 0, num_actions)
                action = jnp.where(jax.random.uniform(explore_key, (num_envs,)) < eps, random, greedy)
                next_obs, env_state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                    jax.random.split(env_key, num_envs), env_state, action, env_params
                )
                step = {
                    "obs": obs,
                    "action": action,
                    "reward": reward,
                    "next_obs": info["final_observation"],
                    "terminated": terminated.astype(jnp.float32),
                    "done": (terminated | truncated).astype(jnp.float32),
                }
                return (env_state, next_obs), step

            return env_step

        # Prime the n-step window with n - 1 random steps per env (eps = 1; not counted as training steps).
        key, warmup_key = jax.random.split(key)
        (env_state, obs), pending = jax.lax.scan(
            make_env_step(params, 1.0), (env_state, obs), jax.random.split(warmup_key, n_step - 1)
        )

        def iteration(runner_state, _):
            params, target_params, opt_state, buffer, position, size, env_state, obs, pending, timesteps, key = (
                runner_state
            )
            key, rollout_key, learn_key = jax.random.split(key, 3)
            eps = eps_start + jnp.minimum(timesteps / decay_steps, 1.0) * (eps_end - eps_start)

            # 1. train_freq epsilon-greedy steps -> the n-step transitions of the first train_freq window steps.
            (env_state, obs), steps = jax.lax.scan(
                make_env_step(params, eps), (env_state, obs), jax.random.split(rollout_key, train_freq)
            )
            window = jax.tree.map(lambda p, x: jnp.concatenate([p, x]), pending, steps)
            items, pending = n_step_items(window), jax.tree.map(lambda x: x[train_freq:], window)

            # 2. Store them in the ring buffer.
            items = jax.tree.map(lambda x: x.reshape(steps_per_iter, *x.shape[2:]), items)
            buffer = jax.tree.map(
                lambda store, x: jax.lax.dynamic_update_slice_in_dim(store, x.astype(store.dtype), position, 0),
                buffer,
                items,
            )
            position = (position + steps_per_iter) % config.buffer_size
            size = jnp.minimum(size + steps_per_iter, config.buffer_size)
            new_timesteps = timesteps + steps_per_iter

            # 3. Gradient steps once learning has started.
            def learn(params, opt_state):
                def gradient_step(carry, sample_key):
                    params, opt_state = carry
                    index = jax.random.randint(sample_key, (config.batch_size,), 0, size)
                    batch = jax.tree.map(lambda store: store[index], buffer)
                    loss, grads = jax.value_and_grad(loss_fn)(params, target_params, batch)
                    updates, opt_state = tx.update(grads, opt_state, params)
                    return (optax.apply_updates(params, updates), opt_state), loss

                (params, opt_state), losses = jax.lax.scan(
                    gradient_step, (params, opt_state), jax.random.split(learn_key, config.gradient_steps)
                )
                return params, opt_state, losses.mean()

            learning = new_timesteps >= config.learning_starts
            params, opt_state, loss = jax.lax.cond(
                learning, learn, lambda p, o: (p, o, jnp.float32(0.0)), params, opt_state
            )

            # 4. Target network update each time target_update_interval env steps pass.
            sync = learning & (
                new_timesteps // config.target_update_interval != timesteps // config.target_update_interval
            )
            target_params = jax.lax.cond(
                sync, lambda: optax.incremental_update(params, target_params, tau), lambda: target_params
            )
            runner_state = (
                params,
                target_params,
                opt_state,
                buffer,
                position,
                size,
                env_state,
                obs,
                pending,
                new_timesteps,
                key,
            )
            return runner_state, loss

        def greedy_return(params, key):
            """Mean costed return of `eval_episodes` greedy episodes (each counted up to its first end)."""
            reset_key, run_key = jax.random.split(key)
            obs, state = jax.vmap(env.reset, in_axes=(0, None))(
                jax.random.split(reset_key, config.eval_episodes), env_params
            )

            def step(carry, step_key):
                obs, state, finished, total = carry
                action = jnp.argmax(network.apply(params, obs), -1)
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

        runner_state = (
            params,
            params,
            opt_state,
            buffer,
            jnp.int32(0),
            jnp.int32(0),
            env_state,
            obs,
            pending,
            jnp.int32(0),
            key,
        )
        if not evaluate:
            _, losses = jax.lax.scan(iteration, runner_state, None, num_iters)
            return losses

        def eval_period(runner_state, index):
            runner_state, _ = jax.lax.scan(iteration, runner_state, None, iters_per_eval)
            return runner_state, greedy_return(runner_state[0], jax.random.fold_in(eval_key, index))

        _, returns = jax.lax.scan(eval_period, runner_state, jnp.arange(num_evals))
        return returns

    return train


if __name__ == "__main__":
    # A short learning check: 8 seeds at cost 0.1 on the active-measure CartPole-v0.
    import time

    config = DQNConfig(total_timesteps=50_000, eval_every=5_000, buffer_size=50_000)  # amjax's DQN defaults
    train = jax.jit(jax.vmap(make_train(config)))
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    start = time.perf_counter()
    returns = jax.block_until_ready(train(keys, jnp.full(8, 0.1)))
    print(f"{time.perf_counter() - start:.1f} s (with compile); greedy costed return per evaluation (median):")
    print(jnp.median(returns, axis=0))
