"""The benchmark's measurement helpers (benchmarks/throughput/): timing order and overhead arithmetic.

The benchmark itself is a script, not a test; these check that what it reports is computed as it says.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import types
from pathlib import Path

import pytest

_ROOT = str(Path(__file__).resolve().parents[1])  # the benchmarks are not installed: import them from the checkout
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

from benchmarks.throughput import cases, report, timing  # noqa: E402


def test_interleaved_alternates_and_warms_up(monkeypatch):
    calls = []
    clock = itertools.count()
    monkeypatch.setattr(timing.time, "perf_counter", lambda: float(next(clock)))
    runs = {False: lambda: calls.append("active"), True: lambda: calls.append("vanilla")}
    times = timing.interleaved(runs, rounds=3)
    # One untimed run of each, then a b | b a | a b.
    assert calls == ["active", "vanilla", "active", "vanilla", "vanilla", "active", "active", "vanilla"]
    assert len(times[False]) == len(times[True]) == 3


def test_overhead_figures():
    active, vanilla = [1.10, 1.30, 1.05], [1.00, 1.20, 1.00]
    fig = timing.overhead_figures(active, vanilla)
    assert fig["min"] == pytest.approx(1.05 / 1.00 - 1)
    assert fig["median"] == pytest.approx(1.10 / 1.00 - 1)
    assert fig["rounds"] == pytest.approx([0.10, 1.30 / 1.20 - 1, 0.05])


def test_overhead_cases_are_training_only():
    args = argparse.Namespace(
        quick=False,
        steps=None,
        evals=5,
        eval_episodes=10,
        no_reference_eval=False,
        target_chunks=10,
        sb3_threads=1,
        repeats=2,
        cores=None,
        agents=["ppo", "dqn"],
        sizes=[],
        impls=[],
        sb3=False,
        overhead=[256],
        overhead_rounds=6,
        buffer=None,
        buffer_scan=[],
    )
    built = cases.build_cases(args)
    expected = [("overhead", "ppo", 256), ("overhead", "dqn", 256)]
    assert [(c["impl"], c["agent"], c["configs"]) for c in built] == expected
    for case in built:
        assert (case["evals"], case["eval_episodes"], case["repeats"]) == (1, 1, 6)
        config = cases.agent_config(case, 0.1).validate()
        assert config.num_evals == 1 and config.total_timesteps == case["steps"]


def test_table_without_rows():
    # An overhead-only run (`--impls '' --overhead 256`) has no table rows: the header still prints.
    lines = report.table([{"impl": "overhead"}]).splitlines()
    assert len(lines) == 2 and lines[0].split()[1] == "implementation"


def test_profile_names_the_source_line_behind_each_kernel():
    """benchmarks/profiles.py (gpu_profile.py's and pqn_speed.py --profile's): a profiled program's device (here:
    CPU) time is attributed to the line that built each op, through the optimised HLO's stack-frame tables."""
    import jax
    import jax.numpy as jnp

    from benchmarks import profiles

    def program(x):
        return jnp.tanh(x) @ x  # the line the profile must name

    x = jnp.ones((128, 128))
    # Not from the suite's compile cache: its key leaves out source lines, so an entry compiled before an edit above
    # this test would name the old line.
    cached = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        compiled = jax.jit(program).lower(x).compile()
    finally:
        jax.config.update("jax_enable_compilation_cache", cached)
    compiled(x).block_until_ready()
    summary = profiles.profile_call(lambda: compiled(x).block_until_ready(), [compiled.as_text()], top=5)
    line = program.__code__.co_firstlineno + 1
    assert summary["kernels"] >= 2 and summary["busy_ms"] > 0
    named = [row["name"] for row in summary["top_sources"]]
    assert any(f"test_benchmark_helpers.py:{line} " in name for name in named), named
    assert "| source (op) |" in profiles.top_table(summary["top_sources"], "source (op)")


def test_profile_on_a_cpu_leaves_loops_and_branches_out():
    """On a CPU a loop's or branch's thunk spans its body's kernels, which are counted themselves: the summary keeps
    the body's kernels only, so no time is counted twice."""
    import jax
    import jax.numpy as jnp

    from benchmarks import profiles

    def program(x):
        body = lambda _, x: jax.lax.cond(x.sum() > 0, jnp.tanh, jnp.sin, x @ x)  # noqa: E731
        return jax.lax.fori_loop(0, 20, body, x)

    x = jnp.full((64, 64), 0.01)
    compiled = jax.jit(program).lower(x).compile()
    compiled(x).block_until_ready()
    summary = profiles.profile_call(lambda: compiled(x).block_until_ready(), [compiled.as_text()], top=50)
    names = [row["name"] for row in summary["top_ops"]]
    assert names and not [n for n in names if profiles._CONTROL_FLOW.match(n)], names
    assert summary["kernels"] >= 20  # the body's matrix product, once per iteration


