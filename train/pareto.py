"""`python -m train pareto`: one cost-conditioned agent per seed for a whole range of costs, its front, and per-cost
specialists beside it.

Two resumable sweeps in OUT: `conditioned/` (each episode's cost drawn from [0, --cost-high] and observed; 1.5x one
specialist's env steps, rounded down to whole evaluation periods) and `specialists/` (an ordinary sweep at
--specialist-costs, the env's replication budget; the costs must lie in [0, --cost-high], where the conditioned
agent trained). Then every conditioned policy is scored at the cost grid on 100 fresh episodes: OUT/front.csv
(every point), OUT/table.md (conditioned vs specialists at their costs, medians over seeds) and OUT/front.png.
Rerunning the command resumes the sweeps.
"""

from __future__ import annotations

import argparse
from typing import Any

from amjax.agents.registry import agent_list

PROG = "python -m train pareto"
STEPS_FACTOR = 1.5  # the conditioned run's env steps, at most this many times one specialist's


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "pareto",
        help="one cost-conditioned agent per seed: the cost front, with per-cost specialists",
        description=" ".join(__doc__.split("\n\n")[0].split()),
    )
    parser.add_argument("--env", default="CartPole-v0", help="environment id (default: CartPole-v0)")
    parser.add_argument(
        "--agent", nargs="+", default=["dqn", "ppo"], metavar="AGENT", help=f"agents (default: dqn ppo): {agent_list()}"
    )
    parser.add_argument("--seeds", type=int, metavar="N", help="seeds 0..N-1 (default: 5)")
    parser.add_argument("--seed-list", nargs="+", type=int, metavar="S", help="explicit seeds instead")
    parser.add_argument(
        "--cost-high", type=float, default=0.5, help="costs are drawn from [0, COST_HIGH] (default: 0.5)"
    )
    parser.add_argument(
        "--grid-step", type=float, default=0.05, help="the front's cost grid: 0, STEP, ..., COST_HIGH (default: 0.05)"
    )
    parser.add_argument(
        "--specialist-costs",
        nargs="*",
        type=float,
        default=[0.1, 0.2, 0.3],
        metavar="C",
        help="costs of the per-cost specialists, in [0, COST_HIGH]; none: skip them (default: 0.1 0.2 0.3)",
    )
    parser.add_argument("--steps", type=int, help="a specialist's env steps (default: the env's replication budget)")
    parser.add_argument("--eval-every", type=int, help="env steps between evaluations (default: the env's)")
    parser.add_argument("--out", required=True, help="output folder (rerun to resume)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return parser


def _specs(args: argparse.Namespace) -> tuple[Any, Any, list[float]]:
    """The conditioned and specialist sweeps and the cost grid, checked before anything runs."""
    from amjax.presets import env_hyperparams
    from amjax.sweep import SweepSpec, expand
    from amjax.sweep.grid import round_schedule
    from amjax.validation import check_positive_int, check_real
    from train.presets import QUICK_BUDGETS, REPLICATE_BUDGETS

    if args.seeds is not None and args.seed_list:
        raise ValueError("--seeds and --seed-list: give one of them")
    count = check_positive_int("--seeds", 5 if args.seeds is None else args.seeds)
    seeds = tuple(args.seed_list) if args.seed_list else tuple(range(count))
    high = float(check_real("--cost-high", args.cost_high, low=0.0, low_inclusive=False))
    step = float(check_real("--grid-step", args.grid_step, low=0.0, high=high, low_inclusive=False))
    for cost in args.specialist_costs:
        check_real("--specialist-costs", cost, low=0.0)
        if cost > high:  # the conditioned agent would be scored at a cost it never trained on
            raise ValueError(
                f"--specialist-costs: got {cost:g}, above --cost-high {high:g}; the conditioned agent "
                f"trains on costs in [0, {high:g}] and is compared with each specialist at its cost; "
                f"allowed values: costs in [0, {high:g}] (or raise --cost-high)"
            )
    steps, every = REPLICATE_BUDGETS.get(args.env, QUICK_BUDGETS.get(args.env, (153_600, 10_240)))
    steps = steps if args.steps is None else check_positive_int("--steps", args.steps)
    every = every if args.eval_every is None else check_positive_int("--eval-every", args.eval_every)
    agents = tuple(args.agent)
    common = {
        "envs": (args.env,),
        "agents": agents,
        "seeds": seeds,
        "eval_every": every,
        "env_defaults": {args.env: env_hyperparams(args.env, agents)},
    }
    specialists, _ = round_schedule(
        SweepSpec(**common, costs=tuple(args.specialist_costs) or (0.1,), total_timesteps=steps)
    )
    every = specialists.eval_every
    conditioned_steps = max(every, int(STEPS_FACTOR * specialists.total_timesteps) // every * every)
    conditioned = SweepSpec(
        **{**common, "eval_every": every},
        costs=(0.0,),
        total_timesteps=conditioned_steps,
        hyperparams={"cost_conditioned": True, "cost_high": high},
    )
    expand(conditioned)
    expand(specialists)
    grid = {round(step * i, 6) for i in range(int(high / step + 1e-9) + 1)}
    grid |= {round(cost, 6) for cost in args.specialist_costs}  # the specialists' costs are on the front too
    return conditioned, specialists if args.specialist_costs else None, sorted(grid)


def _costs_as_text(table: Any) -> Any:
    return table.assign(cost=table.cost.map("{:g}".format))


def run(args: argparse.Namespace, error: Any) -> int:
    from pathlib import Path

    from amjax.analysis import load_results, to_markdown
    from amjax.analysis.pareto import cost_front, front_medians, front_table, plot_front
    from amjax.files import use_compile_cache
    from amjax.sweep import run_sweep

    try:
        conditioned, specialists, grid = _specs(args)
    except (ValueError, TypeError) as exc:
        error(str(exc))  # exits with status 2, before anything is written
    out = Path(args.out)
    use_compile_cache(out)  # a resumed run loads its programs instead of compiling them again
    run_sweep(conditioned, out / "conditioned", progress=not args.no_progress)
    special = None
    if specialists is not None:
        run_sweep(specialists, out / "specialists", progress=not args.no_progress)
        special = load_results(out / "specialists").summary
    points = cost_front(out / "conditioned", grid)
    points.to_csv(out / "front.csv", index=False)
    ratio = conditioned.total_timesteps / (specialists or conditioned).total_timesteps
    seeds = conditioned.seeds
    shown = f"0-{seeds[-1]}" if seeds == tuple(range(len(seeds))) else " ".join(map(str, seeds))
    lines = [
        f"# Cost front: {args.env}, agents {', '.join(args.agent)}, seeds {shown}",
        "",
        f"Conditioned agents: costs drawn from [0, {args.cost_high}], {conditioned.total_timesteps:,} env steps "
        f"each ({ratio:.2f}x a specialist's). Medians over seeds, 100 fresh test episodes per cost.",
        "",
        to_markdown(_costs_as_text(front_medians(points))),
        "",
    ]
    if special is not None:
        lines += [
            "Against the specialists (their best policies re-scored by their sweep on 100 fresh episodes; gap: "
            "(conditioned - specialists) / |specialists|, positive when the conditioned agent scores more):",
            "",
            to_markdown(_costs_as_text(front_table(points, special))),
            "",
        ]
    (out / "table.md").write_text("\n".join(lines))
    plot_front(points, special, out / "front.png", title=args.env)
    print("\n".join(lines))
    print(f"front: {out / 'front.csv'}, {out / 'table.md'}, {out / 'front.png'}")
    return 0
