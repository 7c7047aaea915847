"""Generic particle filters: resampling schemes, Kalman agreement, collapse handling."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from formtwin.filters import (
    FILTERS,
    RESAMPLERS,
    SIR,
    ResampleMoveSIR,
    get_filter,
    get_resampler,
    make_filter,
)


@pytest.mark.parametrize("name", sorted(RESAMPLERS))
def test_resamplers_are_unbiased(name: str) -> None:
    rng = np.random.default_rng(0)
    w = rng.random(50) ** 3
    w[[3, 7]] = 0.0
    w /= w.sum()
    scheme = get_resampler(name)
    counts = np.zeros(50)
    reps = 2000
    for _ in range(reps):
        idx = scheme(w, rng, 50)
        assert idx.shape == (50,) and idx.dtype == np.intp
        assert idx.min() >= 0 and idx.max() < 50
        counts += np.bincount(idx, minlength=50)
    assert counts[3] == counts[7] == 0  # zero weight: never drawn
    # E[count_k] = N w_k; multinomial variance bounds the others
    se = np.sqrt(50 * w * (1 - w) / reps)
    assert np.all(np.abs(counts / reps - 50 * w) < 5 * se + 1e-9)


def test_low_variance_schemes_keep_the_integer_part() -> None:
    w = np.array([0.52, 0.27, 0.21])
    for name in ("systematic", "residual"):
        c = np.bincount(get_resampler(name)(w, np.random.default_rng(1), 10), minlength=3)
        assert np.all(c >= np.floor(10 * w)) and c.sum() == 10


def test_unknown_names_list_the_known_ones_and_callables_pass() -> None:
    with pytest.raises(ValueError, match="known: multinomial, residual, stratified, systematic"):
        get_resampler("bogus")
    with pytest.raises(ValueError, match="known: guided, guided_lin, move, regularised, sir"):
        get_filter("bogus")
    first = lambda w, rng, m: np.zeros(m, dtype=np.intp)  # noqa: E731
    assert get_resampler(first) is first
    assert FILTERS["sir"] is SIR and get_filter(SIR) is SIR


class LinearGaussian:
    """x_t = A x_{t-1} + v, v ~ N(0, Q);  y_t = H x_t + w, w ~ N(0, R);  x_0 ~ N(m0, P0)."""

    def __init__(self) -> None:
        self.A = np.array([[0.9, 0.2], [0.0, 0.7]])
        self.Q = np.array([[0.3, 0.05], [0.05, 0.2]])
        self.H = np.array([[1.0, 0.5]])
        self.R = np.array([[0.4]])
        self.m0 = np.array([1.0, -1.0])
        self.P0 = np.eye(2)
        self.lq = np.linalg.cholesky(self.Q)

    def sample_initial(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return self.m0 + rng.standard_normal((n, 2)) @ np.linalg.cholesky(self.P0).T

    def sample_transition(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return x @ self.A.T + rng.standard_normal(x.shape) @ self.lq.T

    def loglik(self, x: np.ndarray, y: Any) -> np.ndarray:
        r = float(self.R[0, 0])
        return -0.5 * ((y - x @ self.H[0]) ** 2 / r + math.log(2 * math.pi * r))

    def kalman(self, ys: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray], list[float]]:
        """Filtering means, covariances and log predictive likelihoods. The filter's first
        step propagates x_0, so the first prediction is A m0."""
        m, p = self.m0, self.P0
        means, covs, lls = [], [], []
        for y in ys:
            m, p = self.A @ m, self.A @ p @ self.A.T + self.Q
            s = self.H @ p @ self.H.T + self.R
            k = p @ self.H.T / s
            innov = y - float((self.H @ m)[0])
            sv = float(s[0, 0])
            lls.append(-0.5 * (innov**2 / sv + math.log(2 * math.pi * sv)))
            m = m + (k * innov).ravel()
            p = p - k @ self.H @ p
            means.append(m)
            covs.append(p)
        return means, covs, lls


def simulate_lg(model: LinearGaussian, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = model.sample_initial(1, rng)
    ys = []
    for _ in range(n):
        x = model.sample_transition(x, rng)
        ys.append(float((x @ model.H[0])[0]) + math.sqrt(model.R[0, 0]) * rng.standard_normal())
    return np.array(ys)


@pytest.mark.parametrize("scheme,threshold", [("systematic", 1.0), ("residual", 0.5)])
def test_sir_matches_the_kalman_filter(scheme: str, threshold: float) -> None:
    model = LinearGaussian()
    ys = simulate_lg(model, 25, seed=5)
    means, covs, lls = model.kalman(ys)
    n = 20_000
    f = SIR(model, n, np.random.default_rng(6), resampling=scheme, ess_threshold=threshold)
    for t, y in enumerate(ys):
        s = f.step(y)
        assert s.ess > 0.05 * n
        var = np.diag(covs[t])
        # Monte-Carlo error of a weighted mean ~ sqrt(var / ESS); allow 6 of them (observed
        # up to 3.3 over these 25 steps; a filter ignoring the weights is off by > 100)
        tol = 6 * np.sqrt(var / s.ess)
        np.testing.assert_array_less(np.abs(s.mean() - means[t]), tol)
        # sample variance: relative error ~ sqrt(2 / ESS)
        np.testing.assert_allclose(s.std() ** 2, var, rtol=6 * math.sqrt(2 / s.ess))
        assert abs(s.loglik - lls[t]) < 0.05
    assert f.t == 25


def test_collapse_keeps_the_predictive_and_never_gives_nan() -> None:
    class Picky(LinearGaussian):
        def loglik(self, x: np.ndarray, y: Any) -> np.ndarray:
            if y is None:  # a curve no particle can explain
                return np.full(x.shape[0], -np.inf)
            if y == "nan":
                return np.full(x.shape[0], np.nan)
            return super().loglik(x, y)

    f = make_filter("sir", Picky(), 500, np.random.default_rng(0))
    f.step(0.5)
    for bad in (None, "nan"):
        s = f.step(bad)
        assert s.collapsed and s.loglik == -np.inf
        assert np.all(np.isfinite(s.w)) and s.w.sum() == pytest.approx(1.0)
        np.testing.assert_allclose(s.w, 1 / 500)  # uniform: the predictive sample
        assert np.all(np.isfinite(s.mean())) and np.all(np.isfinite(s.std()))
        assert s.ess == pytest.approx(500)
    s = f.step(0.3)
    assert not s.collapsed and np.isfinite(s.loglik)


def test_some_nan_logliks_get_zero_weight() -> None:
    class Half(LinearGaussian):
        def loglik(self, x: np.ndarray, y: Any) -> np.ndarray:
            ll = super().loglik(x, y)
            ll[::2] = np.nan
            return ll

    s = SIR(Half(), 100, np.random.default_rng(0)).step(0.0)
    assert np.all(s.w[::2] == 0.0) and s.w.sum() == pytest.approx(1.0) and not s.collapsed


def test_far_outlier_does_not_underflow() -> None:
    # log-likelihoods around -1e6: plain weights would all underflow to 0
    s = SIR(LinearGaussian(), 1000, np.random.default_rng(0)).step(1e3)
    assert not s.collapsed and np.all(np.isfinite(s.w)) and s.loglik < -1e5


def test_adaptive_resampling_skips_when_ess_is_high() -> None:
    f = SIR(LinearGaussian(), 1000, np.random.default_rng(0), ess_threshold=0.01)
    s = f.step(0.0)
    assert not s.resampled and not np.allclose(f.logw, f.logw[0])


def test_regularised_filter_keeps_the_kalman_moments_and_constrains() -> None:
    model = LinearGaussian()
    ys = simulate_lg(model, 15, seed=8)
    means, covs, _ = model.kalman(ys)
    f = make_filter("regularised", model, 20_000, np.random.default_rng(9))
    for t, y in enumerate(ys):
        s = f.step(y)
        var = np.diag(covs[t])
        np.testing.assert_array_less(np.abs(s.mean() - means[t]), 6 * np.sqrt(var / s.ess))
        np.testing.assert_allclose(s.std() ** 2, var, rtol=6 * math.sqrt(2 / s.ess))
    # the move keeps the cloud's moments: resampled-and-moved particles vs the weighted ones
    assert f.x is not None
    np.testing.assert_allclose(f.x.mean(axis=0), s.mean(), atol=0.03)
    np.testing.assert_allclose(f.x.std(axis=0), s.std(), rtol=0.03)

    class Boxed(LinearGaussian):
        def constrain(self, x: np.ndarray) -> np.ndarray:
            return np.clip(x, -0.5, 0.5)

    g = make_filter("regularised", Boxed(), 500, np.random.default_rng(0))
    g.step(0.0)
    assert g.x is not None and np.all(np.abs(g.x) <= 0.5)
    with pytest.raises(ValueError, match="bandwidth"):
        make_filter("regularised", model, 10, np.random.default_rng(0), bandwidth=1.5)


class MovableLinearGaussian(LinearGaussian):
    """:class:`LinearGaussian` with the hooks of the resample-move filter."""

    move_mask = np.array([True, True])

    def log_transition(self, parents: np.ndarray, x: np.ndarray) -> np.ndarray:
        d = x - parents @ self.A.T
        return -0.5 * np.sum(d * np.linalg.solve(self.Q, d.T).T, axis=1)

    def loglik_fixed(self, x: np.ndarray, y: Any) -> np.ndarray:
        return self.loglik(x, y)

    def in_bounds(self, x: np.ndarray) -> np.ndarray:
        return np.ones(x.shape[0], dtype=bool)


@pytest.mark.parametrize("bandwidth", [0.5, 1.5])
def test_resample_move_leaves_the_kalman_posterior_invariant(bandwidth: float) -> None:
    """The Metropolis-Hastings move after resampling (parents fixed) moves most particles
    and keeps the filter on the exact (Kalman) posterior; a move that left out the
    transition density in its ratio would widen it (checked: the last assertion fails)."""
    model = MovableLinearGaussian()
    ys = simulate_lg(model, 25, seed=5)
    means, covs, _ = model.kalman(ys)
    n = 20_000
    f = ResampleMoveSIR(model, n, np.random.default_rng(7), bandwidth=bandwidth, n_moves=2)
    for t, y in enumerate(ys):
        s = f.step(y)
        assert f.acceptance > 0.2
        if t == 0:
            continue
        # the particles after the move at t-1, propagated, are the predictive at t: their
        # weighted cloud is the posterior at t (same tolerances as for SIR)
        var = np.diag(covs[t])
        # (errors observed up to 6.1 sqrt(var / ESS) in the mean, 8 % in the variance; with
        # the transition left out of the ratio the variance is up to 50 % too large)
        np.testing.assert_array_less(np.abs(s.mean() - means[t]), 8 * np.sqrt(var / s.ess))
        np.testing.assert_allclose(s.std() ** 2, var, rtol=6 * math.sqrt(2 / s.ess))
    # the moved, equally weighted particles are the posterior at the last step as well
    # (variance 2 % off observed; 40-110 % too large without the transition density)
    assert f.x is not None
    sd = np.sqrt(np.diag(covs[-1]))
    np.testing.assert_array_less(np.abs(f.x.mean(axis=0) - means[-1]), 0.05 * sd)
    np.testing.assert_allclose(f.x.var(axis=0), sd**2, rtol=0.1)


def test_resample_move_needs_the_models_hooks() -> None:
    with pytest.raises(ValueError, match="log_transition"):
        ResampleMoveSIR(LinearGaussian(), 10, np.random.default_rng(0))
    with pytest.raises(ValueError, match="bandwidth"):
        ResampleMoveSIR(MovableLinearGaussian(), 10, np.random.default_rng(0), bandwidth=0)


def test_logsumexp_over_rows_is_the_generic_formula_bit_for_bit() -> None:
    """``logsumexp(a, axis=0)`` of a 2-D array takes a transposed path; its numbers are the
    generic max / exp / sum / log formula's exactly (NaN, -inf rows and columns included)."""
    from formtwin.filters import sir

    def generic(a: np.ndarray) -> np.ndarray:
        top = np.max(a, axis=0, keepdims=True)
        top = np.where(np.isfinite(top), top, 0.0)
        with np.errstate(divide="ignore"):
            out = np.log(np.sum(np.exp(a - top), axis=0, keepdims=True)) + top
        return np.squeeze(out, axis=0)

    rng = np.random.default_rng(11)
    for shape in [(500, 5), (1, 3), (7, 1), (1000, 13), (64, 64)]:
        for _ in range(20):
            a = rng.standard_normal(shape) * rng.uniform(0.1, 500.0)
            a[rng.random(shape) < 0.05] = -np.inf
            if rng.random() < 0.3:
                a[:, 0] = -np.inf
            if rng.random() < 0.2:
                a[rng.integers(shape[0]), -1] = np.nan
            with np.errstate(over="ignore", invalid="ignore"):  # NaN columns: max is NaN
                got, want = sir.logsumexp(a, axis=0), generic(a)
            assert got.shape == want.shape
            np.testing.assert_array_equal(got, want)
