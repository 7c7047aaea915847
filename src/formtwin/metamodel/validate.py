"""k-fold validation of the metamodel and its plots.

Error measures (all on runs the metamodel did not see):

* ``curve_rel_err``: pooled relative L2 error of the curves,
  ``sqrt(sum_i |f^_i - f_i|^2 / sum_i |f_i|^2)``;
* ``curve_var_rel_err``: the same relative to the curves' variation about their mean,
  ``sqrt(sum_i |f^_i - f_i|^2 / sum_i |f_i - f_mean|^2)`` (the share of the variation
  not explained; a model that predicts the mean curve scores 1);
* ``angle_rmse_deg``: RMSE of each angle, degrees, and ``angle_nrmse`` the same divided
  by the angle's standard deviation over the runs (predicting the mean scores 1);
* the worst runs: their row numbers (in the successful rows of the dataset) and errors.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.figures import pyplot
from formtwin.metamodel.model import Metamodel
from formtwin.metamodel.protocols import Dataset
from formtwin.metamodel.residuals import ResidualModel
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Rows:
    """A subset of a dataset's rows (a :class:`Dataset`)."""

    spec: ProcessSpec
    spec_text: str
    inputs: FloatArray
    curves: FloatArray
    angles: FloatArray
    ok: BoolArray
    model_version: str


@dataclass(frozen=True)
class CrossValidation:
    """Out-of-fold predictions for the successful runs of a dataset.

    Attributes
    ----------
    spec : ProcessSpec
    inputs : ndarray, shape (n, 10)
    curves, predicted_curves : ndarray, shape (n, n_t)
        True and predicted force curves, N.
    angles, predicted_angles : ndarray, shape (n, 2)
        True and predicted angles, degrees.
    fold : ndarray of int, shape (n,)
        Fold in which each run was held out.
    fit_seconds : float
        Mean fit time per fold, s.
    """

    spec: ProcessSpec
    inputs: FloatArray
    curves: FloatArray
    predicted_curves: FloatArray
    angles: FloatArray
    predicted_angles: FloatArray
    fold: NDArray[np.int64]
    fit_seconds: float


def curve_errors(predicted: FloatArray, true: FloatArray, mean: FloatArray) -> dict[str, Any]:
    """Relative L2 errors of curves ``predicted`` vs ``true`` (n, n_t); ``mean`` (n_t,)."""
    sq = np.sum((predicted - true) ** 2, axis=1)
    per_run = np.sqrt(sq / np.maximum(np.sum(true**2, axis=1), 1e-300))
    return {"curve_rel_err": float(np.sqrt(sq.sum() / np.sum(true**2))),
            "curve_var_rel_err": float(np.sqrt(sq.sum() / np.sum((true - mean) ** 2))),
            "curve_rel_err_median": float(np.median(per_run)),
            "curve_rel_err_max": float(per_run.max()),
            "worst_curve_runs": [int(i) for i in np.argsort(per_run)[::-1][:3]]}


def angle_errors(predicted: FloatArray, true: FloatArray) -> dict[str, Any]:
    """RMSE (degrees), normalised RMSE and worst runs of angles (n, 2)."""
    err = predicted - true
    rmse = np.sqrt(np.mean(err**2, axis=0))
    return {"angle_rmse_deg": [float(v) for v in rmse],
            "angle_nrmse": [float(v) for v in rmse / true.std(axis=0)],
            "angle_max_abs_err_deg": [float(v) for v in np.abs(err).max(axis=0)],
            "worst_angle_runs": [int(i) for i in np.argsort(np.abs(err).max(axis=1))[::-1][:3]]}


