"""Normalised RMSE of the study, as in the paper's Fig. 4.

RMSE per component over the last ``window`` products (500 in the paper) of a run,
normalised by ``sigma`` (state variables), by ``(max - min) / sqrt 6`` (constant and
deviation parameters: the RMSE a uniform random guess would make) and by the standard
deviation of the real angles in the same window (angles). A value above 1 means the
estimate is no better than the spread of the data, or than guessing.

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
