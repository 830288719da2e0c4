"""brax's physics environments behind the gymnax API: ids "brax:<env_name>" and "brax:<env_name>:<backend>".

`make_brax("brax:reacher:spring")` builds brax's `reacher` (`brax.envs.get_environment`) on the `spring` physics
pipeline and wraps it as a gymnax `Environment`, so `amjax.make` puts the active-measure wrapper on top like on any
other Box-action environment. Without a backend the env's own default is used (generalized for brax's classic
envs). What the adapter does (docs/brax.md has the details):

- Auto-reset with fresh randomness: gymnax's `Environment.step` splits the step's key and resets from one half
  where an episode ended. (brax's own `AutoResetWrapper` restores the episode's first state instead, so every
  episode of an env would start the same; it is not used.)
- Time limit: `BraxParams.max_steps_in_episode` (default 1000, as brax's `EpisodeWrapper`) ends an episode as
  *truncated*; brax's `done` is reported as *terminated*. Both can hold on one step.
- Actions are clipped to the action space, [-1, 1] per actuator, before brax steps: the agents sample unclipped
  Gaussians. Every brax env takes actions in [-1, 1]: those whose actuators have another control range (e.g.
  inverted_pendulum's [-3, 3]) map [-1, 1] onto it in their own `step`, the others have range [-1, 1]. The
  physics would clip to the control range anyway, but some rewards charge the action itself (reacher's control
  cost is -|a|^2), so an out-of-range action would be charged for force it never applied.
- `info`: "discount" (0 on termination, else 1) and brax's per-step metrics as "metrics/<name>" (e.g. reacher's
  "metrics/reward_dist"); gymnax's `step` adds "terminated", "truncated" and "final_observation".
- Dtypes: brax returns some leaves as weakly typed floats (inverted_pendulum's reward is a Python 1.0); the stored
  state keeps each leaf's dtype from the reset, so the state is a fixed pytree that `lax.scan` can carry.

brax is an optional dependency (`pip install "amjax-rl[brax]"`) imported on first use; this module imports without
it. `brax.training` is never used: it calls `jax.device_put_replicated`, which this JAX no longer has.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.util
import io
import warnings
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import environment, spaces

PREFIX = "brax:"
BACKENDS = ("generalized", "positional", "spring", "mjx")
# The ids `registered_envs()` lists when brax is installed (the ones amjax's tests step against brax); every other
# brax env name works too.
LISTED = ("brax:inverted_pendulum", "brax:inverted_double_pendulum", "brax:reacher")
INSTALL_HINT = 'pip install "amjax-rl[brax]"'
UNMAINTAINED = "Brax System, piplines and environments are not actively being maintained"  # sic
UNBOUNDED = float(jnp.finfo(jnp.float32).max)  # gymnax writes an unbounded Box as +-finfo(float32).max


@struct.dataclass
class BraxParams(environment.EnvParams):
    max_steps_in_episode: int = 1000  # then the episode is truncated (brax's EpisodeWrapper default)


@struct.dataclass
class BraxState(environment.EnvState):
    time: int  # steps taken in this episode
    brax_state: Any  # brax.envs.State: pipeline_state, obs, reward, done, metrics, info


def brax_installed() -> bool:
    """Whether brax can be imported (without importing it)."""
    try:
        return importlib.util.find_spec("brax") is not None
    except (ImportError, ValueError):  # ValueError: sys.modules["brax"] is None or has no spec
        return False


def import_brax_envs(env_id: str) -> Any:
    """`brax.envs`, or an ImportError that says how to install it."""
    try:
        # mujoco's MJX prints "Failed to import warp" lines on import (warp is its optional backend for NVIDIA
        # GPUs), which do not concern the JAX pipelines used here.
        with contextlib.redirect_stdout(io.StringIO()):
            return importlib.import_module("brax.envs")
    except ImportError as error:
        raise ImportError(f"env_id {env_id!r} needs brax, an optional dependency: {INSTALL_HINT}") from error


def parse_id(env_id: str) -> tuple[str, str | None]:
    """("reacher", "spring") for "brax:reacher:spring", ("reacher", None) for "brax:reacher"; ValueError for a
    malformed id or an unknown backend."""
    parts = env_id.removeprefix(PREFIX).split(":")
    if not env_id.startswith(PREFIX) or len(parts) > 2 or not parts[0]:
        raise ValueError(f"env_id: got {env_id!r}; allowed values: 'brax:<env_name>' or 'brax:<env_name>:<backend>'")
    if len(parts) == 2 and parts[1] not in BACKENDS:
        raise ValueError(
            f"env_id: unknown brax backend {parts[1]!r} in {env_id!r}; allowed values: {', '.join(BACKENDS)}"
        )
    return parts[0], parts[1] if len(parts) == 2 else None


def make_brax(env_id: str) -> tuple[BraxEnv, BraxParams]:
    """The gymnax-API environment for a "brax:<env_name>[:<backend>]" id and its default params."""
    name, backend = parse_id(env_id)
    import_brax_envs(env_id)  # before the cache: an uninstalled brax must raise even for an id made before
    env = _cached_env(name, backend, env_id)
    return env, env.default_params


@functools.cache
def _cached_env(name: str, backend: str | None, env_id: str) -> BraxEnv:
    # One object per id: loading the model takes about a second, and the object is the jitted reset/step's static
    # argument, so every `make` of the same id shares their compiled programs.
    envs = import_brax_envs(env_id)
    known = sorted(getattr(envs, "_envs", {}))  # brax's registry (no public listing)
    if name not in known:
        raise ValueError(f"env_id: unknown brax environment {name!r} in {env_id!r}; allowed values: {', '.join(known)}")
    kwargs = {} if backend is None else {"backend": backend}
    # Loading a model computes arrays with jnp; inside a trace (an env first made inside a jitted function) they
    # would be tracers, cached here and leaked into every later program: compute them eagerly.
    with warnings.catch_warnings(), jax.ensure_compile_time_eval():
        warnings.filterwarnings("ignore", message=UNMAINTAINED)  # on loading every model; see docs/brax.md
        try:
            brax_env = envs.get_environment(name, **kwargs)
        except ValueError as error:  # e.g. swimmer on any backend but generalized: "Unsupported backend: spring."
            raise ValueError(f"env_id: brax refused {env_id!r}: {error}") from error
    return BraxEnv(brax_env, env_id)


def _strong(tree: Any) -> Any:
    """Every leaf as a JAX array of its own dtype, not weakly typed (Python floats included)."""
    return jax.tree.map(lambda leaf: jnp.asarray(leaf, jnp.asarray(leaf).dtype), tree)


class BraxEnv(environment.Environment[BraxState, BraxParams]):
    """A brax `Env` as a gymnax `Environment` (see the module docstring)."""

    def __init__(self, brax_env: Any, env_id: str = "brax"):
        super().__init__()
        self.brax_env = brax_env
        self.env_id = env_id
        obs = jax.eval_shape(brax_env.reset, jax.random.key(0)).obs  # traced, not compiled
        if not isinstance(obs, jax.ShapeDtypeStruct) or len(obs.shape) != 1:
            raise TypeError(
                f"env: {env_id} observes {obs}; amjax needs one 1-D array (brax's dict observations, "
                "e.g. for pixels, are not supported)"
            )
        self.obs_size = int(obs.shape[0])
        self.action_size = int(brax_env.action_size)

    @property
    def default_params(self) -> BraxParams:
        return BraxParams()

    def reset_env(self, key: jax.Array, params: BraxParams) -> tuple[jax.Array, BraxState]:
        brax_state = _strong(self.brax_env.reset(key))
        return brax_state.obs, BraxState(time=0, brax_state=brax_state)

    def step_env(
        self, key: jax.Array, state: BraxState, action: jax.Array, params: BraxParams
    ) -> tuple[jax.Array, BraxState, jax.Array, jax.Array, dict[str, Any]]:
        # brax's step is deterministic: `key` is unused (gymnax's `step` resets from the other half of its key).
        before = state.brax_state
        action = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        # Fresh dicts: reacher (and others) update `state.metrics` in place inside `step`.
        stepped = self.brax_env.step(before.replace(metrics=dict(before.metrics), info=dict(before.info)), action)
        stepped = jax.tree.map(lambda new, old: jnp.asarray(new, old.dtype), stepped, before)
        terminated = stepped.done > 0
        info = {
            "discount": 1.0 - terminated.astype(jnp.float32),
            **{f"metrics/{name}": value for name, value in stepped.metrics.items()},
        }
        return stepped.obs, BraxState(time=state.time + 1, brax_state=stepped), stepped.reward, terminated, info

    def is_terminated(self, state: BraxState, params: BraxParams) -> jax.Array:
        return state.brax_state.done > 0

    @property
    def name(self) -> str:
        return self.env_id

    @property
    def num_actions(self) -> int:
        """The action dimension (as gymnax counts it for Box actions)."""
        return self.action_size

    def action_space(self, params: BraxParams | None = None) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (self.action_size,), jnp.float32)

    def observation_space(self, params: BraxParams | None = None) -> spaces.Box:
        return spaces.Box(-UNBOUNDED, UNBOUNDED, (self.obs_size,), jnp.float32)


__all__ = ["BACKENDS", "BraxEnv", "BraxParams", "BraxState", "make_brax"]
