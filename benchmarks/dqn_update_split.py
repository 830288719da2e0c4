"""Where a Dueling DQN update of `amjax replicate` spends its time: env stepping or gradient steps.

One core, the per-core share of the replicate's costed DQN batch (`--configs`, default 20 = 40 configurations over
2 cores), steady state (`--updates` updates in one compiled `lax.scan`, after a warm-up call):

- full update: act, step `train_freq` times, n-step transitions, buffer write, gradient step, target update;
- without the gradient step: the same update before `learning_starts` (a real branch: no gradient is computed);
- rollout alone: the same `rollout` with uniform random actions, nothing else carried;
- the env alone: the configuration's wrapped training envs stepped as many times, in a plain `lax.scan`.

`--layouts 1x4 2x2 4x1` also times the full update with other envs per configuration x steps per env between
gradient steps (the same env steps per gradient step: the replay ratio).

    taskset -c 0 python benchmarks/dqn_update_split.py                       # LunarLander-v3, 20 configurations
    taskset -c 0 python benchmarks/dqn_update_split.py --layouts 1x4 2x2    # the preset's 4x1 against these
    taskset -c 0 python benchmarks/dqn_update_split.py --env Acrobot-v1
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax
import jax.numpy as jnp

from amjax.agents import ALGORITHMS, stack_configs
from amjax.agents.rollout import fast_key, rollout
from amjax.sweep.grid import expand
from train.presets import replicate_specs


def seconds(fn, *args) -> float:
    """The fastest of three calls of the compiled `fn` (after one warm-up call). The second argument (the train
    state or envs) is donated, as the sweep's chunk program donates it, and copied afresh before each call."""
    compiled = jax.jit(fn, donate_argnums=1).lower(*args).compile()
    fresh = lambda: (args[0], jax.tree.map(jnp.copy, args[1]), *args[2:])  # noqa: E731
    jax.block_until_ready(compiled(*fresh()))
    times = []
    for _ in range(3):
        call_args = jax.block_until_ready(fresh())
        start = time.perf_counter()
        jax.block_until_ready(compiled(*call_args))
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="LunarLander-v3")
    parser.add_argument("--configs", type=int, default=20, help="configurations on this core")
    parser.add_argument("--updates", type=int, default=512, help="updates per timed call")
    parser.add_argument(
        "--layouts",
        nargs="*",
        default=[],
        metavar="ENVSxFREQ",
        help="also time the full update with these envs per configuration x steps per env between "
        "gradient steps (e.g. 1x4 4x1: the same 4 env steps per gradient step)",
    )
    args = parser.parse_args()
    # The env-alone case returns a scalar, so its donated envs are not reused; nothing to warn about.
    warnings.filterwarnings("ignore", message="Some donated buffers were not usable")

    algo = ALGORITHMS["dqn"]
    spec = replicate_specs((args.env,), ("dqn",))[args.env]
    configs = [run.config for run in expand(spec) if not run.config.vanilla][: args.configs]
    if configs[0].learning_starts == 0:
        raise SystemExit("learning_starts is 0: no update of this batch skips the gradient step")
    split(algo, args, configs, all_cases=True)
    for layout in args.layouts:
        num_envs, train_freq = (int(part) for part in layout.split("x"))
        split(algo, args, [c.replace(num_envs=num_envs, train_freq=train_freq) for c in configs], all_cases=False)


def split(algo, args, configs, all_cases: bool) -> None:
    """Time the cases for `configs` (all four, or the full update alone) and print them."""
    stacked = stack_configs(configs)
    keys = jnp.stack([jax.random.PRNGKey(i) for i in range(len(configs))])
    state = jax.jit(jax.vmap(lambda c, k: algo.init(c, algo.setup(c), k)))(stacked, keys)
    # Past learning_starts, with a full buffer: the steady state of a long run.
    state = state.replace(
        env_steps=state.env_steps + 10 * configs[0].learning_starts,
        buffer=state.buffer.replace(size=jnp.full_like(state.buffer.size, state.buffer.capacity)),
    )
    updates, per_update = args.updates, configs[0].steps_per_update()

    def full(config, state):
        setup = algo.setup(config)
        return jax.lax.scan(lambda s, _: (algo.update(config, setup, s)[0], None), state, None, updates)[0]

    def without_gradient(config, state):
        setup = algo.setup(config)

        def body(s, _):
            new, _ = algo.update(config, setup, s.replace(env_steps=jnp.zeros_like(s.env_steps)))
            return new.replace(env_steps=s.env_steps), None

        return jax.lax.scan(body, state, None, updates)[0]

    def random_rollout(config, envs, key):
        setup = algo.setup(config)

        def act(batch, carry, key):
            return jax.random.randint(key, batch.first.shape, 0, setup.num_actions), carry, None

        def body(envs, key):
            envs, _, transitions, _, _ = rollout(setup.env, setup.env_params, envs, None, act, key, config.train_freq)
            return envs, transitions.reward.sum()

        return jax.lax.scan(body, envs, jax.random.split(fast_key(key), updates))

    def env_alone(config, envs, key):
        setup = algo.setup(config)
        step = jax.vmap(setup.env.step, (0, 0, 0, None))  # the configuration's num_envs envs

        def body(state, key):
            action_key, step_key = jax.random.split(key)
            action = jax.random.randint(action_key, (config.num_envs,), 0, setup.num_actions)
            _, state, reward, *_ = step(jax.random.split(step_key, config.num_envs), state, action, setup.env_params)
            return state, reward.sum()

        steps = updates * config.train_freq
        return jax.lax.scan(body, envs.state, jax.random.split(fast_key(key), steps))[1].sum()

    cases = {"full update": seconds(jax.vmap(full), stacked, state)}
    if all_cases:
        cases |= {
            "without the gradient step": seconds(jax.vmap(without_gradient), stacked, state),
            "rollout alone (random actions)": seconds(jax.vmap(random_rollout), stacked, state.envs, keys),
            "the env alone": seconds(jax.vmap(env_alone), stacked, state.envs, keys),
        }
    steps = len(configs) * updates * per_update
    print(
        f"{args.env} Dueling DQN, {len(configs)} configurations on one core, {updates} updates of "
        f"{configs[0].num_envs} envs x {configs[0].train_freq} steps each ({jax.devices()[0].device_kind})"
    )
    print(f"{'case':<32} {'ms / update':>12} {'share':>7} {'env-steps/s':>12}")
    for name, secs in cases.items():
        print(f"{name:<32} {secs / updates * 1e3:>12.3f} {secs / cases['full update']:>7.0%} {steps / secs:>12,.0f}")


if __name__ == "__main__":
    main()
