"""PQN beside Dueling DQN and recurrent PQN beside DRQN at the paper grid's batch size, in one invocation (issue 54).

Each case trains `--configs` configurations of one agent on one environment (costs 0.1 / 0.2 / 0.3 x seeds, the
env's presets, as `amjax replicate` builds them) as one vmapped, jitted program, in its own child process (so peak
memory is the case's own), split over `--devices` CPU devices as a sweep does. It reports the compile time, the env
steps per second of the compiled run (all configurations together, evaluations included) and the child's peak
resident memory; the table gives each agent's speed against its Q-learning counterpart on the same env (pqn
against dqn, pqn-rnn against drqn).

    python benchmarks/pqn_speed.py                 # benchmarks/results/pqn_speed_<date>_<machine>.jsonl / .md
    python benchmarks/pqn_speed.py --configs 4 --steps 8192 --envs CartPole-v0   # a smoke run
    python benchmarks/pqn_speed.py --envs CartPole-v0 --agents dqn pqn --set pqn.update_epochs=2   # an ablation
    python benchmarks/pqn_speed.py --envs CartPole-v0 --agents pqn --profile 15   # where PQN's time goes
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
from benchmarks.profiles import top_table  # noqa: E402

COSTS = (0.1, 0.2, 0.3)
ENVS = ("CartPole-v0", "Acrobot-v1", "LunarLander-v3")
AGENTS = ("dqn", "pqn", "drqn", "pqn-rnn")
COUNTERPART = {"pqn": "dqn", "pqn-rnn": "drqn"}  # the speed ratio's denominator


def run_case(
    env_id: str,
    agent: str,
    configs: int,
    steps: int,
    eval_every: int,
    devices: int,
    overrides: dict[str, Any],
    profile_top: int = 0,
) -> dict[str, Any]:
    """Compile and time one case in this process, its configurations split over `devices` CPU devices, with the
    config fields `overrides` set on top of the env's presets; with `profile_top` > 0, then trace one more run and
    keep its `profile_top` costliest source lines, ops and kernels (under "profile")."""
    import jax

    jax.config.update("jax_num_cpu_devices", devices)  # before JAX starts (this child's first JAX call)
    import jax.numpy as jnp

    from amjax.agents import ALGORITHMS

    items = case_configs(env_id, agent, configs, steps, eval_every, overrides)
    keys = jnp.stack([jax.random.PRNGKey(i // len(COSTS)) for i in range(configs)])
    timing = harness.time_training_batch(ALGORITHMS[agent], items, keys, profile_top)  # on the `devices` set above
    return {"env": env_id, "agent": agent, "overrides": overrides, "configs": configs, "devices": devices, **timing}


def case_configs(
    env_id: str, agent: str, configs: int, steps: int, eval_every: int, overrides: dict[str, Any]
) -> list[Any]:
    """One case's validated configs: costs 0.1 / 0.2 / 0.3 in turn, the env's presets with the fields `overrides`
    on top, the schedule nearest to `steps` and `eval_every`. ValueError or TypeError for a value the config
    refuses (`main` builds them once before any case runs)."""
    from amjax.agents import config_for
    from amjax.agents.config import nearest_schedule

    fields = {name: as_tuples(value) for name, value in overrides.items()}  # the child's JSON made tuples lists
    items = [config_for(env_id, agent, cost=COSTS[i % len(COSTS)]).replace(**fields) for i in range(configs)]
    total, every = nearest_schedule(steps, eval_every, items[0].steps_per_update())
    return [c.replace(eval_every=every, total_timesteps=total).validate() for c in items]


# Fields the script itself sets (from --steps and --eval-every), which `--set` may not change.
SCRIPT_FIELDS = ("total_timesteps", "eval_every")


def as_tuples(value: Any) -> Any:
    """`value` with every list turned back into a tuple, at any depth (a results file's JSON writes tuples as
    lists, and config fields such as `hidden` take tuples)."""
    return tuple(as_tuples(v) for v in value) if isinstance(value, (list, tuple)) else value


def parse_value(text: str) -> Any:
    """One `--set` value, in the syntax of `amjax sweep --set` (`train.flags.parse_set_value`). ValueError for an
    empty value or one a results file cannot record (JSON: no sets or complex numbers)."""
    from train.flags import parse_set_value

    if not text.strip():
        raise ValueError("an empty value")
    try:
        value = parse_set_value(text)
        json.dumps(value)
    except TypeError:
        raise ValueError(f"{text!r} is not a number, string, boolean or tuple of them") from None
    return value


def parse_overrides(items: list[str], agents: list[str]) -> dict[str, dict[str, Any]]:
    """`--set AGENT.FIELD=VALUE` items -> {agent: {field: value}}. ValueError naming the item if the agent is not
    benchmarked, has no such config field, the field is one the script sets, it is given twice, or its value does
    not parse (`parse_value`). The values are checked against each env's config in `main`."""
    import dataclasses

    from amjax.agents import ALGORITHMS

    overrides: dict[str, dict[str, Any]] = {agent: {} for agent in agents}
    for item in items:
        name, sep, text = item.partition("=")
        agent, dot, field = name.rpartition(".")
        if not (sep and dot) or agent not in overrides:
            raise ValueError(f"got {item!r}; expected AGENT.FIELD=VALUE with AGENT one of {', '.join(agents)}")
        allowed = [f.name for f in dataclasses.fields(ALGORITHMS[agent].config_type) if f.name not in SCRIPT_FIELDS]
        if field in SCRIPT_FIELDS:
            raise ValueError(f"got {item!r}: {field} is set by --steps and --eval-every")
        if field not in allowed:
            raise ValueError(f"got {item!r}: {agent} has no field {field!r}; allowed: {', '.join(allowed)}")
        if field in overrides[agent]:
            raise ValueError(f"got {item!r}: {agent}.{field} is set twice")
        try:
            overrides[agent][field] = parse_value(text)
        except ValueError as error:
            raise ValueError(f"got {item!r}: {error}") from None
    return overrides


