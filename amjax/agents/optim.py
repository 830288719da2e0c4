"""The optimiser every agent uses: global-norm clipping + Adam, with an optional linear decay to zero."""

from __future__ import annotations

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