def test_gpu_profile_variants_change_the_program_they_name():
    """benchmarks/gpu_profile.py --variants, on the sweep's chunk program under the GPU strategy (StableHLO loops
    include scans): `conditional-updates` makes the learning step and the target update conditionals again instead
    of loops of at most one iteration; `batched-counters` (on top of that) batches the step counters, so each also
    adds a loop for disagreeing members (the learning one holds the gradient steps' scan a second time);
    `pass-through` goes back to a learning step whose waiting branch passes the state through (one three-way
    conditional, whose "some members" branch holds that scan again) and a target update that selects (no
    conditional). The patches are gone after the block."""
    import jax
    import jax.numpy as jnp

    from amjax import batching
    from amjax.agents import DQN, DQNConfig, dqn, stack_configs
    from amjax.sweep import batches
    from benchmarks import gpu_profile

    configs = [DQNConfig(cost=c, num_envs=2, buffer_size=64, learning_starts=8).validate() for c in (0.1, 0.2)]
    stacked = stack_configs(configs)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)])
    devices = tuple(jax.devices()[:1])

    def control_flow(name: str | None) -> tuple[int, int]:
        with gpu_profile.variant(name):
            init, chunk = batches.compiled_programs(DQN, 1, devices, "gpu")
            text = chunk.lower(stacked, init(stacked, keys)).as_text()
            batches._compiled_programs.cache_clear()  # the next variant traces afresh
        return text.count("stablehlo.case") + text.count("stablehlo.if"), text.count("stablehlo.while")

    originals = (dqn.update_target, batches.member_axes, batches.take_shared, batching._update_once)
    conds, loops = control_flow(None)
    counted = {name: control_flow(name) for name in ("conditional-updates", "batched-counters", "pass-through")}
    differences = {name: (c - conds, n - loops) for name, (c, n) in counted.items()}
    assert differences == {
        "conditional-updates": (2, -2),
        "batched-counters": (2, 1),
        "pass-through": (1, -1),
    }, (conds, loops, counted)
    assert (dqn.update_target, batches.member_axes, batches.take_shared, batching._update_once) == originals


def test_gpu_profile_compiler_variants_compile_both_implementations(monkeypatch):
    """benchmarks/gpu_profile.py's compiler variants: XLA options this jaxlib takes (a misspelt kind of command buffer
    would fail every GPU compile), passed to amjax's programs and the reference's alike; a variant whose compile fails
    is left out and named, the rest still built."""
    import jax
    import jax.numpy as jnp

    from benchmarks import gpu_profile
    from benchmarks.throughput import runners

    options = gpu_profile.COMPILER_VARIANTS["command-buffers"][1]
    program = jax.jit(lambda x: jax.lax.cond(x.sum() > 0, jnp.tanh, jnp.sin, x))
    assert program.lower(jnp.ones(3)).compile(options)(jnp.ones(3)).tolist() == jnp.tanh(jnp.ones(3)).tolist()
    with pytest.raises(Exception, match="not a valid enum value"):
        program.lower(jnp.ones(3)).compile({"xla_gpu_enable_command_buffer": "FUSION,BOGUS"})

    broken = {"xla_gpu_enable_command_buffer": "BOGUS"}
    monkeypatch.setitem(gpu_profile.COMPILER_VARIANTS, "broken", ("an option XLA refuses", broken))
    compiled = []

    def compile_program(impl):
        def compile_(case, compiler_options=None):
            if compiler_options == broken:
                raise RuntimeError("not a valid enum value")
            compiled.append((impl, compiler_options))
            text = types.SimpleNamespace(as_text=lambda: impl)
            return types.SimpleNamespace(chunk=text, init=text) if impl == "amjax" else (text, lambda: None, 0.0)

        return compile_

    monkeypatch.setattr(runners, "_compile_amjax", compile_program("amjax"))
    monkeypatch.setattr(runners, "compile_reference", compile_program("reference"))
    monkeypatch.setattr(runners, "sweep_run", lambda programs: lambda: None)
    built, failed = gpu_profile.build({"agent": "dqn"}, ["command-buffers", "broken", "batched-counters"])
    assert list(built) == [
        "amjax",
        "amjax+command-buffers",
        "amjax+batched-counters",
        "reference",
        "reference+command-buffers",
    ]
    assert sorted(failed) == ["amjax+broken", "reference+broken"]
    assert compiled.count(("amjax", options)) == compiled.count(("reference", options)) == 1
    assert compiled.count(("amjax", None)) == 2 and compiled.count(("reference", None)) == 1


