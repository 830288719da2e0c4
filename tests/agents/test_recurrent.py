"""Recurrent agents (DRQN, recurrent PPO, recurrent PQN): the memory probe, hidden-state resets, sequence replay,
stored state + burn-in, and vmapped == alone.

The memory probe (amjax/envs/memory_probe.py) shows a cue only at an episode's first step and pays for naming it
at every step: a recurrent agent earns 1 per episode, a memoryless one 1/L = 0.2 in expectation. It is used
without the active-measure wrapper (`vanilla=True`): with it, an agent can keep the cue on screen (mode "last") or
encode it in its own measure / don't-measure choices (seen with DQN in mode "random"), which needs no memory.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import amjax.envs.memory_probe  # noqa: F401  (registers MemoryProbe-v0)
from amjax.agents import (
    ALGORITHMS,
    DQNConfig,
    DRQNConfig,
    PPOConfig,
    PPORNNConfig,
    PQNRNNConfig,
    agent_of,
    drqn,
    ppo_rnn,
    pqn_rnn,
    stack_configs,
    unstack_config,
)
from amjax.agents.networks import zero_carry
from amjax.agents.replay import sequence_add, sequence_init, sequence_sample, sequence_windows
from amjax.agents.rollout import EnvBatch

PROBE = {"env_id": "MemoryProbe-v0", "vanilla": True, "eval_episodes": 64}
PQN_PROBE_STEPS = 3200
# Small budgets: the recurrent agents reach 1.0 at their first evaluation on 2 cores.
PROBE_CONFIGS = {
    "drqn": DRQNConfig(
        total_timesteps=4000,
        eval_every=2000,
        learning_starts=500,
        num_envs=4,
        buffer_size=500,
        seq_len=8,
        burn_in=2,
        train_freq=5,
        target_update_interval=200,
        exploration_fraction=0.3,
        **PROBE,
    ),
    "ppo-rnn": PPORNNConfig(
        total_timesteps=6400, eval_every=3200, num_envs=8, num_steps=40, num_minibatches=2, **PROBE
    ),
    "pqn-rnn": PQNRNNConfig(
        total_timesteps=PQN_PROBE_STEPS,
        eval_every=PQN_PROBE_STEPS // 2,
        num_envs=8,
        num_steps=20,
        num_minibatches=2,
        **PROBE,
    ),
    "dqn": DQNConfig(total_timesteps=4000, eval_every=2000, learning_starts=500, buffer_size=4000, **PROBE),
    "ppo": PPOConfig(total_timesteps=6400, eval_every=3200, num_envs=8, num_steps=40, **PROBE),
}
# Three lanes per program: different seeds and traced hyperparameters.
Q_LANES = [{"learning_rate": 5e-4}, {"learning_rate": 1e-3, "gamma": 0.95}, {"learning_rate": 3e-4, "epsilon_end": 0.1}]
PG_LANES = [{"learning_rate": 1e-3}, {"learning_rate": 2e-3, "gamma": 0.95}, {"learning_rate": 5e-4, "ent_coef": 0.0}]
PQN_LANES = [{"learning_rate": 6e-3}, {"learning_rate": 3e-3, "gamma": 0.95}, {"learning_rate": 1e-3, "q_lambda": 0.5}]
LANES = {"drqn": Q_LANES, "dqn": Q_LANES, "ppo-rnn": PG_LANES, "ppo": PG_LANES, "pqn-rnn": PQN_LANES}
RECURRENT = ["drqn", "ppo-rnn", "pqn-rnn"]
KEYS = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1, 2)])


def _setup(config):
    """The env and network an algorithm's functions take (`Algorithm.setup`)."""
    return ALGORITHMS[agent_of(config)].setup(config)


def _net(config):
    return _setup(config).network


@pytest.fixture(scope="module")
def probe_run(training_programs):
    """`probe_run(name) -> (stacked configs, final states, rows)`: the memory probe's three lanes, trained once."""

    @functools.cache
    def run(name):
        stacked = stack_configs([PROBE_CONFIGS[name].replace(**lane) for lane in LANES[name]])
        states, rows = training_programs(ALGORITHMS[name]).batched(stacked, KEYS)
        return stacked, states, jax.device_get(rows)

    return run


