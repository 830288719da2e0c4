import sys, time, pandas as pd
from amjax.sweep import SweepSpec, run_sweep
import amjax; print(amjax.__file__)
spec = SweepSpec(envs=("CartPole-v0",), agents=("ppo", "dqn"), costs=(0.0, 0.2), seeds=(0, 1), total_timesteps=4096, eval_every=2048)
t = time.perf_counter(); a = run_sweep(spec, "/tmp/cl_local", progress=False); tl = time.perf_counter() - t
t = time.perf_counter(); b = run_sweep(spec, "/tmp/cl_cluster", progress=False, cluster="local:2"); tc = time.perf_counter() - t
print("local", tl, "cluster", tc)
cols = ["config_id", "env_steps", "eval_return", "loss"]
ra = a.results.sort_values(["config_id", "env_steps"]).reset_index(drop=True)
rb = b.results.sort_values(["config_id", "env_steps"]).reset_index(drop=True)
print(ra.columns.tolist()[:12])
pd.testing.assert_frame_equal(ra, rb, check_exact=False, rtol=1e-5)
pd.testing.assert_frame_equal(a.summary, b.summary, check_exact=False, rtol=1e-5)
print("same results", len(ra))
import os; print(os.listdir("/tmp/cl_cluster"), open("/tmp/cl_cluster/cluster.json").read()[:500])
