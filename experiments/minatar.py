"""Active measurement on MinAtar (issue 53): PPO with the MinAtar CNN on Breakout and SpaceInvaders, vanilla and at
three measurement costs, 5 seeds; the frame stays an image and the stale flag is one more channel
(docs/guide/envs.md, Image observations).

Each env is one sweep, then its report (measurement maps of the saved best policies) and the joint paper-style
table in OUT/table.md (experiments/cost_experiment.py: re-scored best policies beside the paper's metric, raw
returns, measured fractions, the always-measure bound).

    python experiments/minatar.py --out runs/minatar                     # 10 M steps per configuration
    python experiments/minatar.py --out runs/minatar_1m --steps 1000000  # what fits a small machine
    python experiments/minatar.py --smoke --out /tmp/minatar_smoke       # a tiny smoke run

Costs: both games pay +1 per brick or alien destroyed, and a trained agent collects about one every 5-10 steps
(0.1-0.2 per step), against CartPole's 1 per step: a cost of 0.01 per measurement is then about 5-10% of the reward
rate, 0.05 about 25-50% and 0.1 about 50-100%, so the three costs range from a small tax to one that only a policy
measuring on few steps can afford. Speed on 2 CPU cores (2026-11-28, AMD EPYC): PPO with the CNN trains about 3,600
env-steps/s (one configuration or eight side by side), so the full experiment (2 games x 4 settings x 5 seeds x
10 M steps) is about 30 hours there; a GPU or `--steps` makes it fit. docs/minatar.md reports the run at
`--steps 307200` (44 minutes there).
"""

from __future__ import annotations

import sys
from pathlib import Path

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the experiments are not installed

from experiments import cost_experiment  # noqa: E402

EXPERIMENTS: cost_experiment.Experiments = {
    "Breakout-MinAtar": ((0.01, 0.05, 0.1), 10_240_000, 512_000),
    "SpaceInvaders-MinAtar": ((0.01, 0.05, 0.1), 10_240_000, 512_000),
}


if __name__ == "__main__":
    sys.exit(cost_experiment.main(__doc__, EXPERIMENTS, ("ppo",)))
