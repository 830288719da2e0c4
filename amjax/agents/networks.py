"""Flax networks shared by the agents.

Initialisers are QR-free on purpose: orthogonal initialisation vmapped over many configurations inside one jitted
program (batched QR) deadlocks jaxlib 0.10.2's CPU thread pool on 2 cores (see the research notes). A scaled
normal with the orthogonal initialiser's variance (gain^2 / fan_in) behaves the same for these small MLPs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from amjax import strategy
from amjax.agents.policies import Categorical, Distribution, GaussianOutputs
from amjax.validation import check_choice, check_positive_int

ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu, "elu": nn.elu}


def scaled_init(gain: float) -> nn.initializers.Initializer:
    """Truncated normal with variance gain^2 / fan_in (the variance of an orthogonal init with this gain)."""
    return nn.initializers.variance_scaling(gain**2, "fan_in", "truncated_normal")


LAYER_NORM_EPSILON = 1e-6  # flax's `nn.LayerNorm` default


@jax.custom_vjp
def _layer_norm(x: jax.Array, scale: jax.Array, bias: jax.Array) -> jax.Array:
    return _layer_norm_fwd(x, scale, bias)[0]


def _layer_norm_fwd(x: jax.Array, scale: jax.Array, bias: jax.Array) -> tuple[jax.Array, tuple[jax.Array, ...]]:
    centred = x - x.mean(-1, keepdims=True)
    rstd = jax.lax.rsqrt(jnp.square(centred).mean(-1, keepdims=True) + LAYER_NORM_EPSILON)
    normed = centred * rstd
    return normed * scale + bias, (normed, rstd, scale)


def _layer_norm_bwd(residuals: tuple[jax.Array, ...], grad: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    normed, rstd, scale = residuals
    g = grad * scale
    # d/dx of (x - mean) * rstd: rstd (g - mean(g) - normed mean(g normed)), the means over the features
    dx = rstd * (g - g.mean(-1, keepdims=True) - normed * (g * normed).mean(-1, keepdims=True))
    rows = tuple(range(grad.ndim - 1))
    return dx, (grad * normed).sum(rows), grad.sum(rows)


_layer_norm.defvjp(_layer_norm_fwd, _layer_norm_bwd)


class LayerNorm(nn.Module):
    """LayerNorm over the last axis (Ba et al. 2016) with `nn.LayerNorm`'s parameters ("scale", "bias"), names,
    initialisation and epsilon, and a hand-written gradient. The statistics take two passes, as flax's
    `use_fast_variance=False` (accurate in float32 for features with a large mean and a small spread, where flax's
    default one-pass E[x^2] - E[x]^2 loses every digit); the input's gradient comes from two means. XLA's CPU
    backend runs autodiff's gradient of `nn.LayerNorm` as many small reductions over the 64-128 features; this one
    removes about a fifth of LayerNorm's cost in PQN's gradient step (`benchmarks/layer_norm_grad.py`,
    docs/pqn.md). Equal to flax's in value and gradient to float rounding (tests/agents/test_layer_norm.py)."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        scale = self.param("scale", nn.initializers.ones_init(), (x.shape[-1],), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (x.shape[-1],), jnp.float32)
        return _layer_norm(x, scale, bias)


class MLP(nn.Module):
    """Dense layers with an activation after each, on the observation flattened (its last `obs_ndim` axes; the
    axes before them are batch axes)."""

    hidden: Sequence[int]
    activation: str = "tanh"
    obs_ndim: int = 1
    layer_norm: bool = False  # LayerNorm (Ba et al. 2016) between each Dense layer and its activation (PQN)

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = ACTIVATIONS[self.activation]
        if self.obs_ndim > 1:
            x = x.reshape(*x.shape[: x.ndim - self.obs_ndim], -1)
        for width in self.hidden:
            x = nn.Dense(width, kernel_init=scaled_init(2**0.5))(x)
            x = act(LayerNorm()(x) if self.layer_norm else x)
        return x


CONV_KERNEL = 3  # MinAtar's network: 16 filters of 3 x 3, stride 1, no padding (Young & Tian 2019, section 4)
CONV_FEATURES = 16


