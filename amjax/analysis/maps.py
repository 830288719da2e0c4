"""Measurement maps: which steps of each test episode a policy paid to measure (the paper's grid figure).

`record_measurements` runs any `Policy` in any amjax environment for N episodes in parallel, as one jitted
`lax.scan`, and records per step whether it measured and whether the episode was still running;
`record_agent` does the same for a trained agent (its config and network parameters); `plot_measurement_map` draws
the grid episodes x time steps coloured measured / not measured / episode over. In an env with instruments the map
also records which instruments each step read (`readings`), and with two instruments the grid colours each
combination.

Randomness, so that a hand-written loop can reproduce a map: `reset_key, run_key = split(fast_key(key))` (Philox,
`amjax.agents.rollout.fast_key`); episode i starts from `reset(split(reset_key, N)[i])`; step t uses `act_key,
env_key = split(split(run_key, max_steps)[t])`, the policy gets `act_key` and env i steps with `split(env_key,
N)[i]` (as `amjax.agents.training.evaluate`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from amjax.agents.config import AgentConfig
from amjax.agents.registry import ALGORITHMS, agent_of
from amjax.agents.rollout import ActFn, EnvBatch, fast_key
from amjax.agents.training import Policy

# Colours of the three cell kinds: not measured, measured, episode over.
MAP_COLORS = ("#f2c14e", "#1d4e89", "#e8e8e8")
NOT_MEASURED, MEASURED, OVER = 0, 1, 2
# With two instruments: not measured, the first only, the second only, both, episode over.
INSTRUMENT_COLORS = ("#f2c14e", "#7fb3d5", "#c0392b", "#1d4e89", "#e8e8e8")


@dataclass(frozen=True)
class MeasurementMap:
    """Measure decisions of `episodes` test episodes over `max_steps` time steps (NumPy arrays)."""

    measured: np.ndarray  # [episodes, max_steps] bool: the action at this step paid for a measurement
    active: np.ndarray  # [episodes, max_steps] bool: this step belongs to the episode (it had not ended before)
    costed_return: np.ndarray  # [episodes]
    raw_return: np.ndarray  # [episodes]
    readings: np.ndarray | None = None  # [episodes, max_steps, k] bool: instruments read (envs with instruments)

    @property
    def lengths(self) -> np.ndarray:
        return self.active.sum(axis=1)

    @property
    def measured_fraction(self) -> float:
        """Paid measurements / steps, over all episodes (as the sweep's measured fraction)."""
        return float((self.measured & self.active).sum() / max(self.active.sum(), 1))

    @property
    def reading_fractions(self) -> np.ndarray | None:
        """[k]: the fraction of steps on which each instrument was read (None without instruments)."""
        if self.readings is None:
            return None
        return (self.readings & self.active[..., None]).sum((0, 1)) / max(self.active.sum(), 1)

    def grid(self) -> np.ndarray:
        """[episodes, max_steps] of NOT_MEASURED (0), MEASURED (1), OVER (2); with two instruments the reading
        mask 0-3 (bit j: instrument j read) and 4 for episode over."""
        if self.readings is not None and self.readings.shape[-1] == 2:
            mask = self.readings[..., 0].astype(int) + 2 * self.readings[..., 1].astype(int)
            return np.where(self.active, mask, len(INSTRUMENT_COLORS) - 1)
        return np.where(self.active, self.measured.astype(int), OVER)


def _max_steps(env_params: Any) -> int:
    for params in (env_params, getattr(env_params, "env_params", None)):
        if params is not None and hasattr(params, "max_steps_in_episode"):
            return int(params.max_steps_in_episode)
    raise ValueError("max_steps: the env params have no max_steps_in_episode; pass max_steps")


def _scan(
    env: Any, act: ActFn, num_episodes: int, max_steps: int, env_params: Any, carry: Any, key: jax.Array
) -> dict[str, jax.Array]:
    reset_key, run_key = jax.random.split(fast_key(key))
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, num_episodes), env_params)
    batch = EnvBatch(obs, state, jnp.ones(num_episodes, bool))
    running = jnp.ones(num_episodes, bool)

    def one_step(loop, step_key):
        batch, agent_carry, running = loop
        act_key, env_key = jax.random.split(step_key)
        action, agent_carry, _ = act(batch, agent_carry, act_key)
        obs, state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(env_key, num_episodes), batch.state, action, env_params
        )
        done = terminated | truncated
        record = {
            "measured": jnp.broadcast_to(info["measured"], running.shape) & running,
            "active": running,
            "reward": jnp.where(running, reward, 0.0),
            "raw_reward": jnp.where(running, info["raw_reward"], 0.0),
        }
        if "readings" in info:
            record["readings"] = info["readings"] & running[:, None]
        return (EnvBatch(obs, state, done), agent_carry, running & ~done), record

    _, steps = jax.lax.scan(one_step, (batch, carry, running), jax.random.split(run_key, max_steps))
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), steps)  # [episodes, max_steps]


