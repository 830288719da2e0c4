"""The training driver every algorithm shares: updates -> periodic greedy evaluation -> reduced metrics.

An algorithm supplies `network(config, action_space, torso)`, `init(config, setup, key)`, `update(config, setup, state)`
(one iteration: collect + learn), `params(state)` (its network parameters) and `greedy(config, setup, params,
num_envs)` (its evaluation policy). `Algorithm.setup(config)` builds the env and network once per compiled program
and every function gets them. The driver scans `updates_per_eval` updates, evaluates `eval_episodes` test episodes,
and emits one small `EvalRow` per evaluation: memory grows with the number of evaluations, never with the number of
environment steps. A configuration whose loss or parameters stop being finite is marked diverged and keeps that
mark; it shares nothing with its neighbours in a vmapped sweep.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn
from flax import struct

from amjax import strategy
from amjax.agents.config import AgentConfig
from amjax.agents.networks import Torso, pick_torso
from amjax.agents.rollout import ActFn, EnvBatch, FinishedEpisodes, fast_key, reset_envs, step_envs
from amjax.agents.setup import Setup, training_env
from amjax.batching import in_groups, shared_field
from amjax.wrappers.episode_stats import EpisodeMetrics

Policy = tuple[ActFn, Any]  # (act function, its initial agent carry for a batch of envs; None if memoryless)


@struct.dataclass
class UpdateStats:
    """What one `update` reports: its loss and the training episodes that finished during it, per env ([num_envs]:
    `rollout`'s sums; the driver adds them up over an evaluation period and sums over envs once)."""

    loss: jax.Array
    episodes: FinishedEpisodes


@struct.dataclass
class EvalRow:
    """One evaluation point of one configuration. The results table names `test`'s columns eval_return (costed),
    eval_raw_return, ... and `train`'s train_return, ... (`EpisodeMetrics.columns`)."""

    env_steps: jax.Array
    test: EpisodeMetrics  # means over the greedy test episodes
    train: EpisodeMetrics  # means over the training episodes finished since the last evaluation (NaN if none)
    loss: jax.Array  # mean over the updates since the last evaluation
    diverged: jax.Array  # a loss or a parameter has been non-finite at some point so far

    def columns(self) -> dict[str, jax.Array]:
        """The results table's columns (each with this row's leading axes)."""
        return {
            "env_steps": self.env_steps,
            **self.test.columns("eval_"),
            **self.train.columns("train_"),
            "loss": self.loss,
            "diverged": self.diverged,
        }


@struct.dataclass
class RunState:
    """The whole state of one training run between evaluations (checkpointable)."""

    algo: Any
    key: jax.Array  # for evaluation episodes
    evals_done: jax.Array = shared_field()  # equal in every member of a sweep batch
    best_return: jax.Array  # best greedy test costed return so far (the paper's metric)
    best_measured_fraction: jax.Array  # measured fraction of steps at that best evaluation
    best_params: Any  # network parameters of that best evaluation (the policy a sweep saves)
    diverged: jax.Array


@dataclass(frozen=True)
class Algorithm:
    """An algorithm as pure functions plus its config type.

    `greedy` takes network parameters (not the whole state), so a saved policy needs only its config and them.
    """

    name: str
    config_type: type[AgentConfig]
    network: Callable[[AgentConfig, Any, Torso], nn.Module]  # (config, env action space, body) -> its network
    init: Callable[[AgentConfig, Setup, jax.Array], Any]  # (config, setup, key) -> algorithm state
    update: Callable[[AgentConfig, Setup, Any], tuple[Any, UpdateStats]]  # (config, setup, state) -> (state, stats)
    greedy: Callable[[AgentConfig, Setup, Any, int], Policy]  # (config, setup, params, num_envs) -> policy
    params: Callable[[Any], Any]  # state -> network parameters

    def setup(self, config: AgentConfig) -> Setup:
        """The env and network of `config` (call once per compiled program; the traced cost and noise go into the
        env params)."""
        env, env_params, max_steps = training_env(config)
        torso = pick_torso(config.torso, env.observation_space(env_params).shape)
        return Setup(env, env_params, max_steps, self.network(config, env.action_space(env_params), torso))


def evaluate(
    env: Any,
    env_params: Any,
    max_steps: int,
    policy: Policy,
    key: jax.Array,
    num_episodes: int,
) -> FinishedEpisodes:
    """Run `num_episodes` test episodes in parallel to their end; their count and the sums of their metrics.

    Randomness is drawn with Philox from the key's bits (`rollout.fast_key`): `reset_key, run_key = split(key)`;
    episode i starts from `reset(split(reset_key, N)[i])`; step t uses `act_key, env_key = split(split(run_key,
    max_steps)[t])`, the policy gets `act_key` and env i steps with `split(env_key, N)[i]`."""
    act, carry = policy
    reset_key, run_key = jax.random.split(fast_key(key))
    batch = reset_envs(env, env_params, reset_key, num_episodes)
    finished = jnp.zeros(num_episodes, bool)
    step_keys = jax.random.split(run_key, max_steps)

    def running(loop):
        t, _, _, finished, _ = loop
        return (t < max_steps) & ~jnp.all(finished)

    def one_step(loop):
        t, batch, agent_carry, finished, totals = loop
        act_key, env_key = jax.random.split(step_keys[t])
        action, agent_carry, _ = act(batch, agent_carry, act_key)
        batch, transition = step_envs(env, env_params, batch, action, env_key)
        first_end = transition.episode_done & ~finished  # each episode's metrics kept at its first end
        totals = jax.tree.map(partial(jnp.where, first_end), transition.episode, totals)
        return t + 1, batch, agent_carry, finished | transition.episode_done, totals

    # Every episode ends within `max_steps` (the time limit truncates it); stepping stops once all have ended
    # (later steps would add nothing). On a GPU the loop runs `max_steps` steps instead: a loop that may stop early
    # reads its predicate back to the host every step, which costs more than the steps it saves. The episodes'
    # metrics are kept per episode and summed after the loop (no reduction per step).
    zeros = jax.tree.map(lambda x: jnp.zeros(num_episodes, x.dtype), EpisodeMetrics.zeros())
    initial = (jnp.int32(0), batch, carry, finished, zeros)
    if strategy.is_gpu():
        *_, finished, totals = jax.lax.fori_loop(0, max_steps, lambda _, loop: one_step(loop), initial)
    else:
        *_, finished, totals = jax.lax.while_loop(running, one_step, initial)
    return FinishedEpisodes.zeros().add(finished, totals).total()


def evaluate_greedy(
    algo: Algorithm, config: AgentConfig, setup: Setup, params: Any, key: jax.Array, num_episodes: int
) -> EpisodeMetrics:
    """Means over `num_episodes` test episodes of `algo`'s greedy policy with network `params`."""
    policy = algo.greedy(config, setup, params, num_episodes)
    return evaluate(setup.env, setup.env_params, setup.max_steps, policy, key, num_episodes).means()


# `fold_in` data of the re-scoring episodes. Evaluation i of a run draws its episodes from `fold_in(key, i)` with
# i < num_evals, so no evaluation that selected the best policy shares a key with its re-scoring.
RESCORE_STREAM = 0xFFFFFFFF


def rescore(algo: Algorithm, config: AgentConfig, state: RunState) -> EpisodeMetrics:
    """The best policy a run kept (`state.best_params`) re-scored on `config.rescore_episodes` fresh test episodes.

    The paper's metric, the best of many noisy evaluations, is biased upward; these episodes are drawn from a key
    stream disjoint from the evaluations that picked the policy (`RESCORE_STREAM`), so their mean is not. Returns
    the metrics' means per episode."""
    key = jax.random.fold_in(state.key, jnp.uint32(RESCORE_STREAM))
    return evaluate_greedy(algo, config, algo.setup(config), state.best_params, key, config.rescore_episodes)


def _all_finite(tree: Any) -> jax.Array:
    return jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


def init_run(algo: Algorithm, config: AgentConfig, key: jax.Array) -> RunState:
    """The initial `RunState` of one configuration."""
    algo_key, eval_key = jax.random.split(key)
    algo_state = algo.init(config, algo.setup(config), algo_key)
    return RunState(
        algo=algo_state,
        key=eval_key,
        evals_done=jnp.int32(0),
        best_return=jnp.float32(-jnp.inf),
        best_measured_fraction=jnp.float32(jnp.nan),
        best_params=algo.params(algo_state),
        diverged=jnp.bool_(False),
    )


def _train_period(algo: Algorithm, config: AgentConfig, algo_state: Any) -> tuple[Any, UpdateStats]:
    """One evaluation period's updates (a pure function of its operands, as `in_groups` needs): the new state, the
    losses [updates_per_eval] and the finished training episodes, summed over the period per env."""
    setup = algo.setup(config)

    def one_update(carry: tuple[Any, FinishedEpisodes], _):
        state, episodes = carry
        state, stats = algo.update(config, setup, state)
        return (state, jax.tree.map(jnp.add, episodes, stats.episodes)), stats.loss

    initial = (algo_state, FinishedEpisodes.zeros((config.num_envs,)))
    (algo_state, episodes), losses = jax.lax.scan(one_update, initial, None, config.updates_per_eval)
    return algo_state, UpdateStats(losses, episodes)


def run_evals(algo: Algorithm, config: AgentConfig, state: RunState, num_evals: int) -> tuple[RunState, EvalRow]:
    """Train for `num_evals` evaluation periods; returns the new state and one `EvalRow` per period."""
    setup = algo.setup(config)
    train_period = partial(_train_period, algo)
    if config.train_group:
        train_period = in_groups(train_period, config.train_group)

    def one_period(state: RunState, _):
        algo_state, stats = train_period(config, state.algo)
        train = stats.episodes.total().means()
        loss = stats.loss.mean()
        params = algo.params(algo_state)
        eval_key = jax.random.fold_in(state.key, state.evals_done)
        test = evaluate_greedy(algo, config, setup, params, eval_key, config.eval_episodes)
        diverged = state.diverged | ~jnp.isfinite(loss) | ~_all_finite(params)
        improved = (test.costed_return > state.best_return) & ~diverged
        evals_done = state.evals_done + 1
        row = EvalRow(evals_done * config.eval_every, test, train, loss, diverged)
        state = RunState(
            algo=algo_state,
            key=state.key,
            evals_done=evals_done,
            best_return=jnp.where(improved, test.costed_return, state.best_return),
            best_measured_fraction=jnp.where(improved, test.measured_fraction, state.best_measured_fraction),
            best_params=jax.tree.map(partial(jnp.where, improved), params, state.best_params),
            diverged=diverged,
        )
        return state, row

    return jax.lax.scan(one_period, state, None, num_evals)


def make_train(algo: Algorithm) -> Callable[[AgentConfig, jax.Array], tuple[RunState, EvalRow]]:
    """`train(config, key) -> (final RunState, EvalRow per evaluation)`: a whole run as one jitted program.

    Concrete configs are validated before compiling; under `jax.vmap` (a stacked config of traced leaves) the
    static fields are still checked and the traced ones are left to the caller (the sweep runner checks them).
    The program is compiled for the strategy current at the call (`amjax.strategy`), one per strategy.
    """

    @partial(jax.jit, static_argnums=2)
    def compiled(config: AgentConfig, key: jax.Array, strategy_name: str) -> tuple[RunState, EvalRow]:
        with strategy.use(strategy_name):
            return run_evals(algo, config, init_run(algo, config, key), config.num_evals)

    def train(config: AgentConfig, key: jax.Array) -> tuple[RunState, EvalRow]:
        if type(config) is not algo.config_type:
            raise TypeError(f"config: expected {algo.config_type.__name__}, got {type(config).__name__}")
        config.validate()
        return compiled(config, key, strategy.current())

    train.__doc__ = f"Train {algo.name}: `train(config, key) -> (RunState, EvalRow per evaluation)`."
    return train


def _argmax(values: jax.Array, key: jax.Array) -> jax.Array:
    return jnp.argmax(values, axis=-1)


def greedy_policy(outputs: Callable[[jax.Array], Any], mode: Callable[[Any, jax.Array], jax.Array] = _argmax) -> Policy:
    """A memoryless test policy taking `mode(outputs(obs), key)`: by default the argmax of Q-values."""

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        return mode(outputs(batch.obs), key), carry, None

    return act, None


__all__ = [
    "Algorithm",
    "EvalRow",
    "FinishedEpisodes",
    "Policy",
    "RESCORE_STREAM",
    "RunState",
    "UpdateStats",
    "evaluate",
    "evaluate_greedy",
    "greedy_policy",
    "init_run",
    "make_train",
    "rescore",
    "run_evals",
]
