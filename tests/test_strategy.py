"""amjax.strategy: the CPU and GPU layouts of the same programs. The choice follows the backend and can be
overridden; the GPU layout, forced on the CPU, computes what the CPU layout computes (to float rounding)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amjax import strategy
from amjax.agents import ALGORITHMS, DQNConfig, DRQNConfig, PPOConfig, PQNConfig, stack_configs
from amjax.batching import in_groups, uniform_cond
from amjax.sweep.batches import compiled_programs, rescore_program


def test_the_default_follows_the_backend_and_can_be_overridden(monkeypatch) -> None:
    monkeypatch.delenv(strategy.ENV_VAR, raising=False)
    assert jax.default_backend() == "cpu" and strategy.default() == "cpu" == strategy.current()
    assert strategy.for_backend("gpu") == "gpu" == strategy.for_backend("tpu")
    monkeypatch.setenv(strategy.ENV_VAR, "GPU")
    assert strategy.current() == "gpu"
    with strategy.use("cpu") as name:
        assert name == "cpu" == strategy.current()
        with strategy.use(None):  # None keeps the block's
            assert strategy.current() == "cpu"
    assert strategy.current() == "gpu"
    strategy.set_default("cpu")
    try:
        assert strategy.current() == "cpu"  # set_default wins over the environment variable
    finally:
        strategy.set_default(None)
    monkeypatch.setenv(strategy.ENV_VAR, "tpu")
    with pytest.raises(ValueError, match="AMJAX_STRATEGY: unknown strategy 'tpu'; allowed values: cpu, gpu"):
        strategy.current()
    with pytest.raises(ValueError, match="allowed values: cpu, gpu"), strategy.use("fast"):
        pass


def _jaxpr(fun, *args) -> str:
    return str(jax.make_jaxpr(fun)(*args))


def test_in_groups_runs_the_batch_at_once_under_gpu() -> None:
    x = jnp.arange(32.0).reshape(8, 4)

    def fun(x):  # a new function each time: JAX caches a traced function's program by its identity
        return jax.vmap(in_groups(lambda row: jnp.sin(row) @ row, 2))(x)

    with strategy.use("cpu"):
        grouped, grouped_jaxpr = fun(x), _jaxpr(lambda x: fun(x), x)
    with strategy.use("gpu"):
        whole, whole_jaxpr = fun(x), _jaxpr(lambda x: fun(x), x)
    assert "scan[" in grouped_jaxpr and "scan[" not in whole_jaxpr  # lax.map over groups only under cpu
    np.testing.assert_allclose(whole, grouped, rtol=1e-6)


@pytest.mark.parametrize("pred", [[True] * 4, [False] * 4, [True, False, False, True]], ids=["all", "none", "mixed"])
def test_uniform_cond_under_gpu_is_one_conditional_with_the_same_values(pred) -> None:
    pred, x = jnp.array(pred), jnp.arange(4.0)

    def fun(pred, x):
        return jax.vmap(lambda p, x: uniform_cond(p, lambda x: x + 10.0, lambda x: x * 2.0, x))(pred, x)

    with strategy.use("gpu"):
        out, jaxpr = fun(pred, x), _jaxpr(lambda *a: fun(*a), pred, x)
    with strategy.use("cpu"):
        ref, ref_jaxpr = fun(pred, x), _jaxpr(lambda *a: fun(*a), pred, x)
    np.testing.assert_array_equal(out, jnp.where(pred, x + 10.0, x * 2.0))
    np.testing.assert_array_equal(out, ref)
    # Under cpu the outer conditional (all members?) nests another uniform_cond (any member?); under gpu one
    # conditional of three branches (all / some / none), and only the "some" branch selects.
    assert jaxpr.count("cond[") == 1 and "custom_vmap" not in jaxpr and "custom_vmap" in ref_jaxpr
    with strategy.use("gpu"):
        (eqn,) = [e for e in jax.make_jaxpr(fun)(pred, x).eqns if e.primitive.name == "cond"]
    selects = ["select_n" in str(branch) for branch in eqn.params["branches"]]
    assert selects == [False, True, False]


def _configs(agent: str) -> list:
    """Small configurations of `agent` whose programs take every strategy-dependent path: configurations trained
    in groups of 2 (`train_group`), PPO's grouped epochs and value passes, the Q-learners' conditionals (learning
    starts mid-run, target syncs, DRQN's cached-target refresh), PQN's bootstrap values."""
    common = {"env_id": "CartPole-v0", "train_group": 2, "eval_episodes": 4}
    if agent == "ppo":
        base = PPOConfig(**common, num_envs=4, num_steps=32, num_minibatches=2, update_epochs=2, hidden=(16,))
        base = base.replace(total_timesteps=1024, eval_every=256)
    elif agent == "pqn":  # bootstrap values: gathered truncations and a branch on the CPU, one pass on a GPU
        base = PQNConfig(**common, num_envs=4, num_steps=32, num_minibatches=2, update_epochs=2, hidden=(16,))
        base = base.replace(total_timesteps=1024, eval_every=256)
    elif agent == "dqn":
        base = DQNConfig(**common, num_envs=2, buffer_size=512, batch_size=16, learning_starts=200, hidden=(16,))
        base = base.replace(total_timesteps=800, eval_every=400, target_update_interval=96)
    else:
        base = DRQNConfig(
            **common, buffer_size=64, batch_size=8, learning_starts=200, target_update_interval=160, hidden=(16,)
        )
        base = base.replace(rnn_size=8, total_timesteps=768, eval_every=384)
    return [base.replace(cost=cost, learning_rate=lr).validate() for cost in (0.1, 0.3) for lr in (1e-3, 3e-3)]


@pytest.mark.parametrize("agent", ["ppo", "dqn", "drqn", "pqn"])
@pytest.mark.slow
def test_the_gpu_layout_trains_as_the_cpu_layout(agent, monkeypatch) -> None:
    """A sweep batch's programs compiled for each strategy on the CPU: the same evaluation rows and re-scores (to
    float rounding, which training may grow a little), and two compiled programs, not one."""
    from amjax.agents import ppo

    monkeypatch.setattr(ppo, "_GROUP_BYTES", 1 << 12)  # PPO's epochs and value passes in groups of 2 configs
    algo, configs = ALGORITHMS[agent], _configs(agent)
    stacked = stack_configs(configs)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in range(len(configs))])
    devices = tuple(jax.devices()[:1])
    out = {}
    for name in strategy.STRATEGIES:
        init, chunk = compiled_programs(algo, configs[0].num_evals, devices, strategy_name=name)
        states, rows = chunk(stacked, init(stacked, keys))
        out[name] = (rows, rescore_program(algo, devices, strategy_name=name)(stacked, states))
    assert compiled_programs(algo, configs[0].num_evals, devices, "cpu")[1] is not chunk  # one per strategy
    (rows, rescored), (ref_rows, ref_rescored) = out["gpu"], out["cpu"]
    assert np.isfinite(np.asarray(ref_rows.loss)).all() and float(np.abs(ref_rows.loss).max()) > 0
    for got, want in ((rows.test, ref_rows.test), (rows.loss, ref_rows.loss), (rescored, ref_rescored)):
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3), got, want)


@pytest.mark.slow
def test_trainers_compile_one_program_per_strategy(monkeypatch) -> None:
    """`train` keys its compiled program on the strategy current at the call: a later override traces again."""
    from amjax.agents import dqn

    seen = []
    is_gpu = strategy.is_gpu
    monkeypatch.setattr(strategy, "is_gpu", lambda: seen.append(strategy.current()) or is_gpu())
    config = _configs("dqn")[0]
    with strategy.use("cpu"):
        ref = dqn.train(config, jax.random.PRNGKey(3))[1]
    assert set(seen) == {"cpu"}
    with strategy.use("gpu"):
        out = dqn.train(config, jax.random.PRNGKey(3))[1]
    assert "gpu" in seen  # traced again, under the GPU layout
    np.testing.assert_allclose(out.test.costed_return, ref.test.costed_return, rtol=1e-3, atol=1e-3)


@pytest.mark.slow
def test_a_sweep_compiles_for_the_strategy_of_its_caller(tmp_path, monkeypatch) -> None:
    """`run_sweep` compiles its batches on a background thread; a `strategy.use` block around it reaches them."""
    from amjax.sweep import SweepSpec, run_sweep

    seen = []
    is_gpu = strategy.is_gpu
    monkeypatch.setattr(strategy, "is_gpu", lambda: seen.append(strategy.current()) or is_gpu())
    spec = SweepSpec(
        envs=("CartPole-v0",),
        agents=("dqn",),
        costs=(0.1,),
        seeds=(0,),
        total_timesteps=800,
        eval_every=400,
        hyperparams={"buffer_size": 400, "learning_starts": 200, "hidden": (16,)},
    )
    with strategy.use("gpu"):
        result = run_sweep(spec, tmp_path / "sweep", progress=False, save_policies=False)
    assert set(seen) == {"gpu"} and len(result.table) == 1