def _to_map(steps: dict[str, jax.Array]) -> MeasurementMap:
    steps = jax.device_get(steps)
    return MeasurementMap(
        measured=np.asarray(steps["measured"], bool),
        active=np.asarray(steps["active"], bool),
        costed_return=np.asarray(steps["reward"]).sum(axis=1),
        raw_return=np.asarray(steps["raw_reward"]).sum(axis=1),
        readings=np.asarray(steps["readings"], bool) if "readings" in steps else None,
    )


def record_measurements(
    env: Any,
    env_params: Any,
    policy: Policy,
    key: jax.Array,
    num_episodes: int = 10,
    max_steps: int | None = None,
) -> MeasurementMap:
    """Run `policy` in `env` (an amjax env: its step info reports `measured` and `raw_reward`) for
    `num_episodes` parallel episodes of up to `max_steps` steps (default: the params' episode limit).

    The policy's carry must hold `num_episodes` envs (recurrent agents size it by their config's eval_episodes).
    Steps after an episode ends (the env auto-resets) are marked inactive. Compiles once per call (a policy is a
    closure); for a trained agent prefer `record_agent`, which compiles once per config structure.
    """
    act, carry = policy
    max_steps = _max_steps(env_params) if max_steps is None else int(max_steps)
    run = jax.jit(partial(_scan, env, act, int(num_episodes), max_steps))
    return _to_map(run(env_params, carry, key))


@partial(jax.jit, static_argnames=("algo_name", "num_episodes"))
def _record_agent(
    algo_name: str, config: AgentConfig, params: Any, key: jax.Array, num_episodes: int
) -> dict[str, jax.Array]:
    algo = ALGORITHMS[algo_name]
    setup = algo.setup(config)
    act, carry = algo.greedy(config, setup, params, num_episodes)
    return _scan(setup.env, act, num_episodes, setup.max_steps, setup.env_params, carry, key)


def record_agent(config: AgentConfig, params: Any, key: jax.Array, num_episodes: int = 10) -> MeasurementMap:
    """The measurement map of a trained agent's greedy policy on its own env (`Algorithm.setup(config)`).

    `params` are the agent's network parameters: `RunState.best_params` (the best evaluation's policy) or
    `RunState.algo.params` (the last) from `ppo.train(config, key)`, or a loaded `SavedPolicy.params`. Configs
    that differ only in traced fields (the cost among them) share one compiled program.
    """
    return _to_map(_record_agent(agent_of(config), config, params, key, int(num_episodes)))


def plot_measurement_map(
    maps: MeasurementMap | Mapping[str, MeasurementMap],
    *,
    title: str | None = None,
    path: str | Path | None = None,
    instrument_names: tuple[str, str] | None = None,
) -> Figure:
    """Grid of episodes (rows) x time steps (columns): measured, not measured, or episode over.

    `maps` is one map or a mapping label -> map (one panel each, stacked, e.g. one per cost). Each panel's title
    gives the measured fraction and the mean costed return. Maps of an env with two instruments colour which
    were read (`instrument_names` label them; default "instrument 1" / "instrument 2").
    """
    panels = {"": maps} if isinstance(maps, MeasurementMap) else dict(maps)
    if not panels:
        raise ValueError("plot_measurement_map: no maps")
    height = sum(0.6 + 0.22 * m.measured.shape[0] for m in panels.values())
    fig = Figure(figsize=(9.0, max(2.4, height)), layout="constrained")
    axes = fig.subplots(len(panels), 1, squeeze=False).ravel()
    paired = all(m.readings is not None and m.readings.shape[-1] == 2 for m in panels.values())
    colors = INSTRUMENT_COLORS if paired else MAP_COLORS
    names = instrument_names or ("instrument 1", "instrument 2")
    cmap = ListedColormap(colors)
    for ax, (label, mmap) in zip(axes, panels.items(), strict=True):
        episodes, steps = mmap.measured.shape
        ax.imshow(
            mmap.grid(),
            cmap=cmap,
            vmin=0,
            vmax=len(colors) - 1,
            aspect="auto",
            interpolation="nearest",
            extent=(-0.5, steps - 0.5, episodes - 0.5, -0.5),
        )
        stats = f"measured {mmap.measured_fraction:.0%} of steps"
        if paired:
            stats += " (" + ", ".join(f"{n} {f:.0%}" for n, f in zip(names, mmap.reading_fractions, strict=True)) + ")"
        stats += f", mean costed return {float(np.mean(mmap.costed_return)):.1f}"
        ax.set_title(f"{label}: {stats}" if label else stats, fontsize="medium")
        ax.set_ylabel("episode")
        ax.set_yticks(range(episodes), [str(i + 1) for i in range(episodes)], fontsize="x-small")
    axes[-1].set_xlabel("time step")
    if paired:
        labels = ("not measured", f"{names[0]} only", f"{names[1]} only", "both", "episode over")
        handles = [Patch(color=c, label=n) for c, n in zip(INSTRUMENT_COLORS, labels, strict=True)]
    else:
        handles = [
            Patch(color=MAP_COLORS[i], label=name)
            for i, name in ((MEASURED, "measured"), (NOT_MEASURED, "not measured"), (OVER, "episode over"))
        ]
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize="small")
    if title:
        fig.suptitle(title)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120, bbox_inches="tight")
    return fig
