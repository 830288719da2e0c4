"""What the benchmark runs: the implementations, the step rules, one dict per case, and a case's agent config."""

from __future__ import annotations

import argparse
import math
from typing import Any

COSTS = (0.1, 0.2, 0.3)  # cycled over the configurations of an active-measure case
ENV_ID = "CartPole-v0"
MAX_EPISODE_STEPS = 200  # CartPole-v0; an evaluation scans this many steps whatever the episodes do
TRANSITION_BYTES = 52  # obs + next_obs (5 float32 each with the flag) + action + reward + discount
IMPLS = ("amjax", "amjax-vanilla", "reference", "reference-vanilla")
IMPL_LABELS = {
    "amjax": "amjax",
    "amjax-vanilla": "amjax-vanilla-env",
    "reference": "plain reference",
    "reference-vanilla": "plain reference, vanilla env",
    "amjax-sb3": "amjax, SB3 DQN hyperparameters",
    "amjax-buffer": "amjax (buffer scan)",
    "overhead": "amjax, active vs vanilla env interleaved",
    "sb3": "SB3",
}
# Steps per configuration: min(max, max(min, budget // configs)), rounded to a multiple of evals x steps per
# update. On 2 quiet cores that is about 1-30 s (PPO) and 3-50 s (DQN) of run time per case.
STEP_RULES = {
    "ppo": {"max": 102_400, "min": 5_120, "budget": 2_621_440},
    "dqn": {"max": 50_000, "min": 2_500, "budget": 1_280_000},
}
QUICK_STEP_RULES = {
    "ppo": {"max": 10_240, "min": 5_120, "budget": 20_480},
    "dqn": {"max": 2_000, "min": 1_000, "budget": 4_000},
}
# Stable-Baselines3 2.x DQN defaults, as amjax DQNConfig fields (plain DQN: no dueling, no double-Q).
SB3_DQN = {
    "learning_rate": 1e-4,
    "buffer_size": 1_000_000,
    "learning_starts": 100,
    "batch_size": 32,
    "tau": 1.0,
    "gamma": 0.99,
    "train_freq": 4,
    "gradient_steps": 1,
    "target_update_interval": 10_000,
    "exploration_fraction": 0.1,
    "epsilon_start": 1.0,
    "epsilon_end": 0.05,
    "max_grad_norm": 10.0,
    "hidden": (64, 64),
    "activation": "relu",
    "dueling": False,
    "double_q": False,
    "n_step": 1,  # one-step targets
    "anneal_lr": False,  # constant learning rate
    "num_envs": 1,
}


def agent_config(case: dict[str, Any], cost: float):
    """The amjax config (not yet validated) one configuration of the case trains with."""
    from amjax.agents import DQNConfig, PPOConfig

    steps = case["steps"]
    kwargs: dict[str, Any] = {
        "env_id": case.get("env_id", ENV_ID),
        "total_timesteps": steps,
        "eval_every": steps // case["evals"],
        "eval_episodes": case["eval_episodes"],
        "vanilla": case["vanilla"],
        "cost": cost,
    }
    if case["agent"] == "ppo":
        return PPOConfig(**kwargs)
    if case.get("hparams") == "sb3":
        kwargs.update(SB3_DQN)
    kwargs["buffer_size"] = case["buffer"]
    return DQNConfig(**kwargs)


def costs(case: dict[str, Any]) -> list[float]:
    """The cost of each configuration: COSTS in turn, or 0 on the vanilla env."""
    return [0.0 if case["vanilla"] else COSTS[i % len(COSTS)] for i in range(case["configs"])]


def _steps_per_update(agent: str, hparams: str = "default") -> int:
    from amjax.agents import DQNConfig, PPOConfig

    if agent == "ppo":
        return PPOConfig().steps_per_update()
    return (DQNConfig(**SB3_DQN) if hparams == "sb3" else DQNConfig()).steps_per_update()


def _round_steps(steps: int, unit: int) -> int:
    return max(unit, round(steps / unit) * unit)


def _parse_steps(text: str | None) -> dict[int, int] | int | None:
    if text is None:
        return None
    if ":" not in text:
        return int(text)
    return {int(k): int(v) for k, v in (item.split(":") for item in text.split(","))}


