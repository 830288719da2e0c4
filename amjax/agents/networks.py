"""Flax networks shared by the agents.

Initialisers are QR-free on purpose: orthogonal initialisation vmapped over many configurations inside one jitted
program (batched QR) deadlocks jaxlib 0.10.2's CPU thread pool on 2 cores (see the research notes). A scaled
normal with the orthogonal initialiser's variance (gain^2 / fan_in) behaves the same for these small MLPs.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu, "elu": nn.elu}


def scaled_init(gain: float) -> nn.initializers.Initializer:
    """Truncated normal with variance gain^2 / fan_in (the variance of an orthogonal init with this gain)."""
    return nn.initializers.variance_scaling(gain**2, "fan_in", "truncated_normal")


class MLP(nn.Module):
    """Dense layers with an activation after each."""

    hidden: Sequence[int]
    activation: str = "tanh"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = ACTIVATIONS[self.activation]
        for width in self.hidden:
            x = act(nn.Dense(width, kernel_init=scaled_init(2**0.5))(x))
        return x


class ActorCritic(nn.Module):
    """Categorical policy logits and a state value; separate torsos unless `shared`."""

    num_actions: int
    hidden: Sequence[int] = (64, 64)
    activation: str = "tanh"
    shared: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        actor = MLP(self.hidden, self.activation, name="actor_torso")(obs)
        critic = actor if self.shared else MLP(self.hidden, self.activation, name="critic_torso")(obs)
        logits = nn.Dense(self.num_actions, kernel_init=scaled_init(0.01), name="logits")(actor)
        value = nn.Dense(1, kernel_init=scaled_init(1.0), name="value")(critic)
        return logits, jnp.squeeze(value, -1)


class DuelingQNetwork(nn.Module):
    """Q(s, a) = V(s) + A(s, a) - mean_a A(s, a) on an MLP torso (Wang et al. 2016)."""

    num_actions: int
    hidden: Sequence[int] = (64, 64)
    activation: str = "relu"
    dueling: bool = True

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = MLP(self.hidden, self.activation)(obs)
        return dueling_head(x, self.num_actions, self.dueling)


def dueling_head(x: jax.Array, num_actions: int, dueling: bool) -> jax.Array:
    """Q-values from features: a dueling value/advantage split, or a plain linear head."""
    if not dueling:
        return nn.Dense(num_actions, kernel_init=scaled_init(1.0), name="q")(x)
    value = nn.Dense(1, kernel_init=scaled_init(1.0), name="state_value")(x)
    advantage = nn.Dense(num_actions, kernel_init=scaled_init(1.0), name="advantage")(x)
    return value + advantage - advantage.mean(-1, keepdims=True)
