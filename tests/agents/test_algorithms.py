"""PPO and Dueling Double DQN: scanned maths vs slow references, determinism, vmapped == alone, divergence; the
measurement options (instruments, the factored head, cost-conditioning) of every agent that has them."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amjax import strategy
from amjax.agents import (
    ALGORITHMS,
    DQN,
    PPO,
    PQN,
    PQN_RNN,
    DQNConfig,
    DRQNConfig,
    PPOConfig,
    PPORNNConfig,
    PQNConfig,
    PQNRNNConfig,
    agent_of,
    stack_configs,
    training_env,
    unstack_config,
)
from amjax.agents.drqn import sequence_targets
from amjax.agents.ppo_core import PPOBaseConfig, gae, rollout_advantages
from amjax.agents.q_learning import (
    QLearningConfig,
    epsilon,
    n_step_transitions,
    td_targets,
    transition_arrays,
)
from amjax.agents.replay import replay_add, replay_init, replay_sample
from amjax.agents.rollout import EnvBatch, reset_envs, rollout
from amjax.agents.saved import SavedPolicy
from amjax.batching import member_axes, take_shared
from amjax.sweep.batches import compiled_programs

TINY = {
    "ppo": PPOConfig(total_timesteps=4096, eval_every=2048, num_envs=4, num_steps=64, eval_episodes=2),
    "dqn": DQNConfig(
        total_timesteps=2000, eval_every=1000, buffer_size=1000, learning_starts=200, batch_size=16, eval_episodes=2
    ),
}
# Box control (a Gaussian torque and a Bernoulli measuring choice) on gymnax's Pendulum-v1.
TINY["ppo-box"] = PPOConfig(
    env_id="Pendulum-v1", total_timesteps=2048, eval_every=1024, num_envs=4, num_steps=64, eval_episodes=2, hidden=(16,)
)
# PQN and recurrent PQN, sized so that 2 x 2 minibatch steps per update still learn the cost input in 4,096 steps.
TINY["pqn"] = PQNConfig(
    total_timesteps=4096, eval_every=2048, num_envs=4, num_steps=32, num_minibatches=2, hidden=(32,), eval_episodes=2
)
TINY["pqn-rnn"] = PQNRNNConfig(
    total_timesteps=4096,
    eval_every=2048,
    num_envs=4,
    num_steps=32,
    num_minibatches=2,
    hidden=(16,),
    rnn_size=8,
    eval_episodes=2,
)
ALGOS = {"ppo": PPO, "dqn": DQN, "ppo-box": PPO, "pqn": PQN, "pqn-rnn": PQN_RNN}


def slow_gae(rewards, values, next_values, terminated, done, gamma, lam):
    """Plain-Python GAE over one env's [T] arrays."""
    advantages = np.zeros(len(rewards))
    running = 0.0
    for t in reversed(range(len(rewards))):
        delta = rewards[t] + gamma * (1 - terminated[t]) * next_values[t] - values[t]
        running = delta + gamma * lam * (1 - done[t]) * running
        advantages[t] = running
    return advantages, advantages + np.asarray(values)