# -- the memory probe ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", RECURRENT)
@pytest.mark.slow
def test_recurrent_agents_solve_the_memory_probe(name, probe_run):
    _, _, rows = probe_run(name)
    final = rows.test.costed_return[:, -1]
    assert np.all(final >= 0.8), f"final test returns {final} (optimum 1, memoryless 0.2)"


@pytest.mark.parametrize("name", ["dqn", "ppo"])
@pytest.mark.slow
def test_feed_forward_agents_cannot_solve_the_memory_probe(name, probe_run):
    _, _, rows = probe_run(name)
    final = rows.test.costed_return[:, -1]
    # A memoryless policy earns 0.2 in expectation; the mean of 64 episodes has a standard deviation of 0.1.
    assert np.all(final <= 0.5), f"final test returns {final} (memoryless expectation 0.2)"


@pytest.mark.parametrize("name", RECURRENT)
@pytest.mark.slow
def test_vmapped_configuration_equals_it_alone(name, probe_run, training_programs):
    stacked, _, rows = probe_run(name)
    for i in (0, 2):
        _, alone = training_programs(ALGORITHMS[name]).alone(unstack_config(stacked, i), KEYS[i])
        for field in ("eval_return", "train_return", "loss"):
            np.testing.assert_allclose(rows.columns()[field][i], alone.columns()[field], rtol=2e-4, atol=2e-4)


def test_memory_probe_rewards_and_observations():
    import amjax

    env, params = amjax.make("MemoryProbe-v0", vanilla=True)
    obs, state = env.reset(jax.random.PRNGKey(3), params)
    cue = float(obs[0])
    assert cue in (-1.0, 1.0)
    right = int(cue > 0)
    total = 0.0
    for t in range(5):
        obs, state, reward, terminated, _, _ = env.step(jax.random.PRNGKey(t), state, right if t % 2 else 1 - right)
        total += float(reward)
        assert bool(terminated) == (t == 4)
        if t < 4:
            assert float(obs[0]) == 0.0
    assert total == pytest.approx(-0.2)  # 2 right, 3 wrong
    assert float(obs[0]) in (-1.0, 1.0)  # auto-reset: the next episode's cue


# -- hidden-state resets ------------------------------------------------------------------------------------------


def _probe_obs(values):
    return jnp.asarray(values, jnp.float32)[:, :, None]  # [T, 2 envs, 1]


# Two envs whose first episodes differ (cues, lengths) and whose second episodes are identical.
OBS = _probe_obs([[1, -1], [0, 0.5], [0, 0], [0, -0.7], [0, 0.3], [-1, -1], [0, 0], [0, 0]])
FIRST = jnp.asarray(
    [
        [True, True],
        [False, False],
        [False, False],
        [False, True],
        [False, False],
        [True, True],
        [False, False],
        [False, False],
    ]
)
SECOND = 5  # where the identical second episodes start


def _act_through(act, carry):
    """Feed OBS / FIRST through an act function step by step (as the rollout does); the carries after each step."""
    carries = []
    for t in range(OBS.shape[0]):
        _, carry, _ = act(EnvBatch(OBS[t], None, FIRST[t]), carry, jax.random.PRNGKey(t))
        carries.append(carry)
    return carries


def _assert_second_episode_forgets_the_first(carries, fresh):
    for t in range(SECOND, OBS.shape[0]):
        np.testing.assert_array_equal(carries[t][0], carries[t][1])  # both envs: the same state
        np.testing.assert_allclose(carries[t][0], fresh[t - SECOND][0], rtol=1e-6, atol=1e-6)
    assert not np.allclose(carries[SECOND - 1][0], carries[SECOND - 1][1])  # they did differ before


