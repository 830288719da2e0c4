"""Action distributions of the actor-critic agents (PPO, recurrent PPO), chosen from the env's action space.

- `Categorical(n)` for `Discrete(n)`: logits over the n actions (in an active-measure env n = 2 x controls and
  `action = control + controls * measure`, so one categorical chooses the pair).
- `HybridGaussian(controls, measure)` for `Box` control: a diagonal Gaussian over the control entries with a
  state-independent log standard deviation, sampled unbounded. The environment clips the control to its bounds
  (amjax's brax adapter and gymnax's Pendulum-v1 / MountainCarContinuous-v0 do), and the log-probability is that
  of the unclipped sample, as in CleanRL's and PureJaxRL's continuous PPO. With `measure` (an active-measure env,
  whose Box gains a leading entry that measures iff it is >= 0.5) an independent Bernoulli chooses whether to
  measure, and the action is `[measure in {0, 1}, control...]`. The greedy action (`mode`) measures iff the
  Bernoulli's probability exceeds 1/2 and takes the Gaussian's mean. With k instruments (`readings` = k) the
  Discrete space holds controls x 2^k pairs (`control + controls * mask`) and the Box k leading entries, one
  independent Bernoulli each.

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
    actions are an active-measure env's pairs, `control + controls * measure` (`num_actions` = 2 x controls), or
    with `readings` = k instruments `control + controls * mask` (`num_actions` = 2^k x controls)."""

    num_actions: int
    measure: bool = False
    readings: int = 1
    factored: bool = False  # the head outputs control and measure logits apart (networks.policy_head)

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
        if self.readings > 1:  # instruments: the most probable control, then a mask drawn given it
            masks = 2**self.readings
            controls = self.num_actions // masks
            probs = jax.nn.softmax(logits).reshape(*logits.shape[:-1], masks, controls)
            control = jnp.argmax(probs.sum(-2), axis=-1)
            given = jnp.take_along_axis(probs, control[..., None, None], -1)[..., 0]
            mask = jax.random.categorical(key, jnp.log(given))
            return control + controls * mask
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
    measuring logit [...] (None without a measure entry; [..., k] with k instruments)."""

    mean: jax.Array
    log_std: jax.Array
    measure_logit: Any = None


_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


@dataclass(frozen=True)
class HybridGaussian:
    """Gaussian control (`controls` entries) and, with `measure`, a Bernoulli measuring choice in front of it."""

    controls: int
    measure: bool
    readings: int = 1  # measure entries (instruments), each an independent Bernoulli

    @property
    def action_size(self) -> int:
        return self.controls + self.readings * int(self.measure)

    def _logits(self, out: GaussianOutputs) -> jax.Array:
        """The measuring logits as [..., readings]."""
        return out.measure_logit if self.readings > 1 else out.measure_logit[..., None]

    def _split(self, action: jax.Array) -> tuple[Any, jax.Array]:
        r = self.readings
        return (action[..., :r], action[..., r:]) if self.measure else (None, action)

    def sample(self, key: jax.Array, out: GaussianOutputs) -> jax.Array:
        control_key, measure_key = jax.random.split(key)
        control = out.mean + jnp.exp(out.log_std) * jax.random.normal(control_key, out.mean.shape)
        if not self.measure:
            return control
        measure = jax.random.bernoulli(measure_key, jax.nn.sigmoid(self._logits(out))).astype(control.dtype)
        return jnp.concatenate([measure, control], -1)

    def log_prob(self, out: GaussianOutputs, action: jax.Array) -> jax.Array:
        measure, control = self._split(action)
        z = (control - out.mean) * jnp.exp(-out.log_std)
        log_prob = (-0.5 * z**2 - out.log_std - _HALF_LOG_2PI).sum(-1)
        if self.measure:
            logit = self._logits(out)
            log_prob += (measure * jax.nn.log_sigmoid(logit) + (1.0 - measure) * jax.nn.log_sigmoid(-logit)).sum(-1)
        return log_prob

    def entropy(self, out: GaussianOutputs) -> jax.Array:
        entropy = (out.log_std + _HALF_LOG_2PI + 0.5).sum(-1)
        if self.measure:
            logit = self._logits(out)
            p = jax.nn.sigmoid(logit)
            entropy -= (p * jax.nn.log_sigmoid(logit) + (1.0 - p) * jax.nn.log_sigmoid(-logit)).sum(-1)
        return entropy

    def mode(self, out: GaussianOutputs) -> jax.Array:
        if not self.measure:
            return out.mean
        return jnp.concatenate([(self._logits(out) > 0).astype(out.mean.dtype), out.mean], -1)

    def mode_sampling_measure(self, key: jax.Array, out: GaussianOutputs) -> jax.Array:
        """The Gaussian's mean, measured with the Bernoulli's probability; `mode` without `measure`."""
        if not self.measure:
            return out.mean
        measure = jax.random.bernoulli(key, jax.nn.sigmoid(self._logits(out))).astype(out.mean.dtype)
        return jnp.concatenate([measure, out.mean], -1)


Distribution = Categorical | HybridGaussian


def for_action_space(space: Any, measure: bool, readings: int = 1, factored: bool = False) -> Distribution:
    """The distribution for an env's action space: `Categorical` for Discrete, `HybridGaussian` for a 1-D Box
    (`measure`: the Box's first entry is the active-measure wrapper's measuring choice, i.e. not a vanilla run;
    `readings`: the number of instruments, each a measure choice; `factored`: a Discrete space's pairs from a
    control head and a measure head, whose joint logits are their sums, i.e. a product of two categoricals)."""
    masks = 2**readings
    if isinstance(space, spaces.Discrete):
        if measure and int(space.n) % masks:
            raise ValueError(
                f"action space: an active-measure Discrete space with {readings} instrument(s) has "
                f"{masks} x controls actions, got {space}"
            )
        return Categorical(int(space.n), bool(measure), readings, bool(factored))
    entries = readings * int(measure)
    if isinstance(space, spaces.Box) and len(space.shape) == 1 and space.shape[0] > entries:
        return HybridGaussian(space.shape[0] - entries, bool(measure), readings)
    raise ValueError(f"action space: actor-critic agents need Discrete or a 1-D Box action space, got {space}")


__all__ = ["Categorical", "Distribution", "GaussianOutputs", "HybridGaussian", "for_action_space"]