def test_gae_matches_python_loop():
    rng = np.random.default_rng(0)
    T, E = 50, 3
    rewards, values, next_values = (rng.normal(size=(T, E)).astype(np.float32) for _ in range(3))
    terminated = (rng.random((T, E)) < 0.1).astype(np.float32)
    done = np.maximum(terminated, (rng.random((T, E)) < 0.1)).astype(np.float32)  # some truncations
    adv, targets = gae(*map(jnp.asarray, (rewards, values, next_values, terminated, done)), 0.97, 0.9)
    for e in range(E):
        ref_adv, ref_targets = slow_gae(
            rewards[:, e], values[:, e], next_values[:, e], terminated[:, e], done[:, e], 0.97, 0.9
        )
        np.testing.assert_allclose(adv[:, e], ref_adv, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(targets[:, e], ref_targets, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("double_q", [True, False])
def test_td_targets_match_python_loop(double_q):
    rng = np.random.default_rng(1)
    B, A = 32, 4
    q_online, q_target = rng.normal(size=(B, A)), rng.normal(size=(B, A))
    reward, discount = rng.normal(size=B), 0.9 * (rng.random(B) < 0.7)
    got = td_targets(*map(jnp.asarray, (q_online, q_target, reward, discount)), double_q)
    for i in range(B):
        chosen = int(np.argmax(q_online[i] if double_q else q_target[i]))
        expected = reward[i] + discount[i] * q_target[i, chosen]
        assert got[i] == pytest.approx(expected, rel=1e-5, abs=1e-5)


@pytest.mark.parametrize("n", [1, 3])
def test_n_step_transitions_match_python_loop(n):
    rng = np.random.default_rng(2)
    T, E, gamma = 20, 3, 0.9
    terminated = rng.random((T + n - 1, E)) < 0.15
    done = terminated | (rng.random((T + n - 1, E)) < 0.1)  # truncations too
    window = {
        "obs": rng.normal(size=(T + n - 1, E, 2)).astype(np.float32),
        "action": rng.integers(0, 4, (T + n - 1, E)),
        "reward": rng.normal(size=(T + n - 1, E)).astype(np.float32),
        "next_obs": rng.normal(size=(T + n - 1, E, 2)).astype(np.float32),
        "terminated": terminated.astype(np.float32),
        "done": done.astype(np.float32),
    }
    got = n_step_transitions(jax.tree.map(jnp.asarray, window), n, gamma)
    for t in range(T):
        for e in range(E):
            ret, k = 0.0, 0
            while True:  # sum rewards until n steps or the episode's end
                ret += gamma**k * window["reward"][t + k, e]
                if done[t + k, e] or k == n - 1:
                    break
                k += 1
            assert got["reward"][t, e] == pytest.approx(ret, abs=1e-5)
            np.testing.assert_allclose(got["next_obs"][t, e], window["next_obs"][t + k, e])
            assert got["discount"][t, e] == pytest.approx(gamma ** (k + 1) * (1 - terminated[t + k, e]), abs=1e-6)
            assert got["action"][t, e] == window["action"][t, e]


def test_epsilon_schedule():
    config = DQNConfig(total_timesteps=1000, exploration_fraction=0.5, epsilon_start=1.0, epsilon_end=0.1)
    assert float(epsilon(config, jnp.int32(0))) == pytest.approx(1.0)
    assert float(epsilon(config, jnp.int32(250))) == pytest.approx(0.55)
    assert float(epsilon(config, jnp.int32(900))) == pytest.approx(0.1)


def test_replay_ring_and_sampling():
    buffer = replay_init({"x": jnp.float32(0)}, 6)
    for start in range(0, 12, 3):  # 4 writes of 3 into 6 slots: wraps twice
        buffer = replay_add(buffer, {"x": jnp.arange(start, start + 3, dtype=jnp.float32)})
        if start == 0:
            samples = replay_sample(buffer, jax.random.key(0), 200)["x"]
            assert set(np.asarray(samples).tolist()) <= {0.0, 1.0, 2.0}  # only filled slots
    np.testing.assert_array_equal(buffer.storage["x"], [6, 7, 8, 9, 10, 11])
    assert int(buffer.size) == 6 and int(buffer.position) == 0


@pytest.mark.parametrize("name", ["ppo", "dqn", "ppo-box"])
@pytest.mark.slow
def test_seeds_determinism_and_vmap_equals_alone(name, assert_batch_equals_alone, training_programs):
    base = TINY[name]
    lanes = [(0.0, 1e-3, 1.0), (0.2, 3e-4, 0.1), (0.1, 5e-4, 0.5)]  # cost, learning rate, reward scale: all traced
    configs = [base.replace(cost=c, learning_rate=lr, reward_scale=rs) for c, lr, rs in lanes]
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1, 2)])
    assert_batch_equals_alone(ALGOS[name], configs, keys)
    stacked = stack_configs(configs)
    # Same seed -> bit-identical; different seed -> different.
    alone = training_programs(ALGOS[name]).alone
    _, again = alone(unstack_config(stacked, 0), keys[0])
    _, first = alone(unstack_config(stacked, 0), keys[0])
    _, other = alone(unstack_config(stacked, 0), keys[1])
    assert np.array_equal(np.asarray(first.loss), np.asarray(again.loss))
    assert np.array_equal(np.asarray(first.train.costed_return), np.asarray(again.train.costed_return), equal_nan=True)
    assert not np.array_equal(np.asarray(first.loss), np.asarray(other.loss))