def cross_validate(model: Metamodel | Callable[[], Metamodel], dataset: Dataset, k: int = 5,
                   seed: int = 0) -> CrossValidation:
    """Fit on k-1 folds, predict the k-th, for every fold of the successful runs.

    Parameters
    ----------
    model : Metamodel or callable returning an unfitted Metamodel
        A metamodel (its reduction and approximation settings are copied; it is not
        changed) or a factory.
    dataset : Dataset
        The DOE dataset; only its ``ok`` rows are used.
    k : int
        Number of folds, at least 2.
    seed : int
        Seed of the random assignment of runs to folds.
    """
    if k < 2:
        raise ValueError(f"validate: k = {k}, expected at least 2 folds")
    ok = np.asarray(dataset.ok, dtype=bool)
    X = np.asarray(dataset.inputs, dtype=np.float64)[ok]
    curves = np.asarray(dataset.curves, dtype=np.float64)[ok]
    angles = np.asarray(dataset.angles, dtype=np.float64)[ok]
    n = X.shape[0]
    if n < 2 * k:
        raise ValueError(f"validate: {n} successful runs is too few for k = {k} folds")
    fold = np.random.default_rng(seed).permutation(n) % k

    def fresh() -> Metamodel:
        if isinstance(model, Metamodel):
            return Metamodel(copy.deepcopy(model.reduction), copy.deepcopy(model.approximation),
                             copy.deepcopy(model.angle_approximation))
        return model()

    pc, pa = np.empty_like(curves), np.empty_like(angles)
    seconds = []
    for j in range(k):
        train, test = fold != j, fold == j
        rows = _Rows(dataset.spec, dataset.spec_text, X[train], curves[train], angles[train],
                     np.ones(int(train.sum()), dtype=bool), dataset.model_version)
        mm = fresh().fit(rows)
        seconds.append(mm.fit_seconds)
        p = mm.predict(X[test])
        pc[test], pa[test] = p.curves, p.angles
        log.info("validate: fold %d of %d done (%.1f s fit)", j + 1, k, mm.fit_seconds)
    return CrossValidation(dataset.spec, X, curves, pc, angles, pa, fold.astype(np.int64),
                           float(np.mean(seconds)))


#: half-width of the line's region in state sigmas (:func:`residual_model`)
LINE_SIGMAS = 2.0


def residual_rule(interior: bool = True, line: bool = True) -> str:
    """The name of :func:`residual_model`'s choice of runs, stored with its statistics."""
    return ", ".join(["interior"] * interior + [f"line {LINE_SIGMAS:g} sigma"] * line) or "all"


#: the rule of :func:`calibrate`'s default: a metamodel whose statistics have another is
#: recalibrated by the loaders of the bundled one (:mod:`formtwin.defaults`)
RESIDUAL_RULE = residual_rule()


def residual_model(cv: CrossValidation, interior: bool = True, line: bool = True
                   ) -> ResidualModel:
    """Statistics of the held-out residuals (truth minus prediction) of a cross-validation.

    ``interior``: only runs strictly inside the design box (no input on a bound). The
    paper's design puts 2^d runs on the corners of the box; held out, each is predicted by
    extrapolation, with errors far above those inside the box where a tracker works
    (about mu, a few sigma wide). ``line``: of those, only the runs whose every state lies
    within :data:`LINE_SIGMAS` sigma of the range of its statistics mu
    (``[mu_min - 2 sigma, mu_max + 2 sigma]``), where a line's products are: the box's
    edges (e.g. a punch pinching the flap at the smallest punch end distances) hold a
    large share of the runs and of the error but few products. Each step falls back to the
    rows before it if fewer than ``2 n_t`` remain. The result's ``rows`` names the rule
    asked for (:func:`residual_rule`), its ``n`` the runs used.
    """
    rows = np.ones(cv.inputs.shape[0], dtype=bool)
    n_min = 2 * cv.curves.shape[1]
    if interior:
        lo, hi = cv.spec.run_inputs.lo, cv.spec.run_inputs.hi
        tol = 1e-9 * (hi - lo)
        inside = np.all((cv.inputs > lo + tol) & (cv.inputs < hi - tol), axis=1)
        if inside.sum() >= n_min:
            rows = inside
    if line:
        st = cv.spec.state
        x = cv.inputs[:, :len(st.names)]
        near = rows & np.all((x >= st.mu_min - LINE_SIGMAS * st.sigma)
                             & (x <= st.mu_max + LINE_SIGMAS * st.sigma), axis=1)
        if near.sum() >= n_min:
            rows = near
    return ResidualModel.from_residuals(cv.curves[rows] - cv.predicted_curves[rows],
                                        cv.angles[rows] - cv.predicted_angles[rows],
                                        k=int(cv.fold.max() + 1),
                                        rows=residual_rule(interior, line))


