"""Flax networks shared by the agents.

Initialisers are QR-free on purpose: orthogonal initialisation vmapped over many configurations inside one jitted
program (batched QR) deadlocks jaxlib 0.10.2's CPU thread pool on 2 cores (see the research notes). A scaled
normal with the orthogonal initialiser's variance (gain^2 / fan_in) behaves the same for these small MLPs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

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


@jax.custom_vjp
def _narrow_matmul(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return x @ kernel


def _narrow_matmul_fwd(x: jax.Array, kernel: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    return x @ kernel, (x, kernel)


def _narrow_matmul_bwd(residuals: tuple[jax.Array, jax.Array], g: jax.Array) -> tuple[jax.Array, jax.Array]:
    x, kernel = residuals
    rows_x, rows_g = x.reshape(-1, x.shape[-1]), g.reshape(-1, g.shape[-1])
    # The kernel gradient as [out, in], then transposed: with few outputs (a policy head), XLA's CPU dot is ~5x
    # faster writing the small dimension first; the barrier keeps XLA from folding the transpose back into the dot.
    kernel_grad = jax.lax.optimization_barrier(jnp.einsum("bo,bi->oi", rows_g, rows_x))
    return g @ kernel.T, kernel_grad.T


_narrow_matmul.defvjp(_narrow_matmul_fwd, _narrow_matmul_bwd)


class NarrowDense(nn.Module):
    """`nn.Dense` (same parameters, names and initialisation) for a layer with few outputs, with a faster kernel
    gradient on CPU (see `_narrow_matmul_bwd`)."""

    features: int
    kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel = self.param("kernel", self.kernel_init, (x.shape[-1], self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        return _narrow_matmul(x, kernel) + bias


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
        logits = NarrowDense(self.num_actions, kernel_init=scaled_init(0.01), name="logits")(actor)
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
        return dueling_head(x, self.num_actions, self.dueling, head=NarrowDense)


def dueling_head(x: jax.Array, num_actions: int, dueling: bool, head: type[nn.Module] = nn.Dense) -> jax.Array:
    """Q-values from features: a dueling value/advantage split, or a plain linear head (`head`: the layer class of
    the per-action outputs, `nn.Dense` or the same parameters as `NarrowDense`)."""
    if not dueling:
        return head(num_actions, kernel_init=scaled_init(1.0), name="q")(x)
    value = nn.Dense(1, kernel_init=scaled_init(1.0), name="state_value")(x)
    advantage = head(num_actions, kernel_init=scaled_init(1.0), name="advantage")(x)
    return value + advantage - advantage.mean(-1, keepdims=True)


# -- recurrent networks ---------------------------------------------------------------------------------------
#
# A recurrent network is called one step at a time: `apply(params, carry, obs, first) -> (carry, outputs)`, with the
# carry reset to zeros where `first` (an episode's first step) before the step. `obs`/`first` may have any leading
# batch axes ([envs] when acting, [time, envs] when bootstrapping every step of a sequence at once); `unroll`
# scans the step over a time-major sequence. Carries are pytrees of arrays (checkpointable).

CELLS = ("gru", "lstm")


def zero_carry(cell: str, size: int, batch_shape: tuple[int, ...]) -> Any:
    """The initial (all-zero) carry of a `cell` with `size` units for a batch: an array (GRU) or (c, h) (LSTM)."""
    zeros = jnp.zeros((*batch_shape, size), jnp.float32)
    return (zeros, zeros) if cell == "lstm" else zeros


def reset_carry(carry: Any, first: jax.Array) -> Any:
    """Zero the carry where `first` (shape = the carry's batch axes)."""
    return jax.tree.map(lambda c: jnp.where(first[..., None], jnp.zeros_like(c), c), carry)


class RecurrentCore(nn.Module):
    """MLP torso -> one GRU or LSTM step; outputs [torso features, cell output] (a skip connection: the heads see
    the current observation at once, without waiting for the cell's gates to open, and the memory beside it).
    Recurrent kernels use `scaled_init` (QR-free, see above)."""

    hidden: Sequence[int] = (64,)
    rnn_size: int = 64
    cell: str = "gru"
    activation: str = "relu"

    @nn.compact
    def __call__(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, jax.Array]:
        carry = reset_carry(carry, first)
        x = MLP(self.hidden, self.activation)(obs)
        inits = {"kernel_init": scaled_init(1.0), "recurrent_kernel_init": scaled_init(1.0)}
        if self.cell == "lstm":
            cell = nn.OptimizedLSTMCell(self.rnn_size, **inits, name="lstm")
        else:
            cell = nn.GRUCell(self.rnn_size, **inits, name="gru")
        carry, y = cell(carry, x)
        return carry, jnp.concatenate([x, y], -1)


class RecurrentQNetwork(nn.Module):
    """DRQN (Hausknecht & Stone 2015): a recurrent core under the dueling head; one step -> (carry, Q-values)."""

    num_actions: int
    hidden: Sequence[int] = (64,)
    rnn_size: int = 64
    cell: str = "gru"
    activation: str = "relu"
    dueling: bool = True

    @nn.compact
    def __call__(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, jax.Array]:
        carry, x = RecurrentCore(self.hidden, self.rnn_size, self.cell, self.activation)(carry, obs, first)
        return carry, dueling_head(x, self.num_actions, self.dueling)


class RecurrentActorCritic(nn.Module):
    """One recurrent core shared by a categorical policy head and a value head; one step -> (carry, (logits,
    value))."""

    num_actions: int
    hidden: Sequence[int] = (64,)
    rnn_size: int = 64
    cell: str = "gru"
    activation: str = "tanh"

    @nn.compact
    def __call__(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, tuple[jax.Array, jax.Array]]:
        carry, x = RecurrentCore(self.hidden, self.rnn_size, self.cell, self.activation)(carry, obs, first)
        logits = nn.Dense(self.num_actions, kernel_init=scaled_init(0.01), name="logits")(x)
        value = nn.Dense(1, kernel_init=scaled_init(1.0), name="value")(x)
        return carry, (logits, jnp.squeeze(value, -1))


def unroll(
    step: Callable[[Any, jax.Array, jax.Array], tuple[Any, Any]], carry: Any, obs: jax.Array, first: jax.Array
) -> tuple[Any, Any]:
    """Scan `step(carry, obs_t, first_t) -> (carry, out)` over a time-major sequence [T, batch, ...].

    Returns (the carry after every step [T, batch, ...], the outputs [T, ...]); the carry after step t is where the
    bootstrap value of step t's (pre-reset) next observation starts from."""

    def body(carry, xs):
        carry, out = step(carry, *xs)
        return carry, (carry, out)

    return jax.lax.scan(body, carry, (obs, first))[1]