@pytest.mark.parametrize("name", ["ppo", "dqn"])
@pytest.mark.slow
def test_train_group_equals_all_at_once(name, assert_batch_equals_alone, training_programs):
    """`train_group` = 2 trains 4 vmapped configurations as 2 groups of 2 (a `lax.map`): each configuration
    equals its ungrouped batch row and its run alone."""
    base = TINY[name]
    configs = [base.replace(cost=c, train_group=2) for c in (0.0, 0.1, 0.2, 0.3)]
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (4, 5, 6, 7)])
    grouped, _ = assert_batch_equals_alone(ALGOS[name], configs, keys)
    ungrouped_configs = stack_configs([c.replace(train_group=0) for c in configs])
    _, ungrouped = training_programs(ALGOS[name]).batched(ungrouped_configs, keys)
    for field in ("eval_return", "train_return", "loss"):
        np.testing.assert_allclose(grouped.columns()[field], ungrouped.columns()[field], rtol=2e-4, atol=2e-4)
    assert not np.array_equal(grouped.columns()["loss"][0], grouped.columns()["loss"][1])


@pytest.mark.parametrize("name", ["dqn", "ppo-box", "pqn", "pqn-rnn"])
@pytest.mark.slow
def test_instrument_prices_vmap_equals_alone(name, assert_batch_equals_alone):
    """Instruments' prices are traced: a batch of prices is one program, config i in it equals config i alone
    (CartPole's cart and pole under the Q-learners' factored head, one advantage per mask; Pendulum's angle and
    rate, two Bernoulli measure entries)."""
    if name == "ppo-box":
        base = TINY[name].replace(instruments=((0, 1), (2,)))
    else:
        base = TINY[name].replace(instruments="default", measure_head="factored")
    configs = [base.replace(cost=c, instrument_costs=p) for c, p in [(0.0, (0.05, 0.3)), (0.1, (0.3, 0.0))]]
    rows, states = assert_batch_equals_alone(ALGOS[name], configs, jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)]))
    assert np.all(np.isfinite(rows.columns()["loss"]))
    if name != "ppo-box":
        params = states[0].best_params["params"]
        head = params.get("head", params)  # a recurrent network keeps its head in a submodule
        assert "control_advantage" in head
        assert head["measure_advantage"]["kernel"].shape[-1] == 4  # 2 instruments: 4 masks


@pytest.mark.parametrize("name", ["dqn", "ppo", "pqn"])
@pytest.mark.slow
def test_cost_conditioned_runs(name, assert_batch_equals_alone):
    """A cost-conditioned run's range is traced: a batch of ranges is one program, config i in it equals config i
    alone. The greedy action of a trained conditioned policy changes with the cost it sees (the scaled last entry
    of the observation), and `SavedPolicy.evaluate(cost=c)` plays episodes at cost c."""
    base = TINY[name].replace(cost_conditioned=True)
    configs = [base.replace(cost_low=lo, cost_high=hi).validate() for lo, hi in [(0.0, 1.0), (0.2, 0.2)]]
    _, states = assert_batch_equals_alone(ALGOS[name], configs, jnp.stack([jax.random.PRNGKey(s) for s in (3, 1)]))
    config = configs[0]
    saved = SavedPolicy(agent_of(config), config, states[0].best_params)
    act, carry = saved.policy(num_envs=256)
    obs = jax.random.uniform(jax.random.key(0), (256, 6), minval=-0.2, maxval=0.2).at[:, 4].set(0.0)  # stale
    actions = [
        np.asarray(act(EnvBatch(obs.at[:, -1].set(seen), None, jnp.ones(256, bool)), carry, jax.random.key(1))[0])
        for seen in (-1.0, 1.0)
    ]
    assert np.any(actions[0] != actions[1]), "the action ignores the cost input"
    free, dear = (saved.evaluate(jax.random.key(2), 4, cost=c) for c in (0.0, 1.0))
    assert free["costed_return"] == pytest.approx(free["raw_return"])
    assert dear["costed_return"] == pytest.approx(dear["raw_return"] - dear["measurements"], rel=1e-5)
    with pytest.raises(ValueError, match="cost: got -1"):
        saved.evaluate(jax.random.key(2), 4, cost=-1.0)
    # A NumPy actor (for a Gymnasium env at a fixed cost) appends the scaled cost itself.
    for seen, cost in ((-1.0, 0.0), (1.0, 1.0)):
        actor = saved.actor(cost=cost)
        got = [actor(np.asarray(o[:-1])) for o in obs.at[:, -1].set(seen)[:16]]
        np.testing.assert_array_equal(got, actions[(seen > 0)][:16])
    with pytest.raises(ValueError, match="cost: a cost-conditioned policy acts at a cost"):
        saved.actor()
    with pytest.raises(ValueError, match="not cost-conditioned"):
        SavedPolicy(agent_of(TINY[name]), TINY[name], states[0].best_params).actor(cost=0.1)


