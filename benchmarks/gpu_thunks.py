"""What a GPU would run, read without one: amjax's sweep chunk program and the plain reference compiled for an NVIDIA
GPU on this machine (XLA's deviceless compilation), and XLA's thunk sequence (the kernels, copies, loops and
conditionals the GPU runtime launches) summarised per loop iteration and per branch, each loop with its trip count
where XLA knows it, and which loops and conditionals a command buffer holds. Outside a command buffer a loop of
unknown count and a conditional each make the host wait for the device (it copies the predicate or branch index
back before it launches more): a loop once per run of its condition, a conditional once. Inside one (a CUDA graph's
conditional node, CUDA 12.3 or later) the device decides.

    pip install "jax-cuda13-plugin==$(python -c 'import jax; print(jax.__version__)')" \\
        "jax-cuda13-pjrt==$(python -c 'import jax; print(jax.__version__)')"   # the compiler (~130 MB), no GPU needed
    python benchmarks/gpu_thunks.py --agent dqn --configs 4096 --steps 2500
    python benchmarks/gpu_thunks.py --agent dqn --variant conditional-updates    # a layout of gpu_profile.VARIANTS

No CUDA libraries are needed (the plugin's version check, which looks for cuDNN, is skipped: JAX_SKIP_CUDA_
CONSTRAINTS_CHECK). The target is `gpu_specs/h100_sxm.txtpb`, a few fields of XLA's H100 SXM description
(`xla/backends/gpu/target_config/specs/h100_sxm.txtpb` in openxla/xla). Without the device there is no autotuning,
so a matrix product's kernels may differ from a real run's; loops, branches and copies come from the same passes.
It counts launches, not time: `gpu_profile.py` on a GPU times them.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.*`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SPEC = Path(__file__).with_name("gpu_specs") / "h100_sxm.txtpb"

_THUNK = re.compile(r"^(\s*)(\d+): (k\w+)")
_MARKER = re.compile(r"^(\s*)(?:No thunks\.\s*)?(condition|body|true_branch|false_branch|branch_\d+):\s*$")


@dataclass
class Thunk:
    """One entry of XLA's thunk sequence; a loop's or conditional's children are its parts (condition, body,
    branches), a command buffer's its commands."""

    kind: str
    children: list[Thunk] = field(default_factory=list)
    id: int | None = None  # its thunk_id (`thunk_metadata.txt` names the HLO instruction)


def parse_thunks(text: str) -> list[Thunk]:
    """The thunk tree of a `*thunk_sequence_after_thunk_passes.txt` dump (nesting by indentation; a loop's
    "condition:" is printed unindented, and an empty condition's "No thunks." shares a line with "body:")."""
    root = Thunk("root")
    stack: list[tuple[int, Thunk]] = [(-1, root)]
    loop_indent = 0
    for line in text.splitlines():
        match = _THUNK.match(line) or _MARKER.match(line)
        if not match:
            continue
        indent, kind = len(match.group(1)), match.group(match.lastindex)
        if kind == "kWhile":
            loop_indent = indent
        if match.re is _MARKER and (kind == "condition" or "No thunks" in line):
            indent = loop_indent + 2
        node = Thunk(kind, id=int(match.group(2)) if match.re is _THUNK else None)
        while stack[-1][0] >= indent:
            stack.pop()
        stack[-1][1].children.append(node)
        stack.append((indent, node))
    return root.children


def launches(thunks: list[Thunk]) -> tuple[int, int]:
    """(kernels, copies) one run of `thunks` launches, its loops and conditionals left out (`report` lists them)."""
    kernels = copies = 0
    for thunk in thunks:
        if thunk.kind == "kCopy":
            copies += 1
        elif thunk.kind == "kCommandBuffer" or (thunk.kind == "kDynamicSliceFusion" and thunk.children):
            k, c = launches(thunk.children)
            kernels, copies = kernels + k, copies + c
        elif thunk.kind not in ("kWhile", "kConditional"):
            kernels += 1
    return kernels, copies


def trip_counts(hlo: str, metadata: str) -> dict[int, int | None]:
    """{thunk_id: iterations} of each loop: XLA's `known_trip_count` of its `while` instruction in the optimised HLO
    (`*_gpu_after_optimizations.txt`), None where XLA does not know it. A loop of known count runs its body that many
    times; any other loop outside a command buffer copies its predicate to the host and waits for it after every
    run of its condition."""
    counts = {}
    for line in hlo.splitlines():
        if (name := re.match(r"\s*(?:ROOT )?%(\S+) = .* while\(", line)) is not None:
            known = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
            counts[name.group(1)] = int(known.group(1)) if known else None
    return {
        int(match.group(2)): counts[match.group(1)]
        for match in re.finditer(r'profile_annotation: "([^"]+)"\s*thunk_id: (\d+)', metadata)
        if match.group(1) in counts
    }


