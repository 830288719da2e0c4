"""Instruments priced differently (issue 15): do agents read the cheap instrument more often than the dear one?

Each experiment is one sweep (`amjax.sweep.run_sweep`: resumable, best policies saved), then every configuration's
saved best policy is run on fresh test episodes (`amjax.analysis.record_agent`, keys disjoint from training's and
the sweep's evaluations) to count how often it reads each instrument. The table gives, per agent and prices, the
medians over seeds of the best test costed reward (the paper's metric, biased upward), the same policies re-scored
on 100 fresh episodes (the sweep's `best_policy_return`), and each instrument's read fraction on the fresh
episodes; the measurement maps of the median seed's policy go beside it.

    python experiments/instruments.py cartpole --out runs/instruments_cartpole   # CartPole-v0, cart vs pole
    python experiments/instruments.py cstr --out runs/instruments_cstr           # the reactor, thermocouple vs assay
    python experiments/instruments.py cartpole --smoke --out /tmp/instruments    # a tiny smoke run

CartPole-v0: the default instruments read the cart (x, x_dot) and the pole (theta, theta_dot); each price setting
is run both ways round, so an agent that reads the cheap one more often in both is following the prices, not the
physics. No charge per sampling occasion (`cost` = 0): the price is the instruments'. The reactor (CSTR-v0): the
thermocouple (temperature) and the concentration assay, at two assay prices.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the experiments are not installed

from amjax.analysis import load_results, plot_measurement_map, record_agent, to_markdown  # noqa: E402
from amjax.presets import env_hyperparams  # noqa: E402
from amjax.sweep import load_sweep_policy, run_sweep  # noqa: E402
from amjax.sweep.grid import SweepSpec  # noqa: E402
from amjax.wrappers.instruments import DEFAULT_INSTRUMENTS  # noqa: E402

# name -> env id, agents, occasion costs, instrument prices (one tuple per setting), env steps, steps per evaluation
EXPERIMENTS = {
    "cartpole": ("CartPole-v0", ("dqn", "ppo"), (0.0,), [(0.05, 0.3), (0.3, 0.05)], 153_600, 10_240),
    "cstr": ("CSTR-v0", ("dqn", "ppo"), (0.0,), [(0.01, 0.1), (0.01, 0.3)], 307_200, 20_480),
}
MAP_EPISODES = 100  # fresh test episodes per saved policy for the read fractions
MAP_KEY = 20_261_125  # their key: apart from the sweep's training and evaluation keys (seeds 0-9)


def read_fractions(out: Path, summary: pd.DataFrame) -> pd.DataFrame:
    """Per configuration: each instrument's read fraction, the costed return and the mean episode length over
    fresh test episodes of its saved best policy (a vanilla run reads everything)."""
    rows = []
    for config_id in summary["config_id"]:
        policy = load_sweep_policy(out, config_id)
        mmap = record_agent(policy.config, policy.params, jax.random.key(MAP_KEY), MAP_EPISODES)
        first, second = (1.0, 1.0) if policy.config.vanilla else mmap.reading_fractions
        rows.append(
            {
                "config_id": config_id,
                "read_first": first,
                "read_second": second,
                "fresh_return": float(np.mean(mmap.costed_return)),
                "fresh_measured": mmap.measured_fraction,
                "fresh_length": float(np.mean(mmap.lengths)),
            }
        )
    return summary.merge(pd.DataFrame(rows), on="config_id")


def always_read_bound(rows: pd.DataFrame, prices: str, cost: float) -> float:
    """The vanilla policies' median re-scored return minus the price of reading every instrument on every step
    of their episodes: what always reading everything would score."""
    vanilla = rows[rows.vanilla]
    per_step = cost + sum(float(p) for p in prices.split("x"))
    return float((vanilla.best_policy_return - per_step * vanilla.fresh_length).median())


def _cheaper_read_more(rows: pd.DataFrame) -> pd.Series:
    """Per configuration: whether its policy read the cheaper instrument more often than the dearer one."""
    prices = rows["instrument_costs"].str.split("x", expand=True).astype(float)
    first_cheaper = prices[0] < prices[1]
    return (rows.read_first > rows.read_second).where(first_cheaper, rows.read_second > rows.read_first)


def table(rows: pd.DataFrame, names: tuple[str, str]) -> pd.DataFrame:
    """Medians over seeds per agent and prices, with the always-read bound of the vanilla runs."""
    columns = {
        "best_return": "best costed reward",
        "best_policy_return": "re-scored",
        "fresh_measured": "any read",
        "read_first": f"{names[0]} read",
        "read_second": f"{names[1]} read",
    }
    measured = rows[~rows.vanilla]
    measured = measured.assign(cheaper_more=_cheaper_read_more(measured))
    grouped = measured.groupby(["agent", "instrument_costs"], as_index=False)
    medians = grouped[list(columns)].median().rename(columns=columns)
    medians.insert(2, "seeds", grouped.size()["size"])
    counts = grouped["cheaper_more"].agg(lambda x: f"{int(x.sum())}/{len(x)}")
    medians.insert(2, "cheaper read more often", counts["cheaper_more"])
    medians.insert(
        6,
        "always-read bound",
        [
            always_read_bound(rows[rows.agent == agent], prices, float(measured.cost.iloc[0]))
            for agent, prices in zip(medians.agent, medians.instrument_costs, strict=True)
        ],
    )
    return medians.rename(columns={"instrument_costs": f"prices ({names[0]} x {names[1]})"})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("experiment", choices=sorted(EXPERIMENTS))
    parser.add_argument("--out", required=True, help="output folder (rerun to resume)")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--smoke", action="store_true", help="2 seeds, a few thousand steps (checks the pipeline)")
    args = parser.parse_args()
    env_id, agents, costs, prices, steps, every = EXPERIMENTS[args.experiment]
    seeds = args.seeds
    if args.smoke:
        seeds, steps, every = 2, 4096, 2048
    names = tuple(name for name, _ in DEFAULT_INSTRUMENTS[env_id])
    out = Path(args.out)
    spec = SweepSpec(
        envs=(env_id,),
        agents=agents,
        costs=costs,
        seeds=tuple(range(seeds)),
        total_timesteps=steps,
        eval_every=every,
        vanilla=True,
        hyperparams={"instruments": "default", "instrument_costs": list(prices)},
        env_defaults={env_id: env_hyperparams(env_id, agents)},
    )
    start = time.perf_counter()
    run_sweep(spec, out, progress=True)
    trained = time.perf_counter() - start
    rows = read_fractions(out, load_results(out).summary)
    rows.to_csv(out / "read_fractions.csv", index=False)
    result = table(rows, names)
    text = to_markdown(result)
    (out / "table.md").write_text(text + "\n")
    print(text)
    for (agent, price), group in rows[~rows.vanilla].groupby(["agent", "instrument_costs"]):
        median = group.iloc[(group["best_policy_return"] - group["best_policy_return"].median()).abs().argmin()]
        policy = load_sweep_policy(out, median["config_id"])
        mmap = record_agent(policy.config, policy.params, jax.random.key(MAP_KEY), 10)
        plot_measurement_map(
            {f"{agent}, prices {price}, seed {median['seed']}": mmap},
            instrument_names=names,
            path=out / f"map_{agent}_{price}.png",
        )
    print(f"sweep {trained:.0f} s, total {time.perf_counter() - start:.0f} s; table and maps in {out}")


if __name__ == "__main__":
    main()