@pytest.mark.slow
def test_cost_conditioned_recurrent_pqn(assert_batch_equals_alone):
    """A cost-conditioned recurrent PQN: a batch of cost ranges equals its configurations alone, and the trained
    network's greedy action at an episode's first step changes with the cost it sees."""
    base = TINY["pqn-rnn"].replace(cost_conditioned=True)
    configs = [base.replace(cost_low=lo, cost_high=hi).validate() for lo, hi in [(0.0, 1.0), (0.2, 0.2)]]
    _, states = assert_batch_equals_alone(PQN_RNN, configs, jnp.stack([jax.random.PRNGKey(s) for s in (3, 1)]))
    setup = PQN_RNN.setup(configs[0])
    obs = jax.random.uniform(jax.random.key(0), (256, 6), minval=-0.2, maxval=0.2).at[:, 4].set(0.0)  # stale
    carry, first = jnp.zeros((256, base.rnn_size)), jnp.ones(256, bool)
    greedy = [
        np.asarray(setup.network.apply(states[0].best_params, carry, obs.at[:, -1].set(seen), first)[1]).argmax(-1)
        for seen in (-1.0, 1.0)
    ]
    assert np.any(greedy[0] != greedy[1]), "the greedy action ignores the cost input"


@pytest.mark.parametrize("name", ["ppo", "dqn"])
@pytest.mark.slow
def test_divergent_configuration_is_flagged_alone(name, training_programs):
    configs = [TINY[name].replace(learning_rate=lr, max_grad_norm=1e30) for lr in (1e-3, 1e30, 3e-4)]
    keys = jnp.stack([jax.random.PRNGKey(0)] * 3)
    states, rows = training_programs(ALGOS[name]).batched(stack_configs(configs), keys)
    diverged = np.asarray(states.diverged)
    assert diverged.tolist() == [False, True, False]
    assert np.asarray(rows.diverged)[1, -1]
    for i in (0, 2):  # the neighbours keep training normally
        assert np.all(np.isfinite(np.asarray(rows.loss)[i]))
        assert np.isfinite(float(states.best_return[i]))


def test_invalid_configs_name_the_field():
    with pytest.raises(ValueError, match="learning_rate"):
        PPOConfig(learning_rate=-1.0).validate()
    with pytest.raises(ValueError, match="gamma"):
        DQNConfig(gamma=1.5).validate()
    with pytest.raises(ValueError, match="cost"):
        DQNConfig(cost=float("nan")).validate()
    with pytest.raises(ValueError, match="num_minibatches"):
        PPOConfig(num_envs=3, num_steps=5, num_minibatches=4).validate()
    with pytest.raises(ValueError, match="eval_every"):
        PPOConfig(total_timesteps=10_000, eval_every=3000).validate()
    with pytest.raises(ValueError, match="env_id"):
        PPOConfig(env_id="NoSuchEnv-v0").validate()
    with pytest.raises(ValueError, match="buffer_size"):
        DQNConfig(buffer_size=1001).validate()
    with pytest.raises(ValueError, match="cost"):
        DQNConfig(vanilla=True, cost=0.1).validate()


