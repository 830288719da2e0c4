"""`python -m train pareto` and `amjax.analysis.pareto`: one cost-conditioned agent per seed, its front at a grid of
costs, per-cost specialists beside it."""

import pandas as pd
import pytest

from amjax.analysis.pareto import cost_front, front_table
from amjax.analysis.results import load_results
from train.cli import main

ARGS = [
    "pareto",
    "--agent",
    "ppo",
    "--seeds",
    "2",
    "--steps",
    "2048",
    "--eval-every",
    "1024",
    "--grid-step",
    "0.25",
    "--specialist-costs",
    "0.2",
    "--no-progress",
]


@pytest.fixture(scope="module")
def front_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("pareto")
    assert main([*ARGS, "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_writes_the_front_the_table_and_the_plot(front_folder):
    points = pd.read_csv(front_folder / "front.csv")
    # 2 seeds x the grid 0, 0.25, 0.5 and the specialists' 0.2.
    assert sorted(points.cost.unique()) == [0.0, 0.2, 0.25, 0.5] and len(points) == 2 * 4
    assert set(points.seed) == {0, 1} and points.measured.between(0, 1).all()
    # The costed return is the raw return less the cost of the measurements, per episode; their means agree.
    steps = points["raw_return"]  # CartPole pays 1 per step: raw return = episode length
    assert ((points["raw_return"] - points["return"]) - points.cost * points.measured * steps).abs().max() < 1e-2
    table = (front_folder / "table.md").read_text()
    assert "| ppo | 0.2 |" in table and "gap" in table
    assert (front_folder / "front.png").stat().st_size > 10_000
    # The conditioned run takes 1.5x a specialist's env steps, rounded down to whole evaluation periods.
    conditioned = load_results(front_folder / "conditioned").summary
    assert conditioned.cost_conditioned.all() and (conditioned.env_steps == 3072).all()


@pytest.mark.slow
def test_rerun_resumes_without_training_again(front_folder, capsys):
    before = pd.read_parquet(front_folder / "conditioned" / "results.parquet")
    front = pd.read_csv(front_folder / "front.csv")
    assert main([*ARGS, "--out", str(front_folder)]) == 0
    pd.testing.assert_frame_equal(pd.read_parquet(front_folder / "conditioned" / "results.parquet"), before)
    pd.testing.assert_frame_equal(pd.read_csv(front_folder / "front.csv"), front)  # the test episodes' keys are fixed


@pytest.mark.slow
def test_table_ratio_against_the_specialists(front_folder):
    points = pd.read_csv(front_folder / "front.csv")
    specialists = load_results(front_folder / "specialists").summary
    table = front_table(points, specialists)
    assert list(table.cost) == [0.2]
    row = table.iloc[0]
    gap = (row["return conditioned"] - row["return specialists"]) / abs(row["return specialists"])
    assert row["gap"] == pytest.approx(gap)
    negative = front_table(
        points.assign(**{"return": -points["return"]}),
        specialists.assign(best_policy_return=-specialists.best_policy_return),
    )
    assert negative["gap"].iloc[0] == pytest.approx(-gap)  # a higher (less negative) reward is a positive gap


@pytest.mark.slow
def test_front_of_an_ordinary_sweep_is_refused(front_folder):
    with pytest.raises(ValueError, match="not cost-conditioned"):
        cost_front(front_folder / "specialists", costs=(0.1,))


def test_seed_list_picks_the_seeds_of_both_sweeps():
    """`amjax pareto --seed-list` works as `amjax sweep --seed-list` does."""
    from train.cli import build_parser
    from train.pareto import _specs

    args = build_parser().parse_args(["pareto", "--seed-list", "7", "11", "--out", "x"])
    conditioned, specialists, _ = _specs(args)
    assert conditioned.seeds == specialists.seeds == (7, 11)
    default, _, _ = _specs(build_parser().parse_args(["pareto", "--out", "x"]))
    assert default.seeds == (0, 1, 2, 3, 4)
