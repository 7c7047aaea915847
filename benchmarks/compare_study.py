"""Does a study made elsewhere reproduce the shipped report? Compares two ``nrmse.csv``.

A study on another CPU or BLAS filters the same physics pseudo-data (its digests agree) and
metamodel pseudo-data that differ in the last bits; a particle filter's resampling then
picks other particles, so single runs part like runs of two seeds. What must agree are the
series means: per series and group (state, theta, angles) the mean over the runs of the
group's mean nRMSE, compared in units of the standard error of the difference of the two
means. Writes ``benchmarks/results/bench_compare_study.json``; exit 1 beyond ``--tolerance``.

    python benchmarks/compare_study.py out/demo/nrmse.csv docs/study_results/nrmse.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from formtwin._bench import write_result

#: the nRMSE columns of each group (after series, realisation, repetition)
GROUPS = {"state": slice(0, 7), "theta": slice(7, 10), "angles": slice(18, 20)}


def read(path: Path) -> np.ndarray:
    """The rows (runs, 3 + 20) of an ``nrmse.csv``."""
    lines = path.read_text(encoding="utf-8").splitlines()[1:]
    return np.array([[float(v) for v in line.split(",")] for line in lines])


def compare(new: np.ndarray, ref: np.ndarray) -> dict[str, dict[str, list[float]]]:
    """Per series and group: ``[reference mean, new mean, difference / standard error]``."""
    out: dict[str, dict[str, list[float]]] = {}
    for s in sorted(set(ref[:, 0].astype(int)) & set(new[:, 0].astype(int))):
        a, b = ref[ref[:, 0] == s, 3:], new[new[:, 0] == s, 3:]
        row = {}
        for name, cols in GROUPS.items():
            ma, mb = a[:, cols].mean(axis=1), b[:, cols].mean(axis=1)
            se = float(np.sqrt(ma.var(ddof=1) / ma.size + mb.var(ddof=1) / mb.size))
            row[name] = [round(float(ma.mean()), 4), round(float(mb.mean()), 4),
                         round(float((mb.mean() - ma.mean()) / se), 2)]
        out[f"series{s}"] = row
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("new", type=Path, help="nrmse.csv of the study to check")
    parser.add_argument("reference", type=Path, help="nrmse.csv of the shipped report")
    parser.add_argument("--tolerance", type=float, default=3.0,
                        help="largest |difference| in standard errors (default: %(default)s)")
    args = parser.parse_args()
    table = compare(read(args.new), read(args.reference))
    worst = max(abs(v[2]) for row in table.values() for v in row.values())
    write_result("compare_study", {"per_series": table, "max_abs_diff_over_se": worst,
                                   "tolerance_se": args.tolerance,
                                   "new": str(args.new), "reference": str(args.reference)})
    return 0 if worst <= args.tolerance else 1


if __name__ == "__main__":
    sys.exit(main())