def _budget_steps(rule: dict[str, int], configs: int) -> int:
    """Steps per configuration by a STEP_RULES entry: the budget shared out, clipped to [min, max]."""
    return min(rule["max"], max(rule["min"], rule["budget"] // configs))


def _default_buffer(steps: int, unit: int) -> int:
    """min(DQNConfig's default buffer, the steps of one run), a multiple of the steps per update."""
    from amjax.agents import DQNConfig

    return min(DQNConfig().buffer_size, math.ceil(steps / unit) * unit)


def _common(args: argparse.Namespace) -> dict[str, Any]:
    """The fields every case shares."""
    return {
        "evals": args.evals,
        "eval_episodes": args.eval_episodes,
        "reference_eval": not args.no_reference_eval,
        "target_chunks": args.target_chunks,
        "sb3_threads": args.sb3_threads,
        "repeats": args.repeats,
        "cores": args.cores,
    }


def _size_steps(args: argparse.Namespace, agent: str, size: int) -> int:
    """Steps per configuration at a size: --steps if it names one, else the step rule; rounded."""
    steps_arg = _parse_steps(args.steps)
    if isinstance(steps_arg, int):
        steps = steps_arg
    elif isinstance(steps_arg, dict) and size in steps_arg:
        steps = steps_arg[size]
    else:
        steps = _budget_steps((QUICK_STEP_RULES if args.quick else STEP_RULES)[agent], size)
    return _round_steps(steps, args.evals * _steps_per_update(agent))


def _table_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The table's cases: agents x sizes x --impls."""
    cases = []
    for agent in args.agents:
        for size in args.sizes:
            steps = _size_steps(args, agent, size)
            for impl in args.impls:
                case = {
                    "impl": impl,
                    "agent": agent,
                    "configs": size,
                    "steps": steps,
                    "vanilla": impl.endswith("vanilla"),
                    **_common(args),
                }
                if agent == "dqn":
                    case["buffer"] = args.buffer or _default_buffer(steps, _steps_per_update(agent))
                cases.append(case)
    return cases


def _sb3_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    """SB3's DQN and PPO (1 env, defaults), and amjax DQN with SB3's DQN hyperparameters."""
    if not args.sb3:
        return []
    common, cases = _common(args), []
    if "dqn" in args.agents:
        steps = _round_steps(args.sb3_steps, args.evals * _steps_per_update("dqn", "sb3"))
        cases.append(
            {
                "impl": "sb3",
                "agent": "dqn",
                "configs": 1,
                "steps": steps,
                "vanilla": True,
                "buffer": SB3_DQN["buffer_size"],
                **common,
            }
        )
        cases.append(
            {
                "impl": "amjax-sb3",
                "agent": "dqn",
                "configs": args.sb3_configs,
                "steps": steps,
                "vanilla": False,
                "hparams": "sb3",
                "buffer": args.sb3_buffer,
                **common,
            }
        )
    if "ppo" in args.agents:
        cases.append({"impl": "sb3", "agent": "ppo", "configs": 1, "steps": args.sb3_steps, "vanilla": True, **common})
    return cases


def _overhead_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The interleaved active-vs-vanilla cases, training only."""
    rules = QUICK_STEP_RULES if args.quick else STEP_RULES
    cases = []
    for agent in args.agents:
        for size in args.overhead:
            steps = _round_steps(_budget_steps(rules[agent], size), _steps_per_update(agent))
            case = {
                "impl": "overhead",
                "agent": agent,
                "configs": size,
                "steps": steps,
                "vanilla": False,
                **_common(args),
            }
            # Training only: one evaluation of one episode at the end, so the env and the learner are what is timed.
            case.update(evals=1, eval_episodes=1, repeats=args.overhead_rounds)
            if agent == "dqn":
                case["buffer"] = args.buffer or _default_buffer(steps, _steps_per_update(agent))
            cases.append(case)
    return cases


def _buffer_scan_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    """amjax DQN at each --buffer-scan capacity."""
    steps = _round_steps(args.buffer_scan_steps, args.evals * _steps_per_update("dqn")) if args.buffer_scan else 0
    return [
        {
            "impl": "amjax-buffer",
            "agent": "dqn",
            "configs": args.buffer_scan_configs,
            "steps": steps,
            "vanilla": False,
            "buffer": _round_steps(buffer, _steps_per_update("dqn")),
            **_common(args),
        }
        for buffer in args.buffer_scan
    ]


def build_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every case the arguments ask for, in the order they run."""
    return _table_cases(args) + _sb3_cases(args) + _overhead_cases(args) + _buffer_scan_cases(args)
