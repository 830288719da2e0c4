"""Active measurement on FrozenLake 4x4, slippery (gymnax's `FrozenLake-misc`, issue 53) and Act-Then-Measure's
semi-slippery variant (Krale et al. 2023): PPO and Dueling DQN, vanilla and at cost 0.05 per measurement (ATM's
cost), 10 seeds, beside exact bounds computed from each lake's transition model (docs/frozen_lake.md).

The lake is small enough to solve. Every step, the agent picks a move and whether to measure; measuring reveals the
cell (and costs 0.05), not measuring leaves the last measured cell on show. Since the reward (1 at the goal) and the
end of an episode are seen either way, what the agent knows is the last measured cell and the moves made since, and
its belief over the cells is that cell pushed through those moves with the holes and the goal masked out. Value
iteration over these beliefs, with the number of moves between measurements capped at `max_gap`, gives the exact
best expected costed return among the policies that measure at least once every `max_gap + 1` steps (time limit of
100 steps and all):

- `max_gap=0` is the always-measure optimum: the best return when every step pays the cost;
- as `max_gap` grows the value rises towards the optimum of the active-measure lake. Each capped value is reached
  by some policy, so it is a lower bound on that optimum; it bounds from above only the policies within its cap;
- at cost 0 with `max_gap=0` it is the lake's own optimum (the vanilla bound), an upper bound on every policy.

The agents see less than these policies use (the shown cell and the flag; not the moves since, nor the time left).
What an agent without memory can do without ever measuring is solved too (`never_measure`): one move for the
fresh view of the start, one for the stale view ever after.

    python experiments/frozen_lake.py --out runs/frozen_lake            # both lakes, 10 seeds, 512,000 steps
    python experiments/frozen_lake.py --bounds                          # the bounds alone (about a minute)
    python experiments/frozen_lake.py --smoke --out /tmp/frozen_smoke   # a tiny smoke run
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

ENV_ID = "FrozenLake-misc"
SEMI_SLIPPERY_ID = "FrozenLake-semi-slippery"  # Act-Then-Measure's own lake, registered by `register_semi_slippery`
DYNAMICS = {ENV_ID: "slippery", SEMI_SLIPPERY_ID: "semi-slippery"}
COST = 0.05
# env id -> (costs, env steps, steps between evaluations)
EXPERIMENTS = {ENV_ID: ((COST,), 512_000, 51_200), SEMI_SLIPPERY_ID: ((COST,), 512_000, 51_200)}
AGENTS = ("ppo", "dqn")
GAPS = tuple(range(8))  # the bounds' max_gap values: 0 (always measure) to 7 moves between measurements

# Gymnasium's FrozenLake-v1, map "4x4" (gymnax's FrozenLake-misc copies it): S start, F frozen, H hole, G goal;
# actions 0 left, 1 down, 2 right, 3 up; slippery: the intended move or either perpendicular one, 1/3 each.
# Semi-slippery (Krale et al.'s `AM_Gyms/frozen_lake_v2.py`, github.com/MKrale/ATM): one cell in the move's
# direction or two, 1/2 each, except that a move onto a hole or the goal stops there.
LAKE_MAP = ("SFFF", "FHFH", "FFFH", "HFFG")
MOVES = ((0, -1), (1, 0), (0, 1), (-1, 0))
MOVE_NAMES = ("left", "down", "right", "up")
TIME_LIMIT = 100


class Lake(NamedTuple):
    """The lake as a tabular model: `transitions[a, s, s']`, the reward on entering s', which cells end an episode,
    and the start cell."""

    transitions: np.ndarray
    reward: np.ndarray
    terminal: np.ndarray
    start: int


def lake_model(dynamics: str = "slippery", lake_map: tuple[str, ...] = LAKE_MAP) -> Lake:
    """The transition model of FrozenLake on `lake_map`, `dynamics` "slippery" or "semi-slippery" (moves off the
    edge stay put)."""
    if dynamics not in ("slippery", "semi-slippery"):
        raise ValueError(f"dynamics must be 'slippery' or 'semi-slippery', got {dynamics!r}")
    rows, cols = len(lake_map), len(lake_map[0])
    cells = "".join(lake_map)
    terminal = np.array([c in "HG" for c in cells])

    def ahead(cell: int, move: int) -> int:
        row, col = divmod(cell, cols)
        drow, dcol = MOVES[move % len(MOVES)]
        return min(max(row + drow, 0), rows - 1) * cols + min(max(col + dcol, 0), cols - 1)

    transitions = np.zeros((len(MOVES), rows * cols, rows * cols))
    for cell in range(rows * cols):
        for action in range(len(MOVES)):
            if dynamics == "slippery":
                for slip in (action - 1, action, action + 1):
                    transitions[action, cell, ahead(cell, slip)] += 1.0 / 3.0
            else:
                first = ahead(cell, action)
                transitions[action, cell, first] += 1.0 if terminal[first] else 0.5
                if not terminal[first]:
                    transitions[action, cell, ahead(first, action)] += 0.5
    reward = np.array([float(c == "G") for c in cells])
    return Lake(transitions, reward, terminal, cells.index("S"))


def register_semi_slippery() -> None:
    """Register the semi-slippery lake as `SEMI_SLIPPERY_ID`: gymnax's FrozenLake with its move replaced (same map,
    observation, reward, 100-step limit). Imports JAX: call it after `amjax.use_all_cores()`."""
    import jax
    import jax.numpy as jnp
    from gymnax.environments.misc import frozen_lake

    import amjax

    class SemiSlipperyLake(frozen_lake.FrozenLake):
        """One cell in the move's direction or two, 1/2 each; a move onto a hole or the goal stops there."""

        @property
        def name(self) -> str:
            return SEMI_SLIPPERY_ID

        def step_env(self, key, state, action, params):
            drow, dcol = jnp.asarray(MOVES)[action]
            row, col = jnp.divmod(state.position, self.ncol)
            row1, col1 = jnp.clip(row + drow, 0, self.nrow - 1), jnp.clip(col + dcol, 0, self.ncol - 1)
            row2, col2 = jnp.clip(row1 + drow, 0, self.nrow - 1), jnp.clip(col1 + dcol, 0, self.ncol - 1)
            first = self.desc[row1, col1]
            stop = (first == frozen_lake.HOLE) | (first == frozen_lake.GOAL) | jax.random.bernoulli(key)
            row, col = jnp.where(stop, row1, row2), jnp.where(stop, col1, col2)
            tile = self.desc[row, col]
            next_state = frozen_lake.EnvState(position=row * self.ncol + col, time=state.time + 1)
            terminated = (tile == frozen_lake.HOLE) | (tile == frozen_lake.GOAL)
            reward = (tile == frozen_lake.GOAL).astype(jnp.float32)
            return self.observe(key, next_state, action, params), next_state, reward, terminated, {}

    def factory():
        env = SemiSlipperyLake()
        return env, env.default_params

    amjax.register(SEMI_SLIPPERY_ID, factory)