# The shape of XLA's GPU thunk sequence dump (`*thunk_sequence_after_thunk_passes.txt`), shortened: a loop whose
# condition is printed unindented, an update loop holding a command buffer, a one-iteration loop with an empty
# condition ("No thunks." on the body's line) and a conditional with a branch of copies.
THUNK_SEQUENCE = """\
000: kCommandBuffer [source       | next=026 (1)]
    001: kCustomKernel [source        | next=002 (1)] loop_add_fusion grid: [32, 1, 1] threads: [128, 1, 1]
    002: kCopy         [prev=001 (1)  | sink        ] kCopy
026: kWhile         [prev=000 (1) | next=000 (1)]
condition:
    027: kCustomKernel [source | sink] loop_compare_fusion grid: [1, 1, 1] threads: [1, 1, 1]
  body:
    000: kCommandBuffer      [source       | next=050 (2)]
        028: kCopy         [source       | next=033 (5)] kCopy
        033: kCustomKernel [prev=032 (1) | sink        ] loop_dynamic_update_slice_fusion grid: [32, 1, 1]
        034: kCustomKernel [prev=031 (3) | sink        ] input_reduce_fusion grid: [512, 1, 1]
    048: kDynamicSliceFusion [source       | next=050 (1)] params=1, results=1
        049: kCopy [source | sink] kCopy
    071: kWhile              [prev=000 (1) | next=118 (1)]
condition:
        No thunks.      body:
        000: kCommandBuffer [source | sink]
            072: kCustomKernel [source        | next=073 (1)] gemm_fusion_dot grid: [32768, 1, 1]
            073: kCopy         [prev=072 (1)  | sink        ] kCopy
    216: kConditional   [prev=000 (1) | next=233 (1)]
      false_branch:
        000: kCommandBuffer [source | sink]
            144: kCustomKernel [source        | next=145 (1) ] loop_slice_fusion grid: [32, 1, 1]
      true_branch:
        000: kCommandBuffer [source | sink]
            190: kCopy [source | sink] kCopy
            191: kCopy [source | sink] kCopy
    217: kCustomKernel [source | sink] loop_add_fusion_9 grid: [1, 1, 1] threads: [1, 1, 1]
"""


def test_gpu_thunks_counts_launches_per_loop_iteration_and_branch():
    """benchmarks/gpu_thunks.py's reading of a thunk sequence: launches at the top level and per loop iteration (a
    command buffer's commands and a dynamic-slice fusion's copy included, nested loops and branches listed apart),
    each conditional's per branch."""
    from benchmarks import gpu_thunks

    thunks = gpu_thunks.parse_thunks(THUNK_SEQUENCE)
    assert [t.kind for t in thunks] == ["kCommandBuffer", "kWhile"]
    assert gpu_thunks.launches(thunks) == (1, 1)
    assert gpu_thunks.report(thunks) == [
        "- loop: 3 kernels + 2 copies per iteration",
        "  - loop: 1 kernels + 1 copies per iteration",
        "  - conditional (the host reads its branch): false_branch: 1 kernels + 0 copies; "
        "true_branch: 0 kernels + 2 copies",
    ]
    spec = gpu_thunks.SPEC.read_text()
    assert spec.count("core_count: 132") == 1  # the target it compiles for ships with it
    # with CUDA versions: below 12.3 XLA would keep every conditional and loop out of command buffers (on the host)
    assert 'driver_version: "13.0.0"' in spec and 'runtime_version: "12.8.0"' in spec


IN_A_COMMAND_BUFFER = """\
000: kCommandBuffer [source | sink]
    005: kWhile [source | next=007 (1)]
condition:
        No thunks.      body:
        000: kCommandBuffer [source | sink]
            006: kCustomKernel [source | sink] loop_add_fusion grid: [1, 1, 1] threads: [1, 1, 1]
    007: kConditional [prev=005 (1) | sink]
      false_branch:
        008: kCustomKernel [source | sink] loop_add_fusion_1 grid: [1, 1, 1] threads: [1, 1, 1]
      true_branch:
        009: kCopy [source | sink] kCopy
"""


