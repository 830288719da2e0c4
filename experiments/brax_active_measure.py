"""Active measurement on brax continuous control (issue 17): PPO's Gaussian + Bernoulli head on inverted_pendulum
and reacher, vanilla and at three measurement costs, 5 seeds.

Each env is one sweep, then its report and the joint paper-style table in OUT/table.md (experiments/
cost_experiment.py, shared with minatar.py: re-scored best policies beside the paper's metric, raw returns,
measured fractions, the always-measure bound).

    python experiments/brax_active_measure.py --out runs/brax_active_measure       # the full experiment
    python experiments/brax_active_measure.py --smoke --out /tmp/brax_smoke         # a tiny smoke run

Costs are per step, scaled to each env's rewards. inverted_pendulum pays 1 per step upright (as CartPole): 0.1 /
0.2 / 0.3. reacher pays minus the fingertip's distance to the target and the squared action, about -0.2 to 0 per
step over 1,000 steps: 0.001 / 0.003 / 0.01, so an always-measuring policy pays 1 / 3 / 10 per episode against
returns of about -100 to -220 at this budget (doing nothing scores -223.5). reacher runs on brax's spring backend,
7x its default generalized one on this CPU (docs/brax.md, Speed). Hyperparameters: PPO's defaults (plus an env's
preset from amjax/presets.py where one exists; none does for these two).
"""

from __future__ import annotations

import sys
from pathlib import Path

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the experiments are not installed

from experiments import cost_experiment  # noqa: E402

EXPERIMENTS: cost_experiment.Experiments = {
    "brax:inverted_pendulum": ((0.1, 0.2, 0.3), 1_638_400, 40_960),
    "brax:reacher:spring": ((0.001, 0.003, 0.01), 1_024_000, 102_400),
}


if __name__ == "__main__":
    sys.exit(cost_experiment.main(__doc__, EXPERIMENTS, ("ppo",)))