class Bound(NamedTuple):
    """The solved lake for one cost and gap cap: the value from the start, the expected episode length and
    measurements under the optimal policy, and the policy itself (`choice[t][k]`: the action, control + 4 * measure,
    at t steps left for each belief node of depth k, as laid out by `_beliefs`; `choice[0]` is empty)."""

    value: float
    length: float
    measurements: float
    choice: list[list[np.ndarray]]


def _alive(lake: Lake) -> np.ndarray:
    """`[a, s, s']`: the moves with the ones that end the episode masked out."""
    return lake.transitions * ~lake.terminal


def _beliefs(lake: Lake, max_gap: int) -> list[np.ndarray]:
    """The belief nodes by depth k (moves since the last measurement): node `cell * 4**k + moves` (moves in base 4,
    the first one most significant) holds the unnormalised distribution over non-terminal cells after those moves
    from `cell` (its mass: the chance the episode is still running)."""
    n_cells = lake.reward.size
    alive = _alive(lake)
    depth = [np.eye(n_cells) * ~lake.terminal[:, None]]
    for _ in range(max_gap):
        depth.append(np.einsum("ns,ast->nat", depth[-1], alive).reshape(-1, n_cells))
    return depth


def solve(lake: Lake, cost: float, max_gap: int, horizon: int = TIME_LIMIT) -> Bound:
    """Finite-horizon value iteration over the belief nodes of `_beliefs`, measuring at least every `max_gap + 1`
    steps; then a forward pass of the optimal policy for its expected length and measurements."""
    n_moves = lake.transitions.shape[0]
    deeper = _beliefs(lake, max_gap + 1)  # depth k + 1 is depth k after each move
    beliefs = deeper[:-1]
    # [node, a, s']: the belief after each move
    after = [d.reshape(len(b), n_moves, -1) for b, d in zip(beliefs, deeper[1:], strict=True)]
    step_reward = [b @ (lake.transitions @ lake.reward).T for b in beliefs]  # [node, a]: expected reward of a move
    mass = [b.sum(axis=1) for b in beliefs]
    values = [np.zeros(len(b)) for b in beliefs]
    choice: list[list[np.ndarray]] = [[] for _ in range(horizon + 1)]
    for left in range(1, horizon + 1):
        new = []
        for k in range(max_gap + 1):
            measure = step_reward[k] + after[k] @ values[0] - cost * mass[k][:, None]
            options = [measure]
            if k < max_gap:
                options.insert(0, step_reward[k] + values[k + 1].reshape(-1, n_moves))
            q = np.concatenate(options, axis=1)  # [node, control + 4 * measure]
            best = q.argmax(axis=1)
            choice[left].append(best if k < max_gap else best + n_moves)
            new.append(q.max(axis=1))
        values = new

    # Forward: the chance of reaching each node with t steps left, then the steps and measurements it takes there.
    reach = [np.zeros(len(b)) for b in beliefs]
    reach[0][lake.start] = 1.0
    length = measurements = 0.0
    for left in range(horizon, 0, -1):
        nxt = [np.zeros(len(b)) for b in beliefs]
        for k in range(max_gap + 1):
            act = choice[left][k]
            control, measured = act % n_moves, act >= n_moves
            live = reach[k] * mass[k]
            length += live.sum()
            measurements += live[measured].sum()
            nodes = np.arange(len(act))
            nxt[0] += (reach[k][measured, None] * after[k][nodes[measured], control[measured]]).sum(axis=0)
            if k < max_gap:
                np.add.at(nxt[k + 1], nodes[~measured] * n_moves + control[~measured], reach[k][~measured])
        reach = nxt
    return Bound(float(values[0][lake.start]), float(length), float(measurements), choice)