def test_n_step_transitions_default_window_longer_than_update():
    """The default n_step (10) exceeds train_freq (4): each update's window is [train_freq + n - 1] steps, most of
    them pending from earlier updates, and episode ends inside it must cut the returns (vs a Python loop)."""
    config = DQNConfig()
    n, T, E, gamma = config.n_step, config.train_freq, 5, 0.99
    assert n > T
    rng = np.random.default_rng(3)
    terminated = rng.random((T + n - 1, E)) < 0.1
    done = terminated | (rng.random((T + n - 1, E)) < 0.05)
    done[:, 0] = terminated[:, 0] = False  # one env whose window has no episode end: a full n-step return
    window = {
        "obs": rng.normal(size=(T + n - 1, E, 5)).astype(np.float32),
        "action": rng.integers(0, 4, (T + n - 1, E)),
        "reward": (1.0 - 0.2 * rng.integers(0, 2, (T + n - 1, E))).astype(np.float32),
        "next_obs": rng.normal(size=(T + n - 1, E, 5)).astype(np.float32),
        "terminated": terminated.astype(np.float32),
        "done": done.astype(np.float32),
    }
    got = n_step_transitions(jax.tree.map(jnp.asarray, window), n, gamma)
    assert got["reward"].shape == (T, E)
    for t in range(T):
        for e in range(E):
            ret, end = 0.0, t + n - 1
            for k in range(n):
                ret += gamma**k * window["reward"][t + k, e]
                if done[t + k, e]:
                    end = t + k
                    break
            m = end - t + 1
            assert got["reward"][t, e] == pytest.approx(ret, abs=1e-4)
            np.testing.assert_allclose(got["next_obs"][t, e], window["next_obs"][end, e])
            assert got["discount"][t, e] == pytest.approx(gamma**m * (1 - terminated[end, e]), abs=1e-6)
    np.testing.assert_allclose(np.asarray(got["discount"][:, 0]), gamma**n, rtol=1e-6)


# -- configs and setup ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("base", "siblings"),
    [(QLearningConfig, (DQNConfig, DRQNConfig)), (PPOBaseConfig, (PPOConfig, PPORNNConfig))],
)
def test_algorithm_pairs_are_siblings_of_one_base_config(base, siblings):
    first, second = siblings
    assert not issubclass(first, second) and not issubclass(second, first)
    for config_type in siblings:
        assert issubclass(config_type, base)
        own = {f.name: f for f in dataclasses.fields(config_type)}
        for field in dataclasses.fields(base):  # every base field, static or traced as the base declares it
            assert own[field.name].metadata.get("pytree_node", True) == field.metadata.get("pytree_node", True)
    assert {agent_of(config_type()) for config_type in siblings} == {
        a.name for a in ALGORITHMS.values() if a.config_type in siblings
    }


def test_ppo_rnn_config_reads_files_that_name_shared_network():
    fields = PPORNNConfig(cost=0.2).to_dict()
    assert "shared_network" not in fields
    assert PPORNNConfig.from_dict({**fields, "shared_network": True}) == PPORNNConfig.from_dict(fields)
    with pytest.raises(ValueError, match="shared_network"):
        PPORNNConfig.from_dict({**fields, "shared_network": False})


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_setup_puts_each_configurations_traced_cost_into_the_env_params(name):
    algo = ALGORITHMS[name]
    configs = stack_configs([algo.config_type(cost=c, noise_std=0.0) for c in (0.0, 0.25, 0.5)])
    costs = jax.jit(jax.vmap(lambda c: algo.setup(c).env_params.cost))(configs)
    np.testing.assert_array_equal(costs, np.float32([0.0, 0.25, 0.5]))
    setup = algo.setup(algo.config_type(cost=0.1))
    assert setup.max_steps == 200 and setup.num_actions == 4  # CartPole-v0: 2 controls x {skip, measure}
    vanilla = algo.setup(algo.config_type(vanilla=True))
    assert vanilla.num_actions == 2 and not hasattr(vanilla.env_params, "cost")