@pytest.mark.parametrize("name", RECURRENT)
def test_hidden_state_resets_at_episode_starts_when_acting(name):
    module = {"drqn": drqn, "ppo-rnn": ppo_rnn, "pqn-rnn": pqn_rnn}[name]
    config = PROBE_CONFIGS[name].replace(eval_episodes=2)
    setup = _setup(config)
    state = module.init(config, setup, jax.random.PRNGKey(0))
    act, carry = module.greedy(config, setup, state.params, 2)
    carries = _act_through(jax.jit(act), carry)
    # A fresh pair of envs playing only the second episode, from the policy's zero state.
    fresh = []
    fresh_carry = zero_carry(config.cell, config.rnn_size, (2,))
    for t in range(SECOND, OBS.shape[0]):
        _, fresh_carry, _ = act(EnvBatch(OBS[t], None, FIRST[t]), fresh_carry, jax.random.PRNGKey(t))
        fresh.append(fresh_carry)
    _assert_second_episode_forgets_the_first(carries, fresh)


def test_hidden_state_resets_inside_replayed_sequences():
    config = PROBE_CONFIGS["drqn"].replace(burn_in=2, seq_len=6)  # 8 steps: OBS / FIRST
    state = drqn.init(config, _setup(config), jax.random.PRNGKey(0))
    steps = {"obs": OBS, "first": FIRST, "next_obs": jnp.zeros_like(OBS)}
    start = jax.random.normal(jax.random.PRNGKey(1), (2, config.rnn_size))  # different stale stored states
    q, _ = drqn.q_values(config, _net(config), state.params, steps, start)
    trained_second = SECOND - config.burn_in
    np.testing.assert_array_equal(q[trained_second:, 0], q[trained_second:, 1])
    assert not np.allclose(q[trained_second - 1, 0], q[trained_second - 1, 1])


