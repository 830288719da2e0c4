"""The optimiser every agent uses (global-norm clipping + Adam, optional linear decay to zero) and the gradient step
the PPO agents scan over minibatches."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax


def clipped_adam(
    learning_rate: jax.Array,
    max_grad_norm: jax.Array,
    *,
    total_steps: int,
    anneal: bool,
    eps: float = 1e-8,
) -> optax.GradientTransformation:
    """Adam after clipping gradients to `max_grad_norm`; with `anneal`, the learning rate decays linearly from
    `learning_rate` to 0 over `total_steps` optimiser steps. Both rates may be traced (vmapped) values."""

    def schedule(count: jax.Array) -> jax.Array:
        if not anneal:
            return learning_rate
        return learning_rate * (1.0 - jnp.minimum(count, total_steps) / max(total_steps, 1))

    return optax.chain(optax.clip_by_global_norm(max_grad_norm), optax.adam(schedule, eps=eps))


def minibatch_step(
    optimizer: optax.GradientTransformation, loss_fn: Callable[[Any, Any], jax.Array]
) -> Callable[[tuple[Any, Any], Any], tuple[tuple[Any, Any], jax.Array]]:
    """`step((params, opt_state), minibatch) -> ((params, opt_state), loss)`: one gradient step on `loss_fn`, in
    the form `lax.scan` takes."""

    def step(carry: tuple[Any, Any], minibatch: Any) -> tuple[tuple[Any, Any], jax.Array]:
        params, opt_state = carry
        loss, grads = jax.value_and_grad(loss_fn)(params, minibatch)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), loss

    return step