@pytest.mark.parametrize("name", ["dqn", "drqn"])
@pytest.mark.slow
def test_reward_scale_multiplies_the_stored_rewards(name):
    """Q-learning's traced `reward_scale` multiplies the rewards replay stores (measurement costs included): on the
    same key, before learning starts, 0.5 stores exactly half of every reward 1.0 stores and everything else the
    same."""
    algo = ALGORITHMS[name]
    base = (
        TINY["dqn"]
        if name == "dqn"
        else DRQNConfig(total_timesteps=2048, eval_every=1024, buffer_size=64, learning_starts=1000, batch_size=4)
    )
    key = jax.random.PRNGKey(3)

    @jax.jit
    def three_updates(config):
        setup = algo.setup(config)
        state = algo.init(config, setup, key)
        for _ in range(3):
            state, _ = algo.update(config, setup, state)
        return state.buffer

    def stored(scale):
        buffer = three_updates(base.replace(cost=0.2, reward_scale=scale).validate())
        leaves = jax.tree_util.tree_flatten_with_path(buffer.storage)[0]
        return {jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in leaves}, int(buffer.size)

    (full, size), (half, _) = stored(1.0), stored(0.5)
    rewards = [path for path in full if "reward" in path]
    assert rewards and size > 0
    for path, leaf in full.items():
        expected = 0.5 * leaf if path in rewards else leaf
        np.testing.assert_array_equal(half[path], expected, err_msg=path)
    assert any(np.any(full[path][:size] != 0) for path in rewards)


def _truncated_unmeasured_rollout(config, steps=5):
    """`steps` unmeasured steps of CartPole-v0 cut by a `steps`-step time limit (no measurement, control 0: the
    pole does not fall so soon), through the trainers' `rollout`: transitions [steps, 1]."""
    env, params, _ = training_env(config)
    params = params.replace(env_params=params.env_params.replace(max_steps_in_episode=steps))
    batch = reset_envs(env, params, jax.random.key(0), 1)

    def never_measure(batch, carry, key):
        return jnp.zeros(batch.obs.shape[0], jnp.int32), carry, None

    _, _, transitions, _, episodes = rollout(env, params, batch, None, never_measure, jax.random.key(1), steps)
    assert not transitions.terminated.any() and transitions.done[:, 0].tolist() == [False] * (steps - 1) + [True]
    assert float(episodes.count[0]) == 1 and float(episodes.sums.raw_return[0]) == steps  # the score counts every step
    return transitions


def test_a_truncated_stale_step_counts_the_owed_reward_once():
    """reward_timing="on_measure": the truncation pays the 5 rewards owed (the episode's score keeps them), but the
    learner's targets bootstrap there from the value of the pre-reset view, which already counts what is owed (the
    next measurement would pay it), so the targets leave the payment out. Hand computation with every value 10 and
    nothing measured (no cost): PPO's target at the truncated step is 0 + gamma 10; DQN's 3-step target two steps
    before it 0 + 0 + 0 + gamma^3 10 (not gamma^2 5 + gamma^3 10); DRQN's the same."""
    gamma, v = 0.99, 10.0
    ppo = PPOConfig(reward_timing="on_measure", gamma=gamma, gae_lambda=0.95)
    transitions = _truncated_unmeasured_rollout(ppo)
    values = jnp.full((5, 1), v)
    _, targets = rollout_advantages(ppo, transitions, values, values)
    assert float(targets[-1, 0]) == pytest.approx(gamma * v, rel=1e-6)

    dqn = DQNConfig(reward_timing="on_measure", gamma=gamma, n_step=3)
    window = transition_arrays(dqn, _truncated_unmeasured_rollout(dqn))
    items = n_step_transitions(window, 3, gamma)
    q = jnp.full((3, 1, 4), v)
    dqn_targets = td_targets(q, q, items["reward"], items["discount"])
    assert float(dqn_targets[2, 0]) == pytest.approx(gamma**3 * v, rel=1e-6)

    drqn = DRQNConfig(reward_timing="on_measure", gamma=gamma, n_step=3, burn_in=0)
    steps = transition_arrays(drqn, _truncated_unmeasured_rollout(drqn))
    q = jnp.full((5, 1, 4), v)
    drqn_targets = sequence_targets(drqn, steps, q, q)
    assert float(drqn_targets[2, 0]) == pytest.approx(gamma**3 * v, rel=1e-6)
    assert float(drqn_targets[4, 0]) == pytest.approx(gamma * v, rel=1e-6)


