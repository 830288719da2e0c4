"""The actor-critic agents' test policy (`eval_policy`, amjax/agents/ppo_core.py): its most probable action
("greedy", the default), the policy as trained ("stochastic"), or its most probable control measuring as the policy
draws it ("greedy_control").

Why it matters: a deterministic memoryless policy that skips on a stale observation sees it again and never
measures again; PPO's policies measure as a mixed strategy, and on costed LunarLander-v3 their modes crashed while
the policies themselves landed (docs/lunar_lander.md)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax.agents import PPOConfig, load_policy, ppo, save_policy
from amjax.agents.policies import Categorical, GaussianOutputs, HybridGaussian
from amjax.agents.ppo_core import eval_action as ppo_eval_action
from amjax.agents.setup import training_env
from amjax.agents.training import evaluate


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), controls=st.integers(1, 5))
def test_sampled_measure_keeps_the_most_probable_control(seed, controls):
    """Invariant: the control is the argmax of the control's marginal whatever the draw."""
    dist = Categorical(2 * controls, measure=True)
    logits = jnp.asarray(np.random.default_rng(seed).normal(size=(64, 2 * controls)) * 2, jnp.float32)
    action = np.asarray(dist.mode_sampling_measure(jax.random.key(seed), logits))
    probs = np.asarray(jax.nn.softmax(logits))
    np.testing.assert_array_equal(action % controls, np.argmax(probs[:, :controls] + probs[:, controls:], -1))
    assert set(np.unique(action // controls)) <= {0, 1}


def test_sampled_measure_has_the_policy_probability_given_the_control():
    # controls 0, 1; P(skip, c) = (0.1, 0.2), P(measure, c) = (0.3, 0.4): control 1 (0.6), P(measure | 1) = 2/3.
    n = 100_000
    logits = jnp.broadcast_to(jnp.log(jnp.array([0.1, 0.2, 0.3, 0.4])), (n, 4))
    action = np.asarray(Categorical(4, measure=True).mode_sampling_measure(jax.random.key(0), logits))
    assert set(np.unique(action % 2)) == {1}
    assert (action >= 2).mean() == pytest.approx(2 / 3, abs=5e-3)
    assert int(Categorical(4, measure=True).mode(logits[0])) == 3  # the mode measures on every step instead


def test_sampled_measure_of_the_hybrid_gaussian_is_bernoulli_and_control_is_the_mean():
    n = 100_000
    out = GaussianOutputs(jnp.full((n, 2), 0.5), jnp.zeros((n, 2)), jnp.full(n, -1.0))
    action = np.asarray(HybridGaussian(2, measure=True).mode_sampling_measure(jax.random.key(0), out))
    assert action[:, 0].mean() == pytest.approx(1 / (1 + np.exp(1.0)), abs=5e-3)
    np.testing.assert_array_equal(action[:, 1:], 0.5)


def test_without_measure_the_eval_action_is_the_mode():
    logits = jnp.asarray(np.random.default_rng(0).normal(size=(16, 3)), jnp.float32)
    dist = Categorical(3)
    np.testing.assert_array_equal(dist.mode_sampling_measure(jax.random.key(0), logits), dist.mode(logits))


TINY = PPOConfig(
    env_id="CartPole-v0",
    cost=0.1,
    total_timesteps=2048,
    eval_every=1024,
    num_envs=4,
    num_steps=64,
    num_minibatches=4,
    eval_episodes=2,
    hidden=(16,),
)


def _half_measuring_params(config):
    """PPO parameters whose policy measures with probability 1/2 whatever the observation (measure logits = skip
    logits), with control 0 the most probable."""
    setup = ppo.PPO.setup(config)
    params = ppo.init(config, setup, jax.random.key(0)).params
    kernel = jnp.zeros_like(params["params"]["logits"]["kernel"])
    params["params"]["logits"] = {"kernel": kernel, "bias": jnp.array([1.0, 0.0, 1.0, 0.0])}
    return setup, params


@pytest.mark.parametrize("eval_policy", ["stochastic", "greedy_control", "greedy"])
def test_ppo_test_policy_follows_eval_policy(eval_policy):
    config = TINY.replace(eval_policy=eval_policy)
    setup, params = _half_measuring_params(config)
    env, env_params, max_steps = training_env(config)
    episodes = evaluate(env, env_params, max_steps, ppo.greedy(config, setup, params, 16), jax.random.key(1), 16)
    fraction = float(episodes.sums.measurements / episodes.sums.length)
    if eval_policy == "greedy":  # ties go to the first (skipping) action: never measured after the reset
        assert fraction == 0.0
    else:
        assert 0.35 < fraction < 0.65


def test_actor_draws_a_fresh_key_each_step(tmp_path):
    config = TINY.replace(eval_policy="stochastic")
    _, params = _half_measuring_params(config)
    saved = load_policy(save_policy(tmp_path / "p.msgpack", config, params))
    obs = np.zeros(5, np.float32)
    actor = saved.actor(seed=3)
    measured = np.array([actor(obs) >= 2 for _ in range(200)])
    assert 0.3 < measured.mean() < 0.7
    again = saved.actor(seed=3)
    assert [again(obs) >= 2 for _ in range(200)] == measured.tolist()  # the same seed, the same draws


def test_eval_policy_is_checked_before_compiling():
    allowed = "'greedy', 'stochastic', 'greedy_control'"
    with pytest.raises(ValueError, match=f"eval_policy: got 'sample'; allowed values: {allowed}"):
        TINY.replace(eval_policy="sample").validate()


def test_eval_action_dispatches_on_the_config():
    n = 20_000
    logits = jnp.broadcast_to(jnp.log(jnp.array([0.1, 0.2, 0.3, 0.4])), (n, 4))
    dist = Categorical(4, measure=True)

    def actions(eval_policy):
        return np.asarray(ppo_eval_action(TINY.replace(eval_policy=eval_policy), dist, logits, jax.random.key(0)))

    assert set(np.unique(actions("greedy"))) == {3}
    assert set(np.unique(actions("greedy_control"))) == {1, 3}
    counts = np.bincount(actions("stochastic"), minlength=4) / n
    np.testing.assert_allclose(counts, [0.1, 0.2, 0.3, 0.4], atol=0.015)


def test_greedy_control_of_a_vanilla_run_is_the_greedy_policy():
    """A vanilla run has no measuring choice: "greedy_control" is "greedy" exactly (LunarLander's PPO preset uses
    it, and its vanilla scores and the always-measure bounds drawn from them stay the greedy policy's)."""
    config = TINY.replace(vanilla=True)
    setup = ppo.PPO.setup(config)
    params = ppo.init(config, setup, jax.random.key(2)).params
    env, env_params, max_steps = training_env(config)

    def scores(eval_policy):
        cfg = config.replace(eval_policy=eval_policy)
        policy = ppo.greedy(cfg, setup, params, 8)
        return jax.tree.map(np.asarray, evaluate(env, env_params, max_steps, policy, jax.random.key(5), 8))

    greedy, greedy_control = scores("greedy"), scores("greedy_control")
    jax.tree.map(np.testing.assert_array_equal, greedy, greedy_control)
    assert float(greedy.sums.length) > 0
