"""Where a sweep's time goes on an accelerator: amjax's sweep programs and the plain reference compiled in one
process, timed in alternation, then each profiled for one run; device time is summed per HLO op and per source line.

    python benchmarks/gpu_profile.py --agent ppo --configs 1024 --steps 51200  # benchmarks/results/, .jsonl and .md
    python benchmarks/gpu_profile.py --agent dqn --configs 4 --steps 2500 --rounds 1 --out /tmp/p.jsonl  # a smoke run
    python benchmarks/gpu_profile.py --agent dqn --configs 4096 --steps 2500 --variants pass-through  # a comparison

Both implementations are compiled and timed in this one process on purpose (the same device state, rounds
alternating, so that a slower or busier device moves both), so this script runs no child processes: it uses
`benchmarks.harness` for its records and markdown only. Each run appends to `--out` (default:
benchmarks/results/gpu_profile_<date>_<machine>.jsonl) a "run" line naming the machine and one "case" line per
implementation (the timed rounds, env-steps/s, kernel count, device busy time, and the ops, source lines and
kernels that take the most device time), and renders the markdown beside it. On a CPU it runs too (the figures are
then the CPU's thunks), which is how the script is checked before a GPU session.

`--variants` adds amjax's programs compiled with a change patched in (`VARIANTS`), timed and profiled beside the
others as "amjax+NAME": an experiment on the device before the library changes. A compiler variant
(`COMPILER_VARIANTS`: XLA options, no change to the code) compiles both implementations with its options, as
"amjax+NAME" and "reference+NAME", so that its gain for amjax can be told from its gain for any program. A variant
whose compile fails (an option this XLA or device does not take) is reported and left out; the rest still run.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

from benchmarks import harness  # noqa: E402
from benchmarks.profiles import profile_call, top_table  # noqa: E402
from benchmarks.throughput import runners  # noqa: E402
from benchmarks.throughput.cases import _default_buffer, _round_steps, _steps_per_update  # noqa: E402
from benchmarks.throughput.timing import interleaved  # noqa: E402


def _batched_counters() -> list[tuple[Any, str, Any]]:
    """The sweep programs' step counters batched like every other leaf of the state (before
    `batching.shared_field`): the learning step and the target update branch on batched predicates, a conditional
    on "every member" and a loop for disagreeing members each (`batching.update_where`), the conditional as it was
    then (`_conditional_updates`)."""
    from amjax.sweep import batches

    return _conditional_updates() + [
        (batches, "member_axes", lambda tree: jax.tree.map(lambda _: 0, tree)),
        (batches, "take_shared", lambda t: t),
    ]


def _pass_through() -> list[tuple[Any, str, Any]]:
    """Dueling DQN's and DRQN's learning step and target update as before `batching.update_where`, on batched step
    counters (`_batched_counters`)."""
    import jax.numpy as jnp
    import optax

    from amjax import strategy
    from amjax.agents import dqn, drqn
    from amjax.batching import uniform_cond

    def learn_or_wait(learning, learn, *operands):
        return uniform_cond(
            learning, learn, lambda params, opt_state, *_: (params, opt_state, jnp.float32(0)), *operands
        )

    def update_target(config, sync, params, target_params):
        if strategy.is_gpu():
            new = optax.incremental_update(params, target_params, config.tau)
            return jax.tree.map(lambda a, b: jnp.where(sync, a, b), new, target_params)
        return uniform_cond(
            sync,
            lambda tau, params, target: optax.incremental_update(params, target, tau),
            lambda tau, params, target: target,
            config.tau,
            params,
            target_params,
        )

    return _batched_counters() + [
        (module, name, value)
        for module in (dqn, drqn)
        for name, value in (("learn_or_wait", learn_or_wait), ("update_target", update_target))
    ]


def _conditional_updates() -> list[tuple[Any, str, Any]]:
    """`batching.update_where` with a shared predicate as one conditional under the GPU strategy too, as before
    its loop of at most one iteration (whose state XLA's GPU compiler does not copy)."""
    from amjax import batching

    def conditional(pred, update, state, *args):
        return jax.lax.cond(pred, update, lambda state, *_: state, state, *args)

    return [(batching, "_update_once", conditional)]


# name -> (what it changes, the (module, attribute, value) patches that make it)
VARIANTS = {
    "conditional-updates": (
        "the Q-learners' learning step, target update and DRQN's target refresh as conditionals (copying the "
        "parameters, Adam's moments and the target network at every update on a GPU) instead of loops of at most "
        "one iteration: the layout before `batching._update_once`",
        _conditional_updates,
    ),
    "batched-counters": (
        "the step counters batched (before `batching.shared_field`): `update_where`'s two host round trips "
        "(every member? any disagreeing?) at the learning step and at the target update instead of one plain "
        "conditional each",
        _batched_counters,
    ),
    "pass-through": (
        "the Q-learners' learning step as a `uniform_cond` whose waiting branch passes the parameters and optimiser "
        "state through (copied back into the loop's state at every update) and the target update as a select under "
        "the GPU strategy, on batched step counters: the layout before `update_where`",
        _pass_through,
    ),
}


# XLA's kinds of GPU command buffer by default (`xla_gpu_enable_command_buffer` in XLA's debug_options_flags.cc, 2026),
# then with conditionals and loops too: a conditional inside a command buffer (a CUDA graph's conditional node) runs
# on the device, without reading its predicate back to the host. jaxlib 0.10.2 records conditionals by default
# already, loops not (read with gpu_thunks.py): the variant's gain is amjax's loops (`batching._update_once`).
DEFAULT_COMMAND_BUFFER = "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,DYNAMIC_SLICE_FUSION"

# name -> (what it changes, XLA compiler options), compiled into amjax's programs and the reference's alike
COMPILER_VARIANTS = {
    "command-buffers": (
        "XLA's GPU command buffers also holding conditionals and loops (`xla_gpu_enable_command_buffer`: the default "
        "kinds plus CONDITIONAL and WHILE): a Q-learner's branches and the update loop without host round trips",
        {"xla_gpu_enable_command_buffer": DEFAULT_COMMAND_BUFFER + ",CONDITIONAL,WHILE"},
    ),
}


@contextlib.contextmanager
def variant(name: str | None) -> Iterator[None]:
    """`VARIANTS[name]` patched in while amjax's programs are traced (nothing for None or a compiler variant)."""
    patches = VARIANTS[name][1]() if name in VARIANTS else []
    saved = [(module, attr, getattr(module, attr)) for module, attr, _ in patches]
    for module, attr, value in patches:
        setattr(module, attr, value)
    try:
        yield
    finally:
        for module, attr, value in saved:
            setattr(module, attr, value)


def build(case: dict[str, Any], variants: Sequence[str] = ()) -> tuple[dict[str, Any], dict[str, str]]:
    """impl -> (run, optimised HLO texts) for amjax (and each of `variants`) and the reference (and each compiler
    variant's), compiled as the throughput benchmark does; and impl -> error for the variants that did not compile."""
    from amjax.sweep.batches import _compiled_programs

    def amjax(name: str | None) -> tuple[Any, list[str]]:
        try:
            with variant(name):
                programs = runners._compile_amjax({**case, "impl": "amjax"}, compiler_options(name))
        finally:
            _compiled_programs.cache_clear()  # the next variant traces afresh
            jax.clear_caches()
        return runners.sweep_run(programs), [programs.chunk.as_text(), programs.init.as_text()]

    def reference(name: str | None) -> tuple[Any, list[str]]:
        compiled, run, _ = runners.compile_reference(case, compiler_options(name))
        return run, [compiled.as_text()]

    built, failed = {}, {}
    jobs = [("amjax", amjax, name) for name in [None, *variants]]
    jobs += [("reference", reference, name) for name in [None, *(v for v in variants if v in COMPILER_VARIANTS)]]
    for implementation, compile_, name in jobs:
        impl = implementation if name is None else f"{implementation}+{name}"
        try:
            built[impl] = compile_(name)
        except Exception as error:  # a variant's options this XLA or device does not take: the rest still run
            if name is None:
                raise
            failed[impl] = f"{type(error).__name__}: {error}"
    return built, failed


def sweep_case(agent: str, configs: int, steps: int) -> dict[str, Any]:
    """The throughput benchmark's case of `configs` configurations of `agent` (costs spread over the grid's), its
    steps rounded to whole updates of its evaluation periods."""
    case = {
        "agent": agent,
        "configs": configs,
        "vanilla": False,
        "evals": 5,
        "eval_episodes": 10,
        "reference_eval": True,
        "target_chunks": 10,
        "sb3_threads": 1,
        "repeats": 1,
        "cores": None,
    }
    case["steps"] = _round_steps(steps, case["evals"] * _steps_per_update(agent))
    if agent == "dqn":
        case["buffer"] = _default_buffer(case["steps"], _steps_per_update("dqn"))
    return case


def compiler_options(name: str | None) -> dict[str, Any] | None:
    """The XLA options of compiler variant `name` (None for the plain programs and code variants)."""
    return COMPILER_VARIANTS[name][1] if name in COMPILER_VARIANTS else None


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: per run, the two implementations' timings side by side (speed as the
    reference's best time over each one's), then, for a profiled run, the source lines, HLO ops and kernels that take
    the most device time in each."""
    parts = []
    for run in runs:
        settings, machine = run["settings"], run["machine"]
        case, results = settings["case"], [r for r in run["cases"] if r["status"] == "ok"]
        base = next((r for r in results if r["impl"] == "reference"), None)

        def ratio(r: dict[str, Any], base: dict[str, Any] | None = base) -> str:
            return f"{base['best_s'] / r['best_s']:.2f}x" if base else ""

        text = (
            f"# {case['agent']} {case['configs']} x {case['steps']} on {machine['device']} ({machine['backend']})\n\n"
            "amjax's sweep programs and the plain reference compiled in one process and timed in alternation, "
            f"{settings['rounds']} round(s) after an untimed run of each, the best kept"
            + (
                "; then each profiled for one run (device time per source line, HLO op and kernel)"
                if settings["profile"]
                else ""
            )
            + f". {harness.describe(run)}\n\n"
            + harness.markdown_table(
                results,
                [
                    ("implementation", lambda r: r["impl"]),
                    ("best (s)", lambda r: f"{r['best_s']:.3f}"),
                    ("rounds (s)", lambda r: ", ".join(f"{w:.3f}" for w in r["rounds_s"])),
                    ("M env-steps/s", lambda r: f"{r['env_steps_per_s'] / 1e6:.2f}"),
                    ("vs reference", ratio),
                    ("kernels", lambda r: r.get("kernels")),
                    ("device busy (ms)", lambda r: f"{r['busy_ms']:.0f}" if "busy_ms" in r else ""),
                    ("span (ms)", lambda r: f"{r['span_ms']:.0f}" if "span_ms" in r else ""),
                ],
            )
        )
        for r in results if settings["profile"] else []:
            text += f"\n## {r['impl']}: where the device time goes\n\n" + "\n".join(
                top_table(r.get(key, []), title)
                for title, key in (
                    ("source (op)", "top_sources"),
                    ("HLO op", "top_ops"),
                    ("kernel in op: source", "top_kernels"),
                )
            )
        parts.append(text + "".join(f"\n{r['impl']}: {r['status']}\n" for r in run["cases"] if r["status"] != "ok"))
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agent", choices=("ppo", "dqn"), default="ppo")
    parser.add_argument("--configs", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=51_200)
    parser.add_argument("--rounds", type=int, default=3, help="timed runs of each implementation, alternating")
    parser.add_argument("--top", type=int, default=25, help="ops and source lines listed per implementation")
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/gpu_profile_<date>_<machine>.jsonl; the "
        "markdown is written beside it)",
    )
    parser.add_argument("--no-profile", dest="profile", action="store_false", help="time only, no trace")
    parser.add_argument(
        "--variants",
        type=lambda text: [v for v in text.split(",") if v],
        default=[],
        help="comma-separated amjax variants to time beside it: "
        + "; ".join(f"{k}: {v[0]}" for k, v in {**VARIANTS, **COMPILER_VARIANTS}.items()),
    )
    args = parser.parse_args(argv)
    known = [*VARIANTS, *COMPILER_VARIANTS]
    unknown = sorted(set(args.variants) - set(known))
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; choose from {', '.join(known)}")

    case = sweep_case(args.agent, args.configs, args.steps)
    # Before this process starts JAX: the recorder asks a child process for the device, which it must not find held.
    recorder = harness.Recorder("gpu_profile", {**vars(args), "case": case}, args.out)
    device = jax.devices()[0]
    print(f"{device.device_kind} ({jax.default_backend()}), {args.agent} {args.configs} x {case['steps']}", flush=True)

    start = time.perf_counter()
    built, failed = build(case, args.variants)
    print(f"compiled {', '.join(built)} in {time.perf_counter() - start:.1f} s", flush=True)
    for impl in [impl for impl in built if "+" in impl]:  # a variant that compiled may still fail on the device
        try:
            built[impl][0]()
        except Exception as error:
            failed[impl] = f"{type(error).__name__}: {error}"
            del built[impl]
    for impl, error in failed.items():
        print(f"{impl}: left out: {error}", file=sys.stderr, flush=True)
    walls = interleaved({impl: run for impl, (run, _) in built.items()}, args.rounds)
    env_steps = case["configs"] * case["steps"]
    for impl, rounds in walls.items():  # printed before profiling, which may outlast a time limit
        print(f"{impl}: best {min(rounds):.3f} s, {env_steps / min(rounds) / 1e6:.2f} M env-steps/s", flush=True)
    for impl, (run, texts) in built.items():
        record: dict[str, Any] = {
            "impl": impl,
            "agent": args.agent,
            "configs": args.configs,
            "steps": case["steps"],
            "status": "ok",
            "rounds_s": walls[impl],
            "best_s": min(walls[impl]),
            "env_steps_per_s": env_steps / min(walls[impl]),
        }
        if args.profile:
            record.update(profile_call(run, texts, args.top))
        recorder.case(record)
    for impl, error in failed.items():
        recorder.case(
            {"impl": impl, "agent": args.agent, "configs": args.configs, "steps": case["steps"], "status": error[:500]}
        )
    recorder.end()
    markdown = harness.write_markdown(recorder.path, render)
    print(render([done for done in harness.read_runs(recorder.path) if done["run"] == recorder.run]))
    print(f"written to {recorder.path} and {markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