def test_a_measured_end_pays_the_learner_as_before():
    """The owed reward stays in the learner's reward where a truncated episode ends on a measurement (the
    measurement pays it): only a stale truncation is corrected."""
    config = PPOConfig(reward_timing="on_measure")
    env, params, _ = training_env(config)
    params = params.replace(env_params=params.env_params.replace(max_steps_in_episode=3))
    batch = reset_envs(env, params, jax.random.key(0), 1)

    def measure_last(batch, carry, key):  # measures on the third step only (flag 0 until then)
        return jnp.where(carry == 2, 2, 0)[None].astype(jnp.int32), carry + 1, None

    _, _, transitions, _, _ = rollout(env, params, batch, jnp.int32(0), measure_last, jax.random.key(1), 3)
    np.testing.assert_allclose(transitions.reward[:, 0], [0.0, 0.0, 3.0])


# A Q-learner whose learning starts inside its first evaluation period and whose target updates twice in it.
SHARED_COUNTER_CONFIGS = {
    "dqn": TINY["dqn"].replace(learning_starts=400, target_update_interval=300),
    "drqn": DRQNConfig(
        total_timesteps=1600,
        eval_every=800,
        learning_starts=400,
        num_envs=4,
        buffer_size=200,
        batch_size=8,
        seq_len=8,
        burn_in=2,
        train_freq=5,
        target_update_interval=300,
        hidden=(16,),
        rnn_size=8,
        eval_episodes=2,
    ),
}


@pytest.mark.parametrize(("name", "branches"), [("dqn", 2), ("drqn", 3)])
def test_a_sweep_batch_branches_once_on_its_shared_step_counter(name, branches, primitive_names):
    """In a sweep batch the step counter goes in unbatched (`batching.shared_field`): each branch of an update
    (learning has started, the target update; DRQN's cached target values) is one conditional over the batch (under
    the "gpu" strategy one loop of at most one iteration), with no loop for disagreeing members and no reduction of
    the predicate, as a plain implementation with one counter has. With the counter batched, the loops are there."""
    algo = ALGORITHMS[name]
    configs = stack_configs([SHARED_COUNTER_CONFIGS[name].replace(cost=c) for c in (0.1, 0.3)])
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    states = jax.eval_shape(jax.vmap(lambda c, k: algo.init(c, algo.setup(c), k)), configs, keys)

    def update(config, state):
        return algo.update(config, algo.setup(config), state)

    def primitives(axes, state):
        return primitive_names(jax.make_jaxpr(jax.vmap(update, in_axes=(0, axes)))(configs, state))

    shared = primitives(member_axes(states), jax.eval_shape(take_shared, states))
    assert shared.count("cond") == branches and "while" not in shared and "reduce_and" not in shared
    batched = primitives(0, states)
    assert batched.count("while") == branches and batched.count("reduce_and") == branches
    # The "gpu" strategy lays each branch out as a loop of at most one iteration (`batching.update_where`).
    with strategy.use("gpu"):
        shared = primitives(member_axes(states), jax.eval_shape(take_shared, states))
    assert shared.count("while") == branches and "cond" not in shared and "reduce_and" not in shared


@pytest.mark.parametrize("name", sorted(SHARED_COUNTER_CONFIGS))
@pytest.mark.slow
def test_the_sweep_program_trains_as_a_plain_vmap(name, training_programs):
    """The sweep runner's chunk program (step counters unbatched, one evaluation per chunk) gives bit for bit the
    rows and final states of a plain `vmap` of the whole run (every leaf batched)."""
    algo = ALGORITHMS[name]
    configs = [SHARED_COUNTER_CONFIGS[name].replace(cost=c, learning_rate=lr) for c, lr in ((0.1, 1e-3), (0.3, 3e-3))]
    stacked = stack_configs([c.validate() for c in configs])
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (3, 4)])
    want_states, want_rows = training_programs(algo).batched(stacked, keys)
    init, chunk = compiled_programs(algo, 1, tuple(jax.devices()[:1]))
    states, rows = init(stacked, keys), []
    for _ in range(configs[0].num_evals):
        states, chunk_rows = chunk(stacked, states)
        rows.append(chunk_rows)
    rows = jax.tree.map(lambda *r: np.concatenate(r, axis=1), *rows)
    assert float(np.abs(np.asarray(want_rows.loss)).max()) > 0  # it learnt
    jax.tree.map(lambda g, w: np.testing.assert_array_equal(g, w), (states, rows), (want_states, want_rows))
