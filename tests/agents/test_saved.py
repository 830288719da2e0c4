"""Saved policies: save -> load -> evaluate equals the in-memory policy; corrupt or mismatched files are refused."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from flax import serialization

from amjax.agents import ALGORITHMS, PolicyFileError, agent_of, load_policy, ppo, save_policy, training_env
from amjax.agents import drqn as drqn_module
from amjax.agents import pqn_rnn as pqn_rnn_module
from amjax.agents.training import evaluate

PPO_CONFIG = ppo.PPOConfig(
    env_id="CartPole-v0",
    cost=0.2,
    num_envs=4,
    num_steps=32,
    hidden=(16,),
    total_timesteps=2560,
    eval_every=1280,
    learning_rate=3e-3,
)


@pytest.fixture(scope="module")
def trained():
    state, rows = ppo.train(PPO_CONFIG, jax.random.key(0))
    return state, rows


def _in_memory(config, params, key, episodes, module):
    setup = ALGORITHMS[agent_of(config)].setup(config)
    policy = module.greedy(config, setup, params, episodes)
    means = evaluate(setup.env, setup.env_params, setup.max_steps, policy, key, episodes).means()
    return {k: float(v) for k, v in dataclasses.asdict(means).items()}


@pytest.mark.slow
def test_save_load_evaluate_equals_in_memory(tmp_path, trained):
    state, rows = trained
    path = save_policy(tmp_path / "p.msgpack", PPO_CONFIG, state.best_params, {"note": "test"})
    saved = load_policy(path)
    assert saved.agent == "ppo" and saved.config == PPO_CONFIG and saved.info == {"note": "test"}
    chex_equal = jax.tree.map(
        lambda a, b: np.array_equal(np.asarray(a), np.asarray(b)), saved.params, state.best_params
    )
    assert all(jax.tree.leaves(chex_equal))
    key = jax.random.key(7)
    assert saved.evaluate(key, 12) == _in_memory(PPO_CONFIG, state.best_params, key, 12, ppo)
    # The best evaluation's parameters reproduce the best evaluation's score (same key as the driver used).
    best = int(np.argmax(np.asarray(rows.test.costed_return)))
    eval_key = jax.random.fold_in(state.key, best)
    assert saved.evaluate(eval_key, PPO_CONFIG.eval_episodes)["costed_return"] == pytest.approx(
        float(state.best_return), rel=1e-6
    )
    # Scored at another cost: same actions, the cost changes the costed return only.
    other = saved.evaluate(key, 12, cost=0.0)
    assert other["raw_return"] == other["costed_return"] == pytest.approx(saved.evaluate(key, 12)["raw_return"])


RECURRENT = {
    "drqn": (drqn_module, drqn_module.DRQNConfig(env_id="CartPole-v0", cost=0.1, hidden=(16,), rnn_size=8)),
    "pqn-rnn": (pqn_rnn_module, pqn_rnn_module.PQNRNNConfig(env_id="CartPole-v0", cost=0.1, hidden=(16,), rnn_size=8)),
}


@pytest.mark.parametrize("name", sorted(RECURRENT))
@pytest.mark.slow
def test_recurrent_policy_round_trip_and_actor(tmp_path, name):
    """A recurrent Q-network's policy (pqn-rnn's with LayerNorm parameters) saved and loaded scores as in memory."""
    module, config = RECURRENT[name]
    algo = ALGORITHMS[name]
    params = algo.params(module.init(config, algo.setup(config), jax.random.key(3)))
    saved = load_policy(save_policy(tmp_path / "r.msgpack", config, params))
    assert saved.agent == name
    key = jax.random.key(1)
    assert saved.evaluate(key, 5) == _in_memory(config, params, key, 5, module)
    # The one-env actor follows the batched greedy policy step by step, hidden state included.
    env, env_params, _ = training_env(config)
    obs, env_state = env.reset(jax.random.key(0), env_params)
    act, carry = saved.policy(num_envs=1)
    actor = saved.actor()
    from amjax.agents.rollout import EnvBatch

    first = True
    for t in range(30):
        batch = EnvBatch(obs[None], None, np.array([first]))
        expected, carry, _ = act(batch, carry, jax.random.key(0))
        assert actor(np.asarray(obs)) == int(expected[0])
        obs, env_state, *_ = env.step(jax.random.key(t), env_state, int(expected[0]), env_params)
        first = False


def _payload(path):
    return serialization.msgpack_restore(path.read_bytes())


def _write(path, payload):
    path.write_bytes(serialization.msgpack_serialize(payload))


def test_bad_files_are_refused_with_the_reason(tmp_path, trained):
    state, _ = trained
    good = save_policy(tmp_path / "good.msgpack", PPO_CONFIG, state.best_params)
    data = good.read_bytes()

    truncated = tmp_path / "truncated.msgpack"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(PolicyFileError, match="truncated.msgpack: unreadable policy file"):
        load_policy(truncated)

    garbage = tmp_path / "garbage.msgpack"
    garbage.write_bytes(b"\x00not msgpack at all")
    with pytest.raises(PolicyFileError, match="unreadable"):
        load_policy(garbage)

    foreign = tmp_path / "foreign.msgpack"
    _write(foreign, {"weights": [1, 2, 3]})
    with pytest.raises(PolicyFileError, match="not an amjax-policy file"):
        load_policy(foreign)

    future = tmp_path / "future.msgpack"
    _write(future, {**_payload(good), "version": 99})
    with pytest.raises(PolicyFileError, match="version 99"):
        load_policy(future)

    # The config describes a wider network than the stored parameters.
    wider = tmp_path / "wider.msgpack"
    config = json.loads(_payload(good)["config"])
    _write(wider, {**_payload(good), "config": json.dumps({**config, "hidden": [32]})})
    needs = r"Dense_0.\]\[.bias.\] has shape \(16,\) float32, the ppo network of its config needs \(32,\)"
    with pytest.raises(PolicyFileError, match=needs):
        load_policy(wider)

    # A layer missing altogether.
    missing = tmp_path / "missing.msgpack"
    payload = _payload(good)
    params = payload["params"]
    params["params"].pop(sorted(params["params"])[0])
    _write(missing, payload)
    with pytest.raises(PolicyFileError, match="do not fit the ppo network"):
        load_policy(missing)

    unknown_agent = tmp_path / "agent.msgpack"
    _write(unknown_agent, {**_payload(good), "agent": "sarsa"})
    with pytest.raises(PolicyFileError, match="unknown agent 'sarsa'"):
        load_policy(unknown_agent)

    with pytest.raises(FileNotFoundError, match="path: no policy file"):
        load_policy(tmp_path / "absent.msgpack")