def label(result: dict[str, Any]) -> str:
    """A case's agent and the fields it set, e.g. "pqn (update_epochs=2)"."""
    fields = ", ".join(f"{name}={as_tuples(value)}" for name, value in result.get("overrides", {}).items())
    return f"{result['agent']} ({fields})" if fields else result["agent"]


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, each agent's env steps/s against its counterpart's."""
    parts = []
    for run in runs:
        settings, results = run["settings"], [r for r in run["cases"] if r["status"] == "ok"]
        speed = {(r["env"], r["agent"]): r["env_steps_per_s"] for r in results if not r.get("overrides")}

        def ratio(r: dict[str, Any], speed: dict[tuple[str, str], int] = speed) -> str:
            base = speed.get((r["env"], COUNTERPART.get(r["agent"], "")))
            return f"{r['env_steps_per_s'] / base:.1f}x" if base else ""

        parts.append(
            "# PQN and recurrent PQN beside their Q-learning counterparts at the grid's batch size "
            f"({run['date'][:10]})\n\n"
            f"{settings['configs']} configurations (costs {', '.join(map(str, COSTS))} x seeds, each env's presets) "
            f"in one vmapped program per case, split over {settings['devices']} CPU device(s), each case in its own "
            "process, one after the other. Env steps/s: all configurations together, evaluations included, compile "
            f"excluded. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                results,
                [
                    ("env", lambda r: r["env"]),
                    ("agent", label),
                    ("steps / config", lambda r: r["steps_per_config"]),
                    ("compile (s)", lambda r: r["compile_s"]),
                    ("run (s)", lambda r: r["run_s"]),
                    ("env steps/s", lambda r: r["env_steps_per_s"]),
                    ("vs counterpart", ratio),
                    ("peak RSS (MiB)", lambda r: r["peak_rss_mib"]),
                ],
            )
            + "".join(f"\n{r['env_id']} {label(r)}: {r['status']}\n" for r in run["cases"] if r["status"] != "ok")
            + "".join(profile_tables(r) for r in results if isinstance(r.get("profile"), dict))
        )
    return "\n".join(parts)


def profile_tables(result: dict[str, Any]) -> str:
    """A profiled case's costliest source lines (`--profile`; the record keeps its ops and kernels too)."""
    profile = result["profile"]
    return (
        f"\n## {result['env']} {label(result)}: where the time goes\n\n"
        f"One more run traced: {profile['kernels']:,} kernels kept in the trace, {profile['busy_ms']:,.0f} ms busy "
        "over both devices' threads (on a CPU the trace keeps part of a long run's kernels: read the shares, not "
        "the totals).\n\n" + top_table(profile["top_sources"], "source (op)")
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(ENVS), metavar="ENV")
    parser.add_argument("--agents", nargs="+", default=list(AGENTS), metavar="AGENT")
    parser.add_argument("--configs", type=int, default=30, help="configurations per case (default 30: 3 costs x 10)")
    parser.add_argument("--steps", type=int, default=40_960, help="env steps per configuration (rounded)")
    parser.add_argument("--eval-every", type=int, default=10_240)
    parser.add_argument("--devices", type=int, default=2, help="CPU devices the configurations are split over")
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/pqn_speed_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="AGENT.FIELD=VALUE",
        help="a config field of one agent's cases on top of the env's presets (repeatable), for ablations; the ratio "
        "is against the counterpart's unchanged cases of the same run",
    )
    parser.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="after timing, trace one more run of each case and list its N costliest source lines (ops and kernels "
        "in the record)",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:  # before anything starts JAX: the child sets its device count first
        case = json.loads(args.child)
        harness.child_result(run_case(**case))
        return 0
    from amjax.agents import ALGORITHMS
    from amjax.cores import usable_cores
    from amjax.envs.registry import make_env

    for agent in args.agents:
        if agent not in ALGORITHMS:
            parser.error(f"--agents: unknown agent {agent!r}; allowed values: {', '.join(ALGORITHMS)}")
    for env_id in args.envs:
        try:
            make_env(env_id)
        except ValueError as error:
            parser.error(f"--envs: {error}")
    if not 1 <= args.devices <= usable_cores():
        parser.error(f"--devices: {args.devices}; allowed values: 1 to {usable_cores()} (usable cores)")
    if args.profile < 0:
        parser.error(f"--profile: got {args.profile}; allowed values: 0 (no trace) or a positive number of rows")
    if args.configs % args.devices:
        parser.error(f"--configs: {args.configs} must be a multiple of --devices ({args.devices})")
    try:
        overrides = parse_overrides(args.set, args.agents)
    except ValueError as error:
        parser.error(f"--set: {error}")
    for env_id in args.envs:  # a value the config refuses stops here, before any case runs
        for agent in args.agents:
            try:
                case_configs(env_id, agent, args.configs, args.steps, args.eval_every, overrides[agent])
            except (ValueError, TypeError) as error:
                parser.error(f"--set: {agent} on {env_id}: {error}")

    cases = [
        {
            "env_id": env_id,
            "agent": agent,
            "configs": args.configs,
            "steps": args.steps,
            "eval_every": args.eval_every,
            "devices": args.devices,
            "overrides": overrides[agent],
            "profile_top": args.profile,
        }
        for env_id in args.envs
        for agent in args.agents
    ]
    harness.run_cases("pqn_speed", harness.settings_of(args), args.out, __file__, cases, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
