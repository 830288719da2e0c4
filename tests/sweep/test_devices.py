"""Configurations spread over CPU devices: same results as on one device, padding, resume across device counts."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax.sweep import SweepSpec, run_sweep
from amjax.sweep.devices import _mulhi

# Three configurations: an odd count, so a 2-device batch carries one padding configuration.
ODD = SweepSpec(
    envs=("CartPole-v0",), agents=("dqn",), costs=(0.1, 0.3), seeds=(0,), vanilla=True,
    total_timesteps=2048, eval_every=1024, eval_episodes=2,
    hyperparams={"learning_starts": 256, "buffer_size": 1024, "n_step": 1},  # n_step 1: zero-size pending arrays
)
COLUMNS = ["config_id", "env_steps", "eval_return", "eval_measurements", "train_return", "loss"]


def _table(result):
    return result.results.sort_values(["config_id", "env_steps"]).reset_index(drop=True)[COLUMNS]


def test_sharded_sweep_equals_one_device(tmp_path):
    assert len(jax.devices()) >= 2  # tests/conftest.py asks for two
    spread = run_sweep(ODD, tmp_path / "spread", progress=False)
    alone = run_sweep(ODD, tmp_path / "alone", progress=False, devices=jax.devices()[:1])
    assert len(spread.results) == 3 * 2
    pd.testing.assert_frame_equal(_table(spread), _table(alone))


def test_resume_on_another_device_count(tmp_path):
    """A sweep checkpointed on one device resumes on two (the checkpoint holds the real rows only)."""
    out = tmp_path / "run"

    class Stop(Exception):
        pass

    def stop(_results):
        raise Stop

    with contextlib.suppress(Stop):
        run_sweep(ODD, out, progress=False, devices=jax.devices()[:1], checkpoint_every_s=0, on_chunk=stop)
    assert (out / "checkpoints").exists()
    resumed = run_sweep(ODD, out, progress=False)
    fresh = run_sweep(ODD, tmp_path / "fresh", progress=False)
    pd.testing.assert_frame_equal(_table(resumed), _table(fresh))


@settings(max_examples=200, deadline=None)
@given(
    bits=st.sampled_from([8, 16, 32]),
    signed=st.booleans(),
    data=st.data(),
)
def test_mulhi_replacement_is_exact(bits, signed, data):
    dtype = np.dtype(f"{'int' if signed else 'uint'}{bits}")
    info = np.iinfo(dtype)
    x, y = (data.draw(st.lists(st.integers(int(info.min), int(info.max)), min_size=4, max_size=4)) for _ in "xy")
    expected = ((np.array(x, object) * np.array(y, object)) >> bits).astype(np.int64).astype(dtype)
    got = jax.jit(_mulhi)(jnp.array(x, dtype), jnp.array(y, dtype))
    np.testing.assert_array_equal(np.asarray(got), expected)


def test_import_gives_one_device_per_core_unless_told():
    code = "import amjax, jax, os; print(len(jax.devices('cpu')), len(os.sched_getaffinity(0)))"
    env = {k: v for k, v in os.environ.items() if k != "JAX_NUM_CPU_DEVICES"}
    devices, cores = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                    check=True).stdout.split()
    assert devices == cores
    one = subprocess.run([sys.executable, "-c", code], env={**env, "JAX_NUM_CPU_DEVICES": "1"},
                         capture_output=True, text=True, check=True).stdout.split()[0]
    assert one == "1"