@pytest.mark.parametrize("cell", ["gru", "lstm"])
def test_straight_unroll_equals_the_loop(cell):
    """The straight-line unroll (burn-ins, target values) computes what the loop does, resets included."""
    config = PROBE_CONFIGS["drqn"].replace(burn_in=2, seq_len=6, cell=cell)
    net, params = _net(config), drqn.init(config, _setup(config), jax.random.PRNGKey(0)).params
    start = jax.tree.map(
        lambda c: jax.random.normal(jax.random.PRNGKey(1), c.shape), zero_carry(cell, config.rnn_size, (2,))
    )
    looped = net.apply(params, start, OBS, FIRST, method="unroll")
    straight = net.apply(params, start, OBS, FIRST, straight=True, method="unroll")
    for a, b in zip(jax.tree.leaves(looped), jax.tree.leaves(straight), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    steps = {"obs": OBS, "first": FIRST, "next_obs": OBS[::-1]}
    np.testing.assert_allclose(
        drqn.target_values(config, net, params, steps, start),
        drqn.q_values(config, net, params, steps, start)[1],
        rtol=1e-5,
        atol=1e-6,
    )


def test_pqn_rnn_hidden_state_resets_inside_update_sequences():
    config = PROBE_CONFIGS["pqn-rnn"]
    state = pqn_rnn.init(config, _setup(config), jax.random.PRNGKey(0))
    start = jax.random.normal(jax.random.PRNGKey(1), (2, config.rnn_size))
    _, q = _net(config).apply(state.params, start, OBS, FIRST, method="unroll")
    np.testing.assert_array_equal(q[SECOND:, 0], q[SECOND:, 1])
    assert not np.allclose(q[SECOND - 1, 0], q[SECOND - 1, 1])


def test_ppo_rnn_hidden_state_resets_inside_update_sequences():
    config = PROBE_CONFIGS["ppo-rnn"]
    state = ppo_rnn.init(config, _setup(config), jax.random.PRNGKey(0))
    start = jax.random.normal(jax.random.PRNGKey(1), (2, config.rnn_size))
    logits, values = ppo_rnn.unroll_sequences(_net(config), state.params, start, OBS, FIRST)
    np.testing.assert_array_equal(logits[SECOND:, 0], logits[SECOND:, 1])
    np.testing.assert_array_equal(values[SECOND:, 0], values[SECOND:, 1])


# -- sequence replay ----------------------------------------------------------------------------------------------


def test_sequence_buffer_windows_ring_and_sampling():
    S, stride, n = 5, 2, 3
    buffer = sequence_init({"t": jnp.int32(0)}, jnp.int32(0), S, capacity=6)
    pending = {"t": jnp.zeros((S - stride, n), jnp.int32) - 1}
    for u in range(4):  # 4 x 3 sequences into 6 slots: wraps
        times = jnp.arange(u * stride, (u + 1) * stride)[:, None]
        new = {"t": times * 10 + jnp.arange(n)}  # [stride, n]: step t of env e is 10 t + e
        window, pending = sequence_windows(pending, new, stride)
        buffer = sequence_add(buffer, window, window["t"][0])
    stored = np.asarray(buffer.storage["steps"]["t"])  # [6, S]
    # The last two updates' sequences: env e, update u holds steps (u+1)*stride - S ... (u+1)*stride - 1.
    for slot, (u, e) in enumerate([(2, 0), (2, 1), (2, 2), (3, 0), (3, 1), (3, 2)]):
        expected = np.arange((u + 1) * stride - S, (u + 1) * stride) * 10 + e
        np.testing.assert_array_equal(stored[slot], expected)
        assert int(buffer.storage["start"][slot]) == expected[0]
    steps, start = sequence_sample(buffer, jax.random.PRNGKey(0), 50)
    assert steps["t"].shape == (S, 50)  # time-major
    np.testing.assert_array_equal(steps["t"][0], start)
    np.testing.assert_array_equal(np.diff(np.asarray(steps["t"]), axis=0), 10)  # consecutive steps of one env


@functools.cache
def _drqn_buffer(burn_in=3):
    """DRQN after 8 updates on the probe (5-step episodes, 11-step sequences), before any learning."""
    config = PROBE_CONFIGS["drqn"].replace(burn_in=burn_in, seq_len=8, train_freq=4, learning_starts=10**6)
    state = drqn.init(config, _setup(config), jax.random.PRNGKey(0))
    update = jax.jit(lambda s: drqn.update(config, _setup(config), s)[0])
    for _ in range(8):
        state = update(state)
    return config, state


@pytest.mark.slow
def test_stored_sequences_keep_their_episode_boundaries():
    config, state = _drqn_buffer()
    steps = jax.device_get(state.buffer.storage["steps"])
    filled = int(state.buffer.size)
    obs, first, done = steps["obs"][:filled, :, 0], steps["first"][:filled], steps["done"][:filled]
    assert first.any(axis=1).all() and done.any(axis=1).all()  # every sequence crosses an episode boundary
    np.testing.assert_array_equal(first[:, 1:], done[:, :-1] > 0)  # a step after an episode end starts one
    np.testing.assert_array_equal(obs != 0, first)  # the probe shows its cue exactly at episode starts
    # next_obs is the pre-reset observation: never the next episode's cue.
    assert np.all(steps["next_obs"][:filled, :, 0] == 0)


@pytest.mark.slow
def test_targets_never_reach_into_the_next_episode():
    config, state = _drqn_buffer()
    steps, start = sequence_sample(state.buffer, jax.random.PRNGKey(0), 16)
    start = start["carry"]
    q, q_next = drqn.q_values(config, _net(config), state.params, steps, start)
    _, q_next_target = drqn.q_values(config, _net(config), state.target_params, steps, start)
    targets = drqn.sequence_targets(config, steps, q_next, q_next_target)
    done = np.asarray(steps["done"][config.burn_in :]) > 0
    # Perturb every reward and bootstrap value after each sequence's first episode end: the targets up to and
    # including that end must not move.
    end = np.where(done.any(0), done.argmax(0), done.shape[0])  # [batch]
    after = np.arange(done.shape[0])[:, None] > end[None, :]
    noise = jnp.where(after, 100.0, 0.0)
    perturbed_steps = {**steps, "reward": steps["reward"].at[config.burn_in :].add(noise)}
    perturbed = drqn.sequence_targets(
        config, perturbed_steps, q_next + noise[..., None], q_next_target + noise[..., None]
    )
    np.testing.assert_allclose(np.where(after, 0, perturbed), np.where(after, 0, targets), rtol=1e-6, atol=1e-6)
    # The probe terminates (no truncation): an episode's last step bootstraps from nothing.
    terminal = done & (np.asarray(steps["terminated"][config.burn_in :]) > 0)
    np.testing.assert_allclose(np.asarray(targets)[terminal], np.asarray(steps["reward"][config.burn_in :])[terminal])
    # Hidden states: Q-values after an episode start do not depend on anything before it.
    first = np.asarray(steps["first"][config.burn_in :])
    shuffled = {**steps, "obs": steps["obs"].at[: config.burn_in].multiply(-3.0)}
    q2, _ = drqn.q_values(config, _net(config), state.params, shuffled, jax.tree.map(lambda c: c * 0 + 5.0, start))
    seen_start = np.maximum.accumulate(first, axis=0)  # at or after the first episode start in the trained part
    np.testing.assert_allclose(np.asarray(q2)[seen_start], np.asarray(q)[seen_start], rtol=1e-6, atol=1e-6)
    assert not np.allclose(np.asarray(q2)[~seen_start], np.asarray(q)[~seen_start])


# -- stored state + burn-in ---------------------------------------------------------------------------------------


@pytest.mark.slow
def test_stored_start_state_is_the_actors_hidden_state():
    """With unchanged parameters, unrolling a stored sequence from its stored state reproduces the hidden states
    the actor had: the state after `train_freq` steps is the next stored sequence's start."""
    config, state = _drqn_buffer(burn_in=0)
    storage, n, f = state.buffer.storage, config.num_envs, config.train_freq
    net = _net(config)
    for slot in range(int(state.buffer.size) - n):
        seq = jax.tree.map(lambda x, slot=slot: x[slot][:, None], storage["steps"])  # one sequence, batch 1
        carry = storage["start"]["carry"][slot][None]
        for t in range(f):
            carry, _ = net.apply(state.params, carry, seq["obs"][t], seq["first"][t])
        np.testing.assert_allclose(carry[0], storage["start"]["carry"][slot + n], rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_cached_target_values_follow_the_target_network(monkeypatch):
    """The buffer's cached target values equal a fresh target-network unroll of every stored sequence: those stored
    before the last target update (refreshed there, in chunks with a remainder) and after it (computed when
    stored)."""
    monkeypatch.setattr(drqn, "REFRESH_CHUNK", 10)  # 24 slots: chunks of 10, 10 and 4
    config = PROBE_CONFIGS["drqn"].replace(
        burn_in=3, seq_len=8, train_freq=4, learning_starts=40, target_update_interval=48, buffer_size=24
    )
    setup = _setup(config)
    state = drqn.init(config, setup, jax.random.PRNGKey(0))
    initial_target = state.target_params
    update = jax.jit(lambda s: drqn.update(config, setup, s)[0])
    for _ in range(10):  # 16 env steps each: target updates in updates 3, 6 and 9; the buffer wraps
        state = update(state)
    leaves = zip(jax.tree.leaves(initial_target), jax.tree.leaves(state.target_params), strict=True)
    assert not all(np.allclose(a, b) for a, b in leaves)
    storage = state.buffer.storage
    assert int(state.buffer.size) == 24
    steps = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), storage["steps"])
    start = storage["start"]["carry"]
    cached = np.asarray(storage["start"]["target_q"])
    fresh = np.swapaxes(drqn.target_values(config, _net(config), state.target_params, steps, start), 0, 1)
    np.testing.assert_allclose(cached, fresh, rtol=1e-5, atol=1e-5)
    online = np.swapaxes(drqn.target_values(config, _net(config), state.params, steps, start), 0, 1)
    assert not np.allclose(cached, online, rtol=1e-3, atol=1e-3)


