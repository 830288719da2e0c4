"""PQN: its Q(lambda) targets against a forward-view Python reference, one-step Q-learning at lambda 0, a vmapped
batch of configurations equal to each run alone, seed by seed, and its saved policies; recurrent PQN's targets
against a step-by-step reference (its memory probe, resets and vmapped runs are in test_recurrent.py)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax import strategy
from amjax.agents import (
    PQN,
    PQN_RNN,
    PQNConfig,
    PQNRNNConfig,
    load_policy,
    pqn,
    pqn_rnn,
    save_policy,
    stack_configs,
    unstack_config,
)
from amjax.agents.pqn import q_lambda_targets
from amjax.agents.q_learning import bootstrap_values, epsilon_greedy_act, recurrent_epsilon_greedy
from amjax.agents.rollout import rollout
from amjax.agents.training import evaluate

T, E = 7, 3  # one shape: the jitted targets compile once for every example
_targets = jax.jit(q_lambda_targets)


def forward_view(reward, terminated, done, next_q, gamma, lam):
    """Plain-Python lambda-returns of one env's [T] arrays, from their definition: the (1 - lam) lam^(n-1)-weighted
    n-step returns G^(n)_t for n < M, and lam^(M-1) G^(M)_t, where M counts the steps from t to the end of the
    episode or of the rollout, whichever comes first; G^(n)_t = sum_{i<n} gamma^i r_{t+i} + gamma^n (1 -
    terminated_{t+n-1}) next_q_{t+n-1} (a bootstrap from inside an episode never sees a termination)."""
    targets = np.zeros(len(reward))
    for t in range(len(reward)):
        end = next((k for k in range(t, len(reward)) if done[k]), len(reward) - 1)
        steps = end - t + 1  # M

        def n_step(n, t=t):
            rewards = sum(gamma**i * reward[t + i] for i in range(n))
            return rewards + gamma**n * (1 - terminated[t + n - 1]) * next_q[t + n - 1]

        mix = sum((1 - lam) * lam ** (n - 1) * n_step(n) for n in range(1, steps))
        targets[t] = mix + lam ** (steps - 1) * n_step(steps)
    return targets


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    done_rate=st.sampled_from([0.0, 0.2, 0.5]),
    gamma=st.floats(0.5, 1.0),
    lam=st.sampled_from([0.0, 0.3, 0.95, 1.0]),
)
def test_q_lambda_targets_match_the_forward_view(seed, done_rate, gamma, lam):
    rng = np.random.default_rng(seed)
    reward = rng.normal(size=(T, E)).astype(np.float32)
    next_q = rng.normal(size=(T, E)).astype(np.float32)
    done = rng.random((T, E)) < done_rate
    terminated = done & (rng.random((T, E)) < 0.5)  # the other ends are truncations, which bootstrap
    got = np.asarray(_targets(reward, terminated, done, next_q, gamma, lam))
    for e in range(E):
        want = forward_view(reward[:, e], terminated[:, e], done[:, e], next_q[:, e], gamma, lam)
        np.testing.assert_allclose(got[:, e], want, rtol=1e-4, atol=1e-4)


def test_lambda_zero_is_one_step_q_learning():
    rng = np.random.default_rng(0)
    reward, next_q = rng.normal(size=(2, T, E)).astype(np.float32)
    done = rng.random((T, E)) < 0.3
    terminated = done & (rng.random((T, E)) < 0.5)
    got = np.asarray(_targets(reward, terminated, done, next_q, 0.9, 0.0))
    np.testing.assert_allclose(got, reward + 0.9 * (1 - terminated) * next_q, rtol=1e-6)


TINY = PQNConfig(
    total_timesteps=2048, eval_every=1024, num_envs=4, num_steps=32, num_minibatches=2, hidden=(32,), eval_episodes=2
)


NOISY_OPTIONS = {"mode": "noisy", "noise_std": 0.1, "extra_obs": ("since_measured", "last_action")}


@pytest.mark.parametrize(
    ("time_limits", "options"),
    [((200, 200), {}), ((13, 13), {}), ((3, 3), {}), ((13, 3), {}), ((13, 13), NOISY_OPTIONS)],
)
@pytest.mark.parametrize("layout", ["cpu", "gpu"])
def test_bootstrap_values_are_the_values_of_every_pre_reset_next_observation(time_limits, options, layout):
    """PQN's bootstrap values (mostly kept from acting) equal one pass of the network over every pre-reset next
    observation wherever a target uses them (not after a termination): for a vmapped batch of two members with
    their own time limits, with no truncation, a few (gathered), more than the envs (the full pass) and one member of
    each (both branches and a select), with the measurement options that draw noise and append to the observation,
    under both strategies; and a member alone as in the batch."""
    config = PQNConfig(num_envs=4, num_steps=24, num_minibatches=2, hidden=(16,), cost=0.1, **options)
    config = config.replace(total_timesteps=9600, eval_every=960).validate()  # the options checked
    setup = PQN.setup(config)

    def values(params, key, time_limit):
        inner = setup.env_params.env_params.replace(max_steps_in_episode=time_limit)
        env_params = setup.env_params.replace(env_params=inner)
        state = pqn.init(config, setup, jax.random.key(0))
        act = epsilon_greedy_act(setup, params, jnp.float32(0.3), greedy_values=True)
        _, _, transitions, acted, _ = rollout(setup.env, env_params, state.envs, None, act, key, config.num_steps)
        kept = bootstrap_values(lambda p, obs: setup.network.apply(p, obs).max(-1), params, acted, transitions)
        fresh = setup.network.apply(params, transitions.next_obs).max(-1)
        return kept, fresh, transitions

    obs = pqn.init(config, setup, jax.random.key(0)).envs.obs
    params = jax.vmap(lambda k: setup.network.init(k, obs[:1]))(jax.random.split(jax.random.key(1), 2))
    keys, limits = jax.random.split(jax.random.key(2), 2), jnp.array(time_limits)
    with strategy.use(layout):
        kept, fresh, transitions = jax.jit(jax.vmap(values))(params, keys, limits)
        alone = jax.jit(values)(jax.tree.map(lambda x: x[1], params), keys[1], limits[1])
    truncated = np.asarray(transitions.done & ~transitions.terminated)
    overflow = truncated.sum((1, 2)) > config.num_envs
    assert overflow.tolist() == [
        limit < 12 for limit in time_limits
    ]  # from a reset, a limit over T / 2 truncates an env at most once
    assert truncated.any((1, 2)).tolist() == [limit < 200 for limit in time_limits]
    used = ~np.asarray(transitions.terminated)
    np.testing.assert_allclose(np.asarray(kept)[used], np.asarray(fresh)[used], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(alone[0]), np.asarray(kept[1]), rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_vmap_equals_alone_and_seeds_differ(assert_batch_equals_alone, training_programs):
    settings = [(0.0, 1e-3, 0.9), (0.2, 3e-4, 0.5)]
    configs = [TINY.replace(cost=c, learning_rate=lr, q_lambda=lam) for c, lr, lam in settings]
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)])
    assert_batch_equals_alone(PQN, configs, keys)
    alone = training_programs(PQN).alone
    config = unstack_config(stack_configs(configs), 0)
    _, first = alone(config, keys[0])
    _, again = alone(config, keys[0])
    _, other = alone(config, keys[1])
    assert np.array_equal(np.asarray(first.loss), np.asarray(again.loss))
    assert not np.array_equal(np.asarray(first.loss), np.asarray(other.loss))


def test_bad_fields_name_themselves():
    with pytest.raises(ValueError, match="num_minibatches=3 must divide"):
        TINY.replace(num_minibatches=3).validate()
    with pytest.raises(ValueError, match="q_lambda"):
        TINY.replace(q_lambda=1.5).validate()
    with pytest.raises(ValueError, match="layer_norm"):
        TINY.replace(layer_norm="yes").validate()


@pytest.mark.slow
def test_saved_policy_round_trip_and_actor(tmp_path):
    """A trained PQN policy saved and loaded acts and scores as in memory; its NumPy actor (the Gymnasium bridge's)
    takes the network's greedy action, LayerNorm parameters included."""
    config = TINY.replace(cost=0.2)
    state, _ = pqn.train(config, jax.random.key(0))
    saved = load_policy(save_policy(tmp_path / "pqn.msgpack", config, state.best_params))
    assert saved.agent == "pqn" and saved.config == config
    setup = PQN.setup(config)
    key = jax.random.key(1)
    policy = pqn.greedy(config, setup, state.best_params, 6)
    in_memory = evaluate(setup.env, setup.env_params, setup.max_steps, policy, key, 6).means()
    assert saved.evaluate(key, 6) == {k: float(v) for k, v in dataclasses.asdict(in_memory).items()}
    observations = np.asarray(jax.random.uniform(jax.random.key(2), (20, 5), minval=-0.3, maxval=0.3))
    q_values = np.asarray(setup.network.apply(state.best_params, observations))
    actor = saved.actor()
    assert [actor(obs) for obs in observations] == q_values.argmax(-1).tolist()
    assert any("LayerNorm" in name for name in state.best_params["params"]["MLP_0"])


@pytest.mark.slow
def test_recurrent_targets_bootstrap_from_the_carry_after_each_step():
    """Recurrent PQN's targets against a step-by-step reference: the network called one env step at a time from a
    mid-episode hidden state, each next observation's value one more step from the carry after its step (no reset),
    mixed by the forward view. And the unroll the minibatches re-run from the rollout's initial hidden states
    reproduces the acting Q-values."""
    config = PQNRNNConfig(num_envs=3, num_steps=40, num_minibatches=1, hidden=(16,), rnn_size=8, cost=0.1)
    setup = PQN_RNN.setup(config)
    net, state = setup.network, pqn_rnn.init(config, setup, jax.random.key(0))
    start = state.carry + 0.3
    act = recurrent_epsilon_greedy(setup, state.params, jnp.float32(0.5))
    _, last, transitions, (carries, first), _ = rollout(
        setup.env, setup.env_params, state.envs, start, act, jax.random.key(1), config.num_steps
    )
    assert transitions.done.any()  # episodes end inside the rollout
    got = np.asarray(pqn_rnn.rollout_targets(config, net, state.params, transitions, carries, last))
    carry, acted_q, next_q = start, [], []
    for t in range(config.num_steps):
        carry, q = net.apply(state.params, carry, transitions.obs[t], first[t])
        _, q_next = net.apply(state.params, carry, transitions.next_obs[t], jnp.zeros(config.num_envs, bool))
        acted_q.append(q)
        next_q.append(q_next.max(-1))
    reward = config.reward_scale * np.asarray(transitions.reward)
    terminated, done, next_q = np.asarray(transitions.terminated), np.asarray(transitions.done), np.stack(next_q)
    for e in range(config.num_envs):
        want = forward_view(reward[:, e], terminated[:, e], done[:, e], next_q[:, e], config.gamma, config.q_lambda)
        np.testing.assert_allclose(got[:, e], want, rtol=1e-4, atol=1e-4)
    _, unrolled = net.apply(state.params, start, transitions.obs, first, method="unroll")
    np.testing.assert_allclose(unrolled, np.stack(acted_q), rtol=1e-5, atol=1e-5)
