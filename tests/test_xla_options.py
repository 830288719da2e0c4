"""`import amjax` sets an XLA CPU option (`amjax.cores.xla_cpu_options`): the XLA_FLAGS it writes, that XLA takes it
(the LunarLander port's loops are single kernels), the opt-out, and the warning when JAX compiled before amjax was
imported. The opt-in per-program option `amjax.cores.REDUCTIONS_IN_XLA`: XLA takes it and it changes only where
reductions run."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amjax.cores import REDUCTIONS_IN_XLA, SMALL_LOOP_BYTES, XLA_CPU_FLAGS, jit_one_kernel, xla_cpu_options

LOOPS = f"xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"


def test_options_added_to_xla_flags_once_and_merged_with_the_users():
    environ = {}
    xla_cpu_options(environ)
    assert environ["XLA_FLAGS"] == f"--xla_backend_extra_options={LOOPS}" == XLA_CPU_FLAGS
    xla_cpu_options(environ)  # idempotent (a worker process inherits the driver's flags)
    assert environ["XLA_FLAGS"] == XLA_CPU_FLAGS

    environ = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2 --xla_backend_extra_options=a=1 --b=2"}
    xla_cpu_options(environ)  # XLA takes one comma-separated list of extra options
    expected = f"--xla_force_host_platform_device_count=2 --xla_backend_extra_options=a=1,{LOOPS} --b=2"
    assert environ["XLA_FLAGS"] == expected

    own = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5"
    environ = {"XLA_FLAGS": own}
    xla_cpu_options(environ)  # the user's own threshold is kept
    assert environ["XLA_FLAGS"] == own

    environ = {"AMJAX_XLA_OPTIONS": "0"}
    assert xla_cpu_options(environ) is False
    assert "XLA_FLAGS" not in environ


def test_imported_amjax_set_the_option_and_xla_compiles_a_loop_as_one_kernel():
    assert LOOPS in os.environ.get("XLA_FLAGS", "")  # tests import amjax before JAX compiles anything
    x = jnp.ones(4096)  # a loop over 16 KiB arrays: above XLA's 1 KiB default, kernel by kernel without the option
    compiled = jax.jit(lambda x: jax.lax.fori_loop(0, 8, lambda i, x: jnp.sin(x) + i, x)).lower(x).compile()
    assert "xla_cpu_small_call" in compiled.as_text()


@pytest.mark.slow
def test_lunar_lander_loops_are_single_kernels():
    from amjax.envs.lunar_lander import LunarLander

    env = LunarLander()
    params = env.default_params
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    _, state = jax.vmap(env.reset, (0, None))(keys, params)
    step = jax.vmap(env.step, (0, 0, 0, None))
    text = jax.jit(step).lower(keys, state, jnp.zeros(64, jnp.int32), params).compile().as_text()
    # The velocity sweeps (joints alone, and every constraint for the compacted envs on the ground), the position
    # iterations, the reset's physics step: each loop one kernel.
    assert text.count('xla_cpu_small_call="true"') >= 6


@pytest.mark.slow
def test_jit_one_kernel_compiles_a_lunar_lander_step_as_one_kernel_with_jits_results():
    """One env's step (typed keys in and out, a state pytree, an info dict): the program's entry holds one kernel,
    the loop, and every output equals `jax.jit`'s to float rounding, step after step."""
    from amjax.envs.lunar_lander import LunarLander

    env = LunarLander()
    params = env.default_params

    def step(key, state, action):
        key, key_step = jax.random.split(key)
        obs, state, reward, terminated, truncated, info = env.step(key_step, state, action, params)
        return key, state, (obs, reward, terminated | truncated), info

    plain, one = jax.jit(step), jit_one_kernel(step)
    key = jax.random.key(3)
    _, state = jax.jit(env.reset)(key, params)
    text = one.lower(key, state, np.int32(0)).compile().as_text()
    entry = text[text.index("ENTRY") :]
    assert entry.count('xla_cpu_small_call="true"') == 1
    for action in np.random.default_rng(0).integers(0, 4, 60).astype(np.int32):
        want, got = plain(key, state, action), one(key, state, action)
        assert jax.tree.structure(got) == jax.tree.structure(want)
        assert jnp.array_equal(jax.random.key_data(got[0]), jax.random.key_data(want[0]))
        for a, b in zip(jax.tree.leaves(got[1:]), jax.tree.leaves(want[1:]), strict=True):
            np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=1e-4, atol=1e-4)
        key, state = want[0], want[1]


def _python(code: str, **env: str) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "AMJAX_XLA_OPTIONS")}
    return subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True)


LATE = """
import warnings, jax, jax.numpy as jnp
jax.jit(lambda x: x + 1)(jnp.ones(2))  # JAX compiles before amjax is imported: XLA has read its flags
import amjax
from amjax.envs.lunar_lander import LunarLander
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    LunarLander()
print(len(caught), caught[0].message if caught else "")
"""


@pytest.mark.slow
def test_warning_when_jax_compiled_before_amjax_was_imported():
    done = _python(LATE)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("1 ") and "import amjax before" in done.stdout.lower()
    # Not with the options set from the start, nor when the user turned them off.
    quiet = _python(LATE, XLA_FLAGS=XLA_CPU_FLAGS)
    off = _python(LATE, AMJAX_XLA_OPTIONS="0")
    assert quiet.stdout.startswith("0") and off.stdout.startswith("0"), (quiet.stderr[-2000:], off.stderr[-2000:])


def _library_calls(compiled) -> int:
    return len(re.findall(r"^\s*(?:ROOT )?%ynn_fusion[\w.]* = ", compiled.as_text(), re.M))


def test_reductions_in_xla_keeps_dots_in_the_library_and_reductions_out_of_it():
    x = jax.random.normal(jax.random.key(0), (4096, 8))
    w = jax.random.normal(jax.random.key(1), (8, 8))

    def f(x, w):
        return jnp.sum(x * x, axis=1), jnp.max(x, axis=1), x @ w

    default = jax.jit(f).lower(x, w).compile()
    opted = jax.jit(f, compiler_options=REDUCTIONS_IN_XLA).lower(x, w).compile()
    if _library_calls(default) == 0:
        pytest.skip("XLA makes no YNNPACK calls on this CPU")
    # XLA's default sends the two reductions (and the dot) to YNNPACK; with the option the reductions stay in XLA.
    assert _library_calls(opted) == _library_calls(default) - 2
    for a, b in zip(default(x, w), opted(x, w), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
