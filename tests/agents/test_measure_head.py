"""The factored measurement head (`measure_head="factored"`): a control head and a measure head whose joint
outputs the rest of each algorithm uses unchanged."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnax.environments import spaces

from amjax.agents import DQNConfig, DRQNConfig, PPOConfig, PPORNNConfig
from amjax.agents.dqn import network as dqn_network
from amjax.agents.networks import ActorCritic
from amjax.agents.policies import Categorical, for_action_space


@pytest.mark.parametrize("dueling", [True, False])
def test_factored_q_is_additive_and_its_argmax_is_taken_apart(dueling):
    """Q(s, c, m) = V + A_c + A_m (centred when dueling): joint argmax = (argmax over c, argmax over m)."""
    config = DQNConfig(measure_head="factored", instruments="default", dueling=dueling, hidden=(8,))
    net = dqn_network(config, spaces.Discrete(8))  # 2 controls x 4 masks (two instruments)
    assert net.factored_masks == 4
    obs = jax.random.normal(jax.random.key(0), (64, 5))
    params = net.init(jax.random.key(1), obs)
    names = set(params["params"])
    assert {"control_advantage", "measure_advantage"} <= names and "advantage" not in names and "q" not in names
    q = np.asarray(net.apply(params, obs)).reshape(64, 4, 2)  # [batch, mask, control]
    # additive: every 2x2 minor of Q over (mask, control) vanishes
    np.testing.assert_allclose(q[:, 1:, 1:] - q[:, 1:, :1] - q[:, :1, 1:] + q[:, :1, :1], 0.0, atol=1e-5)
    joint = q.reshape(64, 8).argmax(-1)
    np.testing.assert_array_equal(joint % 2, q.mean(1).argmax(-1))
    np.testing.assert_array_equal(joint // 2, q.mean(2).argmax(-1))


def test_factored_policy_is_a_product_of_two_categoricals():
    """The joint log-probability of (c, m) is log p_control(c) + log p_measure(m), and the entropy adds up."""
    dist = for_action_space(spaces.Discrete(6), measure=True, factored=True)
    assert dist == Categorical(6, measure=True, readings=1, factored=True)
    net = ActorCritic(dist, hidden=(8,))
    obs = jax.random.normal(jax.random.key(0), (16, 5))
    params = net.init(jax.random.key(1), obs)
    logits, _ = net.apply(params, obs)
    head = params["params"]
    x = jnp.tanh(obs @ head["actor_torso"]["Dense_0"]["kernel"] + head["actor_torso"]["Dense_0"]["bias"])
    control = x @ head["control_logits"]["kernel"] + head["control_logits"]["bias"]
    measure = x @ head["measure_logits"]["kernel"] + head["measure_logits"]["bias"]
    log_c, log_m = jax.nn.log_softmax(control), jax.nn.log_softmax(measure)
    actions = jnp.arange(6)
    got = jax.vmap(lambda a: dist.log_prob(logits, jnp.full(16, a)), out_axes=1)(actions)
    np.testing.assert_allclose(got, log_c[:, actions % 3] + log_m[:, actions // 3], atol=1e-5)
    entropy = -(jnp.exp(log_c) * log_c).sum(-1) - (jnp.exp(log_m) * log_m).sum(-1)
    np.testing.assert_allclose(dist.entropy(logits), entropy, atol=1e-5)


@pytest.mark.parametrize("config", [DQNConfig, DRQNConfig, PPOConfig, PPORNNConfig])
def test_measure_head_is_checked(config):
    with pytest.raises(ValueError, match="measure_head: got 'split'"):
        config(measure_head="split").validate()
    with pytest.raises(ValueError, match="a vanilla run has no measure choice"):
        config(measure_head="factored", vanilla=True).validate()
    assert config(measure_head="factored").factored_masks == 2
    assert config(measure_head="factored", instruments="default").factored_masks == 4
    assert config().factored_masks == 0


def test_box_control_needs_no_factored_head():
    with pytest.raises(ValueError, match="already has a measure entry"):
        PPOConfig(env_id="Pendulum-v1", measure_head="factored").validate()


def _initial_measure_probability(dist, prior, readings=1):
    """Mean over observations of the initial policy's probability of measuring each reading."""
    net = ActorCritic(dist, hidden=(8,), measure_prior=prior)
    obs = jax.random.normal(jax.random.key(0), (256, 5))
    outputs, _ = net.apply(net.init(jax.random.key(1), obs), obs)
    if isinstance(dist, Categorical):
        masks = 2**readings
        probs = jax.nn.softmax(outputs).reshape(256, masks, -1).sum(-1)  # [obs, mask]
        bits = np.array([[(m >> r) & 1 for r in range(readings)] for m in range(masks)])
        return np.asarray(probs @ bits).mean(0)  # P(reading r measured)
    return np.asarray(jax.nn.sigmoid(outputs.measure_logit)).reshape(256, -1).mean(0)


@pytest.mark.parametrize("prior", [0.2, 0.9])
@pytest.mark.parametrize("case", ["joint", "factored", "instruments", "box", "box_instruments"])
def test_measure_prior_sets_the_initial_probability_of_measuring(case, prior):
    """Every policy head starts measuring each reading with probability `measure_prior` (small initial weights),
    and 0.5 gives exactly the zero biases of the uniform policy."""
    readings = 2 if "instruments" in case else 1
    if case.startswith("box"):
        dist = for_action_space(spaces.Box(-1.0, 1.0, (1 + readings,)), measure=True, readings=readings)
    else:
        dist = for_action_space(
            spaces.Discrete(3 * 2**readings), measure=True, readings=readings, factored=case == "factored"
        )
    np.testing.assert_allclose(_initial_measure_probability(dist, prior, readings), prior, atol=0.02)
    net = ActorCritic(dist, hidden=(8,))
    params = net.init(jax.random.key(1), jnp.zeros((1, 5)))["params"]
    heads = [layer for name, layer in params.items() if "torso" not in name and isinstance(layer, dict)]
    assert heads and all(np.all(np.asarray(layer["bias"]) == 0.0) for layer in heads)


def test_measure_prior_leaves_vanilla_runs_and_controls_alone():
    """A vanilla head has no measure biases to set; with a prior the controls stay uniform given the measure bit."""
    vanilla = ActorCritic(for_action_space(spaces.Discrete(3), measure=False), hidden=(8,), measure_prior=0.9)
    params = vanilla.init(jax.random.key(1), jnp.zeros((1, 5)))["params"]
    np.testing.assert_array_equal(params["logits"]["bias"], 0.0)
    dist = for_action_space(spaces.Discrete(6), measure=True)
    params = ActorCritic(dist, hidden=(8,), measure_prior=0.9).init(jax.random.key(1), jnp.zeros((1, 5)))["params"]
    np.testing.assert_allclose(params["logits"]["bias"], [0, 0, 0] + [np.log(9)] * 3, rtol=1e-6)


@pytest.mark.parametrize("config", [PPOConfig, PPORNNConfig])
@pytest.mark.parametrize("bad", [0.0, 1.0, 1.5, float("nan")])
def test_measure_prior_is_checked(config, bad):
    with pytest.raises(ValueError, match=r"measure_prior: got .*allowed values: finite numbers in \(0.0, 1.0\)"):
        config(measure_prior=bad).validate()
