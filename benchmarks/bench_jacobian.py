"""The sandwich interval's Jacobian: closed form against forward differences.

Run ``python benchmarks/bench_jacobian.py [--products 300]``. On the bundled physics
metamodel and ``bench_filter.py``'s series-3-like data (three seeds, N = 500, one BLAS
thread), the tracker's linearisation at the cloud's mean after ``--products`` products
(``Sandwich._refresh``'s Jacobian of the compared curve, (n_t, 18), and the angles'
gradient, (2, 10)):

* ``jacobian_fd32_error_*``: forward differences of the metamodel's float32 evaluation with
  the sandwich's steps (0.1 sigma, 0.1 of the cloud's spread), as the tracker computed them
  before it used the closed form, against the closed form; per column, max abs error over
  the column's max abs value; median and max over the columns of ``[x, theta]`` and of
  ``theta_d`` (there both are differences of ``g``, but the forward differences' rows
  of equal inputs are evaluated at different places of one float32 batch, which
  rounds them differently: up to 0.04 N of a 260 N curve);
* ``jacobian_fd64_error_max``: the same differences of the float64 evaluation in ``[x,
  theta]`` (no rounding of the curves): what the step size alone costs;
* ``std_change_*``: the reported std of the default tracker (``intervals =
  "calibrated_fit"``, mu assumed) and of ``intervals = "cloud_mu"`` (the mu term alone
  on the cloud) with the closed form against forward differences, the same particles:
  ``|new - old| / old`` over products and the 18 variables (median, 90th percentile),
  and the largest change of a variable's run mean; ``std_ratio_runmean_*`` the range of
  new / old of the run means.

Writes ``benchmarks/results/bench_jacobian.json``.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from bench_filter import make_data

from formtwin._bench import bundled_metamodel, write_result
from formtwin._threads import single_blas_thread
from formtwin.measurement import MeasurementModel
from formtwin.tracker import Tracker, TrackerConfig


class WithoutDerivatives:
    """The metamodel, not ``differentiable``: the sandwich then takes forward differences
    of its evaluation (as before the closed form)."""

    differentiable = False

    def __init__(self, model: Any) -> None:
        self._model = model

    def __getattr__(self, name: str) -> Any:
        return getattr(self._model, name)


def column_errors(J: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per column: max |J - ref| over max |ref|."""
    out: np.ndarray = np.abs(J - ref).max(axis=0) / np.abs(ref).max(axis=0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--products", type=int, default=300)
    args = ap.parse_args()
    model, _, info = bundled_metamodel()
    plain = WithoutDerivatives(model)
    fig: dict[str, Any] = {}
    err32, err64, err_td, std = [], [], [], {}
    curve_model = model.curve_model
    assert curve_model is not None
    f32 = curve_model.predict

    def f64(U: np.ndarray) -> np.ndarray:
        """The curve RBF evaluated in float64."""
        out: np.ndarray = curve_model._evaluate(np.asarray(U, dtype=np.float64),
                                                np.dtype(np.float64))
        return out

    for seed in (2024, 7, 99):
        with single_blas_thread():
            data = make_data(model, args.products, seed=seed)
            mm = MeasurementModel.from_monte_carlo(model, mu=data["mu"], n=10_000,
                                                   rng=np.random.default_rng(7))
            for intervals in ("calibrated_fit", "cloud_mu"):
                cfg = TrackerConfig(n_particles=500, mu=tuple(data["mu"]), seed=3,
                                    intervals=intervals)
                new, old = Tracker(model, mm, cfg), Tracker(plain, mm, cfg)  # type: ignore[arg-type]
                e_new, e_old = new.run(data["curves"]), old.run(data["curves"])
                assert np.array_equal(e_new.mean, e_old.mean)  # the same particles
                rel = np.abs(e_new.std[:, :18] - e_old.std[:, :18]) / e_old.std[:, :18]
                run = e_new.std[:, :18].mean(axis=0) / e_old.std[:, :18].mean(axis=0)
                std.setdefault(intervals, []).append((rel, run))
            # the linearisation at the last product's cloud, three ways
            s, ssm = new.filter, new.ssm
            x, w = s.x, np.full(s.n, 1.0 / s.n)
            mean = w @ x
            spread = x[:, ssm.n_x:ssm.n_varying].std(axis=0)
            y = data["curves"][-1]
            exact, _ = ssm._cloud_jacobian(mean, spread, y, exact=True)
            fd32, step = ssm._cloud_jacobian(mean, spread, y)
            curve_model.predict = f64  # type: ignore[method-assign]
            try:
                fd64 = ssm._jacobian(mean, step, y)
            finally:
                curve_model.predict = f32  # type: ignore[method-assign]
            n_in = ssm.n_in
            err32.append(column_errors(fd32, exact)[:n_in])
            err_td.append(column_errors(fd32, exact)[n_in:])
            err64.append(column_errors(fd64, exact)[:n_in])
    e32, etd = np.concatenate(err32), np.concatenate(err_td)
    fig["jacobian_fd32_error_x_theta_median"] = round(float(np.median(e32)), 4)
    fig["jacobian_fd32_error_x_theta_max"] = round(float(e32.max()), 4)
    fig["jacobian_fd32_error_theta_d_median"] = round(float(np.median(etd)), 4)
    fig["jacobian_fd32_error_theta_d_max"] = round(float(etd.max()), 4)
    fig["jacobian_fd64_error_max"] = round(float(np.concatenate(err64).max()), 5)
    for intervals, rows in std.items():
        rel = np.concatenate([r for r, _ in rows])
        run = np.concatenate([r for _, r in rows])
        tag = "default" if intervals == "calibrated_fit" else intervals
        fig[f"std_change_{tag}_median"] = round(float(np.median(rel)), 4)
        fig[f"std_change_{tag}_p90"] = round(float(np.percentile(rel, 90)), 4)
        fig[f"std_change_{tag}_runmean_max"] = round(float(np.abs(run - 1.0).max()), 4)
        fig[f"std_ratio_runmean_{tag}"] = [round(float(run.min()), 3), round(float(run.max()), 3)]
    write_result("jacobian", fig, model=info)


if __name__ == "__main__":
    main()
