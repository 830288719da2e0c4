"""Every registered environment runs inside `jax.shard_map` with its default `check_vma=True`.

A user who splits envs over devices (as amjax's sweep splits configurations, `amjax.sweep.devices`) meets the
varying-manual-axes check in every loop carry of the environment; the conftest gives at least two CPU devices.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh, PartitionSpec

import amjax

ENV_IDS = ("CartPole-v0", "Acrobot-v1", "LunarLander-v3", "MemoryProbe-v0", "CSTR-v0")
# Steps per env, unrolled (each one compiled again). LunarLander's step holds every solver loop and its compile is
# most of this file's time; two steps still feed a step's own output state back into it.
STEPS = {"LunarLander-v3": 2}
# Envs per device. LunarLander's auto-reset and contact solves gather the envs that need them in chunks of at least
# `select_compacted`'s 16 rows: with more envs than that per device they run on gathered rows, whose types under
# shard_map vary more than the operands the branch was first traced with (the benchmark's 512 per core).
ENVS_PER_DEVICE = {"LunarLander-v3": 40}


@pytest.mark.parametrize(
    "env_id", [pytest.param(e, marks=pytest.mark.slow) if e == "LunarLander-v3" else e for e in ENV_IDS]
)
def test_reset_and_step_under_shard_map(env_id: str) -> None:
    env, params = amjax.make(env_id, cost=0.1)
    steps = STEPS.get(env_id, 3)
    devices = jax.devices()
    mesh = Mesh(np.array(devices), ("envs",))
    spec = PartitionSpec("envs")

    def rollout(keys):
        def one(key):
            # Steps unrolled in Python: a scan here would carry `reset`'s constant fields (gymnax's `time=0`),
            # which the check rightly calls unvarying; what is tested is the envs' own loops.
            reset_key, key = jax.random.split(key)
            obs, state = env.reset(reset_key, params)
            rewards = []
            for step_key in jax.random.split(key, steps):
                action_key, step_key = jax.random.split(step_key)
                action = env.action_space(params).sample(action_key)
                obs, state, reward, _, _, _ = env.step(step_key, state, action, params)
                rewards.append(reward)
            return obs, jnp.stack(rewards)

        return jax.vmap(one)(keys)

    keys = jax.random.split(jax.random.key(0), ENVS_PER_DEVICE.get(env_id, 2) * len(devices))
    obs, rewards = jax.jit(jax.shard_map(rollout, mesh=mesh, in_specs=spec, out_specs=spec))(keys)
    assert rewards.shape == (len(keys), steps)
    assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(rewards)).all()
