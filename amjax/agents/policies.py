"""Action distributions of the actor-critic agents (PPO, recurrent PPO), chosen from the env's action space.

- `Categorical(n)` for `Discrete(n)`: logits over the n actions (in an active-measure env n = 2 x controls and
  `action = control + controls * measure`, so one categorical chooses the pair).
- `HybridGaussian(controls, measure)` for `Box` control: a diagonal Gaussian over the control entries with a
  state-independent log standard deviation, sampled unbounded. The environment clips the control to its bounds
  (amjax's brax adapter and gymnax's Pendulum-v1 / MountainCarContinuous-v0 do), and the log-probability is that
  of the unclipped sample, as in CleanRL's and PureJaxRL's continuous PPO. With `measure` (an active-measure env,
  whose Box gains a leading entry that measures iff it is >= 0.5) an independent Bernoulli chooses whether to
  measure, and the action is `[measure in {0, 1}, control...]`. The greedy action measures iff the Bernoulli's
  probability exceeds 1/2 and takes the Gaussian's mean.

Each distribution is a small frozen (hashable) object, a static attribute of the network that outputs its
parameters (`networks.policy_head`): `sample`, `log_prob`, `entropy` and `mode` take those outputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import spaces


@dataclass(frozen=True)
class Categorical:
    """A categorical over `num_actions` actions; its parameters are logits [..., num_actions]."""

    num_actions: int

    def sample(self, key: jax.Array, logits: jax.Array) -> jax.Array:
        return jax.random.categorical(key, logits)

    def log_prob(self, logits: jax.Array, action: jax.Array) -> jax.Array:
        return jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]

    def entropy(self, logits: jax.Array) -> jax.Array:
        log_p = jax.nn.log_softmax(logits)
        return -(jnp.exp(log_p) * log_p).sum(-1)

    def mode(self, logits: jax.Array) -> jax.Array:
        return jnp.argmax(logits, axis=-1)


@struct.dataclass
class GaussianOutputs:
    """Parameters of a `HybridGaussian` for a batch [...]: the control's mean and log std [..., controls] and the
    measuring logit [...] (None without a measure entry)."""

    mean: jax.Array
    log_std: jax.Array
    measure_logit: Any = None


_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


@dataclass(frozen=True)
class HybridGaussian:
    """Gaussian control (`controls` entries) and, with `measure`, a Bernoulli measuring choice in front of it."""

    controls: int
    measure: bool

    @property
    def action_size(self) -> int:
        return self.controls + int(self.measure)

    def _split(self, action: jax.Array) -> tuple[Any, jax.Array]:
        return (action[..., 0], action[..., 1:]) if self.measure else (None, action)

    def sample(self, key: jax.Array, out: GaussianOutputs) -> jax.Array:
        control_key, measure_key = jax.random.split(key)
        control = out.mean + jnp.exp(out.log_std) * jax.random.normal(control_key, out.mean.shape)
        if not self.measure:
            return control
        measure = jax.random.bernoulli(measure_key, jax.nn.sigmoid(out.measure_logit)).astype(control.dtype)
        return jnp.concatenate([measure[..., None], control], -1)

    def log_prob(self, out: GaussianOutputs, action: jax.Array) -> jax.Array:
        measure, control = self._split(action)
        z = (control - out.mean) * jnp.exp(-out.log_std)
        log_prob = (-0.5 * z**2 - out.log_std - _HALF_LOG_2PI).sum(-1)
        if self.measure:
            logit = out.measure_logit
            log_prob += measure * jax.nn.log_sigmoid(logit) + (1.0 - measure) * jax.nn.log_sigmoid(-logit)
        return log_prob

    def entropy(self, out: GaussianOutputs) -> jax.Array:
        entropy = (out.log_std + _HALF_LOG_2PI + 0.5).sum(-1)
        if self.measure:
            logit = out.measure_logit
            p = jax.nn.sigmoid(logit)
            entropy -= p * jax.nn.log_sigmoid(logit) + (1.0 - p) * jax.nn.log_sigmoid(-logit)
        return entropy

    def mode(self, out: GaussianOutputs) -> jax.Array:
        if not self.measure:
            return out.mean
        return jnp.concatenate([(out.measure_logit > 0).astype(out.mean.dtype)[..., None], out.mean], -1)


Distribution = Categorical | HybridGaussian


def for_action_space(space: Any, measure: bool) -> Distribution:
    """The distribution for an env's action space: `Categorical` for Discrete, `HybridGaussian` for a 1-D Box
    (`measure`: the Box's first entry is the active-measure wrapper's measuring choice, i.e. not a vanilla run)."""
    if isinstance(space, spaces.Discrete):
        return Categorical(int(space.n))
    if isinstance(space, spaces.Box) and len(space.shape) == 1 and space.shape[0] > int(measure):
        return HybridGaussian(space.shape[0] - int(measure), bool(measure))
    raise ValueError(f"action space: actor-critic agents need Discrete or a 1-D Box action space, got {space}")


__all__ = ["Categorical", "Distribution", "GaussianOutputs", "HybridGaussian", "for_action_space"]
