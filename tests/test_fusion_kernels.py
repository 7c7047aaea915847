"""The fusion's kernels (formtwin.tracker._fusion_kernels) against the NumPy operations they
replace: the reweighting by a Normal likelihood bit for bit (NumPy's exp and log stay with
the caller), the weighted moments of the final angles to rounding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from formtwin.filters.lagged import reweight
from formtwin.tracker._fusion_kernels import normal_reweight, weighted_moments

_LOG_SQRT_2PI = np.log(np.sqrt(2 * np.pi))


def _numpy_reweight(logw: np.ndarray, pred: np.ndarray, value: float, sd: float
                    ) -> tuple[np.ndarray, float]:
    """What SensorFusion._reweight did with NumPy: norm.logpdf's operations, then
    formtwin.filters.lagged.reweight."""
    z = (value - pred) / sd
    ll = -z**2 / 2.0 - _LOG_SQRT_2PI - np.log(np.float64(sd))
    return reweight(logw, ll)


def _kernel_reweight(logw: np.ndarray, pred: np.ndarray, value: float, sd: float
                     ) -> tuple[np.ndarray, float]:
    new, top, finite = normal_reweight(logw, pred, value, sd, _LOG_SQRT_2PI,
                                       np.log(np.float64(sd)))
    assert finite
    lse = top + math.log(float(np.sum(np.exp(new - top))))
    return new - lse, lse


@pytest.mark.parametrize("seed", range(6))
def test_normal_reweight_is_the_numpy_path_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 500
    logw = rng.normal(0.0, 3.0, n)
    logw -= np.log(np.sum(np.exp(logw)))
    logw[rng.integers(0, n, 20)] = -np.inf  # particles already without weight
    pred = 88.0 + rng.normal(0.0, 0.4, n)
    pred[rng.integers(0, n, 5)] = np.nan  # a model evaluation without a number
    pred[rng.integers(0, n, 3)] = np.inf
    column = np.column_stack([pred, pred + 1.0])[:, 0]  # a strided view, as a kept column
    for p in (pred, column):
        for value, sd in ((88.1, 0.05), (87.0, 0.3), (88.0, 1e-3)):
            got, lse = _kernel_reweight(logw, p, value, sd)
            want, lse_np = _numpy_reweight(logw, p, value, sd)
            assert got.tobytes() == want.tobytes() and lse == lse_np


def test_normal_reweight_without_a_finite_likelihood() -> None:
    logw = np.full(4, -np.log(4.0))
    _, _, finite = normal_reweight(logw, np.full(4, np.nan), 1.0, 0.1, _LOG_SQRT_2PI,
                                   np.log(0.1))
    assert not finite
    with pytest.raises(ValueError, match="finite likelihood"):
        _numpy_reweight(logw, np.full(4, np.nan), 1.0, 0.1)


@pytest.mark.parametrize("seed", range(4))
def test_weighted_moments_are_numpys_to_rounding(seed: int) -> None:
    rng = np.random.default_rng(seed)
    logw = rng.normal(0.0, 2.0 + seed, 500)
    logw[:7] = -np.inf
    a = 88.0 + rng.normal(0.0, 0.3, 500)
    w = np.exp(logw - np.max(logw))
    w /= w.sum()
    mean = float(w @ a)
    var = float(w @ (a - mean) ** 2)
    got = weighted_moments(logw, np.column_stack([a, a])[:, 1])
    eps = np.finfo(float).eps
    assert got[0] == pytest.approx(mean, rel=50 * eps)
    # the variance's terms are differences of ~88 deg near each other: their rounding is
    # eps * 88^2 / var relative to it
    assert got[1] == pytest.approx(var, rel=500 * eps * 88.0**2 / var)
    assert all(math.isnan(v) for v in weighted_moments(np.array([0.0, np.nan]), a[:2]))


def test_load_kernels_compiles_the_tracker_s_argument_types() -> None:
    """:func:`load_kernels` (a service's start) compiles the kernels for contiguous and
    strided (a kept column) arrays: the calls of a fusion add no signature."""
    from formtwin.tracker import _fusion_kernels as k

    k.load_kernels()
    kernels = (k.normal_reweight, k.weighted_moments, k.mixture_forecast,
               k.discrepancy_update)
    before = [list(f.signatures) for f in kernels]
    logw = np.full(8, -np.log(8.0))
    kept = np.zeros((8, 3))[:, 1]
    normal_reweight(logw, kept, 0.0, 1.0, _LOG_SQRT_2PI, 0.0)
    normal_reweight(logw, kept + 1.0, 0.0, 1.0, _LOG_SQRT_2PI, 0.0)
    weighted_moments(logw, kept)
    assert [list(f.signatures) for f in kernels] == before
