import os, signal, threading, time, glob, pandas as pd
from pathlib import Path
from amjax.sweep import SweepSpec, run_sweep
spec = SweepSpec(envs=("CartPole-v0",), agents=("ppo", "dqn"), costs=(0.0, 0.2), seeds=(0, 1), total_timesteps=20480, eval_every=2048)
out = Path("/tmp/cl_kill")
killed = []
def killer():
    import json
    while True:
        for part in glob.glob(str(out / "parts" / "dqn-*")):
            if os.path.exists(part + "/results.parquet") and os.path.exists(part + "/worker.json"):
                pid = json.load(open(part + "/worker.json"))["pid"]; os.kill(pid, signal.SIGKILL); killed.append(pid); return
        time.sleep(0.1)
threading.Thread(target=killer, daemon=True).start()
t = time.perf_counter()
b = run_sweep(spec, out, progress=False, cluster="local:2", target_chunks=10, checkpoint_every_s=0)
print("killed", killed, "cluster", time.perf_counter() - t)
a = run_sweep(spec, "/tmp/cl_kill_local", progress=False)
key = ["config_id", "env_steps"]
pd.testing.assert_frame_equal(a.results.sort_values(key).reset_index(drop=True), b.results.sort_values(key).reset_index(drop=True), check_exact=False, rtol=1e-5)
print("same", len(b.results), open(out / "cluster.json").read())
