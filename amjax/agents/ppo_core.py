"""What PPO (ppo.py) and recurrent PPO (ppo_rnn.py) share: their base config, the optimiser, GAE, the clipped
objective. Both algorithms are siblings of `PPOBaseConfig`.

`reward_scale` multiplies the rewards (measurement costs included) before GAE: the critic must reach the returns'
scale within the first few dozen updates (value clipping moves it at most `clip_eps` per update, Adam's step size
bounds it without). On Acrobot-v1 (-1 per step, returns -60 to -100) unscaled rewards left the critic far behind,
the advantages reduced to the next steps' measurement costs, and PPO stopped measuring under a cost of 0.2 or more
(docs/acrobot.md); the presets scale Acrobot's rewards by 0.1.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax
from flax import struct

from amjax.agents.config import AgentConfig, static
from amjax.agents.networks import check_activation
from amjax.agents.optim import check_epoch_fields, epoch_optimizer
from amjax.agents.policies import Distribution, for_action_space
from amjax.validation import check_bool, check_choice

EVAL_POLICIES = ("greedy", "stochastic", "greedy_control")


@struct.dataclass
class PPOBaseConfig(AgentConfig):
    """Fields of every PPO agent (defaults: feed-forward PPO's)."""

    num_envs: int = static(8)
    num_steps: int = static(128)  # rollout length per env per update
    update_epochs: int = static(4)
    num_minibatches: int = static(4)
    hidden: Sequence[int] = static((64, 64))
    activation: str = static("tanh")
    anneal_lr: bool = static(True)  # linear decay of the learning rate to 0 over training
    clip_value: bool = static(True)  # clip the value update to clip_eps around the rollout's values
    # The test policy (evaluations, re-scoring, saved policies): "greedy" (the most probable action),
    # "stochastic" (the policy as trained) or "greedy_control" (the most probable control, measuring as the policy
    # draws it). A memoryless greedy policy repeats itself on a stale observation (policies.py, docs/eval_policy.md).
    eval_policy: str = static("greedy")
    learning_rate: float = 1e-3
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    # The initial policy's probability of measuring (each reading, with instruments), whatever the control: the
    # measure logits' initial biases (networks.policy_head). 0.5 is the uniform policy. Near 1 the agent starts as
    # the always-measure baseline and learns where it can skip (docs/eval_policy.md). Ignored by vanilla runs.
    measure_prior: float = 0.5
    reward_scale: float = 1.0  # rewards (costs included) are multiplied by this before GAE and the value targets

    WIDTH_FIELDS: ClassVar[tuple[str, ...]] = ("hidden",)
    ACTION_SPACES: ClassVar[tuple[str, ...]] = ("Discrete", "Box")  # categorical or Gaussian + Bernoulli head
    TRACED_BOUNDS: ClassVar[dict[str, str]] = {
        "learning_rate": "positive",
        "gamma": "unit",
        "gae_lambda": "unit",
        "clip_eps": "positive",
        "ent_coef": "nonnegative",
        "vf_coef": "nonnegative",
        "max_grad_norm": "positive",
        "measure_prior": "probability",
        "reward_scale": "positive",
    }

    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps

    def check_fields(self) -> None:
        check_epoch_fields(self.num_envs, self.num_steps, self.update_epochs, self.num_minibatches)
        check_activation(self.activation)
        check_choice("eval_policy", self.eval_policy, EVAL_POLICIES)
        check_bool("clip_value", self.clip_value)
        super().check_fields()


def eval_action(config: PPOBaseConfig, distribution: Distribution, outputs: Any, key: jax.Array) -> jax.Array:
    """The test policy's action for the policy `outputs` (`config.eval_policy`)."""
    if config.eval_policy == "stochastic":
        return distribution.sample(key, outputs)
    if config.eval_policy == "greedy_control":
        return distribution.mode_sampling_measure(key, outputs)
    return distribution.mode(outputs)


def policy_distribution(config: PPOBaseConfig, action_space: Any) -> Distribution:
    """The policy's distribution over `action_space` for `config`'s measurement setting (policies.py)."""
    return for_action_space(
        action_space, measure=not config.vanilla, readings=config.num_instruments, factored=config.factored_masks > 0
    )


def make_optimizer(config: PPOBaseConfig) -> optax.GradientTransformation:
    return epoch_optimizer(config, eps=1e-5)


def gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    done: jax.Array,
    gamma: jax.Array,
    gae_lambda: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """Generalized advantage estimates and value targets over a [T, ...] rollout.

    delta_t = r_t + gamma (1 - terminated_t) V(s'_t) - V(s_t), where s'_t is the pre-reset next observation;
    A_t = delta_t + gamma lambda (1 - done_t) A_{t+1}.
    """
    deltas = rewards + gamma * (1.0 - terminated) * next_values - values

    def backward(advantage, step):
        delta, done_t = step
        advantage = delta + gamma * gae_lambda * (1.0 - done_t) * advantage
        return advantage, advantage

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(deltas[0]), (deltas, done.astype(deltas.dtype)), reverse=True)
    return advantages, advantages + values


def rollout_advantages(config: PPOBaseConfig, transitions: Any, values: jax.Array, next_values: jax.Array):
    """`gae` of a rollout's transitions ([T, E]): advantages and value targets, with `next_values` the values of
    the pre-reset next observations (so a truncated episode bootstraps and a terminated one does not)."""
    # Exactly the unscaled program's rewards at 1.0: a product, even by 1.0, can be fused into the GAE arithmetic
    # (a fused multiply-add rounds differently), so rows of unscaled runs would change in the last bits.
    scale = config.reward_scale
    rewards = jnp.where(scale == 1.0, transitions.reward, scale * transitions.reward)
    return gae(
        rewards,
        values,
        next_values,
        transitions.terminated.astype(jnp.float32),
        transitions.done,
        config.gamma,
        config.gae_lambda,
    )


def clipped_loss(
    config: Any,
    distribution: Distribution,
    policy: Any,
    value: jax.Array,
    action: jax.Array,
    old_log_prob: jax.Array,
    old_value: jax.Array,
    advantage: jax.Array,
    target: jax.Array,
) -> jax.Array:
    """The PPO loss on a batch of any shape [...]: clipped policy objective (advantages normalised over the
    batch) + vf_coef x value loss (clipped if `config.clip_value`) - ent_coef x entropy. `policy` holds the
    parameters of `distribution` (policies.py) for the batch; `config` supplies clip_eps, clip_value, vf_coef,
    ent_coef."""
    log_prob = distribution.log_prob(policy, action)
    value_loss = (value - target) ** 2
    if config.clip_value:
        value_clipped = old_value + jnp.clip(value - old_value, -config.clip_eps, config.clip_eps)
        value_loss = jnp.maximum(value_loss, (value_clipped - target) ** 2)
    value_loss = 0.5 * value_loss.mean()
    ratio = jnp.exp(log_prob - old_log_prob)
    advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    policy_loss = -jnp.minimum(
        ratio * advantage,
        jnp.clip(ratio, 1.0 - config.clip_eps, 1.0 + config.clip_eps) * advantage,
    ).mean()
    entropy = distribution.entropy(policy).mean()
    return policy_loss + config.vf_coef * value_loss - config.ent_coef * entropy
