"""Make docs/figures/monitoring_delays.png: median delay to detect a 2-sigma step in one state
variable's mean, per variable: the charts on the tracker's estimates, the best GLR on the
curves themselves (the linear-Gaussian bound) and the same charts on the true states, from
benchmarks/results/bench_monitoring.json. Runs without a detection count at the scenario's
horizon (150 products after the step), as the benchmark scores them.

    python docs/figures/monitoring_delays.py [bench_monitoring.json]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from formtwin.figures import pyplot


def main() -> None:
    """Read the benchmark JSON and write the figure next to this script."""
    path = Path(sys.argv[1] if len(sys.argv) > 1 else
                "benchmarks/results/bench_monitoring.json")
    fig_data = json.loads(path.read_text())["figures"]
    groups = {
        "charts on the estimates": fig_data["step_2sigma"]["per_variable"],
        "bound: GLR on the curves": fig_data["linearised_bound"]["step_2.0sigma"]["per_variable"],
        "charts on the true states": fig_data["oracle_true_states"]["step_2sigma"]["per_variable"],
    }
    names = list(groups["charts on the estimates"])
    x = np.arange(len(names))
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.2), layout="constrained")
    for k, (label, per_variable) in enumerate(groups.items()):
        ax.bar(x + (k - 1) * 0.27, [per_variable[n]["median"] for n in names], 0.27, label=label)
    target = fig_data["detection_delay_target"]
    ax.axhline(target, color="black", lw=1, ls="--", label=f"target ({target} products)")
    ax.set_xticks(x, [n.replace("_", " ") for n in names], rotation=20, ha="right")
    ax.set_ylabel("median delay, products")
    ax.set_title("Detecting a 2-sigma step in one state's mean (seed 2027, bending-2.4)")
    ax.set_ylim(0, 200)
    ax.legend(fontsize=8, ncols=2, loc="upper left")
    fig.savefig(Path(__file__).with_name("monitoring_delays.png"), dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