@pytest.mark.slow
def test_burn_in_warms_up_the_state_without_gradient_or_loss():
    config, state = _drqn_buffer(burn_in=3)
    steps, start = sequence_sample(state.buffer, jax.random.PRNGKey(1), 32)
    start = start["carry"]
    b = config.burn_in
    # q_values = a full unroll from the stored state, minus the burn-in outputs.
    net = _net(config)
    carry, full = start, []
    for t in range(config.sequence_length):
        carry, q = net.apply(state.params, carry, steps["obs"][t], steps["first"][t])
        full.append(q)
    q, _ = drqn.q_values(config, _net(config), state.params, steps, start)
    np.testing.assert_allclose(q, jnp.stack(full[b:]), rtol=1e-5, atol=1e-5)

    # The loss ignores burn-in rewards / actions / flags, and no gradient flows into burn-in observations.
    q_next_target = drqn.target_values(config, _net(config), state.target_params, steps, start)

    def loss_of(obs, steps):
        return drqn.loss(config, _net(config), state.params, {**steps, "obs": obs}, start, q_next_target)

    noisy = {
        **steps,
        "reward": steps["reward"].at[:b].add(7.0),
        "action": steps["action"].at[:b].set(1),
        "terminated": steps["terminated"].at[:b].set(1.0),
    }
    assert float(loss_of(steps["obs"], noisy)) == pytest.approx(float(loss_of(steps["obs"], steps)), rel=1e-6)
    grad = jax.grad(loss_of)(steps["obs"], steps)
    assert np.all(np.asarray(grad[:b]) == 0)
    assert np.any(np.asarray(grad[b:]) != 0)
    # ... but the burn-in does shape the trained steps' hidden states (where no episode starts in between).
    q_zero_state, _ = drqn.q_values(config, _net(config), state.params, steps, jnp.zeros_like(start))
    no_reset = ~np.asarray(steps["first"][: b + 1]).any(0)
    assert no_reset.any()
    assert not np.allclose(np.asarray(q_zero_state)[0, no_reset], np.asarray(q)[0, no_reset])


