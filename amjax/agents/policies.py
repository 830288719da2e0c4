"""Action distributions of the actor-critic agents (PPO, recurrent PPO), chosen from the env's action space.

- `Categorical(n)` for `Discrete(n)`: logits over the n actions (in an active-measure env n = 2 x controls and
  `action = control + controls * measure`, so one categorical chooses the pair).
- `HybridGaussian(controls, measure)` for `Box` control: a diagonal Gaussian over the control entries with a
  state-independent log standard deviation, sampled unbounded. The environment clips the control to its bounds
  (amjax's brax adapter and gymnax's Pendulum-v1 / MountainCarContinuous-v0 do), and the log-probability is that
  of the unclipped sample, as in CleanRL's and PureJaxRL's continuous PPO. With `measure` (an active-measure env,
  whose Box gains a leading entry that measures iff it is >= 0.5) an independent Bernoulli chooses whether to
  measure, and the action is `[measure in {0, 1}, control...]`. The greedy action (`mode`) measures iff the
  Bernoulli's probability exceeds 1/2 and takes the Gaussian's mean.

The actor-critic agents' test policy (`eval_policy`, ppo_core.py) is by default the most probable action (`mode`);
it can be the policy as trained (`sample`) or the most probable control measuring as the policy draws it
(`mode_sampling_measure`). Without a fresh measurement a memoryless policy sees the same stale observation step
after step, and a deterministic one then repeats the same control and the same choice not to measure: it can skip at
most every other step and holds one action through every gap. PPO learns to measure and act as a mixed strategy
while stale; on costed LunarLander-v3 its modes crash where the policies land (docs/eval_policy.md).

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
    """A categorical over `num_actions` actions; its parameters are logits [..., num_actions]. With `measure` the
    actions are an active-measure env's pairs, `control + controls * measure` (`num_actions` = 2 x controls)."""

    num_actions: int
    measure: bool = False

    def sample(self, key: jax.Array, logits: jax.Array) -> jax.Array:
        return jax.random.categorical(key, logits)

    def log_prob(self, logits: jax.Array, action: jax.Array) -> jax.Array:
        return jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]

    def entropy(self, logits: jax.Array) -> jax.Array:
        log_p = jax.nn.log_softmax(logits)
        return -(jnp.exp(log_p) * log_p).sum(-1)

    def mode(self, logits: jax.Array) -> jax.Array:
        return jnp.argmax(logits, axis=-1)

    def mode_sampling_measure(self, key: jax.Array, logits: jax.Array) -> jax.Array:
        """The most probable control (summed over measuring or not), measured with the policy's probability of
        measuring given that control; `mode` without `measure`."""
        if not self.measure:
            return self.mode(logits)
        controls = self.num_actions // 2
        probs = jax.nn.softmax(logits)
        skip, measure = probs[..., :controls], probs[..., controls:]
        control = jnp.argmax(skip + measure, axis=-1)
        p_skip, p_measure = (jnp.take_along_axis(p, control[..., None], -1)[..., 0] for p in (skip, measure))
        measured = jax.random.uniform(key, control.shape) * (p_skip + p_measure) < p_measure
        return control + controls * measured.astype(control.dtype)


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

    def mode_sampling_measure(self, key: jax.Array, out: GaussianOutputs) -> jax.Array:
        """The Gaussian's mean, measured with the Bernoulli's probability; `mode` without `measure`."""
        if not self.measure:
            return out.mean
        measure = jax.random.bernoulli(key, jax.nn.sigmoid(out.measure_logit)).astype(out.mean.dtype)
        return jnp.concatenate([measure[..., None], out.mean], -1)


Distribution = Categorical | HybridGaussian


def for_action_space(space: Any, measure: bool) -> Distribution:
    """The distribution for an env's action space: `Categorical` for Discrete, `HybridGaussian` for a 1-D Box
    (`measure`: the Box's first entry is the active-measure wrapper's measuring choice, i.e. not a vanilla run)."""
    if isinstance(space, spaces.Discrete):
        if measure and int(space.n) % 2:
            raise ValueError(f"action space: an active-measure Discrete space has 2 x controls actions, got {space}")
        return Categorical(int(space.n), bool(measure))
    if isinstance(space, spaces.Box) and len(space.shape) == 1 and space.shape[0] > int(measure):
        return HybridGaussian(space.shape[0] - int(measure), bool(measure))
    raise ValueError(f"action space: actor-critic agents need Discrete or a 1-D Box action space, got {space}")


__all__ = ["Categorical", "Distribution", "GaussianOutputs", "HybridGaussian", "for_action_space"]
