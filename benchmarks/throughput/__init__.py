"""Throughput of amjax's compiled sweep trainers against plain single-file references and Stable-Baselines3.

For PPO and DQN on CartPole-v0 (the 200-step CartPole) and 1 / 16 / 256 / 1024 configurations it times:
- `amjax`: exactly what `amjax.sweep.run_sweep` compiles for one batch: the configs stacked with
  `amjax.agents.stack_configs` (costs 0.1 / 0.2 / 0.3 cycling, seeds 0..n-1) and the runner's own two programs
  (`init_run` under `lax.map`, then `jax.jit(jax.vmap(run_evals ...))` chunks, from
  `amjax.sweep.batches.compiled_programs`), with periodic greedy evaluation as in a real sweep (every
  steps / --evals env steps);
- `amjax-vanilla-env`: the same on the plain environment (`vanilla=True`: no measure action, no cost), so the
  difference is the active-measure wrapper's cost;
- `plain reference`: benchmarks/reference_{ppo,dqn}.py, PureJaxRL-style single-file trainers with the same
  hyperparameters, env and (by default) the same evaluation, as `jax.jit(jax.vmap(train))(keys, costs)`;
- `SB3` (if stable_baselines3 is importable): DQN and PPO with their default hyperparameters on Gymnasium
  CartPole-v1, 1 env, and amjax DQN with SB3's DQN hyperparameters at --sb3-configs configurations, for a speed-up.

Every case runs in a fresh subprocess (`benchmarks.harness.run_child`), so its peak RSS (getrusage in the child,
`harness.child_result`) is its own, and is recorded as one JSON line of the run's results file
(`benchmarks/results/throughput_<date>_<machine>.jsonl`, `harness.Recorder`; the overhead and SB3 cases too); the
report (table, ratios, notes) is rendered from those lines into the .md beside it (`render`; again with
`python -m benchmarks.harness render FILE.jsonl`). Compile time is `.lower(...).compile()` of every program the
case runs; run time is everything after (initialisation included); env-steps/s = configs x steps per config / run
time (training steps only; evaluation episodes are extra work).

From the repository root (`python benchmarks/throughput ...` runs the same):

    python -m benchmarks.throughput --markdown throughput.md   # the full table: ~15-20 min on 2 quiet cores
    python -m benchmarks.throughput --quick --out /tmp/tp.jsonl  # smoke run, tiny sizes (~5-10 min)
    python -m benchmarks.throughput --agents ppo --sizes 1,16 --steps 1:102400,16:20480 --repeats 3

Modules: cases (what runs), timing (how it is measured, each case in a child process), runners (the child: one
implementation compiled and timed), report (the report rendered from the JSON lines: table, ratios, and the notes
filled into notes.md), __main__ (the command line, and the child's script).
"""

from .report import render

__all__ = ["render"]
