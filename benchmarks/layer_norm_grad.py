"""LayerNorm's share of PQN's gradient step on CPU, and what a hand-written gradient saves (docs/pqn.md, "On an
AVX-512 EPYC, and where PQN's time goes").

Times the gradient step of PQN's CartPole-v0 network (the 64x64 preset: two Dense layers, each followed by
LayerNorm and relu, then a Dense layer of 4 Q-values; `--hidden 128 128` for PQN's default, its Acrobot-v1 width)
on minibatches of 128 rows for 15 configurations under vmap (one device's share of the grid's 30), as a scanned
loop of `--steps` steps on one CPU device, with:

- flax's `nn.LayerNorm` (what amjax ran before 2026-12-07);
- amjax's `networks.LayerNorm`, with a hand-written gradient (`jax.custom_vjp`: two-pass statistics, and the
  input's gradient from two means, rstd * (g - mean(g) - xhat * mean(g * xhat))); checked here against flax's to
  float rounding;
- no LayerNorm.

It records the compile time and microseconds per step of each: the best of `--repeats` timed runs after a
warm-up. The three are timed in turn inside one child process on purpose, so that a noisy spell on the machine
touches them all; the harness keeps the records (`benchmarks/results/layer_norm_grad_<date>_<machine>.jsonl`, and
the `.md` beside it).

    python benchmarks/layer_norm_grad.py
    python benchmarks/layer_norm_grad.py --hidden 128 128
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from amjax.agents.networks import LayerNorm  # noqa: E402
from benchmarks import harness  # noqa: E402

CONFIGS, ROWS, OBS, ACTIONS = 15, 128, 5, 4  # CartPole-v0 with the flag: 5 inputs, 2 x 2 actions
HIDDEN = (64, 64)  # PQN's CartPole-v0 preset; --hidden sets another

NORMS = {"flax nn.LayerNorm": nn.LayerNorm, "hand-written gradient (amjax)": LayerNorm, "none": None}


class QNetwork(nn.Module):
    norm: type[nn.Module] | None
    hidden: tuple[int, ...] = HIDDEN

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.Dense(width)(x)
            x = nn.relu(self.norm()(x) if self.norm else x)
        return nn.Dense(ACTIONS)(x)


def check_gradients() -> float:
    """The largest difference between amjax's LayerNorm's gradients and flax's, on random inputs."""
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    x = 3 * jax.random.normal(keys[0], (32, HIDDEN[0])) + 1
    scale, bias = jax.random.normal(keys[1], (HIDDEN[0],)), jax.random.normal(keys[2], (HIDDEN[0],))

    def grads(norm):
        def loss(x, scale, bias):
            return jnp.sin(norm().apply({"params": {"scale": scale, "bias": bias}}, x)).sum()

        return jax.grad(loss, argnums=(0, 1, 2))(x, scale, bias)

    return max(float(jnp.abs(a - b).max()) for a, b in zip(grads(nn.LayerNorm), grads(LayerNorm), strict=True))


def compile_steps(
    norm: type[nn.Module] | None, steps: int, hidden: tuple[int, ...] = HIDDEN
) -> tuple[float, Callable[[], Any]]:
    """(compile seconds, a call that runs `steps` gradient steps to the end)."""
    network = QNetwork(norm, tuple(hidden))
    keys = jax.random.split(jax.random.PRNGKey(1), CONFIGS)
    obs = jax.random.normal(jax.random.PRNGKey(2), (CONFIGS, ROWS, OBS))
    params = jax.vmap(network.init)(keys, obs)
    grad = jax.vmap(jax.grad(lambda p, o: 0.5 * jnp.square(network.apply(p, o)).mean()))

    def run(params, obs):
        def step(params, _):
            return jax.tree.map(lambda p, g: p - 1e-3 * g, params, grad(params, obs)), None

        return jax.lax.scan(step, params, None, steps)[0]

    start = time.perf_counter()
    compiled = jax.jit(run).lower(params, obs).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(params, obs))  # warm-up
    return compile_s, lambda: jax.block_until_ready(compiled(params, obs))


def run_case(steps: int, repeats: int, hidden: tuple[int, ...] = HIDDEN) -> dict[str, Any]:
    """In the child: the gradients checked, then every variant compiled and timed in turn."""
    difference = check_gradients()
    if difference > 1e-4:
        raise SystemExit(f"amjax's LayerNorm's gradients differ from flax's by {difference:.2e}")
    programs = {name: compile_steps(norm, steps, hidden) for name, norm in NORMS.items()}
    best = dict.fromkeys(NORMS, np.inf)
    for _ in range(repeats):  # the variants in turn, so a noisy spell on the machine touches them all
        for name, (_, run) in programs.items():
            start = time.perf_counter()
            run()
            best[name] = min(best[name], time.perf_counter() - start)
    variants = [
        {"layer_norm": name, "compile_s": round(compile_s, 2), "step_us": round(1e6 * best[name] / steps, 1)}
        for name, (compile_s, _) in programs.items()
    ]
    return {"gradient_difference": difference, "variants": variants}


def render(runs: list[dict[str, Any]]) -> str:
    """One table per run: each variant's compile time, microseconds per gradient step and its cost over none."""
    parts = []
    for run in runs:
        settings = run["settings"]
        for case in run["cases"]:
            if case["status"] != "ok":
                parts.append(f"{case['status']}\n")
                continue
            none = next(v["step_us"] for v in case["variants"] if v["layer_norm"] == "none")
            parts.append(
                f"# LayerNorm in PQN's gradient step on CPU ({run['date'][:10]})\n\n"
                f"{CONFIGS} configurations x {ROWS} rows under vmap, hidden {tuple(settings.get('hidden', HIDDEN))}, "
                "one CPU device, "
                f"{settings['steps']:,} steps per timed run, the best of {settings['repeats']} runs taken in turn; "
                f"the hand-written gradients agree with flax's to {case['gradient_difference']:.1e}. "
                f"{harness.describe(run)}\n\n"
                + harness.markdown_table(
                    case["variants"],
                    [
                        ("LayerNorm", lambda v: v["layer_norm"]),
                        ("compile (s)", lambda v: v["compile_s"]),
                        ("us per gradient step", lambda v: v["step_us"]),
                        ("over none (us)", lambda v, none=none: round(v["step_us"] - none, 1)),
                    ],
                )
            )
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=1000, help="gradient steps per timed run")
    parser.add_argument(
        "--repeats", type=int, default=10, help="timed runs per variant, taken in turn (the best is reported)"
    )
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/layer_norm_grad_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    parser.add_argument(
        "--hidden",
        type=int,
        nargs="+",
        default=list(HIDDEN),
        help="the hidden layers' widths (default: 64 64, PQN's CartPole-v0 preset; 128 128 is PQN's default)",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    for name, value in (("--steps", args.steps), ("--repeats", args.repeats), *(("--hidden", h) for h in args.hidden)):
        if value < 1:
            parser.error(f"{name}: got {value}; allowed values: integers >= 1")
    if args.child:
        harness.child_result(run_case(**json.loads(args.child)))
        return 0
    case = {"steps": args.steps, "repeats": args.repeats, "hidden": list(args.hidden)}
    harness.run_cases("layer_norm_grad", harness.settings_of(args), args.out, __file__, [case], render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