def test_gpu_thunks_says_which_branches_a_command_buffer_holds():
    """A loop or conditional that XLA recorded into a command buffer (`xla_gpu_enable_command_buffer` with WHILE and
    CONDITIONAL: CUDA graph conditional nodes) is decided on the device, whatever its trip count."""
    from benchmarks import gpu_thunks

    thunks = gpu_thunks.parse_thunks(IN_A_COMMAND_BUFFER)
    assert gpu_thunks.launches(thunks) == (0, 0)  # what the loop and the branches launch is listed apart
    assert gpu_thunks.report(thunks, trips={5: None}) == [
        "- loop (in a command buffer: on the device): 1 kernels + 0 copies per iteration",
        "- conditional (in a command buffer: on the device): false_branch: 1 kernels + 0 copies; "
        "true_branch: 0 kernels + 1 copies",
    ]
    assert gpu_thunks.report(thunks, trips={5: 200})[0] == (
        "- loop (200 iterations, in a command buffer: on the device): 1 kernels + 0 copies per iteration"
    )


def test_gpu_thunks_names_each_loops_trip_count():
    """A loop's trip count comes from its `while` in the optimised HLO (XLA's `known_trip_count`), matched to the
    thunk through `thunk_metadata.txt`; a loop without one reads its predicate on the host."""
    from benchmarks import gpu_thunks

    hlo = (
        "  %while.9 = (s32[], f32[8]{0}) while(%tuple.1), condition=%region_1, body=%region_2, "
        'backend_config={"known_trip_count":{"n":"125"},"known_init_step":{"init":"0","step":"1"}}\n'
        "  %fusion.3 = f32[8]{0} fusion(%p), kind=kLoop\n"
        "  ROOT %while.12 = (pred[], f32[8]{0}) while(%tuple.2), condition=%region_3, body=%region_4\n"
    )
    metadata = "\n".join(
        f'thunk_metadata {{\n  thunk_info {{\n    profile_annotation: "{name}"\n    thunk_id: {i}\n  }}\n}}'
        for name, i in (("while.9", 26), ("fusion.3", 27), ("while.12", 71))
    )
    trips = gpu_thunks.trip_counts(hlo, metadata)
    assert trips == {26: 125, 71: None}
    assert gpu_thunks.report(gpu_thunks.parse_thunks(THUNK_SEQUENCE), trips=trips)[:2] == [
        "- loop (125 iterations): 3 kernels + 2 copies per iteration",
        "  - loop (count unknown: a host read per condition): 1 kernels + 1 copies per iteration",
    ]


def test_replicate_time_says_what_a_timed_out_case_measured():
    """benchmarks/replicate_time.py: a case that ran past its time limit lists the batches it finished and the
    compile times of the one it was training (the child's last progress record, `harness.run_child`'s `partial`)."""
    from benchmarks import replicate_time

    batch = {"configs": 40, "compile_s": 61.0, "steps_per_s": 2.5e5, "projected_s": 600.0}
    case = {
        "status": "timeout after 235 s",
        "partial": {"batches": [batch], "current": {"configs": 10, "init_s": 20.5, "compile_s": 55.25}},
    }
    text = replicate_time._partial(case)
    assert "40-configuration batch finished (compile 61.0 s, 250.0 k train steps/s, projected 10.0 m)" in text
    assert "10-configuration batch had compiled (init 20.5 s with its compile, training chunk 55.2 s)" in text
    assert replicate_time._partial({"status": "timeout after 235 s"}) == ""


