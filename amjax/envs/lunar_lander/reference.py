"""Gymnasium's own LunarLander as a reference for tests and benchmarks (needs ``box2d``; not imported by the env).

``free_flight_replay`` records Gymnasium's random draws and feeds them to the port's ``reset_from_draws`` /
``step_from_draws`` (T2 in docs/lunar_lander.md).
"""

from __future__ import annotations

import importlib.util
import os
from types import ModuleType
from typing import Any

import jax
import numpy as np

from amjax.envs.lunar_lander.constants import VELOCITY_ITERATIONS
from amjax.envs.lunar_lander.env import reset_from_draws, step_from_draws
from amjax.envs.lunar_lander.state import EnvParams

# Jitted once per process, shared by the replay and the tests (each compile of the solver takes seconds).
_SOLVER = ("velocity_iterations", "exact_free_flight", "jump_sweeps")
replay_reset = jax.jit(reset_from_draws, static_argnames=_SOLVER)
replay_step = jax.jit(step_from_draws, static_argnames=("continuous", *_SOLVER))


def load_gymnasium_lunar_lander() -> ModuleType:
    """Gymnasium's lunar_lander module (reference for tests/benchmarks; needs ``box2d``).

    Loaded from its file so that Gymnasium's box2d package ``__init__`` (which imports the
    pygame-dependent CarRacing) is not required.
    """
    import gymnasium

    path = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "box2d", "lunar_lander.py")
    spec = importlib.util.spec_from_file_location("_gymnasium_lunar_lander", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class DrawRecorder:
    """Stands in for Gymnasium's ``np_random`` and logs every draw (for replaying in JAX)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.draws: list[np.ndarray] = []

    def uniform(self, *args: Any, **kwargs: Any) -> Any:
        value = self.rng.uniform(*args, **kwargs)
        self.draws.append(np.atleast_1d(value).astype(np.float64))
        return value

    def integers(self, *args: Any, **kwargs: Any) -> Any:
        value = self.rng.integers(*args, **kwargs)
        self.draws.append(np.atleast_1d(value))
        return value


def free_flight_replay(
    seed: int,
    max_steps: int = 1000,
    continuous: bool = False,
    velocity_iterations: int = VELOCITY_ITERATIONS,
    exact_free_flight: bool = False,
    jump_sweeps: bool = False,
) -> dict[str, np.ndarray]:
    """Step Gymnasium and the port side by side on Gymnasium's recorded draws, random actions.

    Stops before Gymnasium's first ground contact (a leg flag or game_over) or termination.
    Returns per-step absolute observation and reward differences (needs ``box2d``).
    """
    module = load_gymnasium_lunar_lander()
    genv = module.LunarLander(continuous=continuous)
    recorder = DrawRecorder(np.random.default_rng(seed))
    genv.np_random = recorder
    genv.action_space.seed(seed)
    obs_g, _ = genv.reset()
    params = EnvParams()
    obs_j, state = replay_reset(
        recorder.draws[0],
        np.concatenate(recorder.draws[1:3]),
        params,
        velocity_iterations=velocity_iterations,
        exact_free_flight=exact_free_flight,
        jump_sweeps=jump_sweeps,
    )
    obs_diff, rew_diff = [np.abs(np.asarray(obs_j) - obs_g).max()], []
    for _ in range(max_steps):
        action = genv.action_space.sample()
        n_draws = len(recorder.draws)
        obs_g, rew_g, term, _, _ = genv.step(action)
        if obs_g[6] or obs_g[7] or genv.game_over or term:
            break
        dispersion = np.concatenate(recorder.draws[n_draws : n_draws + 2])
        obs_j, state, rew_j, _, _ = replay_step(
            state, action, dispersion, params, continuous, velocity_iterations, exact_free_flight, jump_sweeps
        )
        obs_diff.append(np.abs(np.asarray(obs_j) - obs_g).max())
        rew_diff.append(abs(float(rew_j) - rew_g))
    genv.close()
    return {"obs_diff": np.asarray(obs_diff), "reward_diff": np.asarray(rew_diff)}
