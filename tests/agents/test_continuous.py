"""Box control: the hybrid Gaussian + Bernoulli policy of PPO (amjax/agents/policies.py) against scipy, its
sampling statistics, saved Box policies, and the clear error of an agent that needs Discrete actions. (PPO on
Pendulum-v1 vmapped == alone and seeds differing: test_algorithms.py; learning: test_learning.py.)"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from amjax.agents import DQNConfig, PPOConfig, load_policy, ppo, save_policy
from amjax.agents.policies import Categorical, GaussianOutputs, HybridGaussian, for_action_space
from amjax.factory import make
from amjax.wrappers.active_measure import ActiveMeasure, AlwaysMeasured

TINY = PPOConfig(
    env_id="Pendulum-v1",
    total_timesteps=2048,
    eval_every=1024,
    num_envs=4,
    num_steps=64,
    num_minibatches=4,
    eval_episodes=2,
    hidden=(16,),
)


def _outputs(rng: np.random.Generator, batch: int, controls: int, measure: bool) -> GaussianOutputs:
    return GaussianOutputs(
        mean=jnp.asarray(rng.normal(size=(batch, controls)), jnp.float32),
        log_std=jnp.asarray(rng.uniform(-1.5, 0.5, size=(batch, controls)), jnp.float32),
        measure_logit=jnp.asarray(rng.normal(size=batch) * 2, jnp.float32) if measure else None,
    )


@pytest.mark.parametrize("measure", [True, False])
def test_hybrid_log_prob_and_entropy_match_scipy(measure):
    rng = np.random.default_rng(0)
    dist = HybridGaussian(controls=3, measure=measure)
    out = _outputs(rng, 64, 3, measure)
    action = dist.sample(jax.random.key(1), out)
    assert action.shape == (64, 3 + measure)
    mean, std = np.asarray(out.mean), np.exp(np.asarray(out.log_std))
    control = np.asarray(action)[:, int(measure) :]
    expected = stats.norm.logpdf(control, mean, std).sum(-1)
    expected_entropy = stats.norm.entropy(mean, std).sum(-1)
    if measure:
        p = 1 / (1 + np.exp(-np.asarray(out.measure_logit, np.float64)))
        bit = np.asarray(action)[:, 0]
        assert set(np.unique(bit)) <= {0.0, 1.0}
        expected = expected + stats.bernoulli.logpmf(bit, p)
        expected_entropy = expected_entropy + stats.bernoulli.entropy(p)
    np.testing.assert_allclose(dist.log_prob(out, action), expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dist.entropy(out), expected_entropy, rtol=1e-5, atol=1e-5)


def test_hybrid_samples_follow_their_parameters():
    dist = HybridGaussian(controls=2, measure=True)
    n = 200_000
    out = GaussianOutputs(
        mean=jnp.broadcast_to(jnp.array([0.5, -1.0]), (n, 2)),
        log_std=jnp.broadcast_to(jnp.log(jnp.array([0.3, 2.0])), (n, 2)),
        measure_logit=jnp.full(n, 1.0),
    )
    action = np.asarray(dist.sample(jax.random.key(0), out))
    assert action[:, 0].mean() == pytest.approx(1 / (1 + np.exp(-1.0)), abs=5e-3)  # P(measure) = sigmoid(1)
    np.testing.assert_allclose(action[:, 1:].mean(0), [0.5, -1.0], atol=2e-2)
    np.testing.assert_allclose(action[:, 1:].std(0), [0.3, 2.0], rtol=1e-2)
    # Control and measuring are drawn independently.
    assert abs(np.corrcoef(action[:, 0], action[:, 1])[0, 1]) < 1e-2
    np.testing.assert_array_equal(dist.mode(out)[0], [1.0, 0.5, -1.0])


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    controls=st.integers(1, 4),
    measure=st.booleans(),
)
def test_the_mode_is_the_most_probable_action(seed, controls, measure):
    """Invariant: no sampled action is more probable than the greedy one."""
    rng = np.random.default_rng(seed)
    dist = HybridGaussian(controls, measure)
    out = _outputs(rng, 32, controls, measure)
    sampled = dist.log_prob(out, dist.sample(jax.random.key(seed), out))
    greedy = dist.log_prob(out, dist.mode(out))
    assert np.all(np.asarray(greedy) >= np.asarray(sampled) - 1e-5)


def test_distribution_follows_the_action_space():
    env, params = make("Pendulum-v1", cost=0.1)
    assert isinstance(env, ActiveMeasure)
    assert for_action_space(env.action_space(params), measure=True) == HybridGaussian(1, True)
    plain, plain_params = make("Pendulum-v1", vanilla=True)
    assert isinstance(plain, AlwaysMeasured)
    assert for_action_space(plain.action_space(plain_params), measure=False) == HybridGaussian(1, False)
    cartpole, cartpole_params = make("CartPole-v0", cost=0.1)
    assert for_action_space(cartpole.action_space(cartpole_params), measure=True) == Categorical(4, measure=True)


def test_agents_for_discrete_actions_refuse_box_envs_before_compiling():
    with pytest.raises(ValueError, match=r"env_id: Pendulum-v1 has a Box action space; DQNConfig handles Discrete"):
        DQNConfig(env_id="Pendulum-v1").validate()


@pytest.mark.slow
def test_box_policy_round_trip_and_actor(tmp_path):
    state, _ = ppo.train(TINY.replace(cost=0.1), jax.random.key(0))
    saved = load_policy(save_policy(tmp_path / "pendulum.msgpack", TINY.replace(cost=0.1), state.best_params))
    actor = saved.actor()
    env, params = make("Pendulum-v1", cost=0.1)
    obs, _ = env.reset(jax.random.key(2), params)
    action = actor(np.asarray(obs))
    assert isinstance(action, np.ndarray) and action.shape == (2,) and action.dtype == np.float32
    assert action[0] in (0.0, 1.0)  # the measuring choice; then the (unclipped) torque
    key = jax.random.key(5)
    assert saved.evaluate(key, 3) == saved.evaluate(key, 3)
