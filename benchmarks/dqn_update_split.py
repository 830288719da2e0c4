"""Where a Dueling DQN update of `amjax replicate` spends its time: env stepping or gradient steps.

One core, the per-core share of the replicate's costed DQN batch (`--configs`, default 20 = 40 configurations over
2 cores), steady state (`--updates` updates in one compiled `lax.scan`, after a warm-up call):

- full update: act, step `train_freq` times, n-step transitions, buffer write, gradient step, target update;
- without the gradient step: the same update before `learning_starts` (a real branch: no gradient is computed);
- rollout alone: the same `rollout` with uniform random actions, nothing else carried;
- the env alone: the configuration's wrapped training envs stepped as many times, in a plain `lax.scan`.

`--layouts 1x4 2x2 4x1` also times the full update with other envs per configuration x steps per env between
gradient steps (the same env steps per gradient step: the replay ratio).

The four parts of one update are timed one after the other in the same child process, on the same train state and
stacked configurations (they are compared with each other: their share of the full update); each layout is a child
process of its own (`benchmarks.harness.run_child`), with its own peak resident memory.

    taskset -c 0 python benchmarks/dqn_update_split.py                       # LunarLander-v3, 20 configurations
    taskset -c 0 python benchmarks/dqn_update_split.py --layouts 1x4 2x2    # the preset's 4x1 against these
    taskset -c 0 python benchmarks/dqn_update_split.py --env Acrobot-v1
    python benchmarks/dqn_update_split.py --env CartPole-v0 --configs 1 --updates 1 --out /tmp/split.jsonl  # smoke

Results: `benchmarks/results/dqn_update_split_<date>_<machine>.jsonl` (`--out`), the markdown table beside it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

PARTS = ("full update", "without the gradient step", "rollout alone (random actions)", "the env alone")


def seconds(fn, *args) -> float:
    """The fastest of three calls of the compiled `fn` (after one warm-up call). The second argument (the train
    state or envs) is donated, as the sweep's chunk program donates it, and copied afresh before each call."""
    import time

    import jax
    import jax.numpy as jnp

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


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """In a child: time the parts of one layout's update (all four, or the full update alone)."""
    import warnings

    from amjax.agents import ALGORITHMS
    from amjax.sweep.grid import expand
    from train.presets import replicate_specs

    # The env-alone case returns a scalar, so its donated envs are not reused; nothing to warn about.
    warnings.filterwarnings("ignore", message="Some donated buffers were not usable")
    algo = ALGORITHMS["dqn"]
    spec = replicate_specs((case["env"],), ("dqn",))[case["env"]]
    configs = [run.config for run in expand(spec) if not run.config.vanilla][: case["configs"]]
    if case["layout"]:
        num_envs, train_freq = (int(part) for part in case["layout"].split("x"))
        configs = [c.replace(num_envs=num_envs, train_freq=train_freq) for c in configs]
    elif configs[0].learning_starts == 0:
        raise SystemExit("learning_starts is 0: no update of this batch skips the gradient step")
    return split(algo, configs, case["updates"], all_parts=not case["layout"])


def split(algo, configs, updates: int, all_parts: bool) -> dict[str, Any]:
    """Time the parts for `configs` (all four, or the full update alone)."""
    import jax
    import jax.numpy as jnp

    from amjax.agents import stack_configs
    from amjax.agents.rollout import fast_key, rollout

    stacked = stack_configs(configs)
    keys = jnp.stack([jax.random.PRNGKey(i) for i in range(len(configs))])
    state = jax.jit(jax.vmap(lambda c, k: algo.init(c, algo.setup(c), k)))(stacked, keys)
    # Past learning_starts, with a full buffer: the steady state of a long run.
    state = state.replace(
        env_steps=state.env_steps + 10 * configs[0].learning_starts,
        buffer=state.buffer.replace(size=jnp.full_like(state.buffer.size, state.buffer.capacity)),
    )

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

    parts = {"full update": seconds(jax.vmap(full), stacked, state)}
    if all_parts:
        parts |= {
            "without the gradient step": seconds(jax.vmap(without_gradient), stacked, state),
            "rollout alone (random actions)": seconds(jax.vmap(random_rollout), stacked, state.envs, keys),
            "the env alone": seconds(jax.vmap(env_alone), stacked, state.envs, keys),
        }
    return {
        "configurations": len(configs),
        "num_envs": configs[0].num_envs,
        "train_freq": configs[0].train_freq,
        "env_steps_per_call": len(configs) * updates * configs[0].steps_per_update(),
        "device_kind": jax.devices()[0].device_kind,
        "seconds": {name: round(secs, 6) for name, secs in parts.items()},
    }


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, each part of an update against the full update of the
    same layout (its share)."""
    out = []
    for run in runs:
        settings, results = run["settings"], [r for r in run["cases"] if r["status"] == "ok"]
        rows = [
            {
                **r,
                "part": part,
                "s": secs,
                "ms": secs / settings["updates"] * 1e3,
                "share": secs / r["seconds"]["full update"],
            }
            for r in results
            for part, secs in r["seconds"].items()
        ]
        configs = results[0]["configurations"] if results else settings["configs"]
        memory = "; ".join(f"{r['num_envs']} x {r['train_freq']}: {r['peak_rss_mib']:,} MiB" for r in results)
        out.append(
            f"# Where a Dueling DQN update spends its time ({run['date'][:10]})\n\n"
            f"{settings['env']} Dueling DQN of `amjax replicate`'s costed batch, {configs} configurations "
            f"on one CPU device, {settings['updates']} updates in one compiled `lax.scan` per timed call (the fastest "
            "of three, after a warm-up call); the first layout is the preset's, with all four parts of an update timed "
            "in one child process, each other layout (`--layouts`) its full update alone in a child of its own. "
            f"Share: of the same layout's full update. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                rows,
                [
                    ("envs x steps/env", lambda r: f"{r['num_envs']} x {r['train_freq']}"),
                    ("case", lambda r: r["part"]),
                    ("ms / update", lambda r: round(r["ms"], 3)),
                    ("share (%)", lambda r: round(100 * r["share"])),
                    ("env steps/s", lambda r: round(r["env_steps_per_call"] / r["s"])),
                ],
            )
            + (f"\nPeak resident memory of each child: {memory}.\n" if results else "")
            + "".join(f"\n{r['layout'] or 'preset'}: {r['status']}\n" for r in run["cases"] if r["status"] != "ok")
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
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
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/dqn_update_split_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        harness.child_result(run_case(json.loads(args.child)))
        return 0
    for layout in args.layouts:
        parts = layout.split("x")
        if len(parts) != 2 or not all(part.isdigit() and int(part) > 0 for part in parts):
            parser.error(f"--layouts: {layout!r}; expected ENVSxFREQ, e.g. 1x4")

    cases = [
        {"env": args.env, "configs": args.configs, "updates": args.updates, "layout": layout}
        for layout in [None, *args.layouts]
    ]
    harness.run_cases("dqn_update_split", harness.settings_of(args), args.out, __file__, cases, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
