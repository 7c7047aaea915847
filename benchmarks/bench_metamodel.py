"""Metamodel speed and holdout accuracy, side by side with scipy's global thin-plate spline.

One core (one BLAS thread). Data: the paper's design (2^10 corners + 6000 Latin-hypercube
points): by default the DOE of the physics model bundled with formtwin
(``formtwin/data/doe_bending.h5``), ``--dataset analytic`` the same design run on the
closed-form analytic stand-in, or ``--dataset PATH`` any DOE dataset file.
A seeded 10 % of the successful runs is held out.

Figures: ``predict_500_ms`` (median CPU time of ``Metamodel.predict`` on 500 held-out
points, one thread; ``predict_500_wall_ms`` the wall time, which a loaded machine inflates),
``holdout_curve_rel_err`` (pooled relative L2 error of the curves), its variant about the
mean curve, ``holdout_angle_nrmse`` (RMSE / std per angle), ``fit_s``; and for scipy's
``RBFInterpolator(kernel="thin_plate_spline")`` on all training points, on the same unit-box
inputs and the same 40 POD coefficients + 2 angles: ``scipy_tps_predict_500_ms``,
``scipy_tps_holdout_curve_rel_err``, ...

``--tradeoff`` also fits the variants of the accuracy/speed table in docs/explanation/metamodel.md.

    python benchmarks/bench_metamodel.py [--dataset PATH] [--tradeoff]
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import RBFInterpolator

from formtwin._bench import write_result
from formtwin._threads import single_blas_thread
from formtwin.dataset import DoeDataset
from formtwin.metamodel import POD, RBF, Metamodel
from formtwin.metamodel.validate import _Rows, angle_errors, curve_errors


def _data(path: str | None) -> tuple[Any, str]:
    if path is None:
        from formtwin.defaults import bundled_doe

        path = str(bundled_doe("bending"))
    if path != "analytic":
        data = DoeDataset.load(path)
        return data, f"{Path(path).name} ({data.model_version})"
    from formtwin.doe import paper_design
    from formtwin.physics.analytic import AnalyticBending
    from formtwin.spec import load_spec

    spec = load_spec()
    sim = AnalyticBending(spec)
    X = paper_design(spec)
    curves, angles = sim.run_batch(X)
    ok = np.ones(X.shape[0], dtype=bool)
    return DoeDataset(spec=spec, inputs=X, curves=curves, angles=angles, ok=ok,
                      reason=np.full(X.shape[0], ""), model_version=sim.version), "analytic"


def _median_ms(f: Callable[[], object], repeat: int) -> tuple[float, float]:
    """Median CPU time of this thread and median wall time of ``f()``, ms.

    With one BLAS thread all the work runs in the calling thread, so its CPU time is the
    single-core cost, robust to other processes on a loaded machine; wall time is not.
    """
    f()
    cpu, wall = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.thread_time()
        f()
        cpu.append(time.thread_time() - c)
        wall.append(time.perf_counter() - t)
    return float(np.median(cpu) * 1e3), float(np.median(wall) * 1e3)


def _errors(prefix: str, curves: np.ndarray, angles: np.ndarray, test: _Rows,
            mean: np.ndarray) -> dict[str, Any]:
    c = curve_errors(curves, test.curves, mean)
    a = angle_errors(angles, test.angles)
    return {f"{prefix}holdout_curve_rel_err": c["curve_rel_err"],
            f"{prefix}holdout_curve_var_rel_err": c["curve_var_rel_err"],
            f"{prefix}holdout_angle_nrmse": a["angle_nrmse"]}


def _ours(factory: Callable[[], Metamodel], train: _Rows, test: _Rows, mean: np.ndarray,
          repeat: int) -> dict[str, Any]:
    mm = factory().fit(train)
    X500 = test.inputs[:500]
    p = mm.predict(test.inputs)
    cpu, wall = _median_ms(lambda: mm.predict(X500), repeat)
    out = {"predict_500_ms": cpu, "predict_500_wall_ms": wall,
           **_errors("", p.curves, p.angles, test, mean), "fit_s": mm.fit_seconds,
           "n_modes": mm.n_modes}
    out["dtypes"] = [getattr(m, "dtype", np.dtype(np.float64)).name
                     for m in (mm.curve_model, *mm.angle_models)]
    return out


def _scipy(train: _Rows, test: _Rows, mean: np.ndarray, repeat: int) -> dict[str, Any]:
    pod = POD(n_modes=40).fit(train.curves)
    lo, hi = train.spec.run_inputs.lo, train.spec.run_inputs.hi
    U, V = (train.inputs - lo) / (hi - lo), (test.inputs - lo) / (hi - lo)
    t = time.perf_counter()
    rbf = RBFInterpolator(U, np.hstack([pod.transform(train.curves), train.angles]),
                          kernel="thin_plate_spline")
    fit_s = time.perf_counter() - t
    Y = rbf(V)
    k = pod.n_modes
    cpu, wall = _median_ms(lambda: rbf(V[:500]), repeat)
    return {"scipy_tps_predict_500_ms": cpu, "scipy_tps_predict_500_wall_ms": wall,
            **_errors("scipy_tps_", pod.inverse_transform(Y[:, :k]), Y[:, k:], test, mean),
            "scipy_tps_fit_s": fit_s}


#: (label, factory) of the accuracy/speed table in docs/explanation/metamodel.md
VARIANTS: list[tuple[str, Callable[[], Metamodel]]] = [
    ("TPS, unit box, interpolate all", lambda: Metamodel(
        POD(40), RBF(length_scales="box"))),
    ("TPS, LOO scales, interpolate all", lambda: Metamodel(POD(40), RBF())),
    ("TPS, LOO scales, 1000 / 500 centres", lambda: Metamodel(
        POD(40), RBF(n_centres=1000), RBF(n_centres=500))),
    ("cubic, LOO scales, 2000 / 1000 centres", lambda: Metamodel(
        POD(40), RBF("cubic", n_centres=2000), RBF("cubic", n_centres=1000))),
    ("cubic, LOO scales, 1000 / 500 centres", lambda: Metamodel(
        POD(40), RBF("cubic", n_centres=1000), RBF("cubic", n_centres=500))),
    ("cubic, LOO scales, 500 / 300 centres", lambda: Metamodel(
        POD(40), RBF("cubic", n_centres=500), RBF("cubic", n_centres=300))),
    ("cubic, 1000 / 500 centres, POD energy 0.99999", lambda: Metamodel(
        POD(energy=0.99999), RBF("cubic", n_centres=1000), RBF("cubic", n_centres=500))),
    ("cubic, 1000 / 500 centres, float64", lambda: Metamodel(
        POD(40), RBF("cubic", n_centres=1000, dtype=np.float64),
        RBF("cubic", n_centres=500, dtype=np.float64))),
]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", help="DOE dataset file, or 'analytic' "
                    "(default: the bundled physics DOE)")
    ap.add_argument("--holdout", type=float, default=0.1, help="held-out share of the runs")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=30, help="timing repetitions")
    ap.add_argument("--tradeoff", action="store_true", help="also fit the table's variants")
    args = ap.parse_args(argv)

    data, label = _data(args.dataset)
    ok = np.asarray(data.ok, dtype=bool)
    X, C, A = data.inputs[ok], data.curves[ok], data.angles[ok]
    perm = np.random.default_rng(args.seed).permutation(X.shape[0])
    n_test = int(round(args.holdout * X.shape[0]))

    def rows(idx: np.ndarray) -> _Rows:
        return _Rows(data.spec, data.spec_text, X[idx], C[idx], A[idx],
                     np.ones(idx.size, dtype=bool), data.model_version)

    train, test = rows(perm[n_test:]), rows(perm[:n_test])
    mean = train.curves.mean(axis=0)
    figures: dict[str, Any] = {"data": label, "n_train": int(train.inputs.shape[0]),
                               "n_holdout": n_test}
    with single_blas_thread():
        figures.update(_ours(Metamodel, train, test, mean, args.repeat))
        figures.update(_scipy(train, test, mean, max(5, args.repeat // 5)))
        if args.tradeoff:
            rowsout = []
            for name, factory in VARIANTS:
                r = _ours(factory, train, test, mean, args.repeat)
                rowsout.append({"model": name, **r})
                print(f"| {name} | {r['n_modes']} | {r['predict_500_ms']:.2f} | "
                      f"{r['holdout_curve_rel_err']:.4f} | {r['holdout_curve_var_rel_err']:.4f} | "
                      f"{r['holdout_angle_nrmse'][0]:.4f} / {r['holdout_angle_nrmse'][1]:.4f} | "
                      f"{r['fit_s']:.0f} | {'/'.join(r['dtypes'])} |", flush=True)
            figures["tradeoff"] = rowsout
    figures["load_average_1min"] = os.getloadavg()[0]
    figures["doe_7000_s"] = _doe_seconds()
    figures["doe_7000_s_source"] = "elapsed_s of the bundled physics DOE (bending model, 2 cores)"
    write_result("metamodel", figures)


def _doe_seconds() -> float:
    """Wall time of the paper-scale DOE over the physics model on 2 cores, from the runner's
    record in the bundled dataset (``formtwin doe run`` writes it as ``elapsed_s``)."""
    import h5py

    from formtwin.defaults import bundled_doe

    with h5py.File(bundled_doe("bending"), "r") as f:
        return round(float(f.attrs["elapsed_s"]), 1)


if __name__ == "__main__":
    main()
