"""Configurations spread over CPU devices: the same results as on one device (bit for bit in this small case; in
general to float rounding, since XLA's rounding can depend on a shard's size), padding, resume across device
counts."""

from __future__ import annotations

import contextlib
import functools
import os
import subprocess
import sys
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax.sweep import SweepSpec, devices, run_sweep
from amjax.sweep.devices import _mulhi

# Three configurations: an odd count, so a 2-device batch carries one padding configuration.
ODD = SweepSpec(
    envs=("CartPole-v0",),
    agents=("dqn",),
    costs=(0.1, 0.3),
    seeds=(0,),
    vanilla=True,
    total_timesteps=2048,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"learning_starts": 256, "buffer_size": 1024, "n_step": 1},  # n_step 1: zero-size pending arrays
)
COLUMNS = ["config_id", "env_steps", "eval_return", "eval_measurements", "train_return", "loss"]


def _table(result):
    return result.results.sort_values(["config_id", "env_steps"]).reset_index(drop=True)[COLUMNS]


@pytest.mark.slow
def test_sharded_sweep_equals_one_device(tmp_path):
    assert len(jax.devices()) >= 2  # tests/conftest.py asks for two
    spread = run_sweep(ODD, tmp_path / "spread", progress=False)
    alone = run_sweep(ODD, tmp_path / "alone", progress=False, devices=jax.devices()[:1])
    assert len(spread.results) == 3 * 2
    pd.testing.assert_frame_equal(_table(spread), _table(alone))


@pytest.mark.slow
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


@settings(max_examples=200, deadline=None)
@given(
    bits=st.sampled_from([8, 16, 32]),
    signed=st.booleans(),
    scalar_side=st.sampled_from([None, "x", "y"]),
    data=st.data(),
)
def test_mulhi_lowering_of_sharded_programs_is_exact(bits, signed, scalar_side, data):
    """The widening multiply that sharded programs lower `lax.mulhi` to (`_mulhi_lowering`) gives its exact bits,
    with a scalar on either side as Philox's constants are."""
    dtype = np.dtype(f"{'int' if signed else 'uint'}{bits}")
    info = np.iinfo(dtype)
    values = st.integers(int(info.min), int(info.max))
    x, y = (data.draw(st.lists(values, min_size=4, max_size=4)) for _ in "xy")
    x, y = (v[0] if scalar_side == side else v for v, side in ((x, "x"), (y, "y")))
    expected = ((np.array(x, object) * np.array(y, object)) >> bits).astype(np.int64).astype(dtype)
    # The scalar as a literal, as Philox's constants are: a constant in the jaxpr, not an argument.
    if scalar_side == "x":
        program = functools.partial(lambda c, v: jax.lax.mulhi(c, v), dtype.type(x))
        args = (jnp.array(y, dtype),)
    elif scalar_side == "y":
        program = functools.partial(lambda c, v: jax.lax.mulhi(v, c), dtype.type(y))
        args = (jnp.array(x, dtype),)
    else:
        program, args = jax.lax.mulhi, (jnp.array(x, dtype), jnp.array(y, dtype))
    with mock.patch.object(devices, "_MULHI_NEEDS_PLAIN_LOWERING", True), devices._mulhi_lowered_without_chlo():
        lowered = jax.jit(program).lower(*args)
        assert "chlo.mulhi" not in lowered.as_text()
        got = lowered.compile()(*args)
    np.testing.assert_array_equal(np.asarray(got), expected)


def _clean_environ() -> dict[str, str]:
    """This process's environment without the caller's JAX device settings, for a fresh interpreter."""
    return {k: v for k, v in os.environ.items() if k not in ("JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}


def _python(code: str, **env: str) -> str:
    """Run `code` in a fresh interpreter, without the caller's JAX device settings; its stdout."""
    done = subprocess.run([sys.executable, "-c", code], env={**_clean_environ(), **env}, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


MULHI_RULES = (
    "from jax._src.interpreters import mlir; "
    "rules = lambda: jax.lax.mulhi_p in mlir._platform_specific_lowerings['cpu']"
)


def test_import_leaves_jax_as_it_is():
    """Importing amjax (and using it) neither changes JAX's devices nor registers lowering rules."""
    code = f"""
import jax
{MULHI_RULES}
before = rules()
import amjax, amjax.sweep, amjax.agents
env, params = amjax.make("CartPole-v0", cost=0.1)
print(len(jax.devices("cpu")), jax.config.jax_num_cpu_devices, before, rules())
"""
    assert _python(code).split() == ["1", "-1", "False", "False"]


def test_use_all_cores_asks_for_one_device_per_core_unless_told():
    code = "import amjax, jax, os; print(amjax.use_all_cores(), len(jax.devices('cpu')), len(os.sched_getaffinity(0)))"
    asked, devices, cores = _python(code).split()
    assert asked == devices == cores
    assert _python(code, JAX_NUM_CPU_DEVICES="1").split()[:2] == ["1", "1"]


def test_use_all_cores_after_jax_started_keeps_devices_and_says_so():
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: nothing to warn about")
    code = """
import warnings, jax, amjax
jax.numpy.zeros(1).block_until_ready()
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    count = amjax.use_all_cores()
print(count, len(jax.devices("cpu")), any("use_all_cores" in str(w.message) for w in caught))
"""
    assert _python(code).split() == ["1", "1", "True"]


@pytest.mark.slow
def test_sharded_sweep_restores_the_mulhi_lowering(tmp_path):
    """The plain-ops mulhi lowering applies while a sharded sweep is lowered, not after it."""
    code = f"""
import jax
jax.config.update("jax_num_cpu_devices", 2)
{MULHI_RULES}
from amjax.sweep import SweepSpec, run_sweep
spec = SweepSpec(envs=("CartPole-v0",), agents=("ppo",), costs=(0.1,), seeds=(0, 1), total_timesteps=2048,
                 eval_every=1024, eval_episodes=1)
run_sweep(spec, {str(tmp_path / "out")!r}, progress=False)
print(rules())
"""
    assert _python(code).split()[-1] == "False"


@pytest.mark.slow
def test_sharded_dqn_with_instruments_compiles(tmp_path):
    """`amjax sweep --agent dqn --set instruments=default` on two CPU devices trains. With `lax.mulhi` lowered
    through half-width limbs its chunk did not finish compiling in 10 min (LLVM on the env loop that XLA makes one
    kernel, many Philox draws per step); with the widening lowering the command takes about 40 s on two cores. The
    limit only catches that stall."""
    out = tmp_path / "out"
    command = [sys.executable, "-m", "train", "sweep", "--env", "CartPole-v0", "--agent", "dqn", "--cost", "0.1"]
    command += ["--seeds", "2", "--steps", "1024", "--eval-every", "1024", "--eval-episodes", "1", "--no-progress"]
    command += ["--set", "instruments=default", "--set", "learning_starts=256", "--out", str(out)]
    done = subprocess.run(command, env=_clean_environ(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "2 CPU devices" in done.stdout or len(os.sched_getaffinity(0)) < 2
    results = pd.read_parquet(out / "results.parquet")
    assert len(results) == 2 and np.isfinite(results["eval_return"]).all()
