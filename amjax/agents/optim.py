"""The optimiser every agent uses (global-norm clipping + Adam, optional linear decay to zero), the gradient step
that PPO, PQN and their recurrent versions scan over minibatches, and the epochs of shuffled minibatches they run
(of rows for PPO and PQN, of whole env sequences for the recurrent ones), with the checks of their shapes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from amjax.validation import check_positive_int


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


def epoch_optimizer(config: Any, eps: float = 1e-8) -> optax.GradientTransformation:
    """`clipped_adam` for an agent that runs `update_epochs` x `num_minibatches` gradient steps per update of
    `steps_per_update()` env steps (PPO, PQN and their recurrent versions): the learning rate, when annealed,
    reaches 0 at the end of training."""
    num_updates = config.total_timesteps // config.steps_per_update()
    return clipped_adam(
        config.learning_rate,
        config.max_grad_norm,
        total_steps=num_updates * config.update_epochs * config.num_minibatches,
        anneal=config.anneal_lr,
        eps=eps,
    )


def check_epoch_fields(num_envs: Any, num_steps: Any, update_epochs: Any, num_minibatches: Any) -> None:
    """ValueError naming the first of a rollout's shape and its epochs of minibatches that is not a positive int."""
    for name, value in (
        ("num_envs", num_envs),
        ("num_steps", num_steps),
        ("update_epochs", update_epochs),
        ("num_minibatches", num_minibatches),
    ):
        check_positive_int(name, value)


def check_row_minibatches(num_envs: int, num_steps: int, num_minibatches: int) -> None:
    """ValueError unless `num_minibatches` divides the rollout's num_envs x num_steps rows (`minibatch_epochs`)."""
    if (num_envs * num_steps) % num_minibatches:
        raise ValueError(f"num_minibatches={num_minibatches} must divide num_envs * num_steps = {num_envs * num_steps}")


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


def minibatch_epochs(
    step: Callable[[Any, Any], tuple[Any, jax.Array]],
    carry: Any,
    batch: Any,
    key: jax.Array,
    epochs: int,
    minibatches: int,
) -> tuple[Any, jax.Array]:
    """`epochs` passes of `step` (a `minibatch_step`) over `batch` (arrays with one leading axis of rows), each pass
    in a fresh random order (`shuffle`) cut into `minibatches` equal minibatches; the final carry and the mean loss."""
    rows = jax.tree.leaves(batch)[0].shape[0]

    def epoch(carry: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        order = shuffle(key, rows)
        return jax.lax.scan(step, carry, jax.tree.map(lambda x: x[order].reshape(minibatches, -1, *x.shape[1:]), batch))

    carry, losses = jax.lax.scan(epoch, carry, jax.random.split(key, epochs))
    return carry, losses.mean()


def check_sequence_minibatches(num_envs: int, num_minibatches: int) -> None:
    """ValueError unless `num_minibatches` divides `num_envs` (`sequence_minibatch_epochs` splits whole envs)."""
    if num_envs % num_minibatches:
        raise ValueError(
            f"num_minibatches={num_minibatches} must divide num_envs={num_envs} (minibatches are whole env sequences)"
        )


def sequence_minibatch_epochs(
    step: Callable[[Any, Any], tuple[Any, jax.Array]],
    carry: Any,
    starts: Any,
    sequences: Any,
    key: jax.Array,
    epochs: int,
    minibatches: int,
) -> tuple[Any, jax.Array]:
    """`minibatch_epochs` for recurrent learners: the rows are whole env sequences. `sequences` are time-major
    arrays [T, envs, ...] and `starts` each env's initial hidden state [envs, ...]; each pass shuffles the envs and
    gives `step` minibatches `(starts [envs / M, ...], sequences [T, envs / M, ...])`. The final carry and the mean
    loss."""
    envs = jax.tree.leaves(starts)[0].shape[0]

    def epoch(carry: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        order = shuffle(key, envs).reshape(minibatches, -1)  # [M, envs / M]
        minibatch_starts = jax.tree.map(lambda c: c[order], starts)
        minibatch_sequences = jax.tree.map(lambda x: jnp.moveaxis(x[:, order], 1, 0), sequences)  # [M, T, E / M, ...]
        return jax.lax.scan(step, carry, (minibatch_starts, minibatch_sequences))

    carry, losses = jax.lax.scan(epoch, carry, jax.random.split(key, epochs))
    return carry, losses.mean()


def shuffle(key: jax.Array, n: int) -> jax.Array:
    """A uniformly random permutation of `arange(n)`, cheaper than `jax.random.permutation` on CPU.

    Each round sorts one uint32 array whose high bits are random and whose low bits are the index (XLA's CPU sort
    is about 5x faster on one integer array than on the (key, index) pair `permutation` sorts). Equal random bits
    keep index order; a second round with fresh bits re-orders such pairs, so a pair stays in a fixed order only if
    it ties in both rounds (about n^2 / 2 x 2^(-2 (32 - log2 n)) per permutation: ~3e-8 at n = 1024, against ~1e-4
    for `jax.random.permutation`'s single 32-bit round).
    """
    index_bits = max(1, (n - 1).bit_length())
    if index_bits > 20:  # too few random bits left per round: fall back
        return jax.random.permutation(key, n)
    mask = jnp.uint32((1 << index_bits) - 1)
    order = jnp.arange(n, dtype=jnp.uint32)
    for round_key in jax.random.split(key, 2):
        ranks = jnp.sort((jax.random.bits(round_key, (n,), jnp.uint32) & ~mask) | jnp.arange(n, dtype=jnp.uint32))
        order = order[ranks & mask]
    return order.astype(jnp.int32)