def never_measure(lake: Lake, horizon: int = TIME_LIMIT) -> tuple[float, float, int, int]:
    """The best memoryless policy that never measures: it sees the start cell, fresh, then the same cell stale for
    the rest of the episode, so it is one move for each view. Returns its value (the chance of reaching the goal),
    its expected episode length and the two moves."""
    alive, gain = _alive(lake), lake.transitions @ lake.reward  # gain[a, s]: the chance a move from s ends at the goal
    best = (-1.0, 0.0, 0, 0)
    for first in range(len(MOVES)):
        for then in range(len(MOVES)):
            belief, value, length = np.eye(lake.reward.size)[lake.start], 0.0, 0.0
            for step in range(horizon):
                move = first if step == 0 else then
                value, length = value + belief @ gain[move], length + belief.sum()
                belief = belief @ alive[move]
            best = max(best, (float(value), float(length), first, then))
    return best


def bounds_table(dynamics: str = "slippery", cost: float = COST, gaps: tuple[int, ...] = GAPS) -> str:
    """The bounds as a markdown table: the vanilla optimum, then the active-measure lake by gap cap."""
    lake = lake_model(dynamics)
    # Among the vanilla optima the shortest walk (without a cost, a detour that still arrives is as good): a cost of
    # 1e-9 per step breaks the ties and moves the value by less than 1e-6.
    vanilla = solve(lake, 1e-9, 0)
    success = vanilla.value + 1e-9 * vanilla.measurements
    lines = [
        "| policy class | costed return | success (raw return) | episode length | measurements | measured fraction |",
        "|---|---|---|---|---|---|",
        f"| vanilla lake (no cost), optimal | {success:.3f} | {success:.3f} | {vanilla.length:.1f} "
        f"| {vanilla.length:.1f} | 1.00 |",
    ]
    blind, length, first, then = never_measure(lake)
    if blind > 0:
        best, shown = f"best: {MOVE_NAMES[first]}, then {MOVE_NAMES[then]} on every stale view", f"{length:.1f}"
    else:
        best, shown = "no pair of moves reaches the goal", "–"
    lines.append(f"| never measure, memoryless ({best}) | {blind:.3f} | {blind:.3f} | {shown} | 0 | 0.00 |")
    for gap in gaps:
        bound = solve(lake, cost, gap)
        name = "always measure" if gap == 0 else f"measure at least every {gap + 1} steps"
        raw = bound.value + cost * bound.measurements
        lines.append(
            f"| {name}, optimal | {bound.value:.3f} | {raw:.3f} | {bound.length:.1f} | {bound.measurements:.1f} "
            f"| {bound.measurements / max(bound.length, 1e-9):.2f} |"
        )
    return "\n".join(lines)


def all_bounds() -> str:
    """Both lakes' bounds tables, each under a heading."""
    return "\n\n".join(
        f"#### {env_id} ({dynamics})\n\n{bounds_table(dynamics)}" for env_id, dynamics in DYNAMICS.items()
    )


def main(argv: list[str] | None = None) -> int:
    """Train and tabulate (`experiments/cost_experiment.py`), then the bounds; or the bounds alone (`--bounds`)."""
    # `--bounds` is looked for before parsing: it needs no JAX, and the parser below is built after JAX starts.
    if "--bounds" in (sys.argv[1:] if argv is None else argv):
        print(all_bounds())
        return 0
    import amjax

    amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX
    register_semi_slippery()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the experiments are not installed
    from experiments import cost_experiment

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bounds", action="store_true", help="print the exact bounds only (no training)")
    cost_experiment.add_arguments(parser, EXPERIMENTS, seeds=10)
    args = parser.parse_args(argv)
    table = cost_experiment.run(EXPERIMENTS, AGENTS, args)
    bounds = all_bounds()
    (Path(args.out) / "bounds.md").write_text(bounds + "\n")
    print(table, bounds, sep="\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
