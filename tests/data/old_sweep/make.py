"""Write the committed sweep folders `tests/sweep/test_old_folders.py` loads: a finished sweep (`full/`) and the
same sweep stopped just after its first checkpoint (`interrupted/`), as an older amjax wrote them.

Run with the amjax to freeze on the path (a checkout of that commit), from anywhere:
    PYTHONPATH=/path/to/old/checkout python tests/data/old_sweep/make.py tests/data/old_sweep
The folders were written this way at commit 3043e65 (2026-11-28), before `MeasureSpec` (issue 52), in a process
with one JAX CPU device (the default; results across device counts agree only to float rounding); `expected.json`
holds what the old code's saved policies score on fixed keys. `make.py resume FOLDER` reruns the same sweep into
FOLDER (what a user does to resume it; the test runs it with today's code, on one device).

The tables are bit for bit what the machine that wrote them computes; another CPU rounds differently. So
`machine.json` names that machine, as today's amjax describes it (run with today's code on the path, on the same
machine: `python tests/data/old_sweep/make.py machine tests/data/old_sweep`). Rewritten on 2026-11-29 on a 2-core
AMD EPYC with AVX-512 (the first folders, from a machine not recorded, differed from these only in the last bits of
the loss column, by up to 2e-6).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import jax

from amjax.sweep import SweepSpec, load_sweep_policy, run_sweep

SPEC = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo", "dqn"),
    costs=(0.1, 0.3),
    seeds=(0,),
    vanilla=True,
    total_timesteps=2048,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={
        "hidden": (16,),
        "ppo.num_envs": 4,
        "ppo.num_steps": 32,
        "dqn.buffer_size": 256,
        "dqn.learning_starts": 256,
        "extra_obs": ("since_measured",),
        "rescore_episodes": 4,
    },
)
OPTIONS = {"progress": False, "target_chunks": 2, "checkpoint_every_s": 0.0}
EVAL_KEY, EVAL_EPISODES = 7, 6


def main(root: Path) -> None:
    for name in ("full", "interrupted", "expected.json"):
        path = root / name
        shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
    run_sweep(SPEC, root / "full", **OPTIONS)
    # The same sweep again, copied as it stood right after its first checkpoint was committed (what a kill at that
    # instant leaves; `amjax.files.commit` renames every file into place with os.replace).
    replace, copied = os.replace, []

    def copying_replace(source, target, *args, **kwargs):
        replace(source, target, *args, **kwargs)
        if not copied and Path(target).parent.name == "checkpoints":
            shutil.copytree(root / "scratch", root / "interrupted", ignore=shutil.ignore_patterns(".lock"))
            copied.append(target)

    os.replace = copying_replace
    try:
        run_sweep(SPEC, root / "scratch", **OPTIONS)
    finally:
        os.replace = replace
        shutil.rmtree(root / "scratch")
    scores = {}
    for policy in sorted((root / "full" / "policies").glob("*.msgpack")):
        saved = load_sweep_policy(root / "full", policy.stem)
        scores[policy.stem] = saved.evaluate(jax.random.PRNGKey(EVAL_KEY), EVAL_EPISODES)
    (root / "expected.json").write_text(json.dumps(scores, indent=1, sort_keys=True) + "\n")


def machine() -> dict[str, str]:
    """This machine as the test compares it: today's `amjax.cores.cpu_description`, what a sweep's metadata.json
    records as "cpu" (these folders' metadata, written by the old code, has no such entry)."""
    from amjax.cores import cpu_description

    return {"cpu": cpu_description()}


if __name__ == "__main__":
    if sys.argv[1] == "resume":
        run_sweep(SPEC, Path(sys.argv[2]), **OPTIONS)
    elif sys.argv[1] == "machine":
        (Path(sys.argv[2]) / "machine.json").write_text(json.dumps(machine(), indent=1) + "\n")
    else:
        main(Path(sys.argv[1]))