def calibrate(metamodel: Metamodel, dataset: Dataset, k: int = 5, seed: int = 0,
              interior: bool = True, line: bool = True) -> Metamodel:
    """Attach the statistics of k-fold held-out residuals to a fitted ``metamodel``.

    The folds are fitted with ``metamodel``'s settings on ``dataset`` (the one it was
    fitted to); the statistics (of the runs inside the box where a line's products are, see
    :func:`residual_model`) go to ``metamodel.residuals`` (saved with it). Costs ``k`` fits.
    Returns ``metamodel``.
    """
    if metamodel.curve_model is None:
        raise RuntimeError("calibrate: the metamodel is not fitted")
    metamodel.residuals = residual_model(cross_validate(metamodel, dataset, k, seed),
                                         interior, line)
    log.info("calibrate: %d-fold residuals of %d runs, curve rms %.3g N", k,
             metamodel.residuals.n, float(np.sqrt(np.trace(metamodel.residuals.curve_cov)
                                                  / metamodel.residuals.n_t)))
    return metamodel


def figures(cv: CrossValidation) -> dict[str, Any]:
    """The error figures of a cross-validation (see the module docstring)."""
    out: dict[str, Any] = {"n_runs": int(cv.inputs.shape[0]), "k": int(cv.fold.max() + 1),
                           "fit_s": cv.fit_seconds}
    out.update(curve_errors(cv.predicted_curves, cv.curves, cv.curves.mean(axis=0)))
    out.update(angle_errors(cv.predicted_angles, cv.angles))
    return out


def validate(model: Metamodel | Callable[[], Metamodel], dataset: Dataset, k: int = 5,
             seed: int = 0) -> dict[str, Any]:
    """k-fold validation figures of a metamodel on a dataset (see :func:`cross_validate`)."""
    return figures(cross_validate(model, dataset, k, seed))


def plot_validation(cv: CrossValidation, directory: str | Path, n_worst: int = 3) -> list[Path]:
    """Write ``angles.png`` (predicted vs actual) and ``worst_curves.png`` to ``directory``.

    Needs matplotlib (extra ``plot``). Returns the paths written.
    """
    plt = pyplot()

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    ang = angle_errors(cv.predicted_angles, cv.angles)
    outputs = cv.spec.outputs
    fig, axes = plt.subplots(1, max(len(outputs), 1), figsize=(4.5 * max(len(outputs), 1), 4.2),
                             layout="constrained", squeeze=False)
    for j, (ax, o) in enumerate(zip(axes[0], outputs, strict=False)):
        t, p = cv.angles[:, j], cv.predicted_angles[:, j]
        ax.plot(t, p, ".", ms=2, alpha=0.5)
        lim = [min(t.min(), p.min()), max(t.max(), p.max())]
        ax.plot(lim, lim, "k-", lw=0.8)
        ax.set(xlabel=f"actual, {o.unit}", ylabel=f"predicted, {o.unit}",
               title=f"{o.label}: RMSE {ang['angle_rmse_deg'][j]:.3g} {o.unit}, "
                     f"nRMSE {ang['angle_nrmse'][j]:.3g}")
    paths = [out / "angles.png"]
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)

    worst = curve_errors(cv.predicted_curves, cv.curves, cv.curves.mean(axis=0))
    runs = np.argsort(np.sum((cv.predicted_curves - cv.curves) ** 2, axis=1)
                      / np.sum(cv.curves**2, axis=1))[::-1][:n_worst]
    fig, axes = plt.subplots(1, len(runs), figsize=(4 * len(runs), 3.6), layout="constrained",
                             squeeze=False)
    t_ms = cv.spec.time / cv.spec.axis_scale
    for ax, i in zip(axes[0], runs, strict=True):
        ax.plot(t_ms, cv.curves[i], "k-", lw=1.2, label="truth")
        ax.plot(t_ms, cv.predicted_curves[i], "C3--", lw=1.2, label="metamodel")
        rel = np.linalg.norm(cv.predicted_curves[i] - cv.curves[i]) / np.linalg.norm(cv.curves[i])
        ax.set(xlabel=f"{cv.spec.axis}, {cv.spec.axis_unit}", ylabel="punch force, N",
               title=f"run {i}: rel. L2 {rel:.3g}")
        ax.legend(fontsize=8)
    fig.suptitle(f"worst held-out curves (pooled rel. L2 error {worst['curve_rel_err']:.3g})")
    paths.append(out / "worst_curves.png")
    fig.savefig(paths[1], dpi=120)
    plt.close(fig)
    return paths
