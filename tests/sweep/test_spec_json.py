"""`SweepSpec.to_json` / `from_json`: what a cluster worker and a folder's metadata read back is the spec itself.

JSON has no tuples, so tuple values (network widths, `extra_obs`, `instruments`, instrument prices, and the env
presets' widths) came back as lists, which the grid reads as lists of values to sweep: until this was fixed a
cluster worker failed on any LunarLander-v3 or Acrobot-v1 sweep (their presets set `hidden`) and on any tuple set by
`--set`."""

from __future__ import annotations

import pytest

from amjax.sweep import SweepSpec, expand

BASE = {"costs": (0.1,), "seeds": (0,), "total_timesteps": 163_840, "eval_every": 81_920}


@pytest.mark.parametrize(
    ("envs", "agents", "hyperparams"),
    [
        (("LunarLander-v3", "Acrobot-v1"), ("ppo", "dqn"), {}),  # presets with tuple widths
        (
            ("CartPole-v0",),
            ("ppo", "dqn"),
            {
                "hidden": [(16,), (32, 32)],  # a sweep over tuples
                "ppo.hidden": (8,),  # one tuple, scoped
                "learning_rate": [1e-3, 3e-4],
                "extra_obs": ("since_measured",),
                "instruments": "default",
                "instrument_costs": (0.1, 0.2),
            },
        ),
        (
            ("CartPole-v0",),
            ("ppo",),
            {"instruments": ((0, 1), (2, 3)), "extra_obs": [(), ("since_measured", "last_action")]},
        ),
        (("CartPole-v0",), ("drqn",), {"instruments": [((0, 1), (2, 3)), "default"], "hidden": ()}),
    ],
)
def test_a_spec_reads_back_as_itself(envs, agents, hyperparams):
    spec = SweepSpec(envs=envs, agents=agents, hyperparams=hyperparams, **BASE)
    back = SweepSpec.from_json(spec.to_json())
    assert back.hyperparams == spec.hyperparams and back.to_json() == spec.to_json()
    assert back.env_defaults == spec.resolved_env_defaults()
    assert [(r.config_id, r.config) for r in expand(back)] == [(r.config_id, r.config) for r in expand(spec)]
