"""LunarLander-v3 port vs Gymnasium: free-flight replay (T2), heuristic statistics (T3), speed.

    python experiments/lunar_lander_stats.py                  # T2 200 seeds, T3 1000 episodes
    python experiments/lunar_lander_stats.py --episodes 100 --replay-seeds 20   # quick look

Needs ``box2d==2.3.10`` for the Gymnasium reference. Prints a markdown report (the numbers in
docs/lunar_lander.md come from this script).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from amjax.envs.lunar_lander import EnvParams, LunarLander, heuristic_action
from amjax.envs.lunar_lander.reference import free_flight_replay, load_gymnasium_lunar_lander

MAX_STEPS = 1000


def t2_replay(n_seeds: int, **solver: bool) -> dict[str, float]:
    """Free flight on Gymnasium's recorded draws, random actions, until first ground contact."""
    obs_max, rew_max, steps = [], [], 0
    for seed in range(n_seeds):
        out = free_flight_replay(seed, **solver)
        obs_max.append(out["obs_diff"].max())
        rew_max.append(out["reward_diff"].max(initial=0.0))
        steps += len(out["reward_diff"])
    return {
        "seeds": n_seeds,
        "steps": steps,
        "max_obs_diff": float(np.max(obs_max)),
        "max_reward_diff": float(np.max(rew_max)),
    }


def gymnasium_heuristic(n_episodes: int) -> dict[str, np.ndarray]:
    """Gymnasium's own heuristic() on seeds 0..n-1, with the v3 1000-step limit."""
    module = load_gymnasium_lunar_lander()
    env = module.LunarLander()
    returns, outcome, length = [], [], []
    for seed in range(n_episodes):
        obs, _ = env.reset(seed=seed)
        total, kind = 0.0, "timeout"
        t = 0
        for t in range(MAX_STEPS):  # noqa: B007
            obs, reward, terminated, _, _ = env.step(module.heuristic(env, obs))
            total += reward
            if terminated:
                kind = "landed" if not env.lander.awake else "crashed"
                break
        returns.append(total)
        outcome.append(kind)
        length.append(t + 1)
    return {"return": np.array(returns), "outcome": np.array(outcome), "length": np.array(length)}


def jax_heuristic(n_episodes: int, seed: int = 0, **solver: bool) -> dict[str, np.ndarray]:
    """The same controller in the port, all episodes vmapped, no auto-reset."""
    env = LunarLander(**solver)
    params = EnvParams()
    step = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))
    policy = jax.vmap(heuristic_action)

    @jax.jit
    def run(key: jax.Array):
        k_reset, k_run = jax.random.split(key)
        obs, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(k_reset, n_episodes), params)
        zeros = jnp.zeros(n_episodes)
        carry = (
            obs,
            state,
            jnp.zeros(n_episodes, bool),
            zeros,
            zeros.astype(jnp.int32),
            jnp.zeros(n_episodes, jnp.int32),
            k_run,
            jnp.int32(0),
        )

        def cond(c):
            return (c[7] < MAX_STEPS) & ~jnp.all(c[2])

        def body(c):
            obs, state, done, ret, length, kind, key, t = c
            key, sub = jax.random.split(key)
            obs2, state2, reward, term, info = step(jax.random.split(sub, n_episodes), state, policy(obs), params)
            trunc = state2.time >= MAX_STEPS
            active = ~done
            ret = ret + jnp.where(active, reward, 0.0)
            length = length + active
            new_kind = jnp.where(term, jnp.where(info["landed"], 1, 2), jnp.where(trunc, 3, 0))
            kind = jnp.where(active, new_kind, kind)
            freeze = lambda new, old: jnp.where(  # noqa: E731
                done.reshape(done.shape + (1,) * (new.ndim - 1)), old, new
            )
            state = jax.tree.map(freeze, state2, state)
            obs = freeze(obs2, obs)
            return obs, state, done | term | trunc, ret, length, kind, key, t + 1

        out = jax.lax.while_loop(cond, body, carry)
        return out[3], out[5], out[4]

    ret, kind, length = jax.device_get(run(jax.random.PRNGKey(seed)))
    names = np.array(["running", "landed", "crashed", "timeout"])
    return {"return": np.asarray(ret), "outcome": names[np.asarray(kind)], "length": length}


