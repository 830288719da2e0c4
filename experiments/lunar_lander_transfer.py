"""T4 (issue 5): train PPO only in amjax's JAX port of LunarLander-v3, then score it in real Gymnasium.

    python experiments/lunar_lander_transfer.py [--out runs/lunar_lander_transfer] [--seeds 0 1 2]
    python experiments/lunar_lander_transfer.py --eval-only docs/policies/lunar_lander_ppo.msgpack

1. Training (resumable: rerun the same command after an interruption) is amjax's own sweep runner on the plain
   env (`vanilla=True`), one vmapped program for all seeds; each seed's best greedy policy (chosen on the port's
   `--eval-episodes` test episodes at every evaluation) is saved to `<out>/policies/<config_id>.msgpack`.
2. The policy with the highest saved best return is evaluated greedily
   (a) in the JAX port over `--episodes` episodes (keys from `--port-key`, disjoint from training's), and
   (b) in Gymnasium's Box2D `LunarLander-v3` with `env.reset(seed=s)` for s = 0 .. episodes - 1.
   Both are printed as mean / std / min / fraction >= 200, with the gap (port - Gymnasium).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

from amjax.agents.saved import SavedPolicy, load_policy  # noqa: E402
from amjax.analysis.maps import record_agent  # noqa: E402
from amjax.presets import LUNAR_LANDER_PPO  # noqa: E402
from amjax.sweep import SweepSpec, run_sweep  # noqa: E402

ENV_ID = "LunarLander-v3"
SOLVED = 200.0

# PPO hyperparameters: the RL Baselines3 Zoo's tuned LunarLander entry (sources and details in amjax/presets.py).
# Differences that remain: amjax clips the value loss with clip_eps (SB3 does not by default), scales the rewards by
# 0.01 (since 2026-11-28; the committed policy was trained before, unscaled) and initialises with a scaled normal
# instead of orthogonal matrices (amjax/agents/networks.py).
HYPERPARAMS = LUNAR_LANDER_PPO
TOTAL_TIMESTEPS = 64 * 16 * 1024  # 1,048,576 (the Zoo's 1e6, rounded to whole updates)
EVAL_EVERY = 4 * 16 * 1024  # 16 evaluations


def make_spec(seeds: tuple[int, ...], eval_episodes: int) -> SweepSpec:
    return SweepSpec(
        envs=(ENV_ID,),
        agents=("ppo",),
        costs=(),
        vanilla=True,
        seeds=seeds,
        total_timesteps=TOTAL_TIMESTEPS,
        eval_every=EVAL_EVERY,
        eval_episodes=eval_episodes,
        hyperparams=HYPERPARAMS,
    )


def train(out: Path, seeds: tuple[int, ...], eval_episodes: int) -> Path:
    """Run (or resume) the sweep; returns the policy file with the highest best return over its seeds."""
    start = time.monotonic()
    result = run_sweep(make_spec(seeds, eval_episodes), out, target_chunks=8)
    print(f"training: {time.monotonic() - start:.0f} s wall in this process (resumed work excluded)")
    columns = ["config_id", "seed", "best_return", "best_env_steps", "final_return"]
    print(result.summary.sort_values("best_return", ascending=False)[columns].to_string(index=False))
    files = sorted((out / "policies").glob("*.msgpack"))
    if not files:
        raise FileNotFoundError(f"no policies under {out / 'policies'}")
    return max(files, key=lambda p: load_policy(p).info.get("best_return", -np.inf))


def port_returns(saved: SavedPolicy, episodes: int, key: int) -> np.ndarray:
    """Greedy raw returns of `episodes` episodes in the JAX port (one vmapped scan)."""
    return record_agent(saved.config, saved.params, jax.random.PRNGKey(key), episodes).raw_return


def make_gymnasium_env():
    """`gymnasium.make("LunarLander-v3")`. Without pygame, Gymnasium's box2d package (its CarRacing) cannot be
    imported, so the registered spec (TimeLimit 1000, order and passive checkers) is made with the class loaded
    from Gymnasium's lunar_lander.py file instead of its import path: the same env and wrappers."""
    import dataclasses

    import gymnasium
    from gymnasium.error import DependencyNotInstalled

    from amjax.envs.lunar_lander.reference import load_gymnasium_lunar_lander

    try:
        return gymnasium.make(ENV_ID)
    except DependencyNotInstalled:
        entry_point = load_gymnasium_lunar_lander().LunarLander
        return gymnasium.make(dataclasses.replace(gymnasium.spec(ENV_ID), entry_point=entry_point))


def gymnasium_returns(saved: SavedPolicy, seeds: range) -> np.ndarray:
    """Greedy returns in Gymnasium's Box2D LunarLander-v3, one episode per `env.reset(seed=s)`."""
    env = make_gymnasium_env()
    actor = saved.actor()
    returns = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        actor.reset()
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(actor(obs))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    env.close()
    return np.asarray(returns)


def describe(name: str, returns: np.ndarray) -> dict[str, float]:
    stats = {
        "mean": float(returns.mean()),
        "sem": float(returns.std(ddof=1) / np.sqrt(len(returns))),
        "std": float(returns.std()),
        "min": float(returns.min()),
        "solved": float((returns >= SOLVED).mean()),
    }
    print(
        f"{name:<22} n={len(returns):>4}  mean {stats['mean']:7.1f} ± {stats['sem']:4.1f} (s.e.)  "
        f"std {stats['std']:6.1f}  min {stats['min']:7.1f}  >= {SOLVED:.0f}: {100 * stats['solved']:5.1f} %"
    )
    return stats


def evaluate(path: Path, episodes: int, port_key: int) -> dict[str, dict[str, float]]:
    saved = load_policy(path)
    print(f"policy {path}: {json.dumps(saved.info)}")
    start = time.monotonic()
    port = describe("JAX port (amjax)", port_returns(saved, episodes, port_key))
    port_s = time.monotonic() - start
    start = time.monotonic()
    gym = describe("Gymnasium (Box2D)", gymnasium_returns(saved, range(episodes)))
    print(
        f"gap (port - Gymnasium): mean {port['mean'] - gym['mean']:+.1f}, "
        f">= {SOLVED:.0f} {100 * (port['solved'] - gym['solved']):+.1f} pp  "
        f"(eval wall: port {port_s:.0f} s incl. compile, Gymnasium {time.monotonic() - start:.0f} s)"
    )
    return {"port": port, "gymnasium": gym}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/lunar_lander_transfer"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--eval-episodes", type=int, default=64, help="port test episodes per training evaluation")
    parser.add_argument("--episodes", type=int, default=100, help="episodes (Gymnasium seeds 0..N-1) in the final test")
    parser.add_argument("--port-key", type=int, default=12345, help="PRNGKey of the final port evaluation")
    parser.add_argument("--eval-only", type=Path, metavar="POLICY_FILE", help="skip training; evaluate this file")
    args = parser.parse_args()
    path = args.eval_only or train(args.out, tuple(args.seeds), args.eval_episodes)
    evaluate(path, args.episodes, args.port_key)


if __name__ == "__main__":
    main()