class PatchConv(nn.Module):
    """`nn.Conv(features, (k, k), padding="VALID")` (the same parameters, names and shapes) computed as one matrix
    product of the image's k x k patches: XLA's CPU backend runs that product several times faster than its
    convolution inside the agents' loops, vmapped over configurations."""

    features: int
    kernel_size: int
    kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k, channels = self.kernel_size, x.shape[-1]
        kernel = self.param("kernel", self.kernel_init, (k, k, channels, self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        height, width = x.shape[-3] - k + 1, x.shape[-2] - k + 1
        # [..., height, width, k * k * channels], ordered (row, column, channel) as the kernel's rows below
        patches = jnp.concatenate([x[..., i : i + height, j : j + width, :] for i in range(k) for j in range(k)], -1)
        return patches @ kernel.reshape(k * k * channels, self.features) + bias


class ConvTorso(nn.Module):
    """The MinAtar paper's network body for an image [height, width, channels] with any batch axes before it: one
    convolution (16 filters of 3 x 3, stride 1, no padding; Young & Tian 2019, "MinAtar", section 4), flattened,
    then Dense layers `hidden` (the paper's one layer of 128 units is `hidden=(128,)`)."""

    hidden: Sequence[int]
    activation: str = "relu"
    layer_norm: bool = False  # in the Dense layers (`MLP`)

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        conv = PatchConv(CONV_FEATURES, CONV_KERNEL, kernel_init=scaled_init(2**0.5), name="Conv_0")
        x = ACTIVATIONS[self.activation](conv(x))
        return MLP(self.hidden, self.activation, obs_ndim=3, layer_norm=self.layer_norm)(x)


TORSOS = ("auto", "mlp", "cnn")


@dataclasses.dataclass(frozen=True)
class Torso:
    """The body every network puts before its heads: "mlp" (the observation flattened, then Dense layers) or "cnn"
    (`ConvTorso`, for images); `obs_ndim`: the observation's own axes (1 for a vector, 3 for an image)."""

    kind: str = "mlp"
    obs_ndim: int = 1

    def build(
        self, hidden: Sequence[int], activation: str, name: str | None = None, layer_norm: bool = False
    ) -> nn.Module:
        if self.kind == "cnn":
            return ConvTorso(hidden, activation, layer_norm, name=name)
        return MLP(hidden, activation, self.obs_ndim, layer_norm, name=name)


VECTOR_TORSO = Torso()  # the default body: an MLP on a vector observation


def pick_torso(torso: str, obs_shape: tuple[int, ...]) -> Torso:
    """The `Torso` for `obs_shape` (one observation's): `torso` "auto" takes "cnn" for an image [height, width,
    channels] at least `CONV_KERNEL` pixels on a side, else "mlp"; "mlp" or "cnn" force one. ValueError for "cnn" on
    an observation that is not such an image, or for another name."""
    if torso not in TORSOS:
        raise ValueError(f"torso: got {torso!r}; allowed values: {', '.join(map(repr, TORSOS))}")
    image = len(obs_shape) == 3 and min(obs_shape[:2]) >= CONV_KERNEL
    if torso == "cnn" and not image:
        raise ValueError(
            f"torso: 'cnn' needs an image observation [height, width, channels] at least {CONV_KERNEL} pixels on a "
            f"side, but the observation's shape is {tuple(obs_shape)}; allowed here: 'auto' or 'mlp'"
        )
    kind = "cnn" if torso == "cnn" or (torso == "auto" and image) else "mlp"
    return Torso(kind, len(obs_shape))


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
    bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel = self.param("kernel", self.kernel_init, (x.shape[-1], self.features), jnp.float32)
        bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
        if strategy.is_gpu():  # the barrier and transpose of the CPU gradient are two more kernels on a GPU
            return x @ kernel + bias
        return _narrow_matmul(x, kernel) + bias


def prior_logit(prior: Any, dtype: Any = jnp.float32) -> jax.Array:
    """log(prior / (1 - prior)); `prior` may be traced, and 0.5 gives 0 exactly."""
    prior = jnp.asarray(prior, dtype)
    return jnp.log(prior / (1 - prior))


def measure_bias(masks: int, controls: int, prior: Any) -> nn.initializers.Initializer:
    """Initial biases of `masks` x `controls` logits ordered `control + controls * mask` that make each reading
    measured with probability `prior`, whatever the control: the logits of mask m get popcount(m) x logit(prior)."""

    def init(key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
        readings = jnp.array([bin(m).count("1") for m in range(masks)], dtype)
        return jnp.broadcast_to(readings[:, None] * prior_logit(prior, dtype), (masks, controls)).reshape(shape)

    return init


def policy_head(
    module: nn.Module,
    x: jax.Array,
    distribution: Distribution,
    dense: type[nn.Module] = nn.Dense,
    measure_prior: Any = 0.5,
) -> Any:
    """The parameters of `distribution` from features `x`, as layers of `module` (call inside its compact
    `__call__`): logits for a `Categorical` (layer "logits"), `GaussianOutputs` for a `HybridGaussian` (layers
    "mean" and "measure_logit", parameter "log_std", initialised to 0). Small initial weights start every policy
    near uniform over controls, measuring each reading with probability `measure_prior` (the biases of the measure
    logits, `measure_bias`; 0.5 by default, the uniform policy)."""
    if isinstance(distribution, Categorical):
        masks = 2**distribution.readings if distribution.measure else 1
        controls = distribution.num_actions // masks
        if distribution.factored:  # a control categorical times a measure categorical, as joint logits
            control = dense(controls, kernel_init=scaled_init(0.01), name="control_logits")(x)
            measure = dense(
                masks,
                kernel_init=scaled_init(0.01),
                bias_init=measure_bias(masks, 1, measure_prior),
                name="measure_logits",
            )(x)
            return _joint(control, measure)
        bias = measure_bias(masks, controls, measure_prior) if distribution.measure else nn.initializers.zeros_init()
        return dense(distribution.num_actions, kernel_init=scaled_init(0.01), bias_init=bias, name="logits")(x)
    mean = dense(distribution.controls, kernel_init=scaled_init(0.01), name="mean")(x)
    log_std = module.param("log_std", nn.initializers.zeros_init(), (distribution.controls,), jnp.float32)
    measure_logit = None
    if distribution.measure:
        measure_logit = dense(
            distribution.readings,
            kernel_init=scaled_init(0.01),
            bias_init=lambda key, shape, dtype=jnp.float32: jnp.full(shape, prior_logit(measure_prior, dtype)),
            name="measure_logit",
        )(x)
        measure_logit = measure_logit if distribution.readings > 1 else measure_logit[..., 0]
    return GaussianOutputs(mean, jnp.broadcast_to(log_std, mean.shape), measure_logit)


class ActorCritic(nn.Module):
    """A policy head for `distribution` (see policies.py) and a state value; separate torsos unless `shared`."""

    distribution: Distribution
    hidden: Sequence[int] = (64, 64)
    activation: str = "tanh"
    shared: bool = False
    measure_prior: Any = 0.5  # the initial policy's probability of measuring (`policy_head`)
    torso: Torso = Torso()

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[Any, jax.Array]:
        actor = self.torso.build(self.hidden, self.activation, name="actor_torso")(obs)
        critic = actor if self.shared else self.torso.build(self.hidden, self.activation, name="critic_torso")(obs)
        policy = policy_head(self, actor, self.distribution, dense=NarrowDense, measure_prior=self.measure_prior)
        value = nn.Dense(1, kernel_init=scaled_init(1.0), name="value")(critic)
        return policy, jnp.squeeze(value, -1)


class DuelingQNetwork(nn.Module):
    """Q(s, a) = V(s) + A(s, a) - mean_a A(s, a) on a torso (an MLP or a CNN; Wang et al. 2016)."""

    num_actions: int
    hidden: Sequence[int] = (64, 64)
    activation: str = "relu"
    dueling: bool = True
    factored_masks: int = 0  # > 0: a factored head over (control, measure mask), this many masks
    torso: Torso = Torso()
    layer_norm: bool = False  # in the torso's Dense layers (PQN)

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = self.torso.build(self.hidden, self.activation, layer_norm=self.layer_norm)(obs)
        return dueling_head(x, self.num_actions, self.dueling, head=NarrowDense, factored_masks=self.factored_masks)


def _joint(control: jax.Array, measure: jax.Array) -> jax.Array:
    """[..., masks * controls] outputs `control[c] + measure[m]` at index `c + controls * m` (the env's action)."""
    joint = measure[..., :, None] + control[..., None, :]
    return joint.reshape(*joint.shape[:-2], -1)


def dueling_head(
    x: jax.Array, num_actions: int, dueling: bool, head: type[nn.Module] = nn.Dense, factored_masks: int = 0
) -> jax.Array:
    """Q-values from features: a dueling value/advantage split, or a plain linear head (`head`: the layer class of
    the per-action outputs, `nn.Dense` or the same parameters as `NarrowDense`).

    With `factored_masks` = M > 0 the head is factored over the active-measure pair: Q(s, c, m) = V(s) + A_c(s, c) +
    A_m(s, m) (each advantage centred when dueling; without it Q_c(s, c) + Q_m(s, m)), an additive action-branching
    decomposition (Tavakoli et al. 2018): the joint argmax is the control's and the measure's argmax taken apart,
    and the rest of the algorithm sees the joint Q-values unchanged."""
    if factored_masks:
        controls = num_actions // factored_masks
        control = head(controls, kernel_init=scaled_init(1.0), name="control_advantage")(x)
        measure = head(factored_masks, kernel_init=scaled_init(1.0), name="measure_advantage")(x)
        if not dueling:
            return _joint(control, measure)
        value = nn.Dense(1, kernel_init=scaled_init(1.0), name="state_value")(x)
        centred = _joint(control - control.mean(-1, keepdims=True), measure - measure.mean(-1, keepdims=True))
        return value + centred
    if not dueling:
        return head(num_actions, kernel_init=scaled_init(1.0), name="q")(x)
    value = nn.Dense(1, kernel_init=scaled_init(1.0), name="state_value")(x)
    advantage = head(num_actions, kernel_init=scaled_init(1.0), name="advantage")(x)
    return value + advantage - advantage.mean(-1, keepdims=True)


# -- recurrent networks ---------------------------------------------------------------------------------------
#
# A recurrent network is called one step at a time: `apply(params, carry, obs, first) -> (carry, outputs)`, with the
# carry reset to zeros where `first` (an episode's first step) before the step. `obs`/`first` may have any leading
# batch axes ([envs] when acting, [time, envs] when bootstrapping every step of a sequence at once). A learner
# re-runs stored time-major sequences [T, batch, ...] with `apply(..., method="unroll")`: the torso and the cell's
# input projection run once for the whole sequence, outside the scan, which keeps only the recurrent matmul and the
# gates (one [batch, size] x [size, gates * size] product per step). Carries are pytrees of arrays
# (checkpointable).

CELLS = ("gru", "lstm")


def check_activation(activation: Any) -> None:
    """ValueError naming `activation` unless it is one of `ACTIVATIONS`."""
    check_choice("activation", activation, tuple(ACTIVATIONS))


def check_core_fields(rnn_size: Any, cell: Any) -> None:
    """ValueError naming `rnn_size` (a positive int) or `cell` (one of `CELLS`) if either is bad."""
    check_positive_int("rnn_size", rnn_size)
    check_choice("cell", cell, CELLS)


def zero_carry(cell: str, size: int, batch_shape: tuple[int, ...]) -> Any:
    """The initial (all-zero) carry of a `cell` with `size` units for a batch: an array (GRU) or (c, h) (LSTM)."""
    zeros = jnp.zeros((*batch_shape, size), jnp.float32)
    return (zeros, zeros) if cell == "lstm" else zeros


def reset_carry(carry: Any, first: jax.Array) -> Any:
    """Zero the carry where `first` (shape = the carry's batch axes)."""
    return jax.tree.map(lambda c: jnp.where(first[..., None], jnp.zeros_like(c), c), carry)


def cell_step(cell: str, recurrent_kernel: jax.Array, carry: Any, inputs: jax.Array) -> tuple[Any, jax.Array]:
    """One GRU / LSTM step from the input projection `inputs` (x W_i + b, gates * size wide) -> (carry, output).

    GRU (the cuDNN form, no recurrent bias): r, z = sigmoid(x W_ir + h W_hr), sigmoid(x W_iz + h W_hz);
    n = tanh(x W_in + r * (h W_hn)); h' = (1 - z) n + z h. LSTM: i, f, g, o from x W_i + h W_h; c' = f c + i g;
    h' = o tanh(c'), carry (c, h)."""
    if cell == "lstm":
        c, h = carry
        i, f, g, o = jnp.split(inputs + h @ recurrent_kernel, 4, -1)
        c = nn.sigmoid(f) * c + nn.sigmoid(i) * jnp.tanh(g)
        h = nn.sigmoid(o) * jnp.tanh(c)
        return (c, h), h
    x_r, x_z, x_n = jnp.split(inputs, 3, -1)
    h_r, h_z, h_n = jnp.split(carry @ recurrent_kernel, 3, -1)
    r, z = nn.sigmoid(x_r + h_r), nn.sigmoid(x_z + h_z)
    h = (1.0 - z) * jnp.tanh(x_n + r * h_n) + z * carry
    return h, h


class RecurrentCore(nn.Module):
    """Torso (an MLP or a CNN) -> one GRU or LSTM step; outputs [torso features, cell output] (a skip connection:
    the heads see the current observation at once, without waiting for the cell's gates to open, and the memory
    beside it).
    The cell's input and recurrent kernels are fused across gates and use `scaled_init` (QR-free, see above)."""

    hidden: Sequence[int] = (64,)
    rnn_size: int = 64
    cell: str = "gru"
    activation: str = "relu"
    body: Torso = Torso()  # builds the submodule named "torso", as saved parameters name it
    layer_norm: bool = False  # in the torso's Dense layers (recurrent PQN)

    def setup(self) -> None:
        gates = (4 if self.cell == "lstm" else 3) * self.rnn_size
        self.torso = self.body.build(self.hidden, self.activation, layer_norm=self.layer_norm)
        self.input_projection = nn.Dense(gates, kernel_init=scaled_init(1.0))
        self.recurrent_kernel = self.param("recurrent_kernel", scaled_init(1.0), (self.rnn_size, gates))

    def __call__(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, jax.Array]:
        x = self.torso(obs)
        carry, y = cell_step(self.cell, self.recurrent_kernel, reset_carry(carry, first), self.input_projection(x))
        return carry, jnp.concatenate([x, y], -1)

    def unroll(self, carry: Any, obs: jax.Array, first: jax.Array, straight: bool = False) -> tuple[Any, jax.Array]:
        """A time-major sequence [T, batch, ...] -> (the carry after every step, the outputs), both [T, batch, ...];
        the carry after step t is where the bootstrap value of step t's (pre-reset) next observation starts.

        `straight`: the steps as straight-line code instead of a loop, for unrolls that are not differentiated
        (burn-ins, target values): about 4x faster per step on XLA's CPU backend, where a loop body's gate
        arithmetic, fused with the read of its step's inputs, compiles to scalar code (docs/recurrent.md); its
        gradient is slower than the loop's, so a differentiated unroll keeps the loop."""
        x = self.torso(obs)
        kernel = self.recurrent_kernel

        def body(carry, inputs):
            projection, first = inputs
            carry, y = cell_step(self.cell, kernel, reset_carry(carry, first), projection)
            return carry, (carry, y)

        _, (carries, y) = jax.lax.scan(body, carry, (self.input_projection(x), first), unroll=straight or 1)
        return carries, jnp.concatenate([x, y], -1)


class DuelingHead(nn.Module):
    """`dueling_head` as a module."""

    num_actions: int
    dueling: bool = True
    factored_masks: int = 0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        return dueling_head(x, self.num_actions, self.dueling, head=NarrowDense, factored_masks=self.factored_masks)


class ActorCriticHeads(nn.Module):
    """A policy head for `distribution` and a state value from shared features."""

    distribution: Distribution
    measure_prior: Any = 0.5

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[Any, jax.Array]:
        policy = policy_head(self, x, self.distribution, dense=NarrowDense, measure_prior=self.measure_prior)
        value = nn.Dense(1, kernel_init=scaled_init(1.0), name="value")(x)
        return policy, jnp.squeeze(value, -1)


class RecurrentQNetwork(nn.Module):
    """DRQN (Hausknecht & Stone 2015) and recurrent PQN: a recurrent core under the dueling (or plain) head; one
    step -> (carry, Q-values); `unroll` -> (carries, Q-values) of a sequence."""

    num_actions: int
    hidden: Sequence[int] = (64,)
    rnn_size: int = 64
    cell: str = "gru"
    activation: str = "relu"
    dueling: bool = True
    factored_masks: int = 0
    torso: Torso = Torso()
    layer_norm: bool = False  # in the torso's Dense layers (recurrent PQN)

    def setup(self) -> None:
        self.core = RecurrentCore(
            self.hidden, self.rnn_size, self.cell, self.activation, self.torso, layer_norm=self.layer_norm
        )
        self.head = DuelingHead(self.num_actions, self.dueling, self.factored_masks)

    def __call__(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, jax.Array]:
        carry, x = self.core(carry, obs, first)
        return carry, self.head(x)

    def unroll(self, carry: Any, obs: jax.Array, first: jax.Array, straight: bool = False) -> tuple[Any, jax.Array]:
        carries, x = self.core.unroll(carry, obs, first, straight)
        return carries, self.head(x)


class RecurrentActorCritic(nn.Module):
    """One recurrent core shared by a policy head for `distribution` and a value head; one step -> (carry,
    (policy, value)); `unroll` -> (carries, (policy, values)) of a sequence."""

    distribution: Distribution
    hidden: Sequence[int] = (64,)
    rnn_size: int = 64
    cell: str = "gru"
    activation: str = "tanh"
    measure_prior: Any = 0.5
    torso: Torso = Torso()

    def setup(self) -> None:
        self.core = RecurrentCore(self.hidden, self.rnn_size, self.cell, self.activation, self.torso)
        self.heads = ActorCriticHeads(self.distribution, self.measure_prior)

    def __call__(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, tuple[jax.Array, jax.Array]]:
        carry, x = self.core(carry, obs, first)
        return carry, self.heads(x)

    def unroll(self, carry: Any, obs: jax.Array, first: jax.Array) -> tuple[Any, tuple[jax.Array, jax.Array]]:
        carries, x = self.core.unroll(carry, obs, first)
        return carries, self.heads(x)