def throughput(n_envs: int = 1024, n_steps: int = 100, **solver: bool) -> float:
    """Steps/s of env.step (gymnax auto-reset), vmapped over n_envs, random actions."""
    env = LunarLander(**solver)
    params = env.default_params
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), n_envs), params)

    @jax.jit
    def roll(state, key):
        def body(state, k):
            ks = jax.random.split(k, n_envs + 1)
            action = jax.random.randint(ks[0], (n_envs,), 0, 4)
            _, state, reward, _, _, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(ks[1:], state, action, params)
            return state, reward

        return jax.lax.scan(body, state, jax.random.split(key, n_steps))

    jax.block_until_ready(roll(state, jax.random.PRNGKey(1)))
    start = time.perf_counter()
    jax.block_until_ready(roll(state, jax.random.PRNGKey(2)))
    return n_envs * n_steps / (time.perf_counter() - start)


def summary(name: str, res: dict[str, np.ndarray]) -> dict[str, float]:
    n = len(res["return"])
    row = {
        "env": name,
        "episodes": n,
        "mean_return": float(res["return"].mean()),
        "stderr": float(res["return"].std(ddof=1) / np.sqrt(n)),
        "mean_length": float(np.mean(res["length"])),
    }
    for kind in ("landed", "crashed", "timeout"):
        row[kind] = float(np.mean(res["outcome"] == kind) * 100)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--replay-seeds", type=int, default=200)
    parser.add_argument("--throughput-envs", type=int, default=1024)
    parser.add_argument(
        "--exact-free-flight",
        action="store_true",
        help="the port's LunarLander(exact_free_flight=True) instead of Box2D's sweeps everywhere",
    )
    parser.add_argument(
        "--jump-sweeps",
        action="store_true",
        help="the port's LunarLander(jump_sweeps=True) instead of Box2D's sweeps everywhere",
    )
    args = parser.parse_args()
    solver = {"exact_free_flight": args.exact_free_flight, "jump_sweeps": args.jump_sweeps}

    if args.replay_seeds > 0:
        start = time.perf_counter()
        t2 = t2_replay(args.replay_seeds, **solver)
        print(f"## T2 free-flight replay ({time.perf_counter() - start:.0f} s)\n")
        print(
            f"{t2['seeds']} seeds, {t2['steps']} steps compared before Gymnasium's first "
            f"contact: max |obs diff| = {t2['max_obs_diff']:.2e}, "
            f"max |reward diff| = {t2['max_reward_diff']:.2e}\n"
        )

    start = time.perf_counter()
    rows = [summary("Gymnasium (Box2D)", gymnasium_heuristic(args.episodes))]
    t_gym = time.perf_counter() - start
    start = time.perf_counter()
    rows.append(summary("amjax (JAX)", jax_heuristic(args.episodes, **solver)))
    t_jax = time.perf_counter() - start
    print(f"## T3 heuristic controller (Gymnasium {t_gym:.0f} s, JAX {t_jax:.0f} s incl. compile)\n")
    print("| env | episodes | mean return (± s.e.) | landed % | crashed % | timeout % | mean length |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['env']} | {r['episodes']} | {r['mean_return']:.1f} ± {r['stderr']:.1f} | "
            f"{r['landed']:.1f} | {r['crashed']:.1f} | {r['timeout']:.1f} | "
            f"{r['mean_length']:.0f} |"
        )
    gym_row, jax_row = rows
    diffs = {k: jax_row[k] - gym_row[k] for k in ("mean_return", "landed", "crashed", "timeout")}
    ok = abs(diffs["mean_return"]) <= 10 and all(abs(diffs[k]) <= 5 for k in ("landed", "crashed", "timeout"))
    print(
        f"\ndifferences (JAX - Gymnasium): return {diffs['mean_return']:+.1f}, landed "
        f"{diffs['landed']:+.1f} pp, crashed {diffs['crashed']:+.1f} pp, timeout "
        f"{diffs['timeout']:+.1f} pp -> {'PASS' if ok else 'FAIL'} (targets ±10, ±5 pp)\n"
    )

    sps = throughput(args.throughput_envs, **solver)
    print(
        f"## Throughput\n\nenv.step with auto-reset, vmapped over {args.throughput_envs} envs, "
        f"{jax.devices()[0].platform}: {sps:,.0f} steps/s"
    )


if __name__ == "__main__":
    main()