def test_pqn_speed_overrides_parse_and_label_their_cases():
    from benchmarks import pqn_speed

    items = ["pqn.update_epochs=2", "pqn.hidden=(32,32)", "pqn.activation=tanh", "pqn.layer_norm=FALSE"]
    overrides = pqn_speed.parse_overrides(items, ["dqn", "pqn"])
    want = {"update_epochs": 2, "hidden": (32, 32), "activation": "tanh", "layer_norm": False}
    assert overrides == {"dqn": {}, "pqn": want}
    for item, message in [
        ("drqn.update_epochs=2", "AGENT one of dqn, pqn"),
        ("pqn.epochs=2", "pqn has no field 'epochs'.*update_epochs"),
        ("pqn.eval_every=2048", "set by --steps and --eval-every"),
        ("pqn.learning_rate=", "an empty value"),
        ("pqn.learning_rate={1, 2}", "not a number, string, boolean or tuple"),
    ]:
        with pytest.raises(ValueError, match=message):
            pqn_speed.parse_overrides([item], ["dqn", "pqn"])
    with pytest.raises(ValueError, match="pqn.gamma is set twice"):
        pqn_speed.parse_overrides(["pqn.gamma=0.9", "pqn.gamma=0.95"], ["pqn"])

    case = {"env": "CartPole-v0", "status": "ok", "steps_per_config": 8192, "compile_s": 1.0, "run_s": 1.0}
    case |= {"env_steps_per_s": 100, "peak_rss_mib": 500}
    changed = {"update_epochs": 2, "hidden": [32, 32]}  # as a results file holds it (JSON)
    results = [{**case, "agent": "dqn", "overrides": {}}, {**case, "agent": "pqn", "overrides": changed}]
    results[1]["env_steps_per_s"] = 300
    machine = {"cpu": "AMD EPYC", "affinity": 1, "memory_gib": 23.5, "backend": "cpu", "jax": "0.10.2"}
    run = {"date": "2026-12-03T13:05", "commit": "abc1234", "command": "python benchmarks/pqn_speed.py"}
    run |= {"load_start": 0.5, "load_end": 0.7, "machine": machine, "settings": {"configs": 2, "devices": 1}}
    table = pqn_speed.render([run | {"cases": results}])
    # Against the unchanged dqn of the same run; an older file's cases have no "overrides" at all.
    assert "| pqn (update_epochs=2, hidden=(32, 32)) |" in table and "3.0x" in table
    older = [{k: v for k, v in r.items() if k != "overrides"} for r in results]
    assert "| pqn |" in pqn_speed.render([run | {"cases": older}])
    # A profiled case (--profile) gets its costliest source lines after the table; an unprofiled one none.
    rows = [{"name": "networks.py:70 LayerNorm.__call__ (reduce_sum)", "count": 4096, "ms": 25.7, "share": 0.108}]
    results[1]["profile"] = {"kernels": 141141, "busy_ms": 400.4, "span_ms": 165.0, "top_sources": rows}
    results[0]["profile"] = 0  # a case of a run before `profile_top` was named so: the row count, no trace
    profiled = pqn_speed.render([run | {"cases": results}])
    assert "## CartPole-v0 pqn (update_epochs=2, hidden=(32, 32)): where the time goes" in profiled
    assert "| networks.py:70 LayerNorm.__call__ (reduce_sum) | 4,096 | 25.7 | 10.8% |" in profiled
    assert "CartPole-v0 dqn: where" not in profiled


def test_pqn_speed_refuses_a_negative_profile(capsys):
    from benchmarks import pqn_speed

    with pytest.raises(SystemExit) as exit_info:
        pqn_speed.main(["--envs", "CartPole-v0", "--agents", "pqn", "--profile", "-1"])
    assert exit_info.value.code == 2
    assert "--profile: got -1; allowed values: 0" in capsys.readouterr().err


def test_pqn_speed_refuses_a_value_the_config_refuses_before_any_case_runs(capsys):
    from benchmarks import pqn_speed

    with pytest.raises(SystemExit) as exit_info:
        pqn_speed.main(["--envs", "CartPole-v0", "--agents", "pqn", "--set", "pqn.update_epochs=0"])
    assert exit_info.value.code == 2
    assert "--set: pqn on CartPole-v0:" in capsys.readouterr().err


def test_layer_norm_grad_checks_amjax_layer_norm_against_flax():
    """benchmarks/layer_norm_grad.py times amjax's LayerNorm, and its gradient check against flax's passes."""
    from amjax.agents.networks import LayerNorm
    from benchmarks import layer_norm_grad

    assert layer_norm_grad.NORMS["hand-written gradient (amjax)"] is LayerNorm
    assert layer_norm_grad.check_gradients() < 1e-5


def test_layer_norm_grad_times_the_widths_asked_for(capsys):
    """`--hidden` sets the timed network's widths (a bad width is refused before any case runs)."""
    import jax

    from benchmarks import layer_norm_grad

    network = layer_norm_grad.QNetwork(None, (8, 8, 8))
    params = network.init(jax.random.PRNGKey(0), jax.numpy.zeros((2, layer_norm_grad.OBS)))["params"]
    assert [params[f"Dense_{i}"]["kernel"].shape[1] for i in range(4)] == [8, 8, 8, layer_norm_grad.ACTIONS]
    compile_s, run = layer_norm_grad.compile_steps(layer_norm_grad.LayerNorm, 2, (8, 8, 8))
    assert compile_s > 0
    run()
    with pytest.raises(SystemExit) as exit_info:
        layer_norm_grad.main(["--hidden", "64", "0"])
    assert exit_info.value.code == 2
    assert "--hidden: got 0" in capsys.readouterr().err
