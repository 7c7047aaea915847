"""Normalised RMSE of the study, as in the paper's Fig. 4.

RMSE per component over the last ``window`` products (500 in the paper) of a run,
normalised by ``sigma`` (state variables), by ``(max - min) / sqrt 6`` (constant and
deviation parameters: the RMSE a uniform random guess would make) and by the standard
deviation of the real angles in the same window (angles). For a state variable, 1 is the
error of always answering the *true* mu; with mu unknown even the prior-only guess (the
assumed mu) scores above 1, so a value above 1 does not by itself mean "no better than
guessing". That is what the skill says:

* ``skill = 1 - RMSE / RMSE_prior`` per component, where ``RMSE_prior`` is the error of the
  prior-only estimate on the same data (no measurement: the assumed mu for the state, the
  middle of the bounds for theta and theta_d, the prior mean of the angle model for the
  angles). Above 0: the measurements helped; 1: perfect.
* ``coverage``: how often the truth lies in the 90 % interval ``mean +- 1.645 std`` (0.90
  for an honest Gaussian posterior; below: overconfident).

>>> import numpy as np
>>> float(rmse(np.array([[1.0], [3.0]]), np.array([[2.0], [2.0]]))[0])
1.0
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]


def rmse(estimate: FloatArray, truth: FloatArray) -> FloatArray:
    """Column-wise RMSE of ``(n, d)`` arrays, ignoring rows with NaN estimates -> ``(d,)``."""
    err = estimate - truth
    out: FloatArray = np.sqrt(np.nanmean(err**2, axis=0))
    return out


def normalisers(spec: ProcessSpec) -> FloatArray:
    """Scale of each augmented component ``(18,)``: sigma for x, range/sqrt 6 for the rest."""
    rest = spec.params + spec.deviation.group
    return np.concatenate([spec.state.sigma, (rest.hi - rest.lo) / np.sqrt(6.0)])


def normalised_rmse(spec: ProcessSpec, mean: FloatArray, truth: FloatArray,
                    angles_mean: FloatArray, angles_true: FloatArray,
                    window: int = 500) -> FloatArray:
    """Normalised RMSE ``(20,)``: the 18 augmented components, then the two angles.

    ``mean, truth`` are ``(n, 18)``; ``angles_mean, angles_true`` ``(n, 2)``; only the last
    ``window`` products count.
    """
    sl = slice(-window, None)
    state = rmse(mean[sl], truth[sl]) / normalisers(spec)
    angles_true_w = angles_true[sl]
    valid = np.all(np.isfinite(angles_mean[sl]), axis=1) & np.all(np.isfinite(angles_true_w),
                                                                   axis=1)
    angle = rmse(angles_mean[sl][valid], angles_true_w[valid]) / angles_true_w[valid].std(axis=0)
    return np.concatenate([state, angle])


#: half-width of the central 90 % interval of a Gaussian, in standard deviations
Z90 = 1.6448536269514722


def coverage(mean: FloatArray, std: FloatArray, truth: FloatArray, window: int = 500,
             z: float = Z90) -> FloatArray:
    """Share (d,) of the last ``window`` products whose truth lies in ``mean +- z std``
    (``(n, d)`` arrays; rows with NaN do not count; NaN where none is left)."""
    sl = slice(-window, None)
    m, s, t = mean[sl], std[sl], truth[sl]
    ok = np.isfinite(m) & np.isfinite(s) & np.isfinite(t)
    inside = (np.abs(t - m) <= z * s) & ok
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = inside.sum(axis=0) / ok.sum(axis=0)
    return out


def prior_estimate(spec: ProcessSpec, mu: FloatArray) -> FloatArray:
    """The prior-only estimate (18,) of the augmented state: the assumed ``mu`` (7,) for x,
    the middle of the bounds for theta and theta_d."""
    rest = spec.params + spec.deviation.group
    return np.concatenate([np.asarray(mu, dtype=np.float64), 0.5 * (rest.lo + rest.hi)])


def skill(spec: ProcessSpec, mean: FloatArray, truth: FloatArray, angles_mean: FloatArray,
          angles_true: FloatArray, mu: FloatArray, prior_angles: FloatArray,
          window: int = 500) -> FloatArray:
    """Skill ``1 - RMSE / RMSE_prior`` (20,): 18 augmented components, then the 2 angles.

    ``mu`` (7,) is the mean the filter assumed (or its prior mean when it learns mu);
    ``prior_angles`` (2,) the prior-only angle prediction.
    """
    n = truth.shape[0]
    ours = normalised_rmse(spec, mean, truth, angles_mean, angles_true, window)
    prior = normalised_rmse(spec, np.tile(prior_estimate(spec, mu), (n, 1)), truth,
                            np.tile(prior_angles, (n, 1)), angles_true, window)
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = 1.0 - ours / prior
    return out


def run_scores(spec: ProcessSpec, run: dict[str, FloatArray], truth: FloatArray,
               angles_true: FloatArray, mu: FloatArray, prior_angles: FloatArray,
               deviation: bool, window: int = 500) -> dict[str, FloatArray]:
    """Scores of one filter run (arrays of a run file: ``mean``, ``std`` (n, 18),
    ``angles_mean``, ``angles_std`` (n, 2), ``ess``, optionally ``loglik`` (n,)).

    Returns ``nrmse``, ``skill``, ``coverage`` (20,) (theta_d NaN when the run did not
    estimate it), ``ess`` (mean) and ``log_evidence`` (sum of the log-evidence increments
    over all products, NaN if the run has none).
    """
    nr = normalised_rmse(spec, run["mean"], truth, run["angles_mean"], angles_true, window)
    sk = skill(spec, run["mean"], truth, run["angles_mean"], angles_true, mu, prior_angles,
               window)
    cov = np.concatenate([coverage(run["mean"], run["std"], truth, window),
                          coverage(run["angles_mean"], run["angles_std"], angles_true,
                                   window)])
    if not deviation:
        dev = slice(len(spec.inputs), len(spec.augmented))
        for a in (nr, sk, cov):
            a[dev] = np.nan
    ll = run.get("loglik")
    return {"nrmse": nr, "skill": sk, "coverage": cov,
            "ess": np.asarray(np.nanmean(run["ess"])),
            "log_evidence": np.asarray(np.nansum(ll) if ll is not None else np.nan)}


def summarise(nrmse: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-dataset (mean over repetitions) and overall (mean over datasets) normalised RMSE.

    ``nrmse`` is ``(series, realisation, repetition, component)``; components a series
    does not estimate are NaN and stay NaN.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices stay NaN
        per_dataset: FloatArray = np.nanmean(nrmse, axis=2)
        overall: FloatArray = np.nanmean(per_dataset, axis=1)
    return per_dataset, overall