def test_ppo_rnn_update_recomputes_the_rollouts_outputs():
    """The update epochs re-unroll whole env sequences from the rollout's initial hidden states: at the rollout's
    parameters they reproduce the acting log-probabilities and values, for any subset of envs."""
    config = PROBE_CONFIGS["ppo-rnn"].replace(num_steps=12)
    state = ppo_rnn.init(config, _setup(config), jax.random.PRNGKey(0))
    start = jax.tree.map(lambda c: c + 0.3, state.carry)  # a mid-episode state
    _, _, transitions, (log_probs, values, first, _), _ = ppo_rnn.collect(
        config, _setup(config), state.params, state.envs, start, jax.random.PRNGKey(1)
    )
    envs = jnp.asarray([5, 2, 7])
    logits, new_values = ppo_rnn.unroll_sequences(
        _net(config), state.params, start[envs], transitions.obs[:, envs], first[:, envs]
    )
    new_log_probs = jnp.take_along_axis(jax.nn.log_softmax(logits), transitions.action[:, envs, None], -1)[..., 0]
    np.testing.assert_allclose(new_log_probs, log_probs[:, envs], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(new_values, values[:, envs], rtol=1e-5, atol=1e-5)


def test_invalid_recurrent_configs_name_the_field():
    with pytest.raises(ValueError, match="cell"):
        DRQNConfig(cell="rnn").validate()
    with pytest.raises(ValueError, match="train_freq"):
        DRQNConfig(burn_in=2, seq_len=4, train_freq=8).validate()
    with pytest.raises(ValueError, match="buffer_size"):
        DRQNConfig(num_envs=3, buffer_size=1000, eval_every=9600, total_timesteps=96000).validate()
    with pytest.raises(ValueError, match="num_minibatches"):
        PPORNNConfig(num_envs=6, num_minibatches=4).validate()
    with pytest.raises(ValueError, match="learning_rate"):
        PPORNNConfig(learning_rate=0.0).validate()
    with pytest.raises(ValueError, match="num_minibatches=4 must divide num_envs=6"):
        PQNRNNConfig(num_envs=6, num_minibatches=4, num_steps=32).validate()
    with pytest.raises(ValueError, match="cell"):
        PQNRNNConfig(cell="rnn").validate()


@pytest.mark.slow
def test_lstm_cells_train_and_checkpoint_as_arrays():
    config = PROBE_CONFIGS["drqn"].replace(cell="lstm")
    state = drqn.init(config, _setup(config), jax.random.PRNGKey(0))
    assert isinstance(state.carry, tuple) and len(state.carry) == 2
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(state))
    state, stats = jax.jit(lambda s: drqn.update(config, _setup(config), s))(state)
    assert np.isfinite(float(stats.loss))