def report(
    thunks: list[Thunk], depth: int = 0, trips: dict[int, int | None] | None = None, on_device: bool = False
) -> list[str]:
    """Markdown list lines: each loop's kernels and copies per iteration (its trip count where `trips` has it) and
    each conditional's per branch; a loop or conditional inside a command buffer (a CUDA graph's conditional node:
    `on_device`, for what it holds too) is decided on the device, without the host."""
    lines, pad, trips = [], "  " * depth, trips or {}
    for thunk in thunks:
        parts = {part.kind: part.children for part in thunk.children}
        if thunk.kind == "kWhile":
            kernels, copies = launches(parts.get("body", []))
            count = trips.get(thunk.id)
            if on_device:
                when = (
                    f" ({count} iterations, in a command buffer: on the device)"
                    if count is not None
                    else " (in a command buffer: on the device)"
                )
            elif thunk.id not in trips:
                when = ""
            elif count is None:
                when = " (count unknown: a host read per condition)"
            else:
                when = f" ({count} iterations)"
            lines.append(f"{pad}- loop{when}: {kernels} kernels + {copies} copies per iteration")
            lines += report(parts.get("body", []), depth + 1, trips, on_device)
        elif thunk.kind == "kConditional":
            branches = [
                f"{name}: {k} kernels + {c} copies" for name, (k, c) in ((n, launches(t)) for n, t in parts.items())
            ]
            where = "in a command buffer: on the device" if on_device else "the host reads its branch"
            lines.append(f"{pad}- conditional ({where}): " + "; ".join(branches))
            for body in parts.values():
                lines += report(body, depth + 1, trips, on_device)
        elif thunk.kind == "kCommandBuffer":
            lines += report(thunk.children, depth, trips, on_device=True)
    return lines


def gpu_device(spec: Path = SPEC) -> Any:
    """A device of a one-GPU CUDA topology described by `spec`, to compile for (no GPU needed)."""
    from jax.experimental import topologies

    try:
        topology = topologies.get_topology_desc("gpu", "cuda", target_config=spec.read_text(), topology="1x1x1")
    except Exception as error:
        raise SystemExit(
            f"benchmarks/gpu_thunks.py: no CUDA compiler ({error}); install jax-cuda13-plugin and jax-cuda13-pjrt "
            "at this jax's version (the module docstring shows how)"
        ) from error
    return topology.devices[0]


def compile_programs(case: dict[str, Any], device: Any, variant: str | None) -> None:
    """amjax's chunk program (`variant` patched in) and the reference for `case`, compiled for `device`; XLA dumps
    their thunk sequences."""
    import jax

    from amjax.agents import ALGORITHMS
    from amjax.sweep.batches import _compiled_programs, chunk_evals, compiled_programs
    from amjax.sweep.devices import config_sharding
    from benchmarks import gpu_profile
    from benchmarks.throughput.runners import case_batch, reference_program

    configs, stacked, keys = case_batch(case)
    sharding = config_sharding([device])

    def placed(tree: Any) -> Any:
        return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), tree)

    options = gpu_profile.compiler_options(variant)  # a compiler variant compiles both programs so
    with gpu_profile.variant(variant):
        init, chunk = compiled_programs(
            ALGORITHMS[case["agent"]], chunk_evals(configs[0].num_evals, case["target_chunks"]), (device,), "gpu"
        )
        chunk.lower(placed(stacked), placed(jax.eval_shape(init, stacked, keys))).compile(options)
        _compiled_programs.cache_clear()
    train, *args = reference_program(case)
    single = jax.sharding.SingleDeviceSharding(device)
    specs = [jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=single) for a in args]
    train.trace(*specs).lower(lowering_platforms=("cuda",)).compile(options)


def main(argv: list[str] | None = None) -> int:
    from benchmarks import gpu_profile

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agent", choices=("ppo", "dqn"), default="dqn")
    parser.add_argument("--configs", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=2500)
    parser.add_argument(
        "--variant",
        choices=sorted([*gpu_profile.VARIANTS, *gpu_profile.COMPILER_VARIANTS]),
        help="amjax with this change patched in, or both programs compiled with these XLA options",
    )
    parser.add_argument("--spec", type=Path, default=SPEC, help="the GPU's XLA target description (text proto)")
    args = parser.parse_args(argv)

    dump = Path(tempfile.mkdtemp(prefix="amjax_gpu_thunks_"))
    # Before JAX starts: the plugin's version check wants cuDNN, which compiling does not; XLA dumps every program.
    os.environ.setdefault("JAX_SKIP_CUDA_CONSTRAINTS_CHECK", "1")
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump}".strip()
    case = gpu_profile.sweep_case(args.agent, args.configs, args.steps)
    compile_programs(case, gpu_device(args.spec), args.variant)
    amjax = "amjax" + (f"+{args.variant}" if args.variant else "")
    reference = "reference" + (f"+{args.variant}" if args.variant in gpu_profile.COMPILER_VARIANTS else "")
    print(f"# {args.agent} {args.configs} x {case['steps']}: launches on {args.spec.stem}, compiled without a GPU\n")
    for name, module in ((amjax, "jit_chunk_batch"), (reference, "jit_train")):
        text = next(dump.glob(f"*.{module}.thunk_sequence_after_thunk_passes.txt")).read_text()
        hlo = next(dump.glob(f"*.{module}.*gpu_after_optimizations.txt")).read_text()
        trips = trip_counts(hlo, next(dump.glob(f"*.{module}.thunk_metadata.txt")).read_text())
        thunks = parse_thunks(text)
        kernels, copies = launches(thunks)
        print(f"## {name}\n\n- program: {kernels} kernels + {copies} copies outside its loops")
        print("\n".join(report(thunks, trips=trips)) + "\n")
    print(f"XLA's dumps: {dump}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
