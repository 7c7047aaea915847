"""Benchmark: the paper's full study (6 series x 5 datasets x 5 repetitions, N = 500).

Runs ``formtwin study`` at the paper's size into ``--out`` (default
``benchmarks/.cache/study``) on the embedded default (bundled physics DOE, its metamodel)
and reports ``full_study_s``: the 150 filter runs, metrics and report, the pseudo-data
generation (physics runs included) apart as ``pseudo_data_s``. A finished study folder is
only re-reported (``from_cache``: the figures are those of the run that computed it); use
``--fresh-runs`` to time the filter runs again. Target: full_study_s <= 600 s on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from formtwin._bench import write_result
from formtwin.cli import study


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="benchmarks/.cache/study")
    parser.add_argument("--fresh-runs", action="store_true",
                        help="delete cached filter runs first (keep the pseudo-data)")
    args = parser.parse_args()
    out = Path(args.out)
    if args.fresh_runs:
        for f in (out / "runs").glob("*.npz"):
            f.unlink()
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    ns = study.build_namespace(out=str(out), physics="bending")
    study.run(ns)
    wall = time.perf_counter() - t0
    import json

    result = json.loads((out / "results.json").read_text())
    timings = result["timings"]
    figures = {
        "full_study_s": round(timings["total_s"] - timings["pseudo_data_s"], 1),
        "filter_runs_s": round(timings["filter_runs_s"], 1),
        "filter_runs_computed": int(timings["filter_runs_computed"]),
        "pseudo_data_s": round(timings["pseudo_data_s"], 1),
        "wall_s": round(wall, 1),
        "from_cache": bool(timings.get("cached", 0.0)),
        "load_average_1min_start": round(load0, 2),
        "load_average_1min_end": round(os.getloadavg()[0], 2),
        "series1_angle_stage1_nrmse": result["nrmse_overall"]["series1"]["angle_stage1"],
        "series1_angle_stage2_nrmse": result["nrmse_overall"]["series1"]["angle_stage2"],
    }
    write_result("study", figures)


if __name__ == "__main__":
    main()
