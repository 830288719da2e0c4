"""Analysis of sweeps: load a results folder, the paper's figures and table, measurement maps, reports.

```python
from amjax import analysis
results, summary, metadata = analysis.load_results("runs/x")
analysis.learning_curves(results, path="curves.png")        # every plot returns a matplotlib Figure
analysis.paper_table(summary, results)                        # the paper's table, ours beside its numbers
analysis.seed_spread(summary)                                 # mean, sd, min and max over seeds beside it
analysis.write_report("runs/x")                               # runs/x/report/report.md + figures
```

Needs matplotlib (`pip install "amjax-rl[plots]"`).
"""

try:
    import matplotlib  # noqa: F401
except ImportError as error:  # pragma: no cover - depends on the installation
    raise ImportError('amjax.analysis needs matplotlib: pip install "amjax-rl[plots]"') from error

from amjax.analysis.maps import MeasurementMap, plot_measurement_map, record_agent, record_measurements
from amjax.analysis.paper import PAPER_ALWAYS_MEASURE, PAPER_BEST_RETURN
from amjax.analysis.plots import agent_comparison, cost_analysis, learning_curves, save_figure, vanilla_vs_cost0
from amjax.analysis.report import write_report
from amjax.analysis.results import (
    NotASweepError,
    SweepData,
    agent_config,
    always_measure_bound,
    always_measure_return,
    best_hyperparams,
    learning_curve_table,
    load_results,
    sweep_progress,
)
from amjax.analysis.tables import paper_table, seed_spread, to_markdown

__all__ = [
    "PAPER_ALWAYS_MEASURE",
    "PAPER_BEST_RETURN",
    "MeasurementMap",
    "NotASweepError",
    "SweepData",
    "agent_comparison",
    "agent_config",
    "always_measure_bound",
    "always_measure_return",
    "best_hyperparams",
    "cost_analysis",
    "learning_curve_table",
    "learning_curves",
    "load_results",
    "paper_table",
    "plot_measurement_map",
    "record_agent",
    "record_measurements",
    "save_figure",
    "seed_spread",
    "sweep_progress",
    "to_markdown",
    "vanilla_vs_cost0",
    "write_report",
]
