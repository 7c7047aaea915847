"""The Numba kernels of the tracker's own terms (``formtwin.tracker._kernels``) against the
NumPy formulas they replace (written out here as the reference): the particle selection
and the share's evidence bit for bit; the fit's spread and the assumed mu's interval term
to tolerances from ``eps``, the sizes summed over and the solve's condition number."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg.blas import dsyrk

from formtwin.filters import logsumexp
from formtwin.tracker import _kernels as k
from formtwin.tracker.core import heaviest
from formtwin.tracker.sandwich import _gains, _next_G_mu

EPS = np.finfo(float).eps


def _heaviest_reference(w: np.ndarray, mass: float) -> np.ndarray:
    """The selection as NumPy computed it before the kernel."""
    light = np.flatnonzero(w <= mass)
    order = light[np.argsort(w[light], kind="stable")]
    n_drop = int(np.searchsorted(np.cumsum(w[order]), mass, side="right"))
    if n_drop == 0:
        return np.arange(w.size)
    keep = np.ones(w.size, dtype=bool)
    keep[order[:n_drop]] = False
    return np.flatnonzero(keep)


@pytest.mark.parametrize("concentration", [0.01, 0.05, 1.0, 100.0])
def test_heaviest_selects_exactly_what_numpy_selected(concentration: float) -> None:
    """Weights from a Dirichlet (ESS from ~1 to ~N), with ties and zeros: the same
    indices for several masses, and all particles when nothing can be dropped."""
    rng = np.random.default_rng(int(concentration * 100))
    for _ in range(20):
        w = rng.dirichlet(np.full(500, concentration))
        w[rng.integers(0, 500, 30)] = 0.0  # zeros and ties among the lightest
        w[rng.integers(0, 500, 20)] = w[rng.integers(0, 500)]
        w /= w.sum()
        for mass in (0.0, 1e-9, 1e-4, 0.3, 1.0):
            np.testing.assert_array_equal(heaviest(w, mass), _heaviest_reference(w, mass))
    np.testing.assert_array_equal(heaviest(np.full(7, 1 / 7), 1e-4), np.arange(7))


def test_share_evidence_columns_are_logsumexp_bit_for_bit() -> None:
    """``shifted_columns``, NumPy's ``exp``, ``row_sums`` and ``log`` give the column
    ``logsumexp`` of ``a[:, None] + grid`` bit for bit, with columns of ``-inf``, NaN
    and ``+inf`` handled as NumPy's max."""
    rng = np.random.default_rng(3)
    a = rng.normal(-6.0, 3.0, 500)
    a[:40] = -np.inf
    grid = rng.normal(-300.0, 40.0, (500, 5))
    grid[:, 1] = -np.inf
    grid[7, 2] = np.nan
    grid[9, 3] = np.inf
    t, top = k.shifted_columns(a, grid)
    with np.errstate(divide="ignore", invalid="ignore"):
        got = np.log(k.row_sums(np.exp(t, out=t))) + top
        want = logsumexp(a[:, None] + grid, axis=0)
    np.testing.assert_array_equal(got, want)
    assert np.isneginf(got[1]) and np.isnan(got[2])


def test_fit_spread_rows_are_the_centred_weighted_residuals() -> None:
    """The mean residual and the spread's rows from unnormalised weights against the
    NumPy formulas, to ``N eps`` of the residuals' scale, and their Gram matrix by
    ``dsyrk`` as ``assess`` calls it; a weight of 0 or a NaN row is flagged."""
    rng = np.random.default_rng(4)
    r = rng.normal(3.0, 2.0, (500, 101))
    v = rng.random(500) + 0.01
    w = v / v.sum()
    for stride in (1, 2, 3):
        r_bar, finite, rc = k.centred_spread(r, v, stride)
        want_bar = w @ r
        ws = w[::stride]
        want_rc = (r[::stride] - want_bar) * np.sqrt(ws / ws.sum())[:, None]
        assert finite and rc.shape == want_rc.shape
        tol = 500 * EPS * np.abs(r).max()
        np.testing.assert_allclose(r_bar, want_bar, rtol=0, atol=tol)
        np.testing.assert_allclose(rc, want_rc, rtol=0, atol=tol)
        np.testing.assert_allclose(dsyrk(1.0, rc.T, trans=0, lower=1),
                                   np.tril(want_rc.T @ want_rc), rtol=0,
                                   atol=4 * tol * np.abs(rc).max() * rc.shape[0])
    v[3] = 0.0  # a weight of 0: not the usual case either
    assert not k.centred_spread(r, v, 2)[1]
    v[3] = 1.0
    r[17, 5] = np.nan
    assert not k.centred_spread(r, v, 2)[1]


def _recursion_case(m: int = 18, nx: int = 7, n_t: int = 101, seed: int = 5
                    ) -> dict[str, np.ndarray]:
    """A cloud, a whitened Jacobian and the recursion's arrays with variances spanning
    six decades, as the tracker's state, theta and theta_d."""
    rng = np.random.default_rng(seed)
    scales = np.logspace(-3, 0, m)
    a = rng.standard_normal((m, m))
    x = rng.standard_normal((500, m + 3)) * np.r_[scales, np.ones(3)] + 1.0
    return {"x": x, "w": rng.dirichlet(np.full(500, 0.3)),
            "P_prev": scales[:, None] * (a @ a.T / m + np.eye(m)) * scales[None, :],
            "TJ": rng.standard_normal((n_t, m)) / scales, "v": rng.uniform(0.5, 3.0, n_t),
            "F": np.r_[rng.uniform(0.5, 0.95, nx), np.ones(m - nx)], "Q": (0.1 * scales) ** 2,
            "G_mu": rng.standard_normal((m, nx)), "half": rng.standard_normal((nx, nx + 1)),
            "Ja": rng.standard_normal((2, 10))}


def test_cloud_moments_and_information_are_the_numpy_products() -> None:
    """``cloud_moments`` gives every column's variance ``w @ (x - mean)^2`` (eq. 14's
    std squared) and the first ``m`` columns' covariance ``(dev w)^T dev``,
    ``information`` is ``TJ^T diag(1/v) TJ``, to ``n eps`` of the products' scale (n the
    rows summed over)."""
    c = _recursion_case()
    x, w, m = c["x"], c["w"], 18
    mean = w @ x
    var, P = k.cloud_moments(x, w, mean, m)
    np.testing.assert_allclose(var, w @ (x - mean) ** 2, rtol=500 * EPS)
    dev = x[:, :m] - mean[:m]
    want = (dev * w[:, None]).T @ dev
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
    assert np.all(np.isfinite(P))
    np.testing.assert_array_less(np.abs(P - want), 500 * EPS * scale + 1e-300)
    var0, P0 = k.cloud_moments(x, w, mean, 0)
    np.testing.assert_array_equal(var0, var)
    assert P0.shape == (0, 0)
    TJ, v = c["TJ"], c["v"]
    info = k.information(TJ, v)
    ref = TJ.T @ (TJ / v[:, None])
    scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref)))
    np.testing.assert_array_less(np.abs(info - ref), 101 * 4 * EPS * scale)
    x[3, 2] = np.inf
    assert not np.all(np.isfinite(k.cloud_moments(x, w, mean, m)[1]))  # the row carries in


def test_angle_moments_leave_out_rows_with_nan_or_inf() -> None:
    """The angles' weighted mean and std, the extra variance added to the std's square:
    as NumPy's formulas on the finite rows with their weights renormalised (to ``M eps``);
    NaN when no row is finite."""
    rng = np.random.default_rng(6)
    a = rng.normal([30.0, 5.0], [2.0, 0.5], (134, 2))
    w = rng.dirichlet(np.full(134, 0.5))
    extra = np.array([0.04, 0.01])
    a[[3, 50], [0, 1]] = np.nan, np.inf
    good = np.all(np.isfinite(a), axis=1)
    wg = w[good] / w[good].sum()
    want_mean = wg @ a[good]
    want_std = np.sqrt(wg @ (a[good] - want_mean) ** 2 + extra)
    mean, std = k.angle_moments(a, w, extra)
    np.testing.assert_allclose(mean, want_mean, rtol=134 * EPS)
    np.testing.assert_allclose(std, want_std, rtol=1e3 * 134 * EPS)
    none = k.angle_moments(np.full((3, 2), np.nan), np.full(3, 1 / 3), extra)
    assert np.isnan(none[0]).all() and np.isnan(none[1]).all()


def test_mu_gain_step_is_the_lapack_solve_of_the_recursion() -> None:
    """``mu_gain_step`` (elimination with partial pivoting) against ``_gains`` (LAPACK's
    ``dgesv`` of ``A`` for ``A^-1``) and ``_next_G_mu``: the same ``G_mu`` to a tolerance
    from ``A``'s condition number; the variances it adds as ``H = G_mu half``; a singular
    ``A`` is reported, not solved."""
    c = _recursion_case()
    P_prev, F, Q, G_mu = c["P_prev"], c["F"], c["Q"], c["G_mu"]
    info = c["TJ"].T @ (c["TJ"] / c["v"][:, None])
    nx = G_mu.shape[1]
    drive = np.eye(F.size, nx) * (1.0 - F[:nx])
    for _ in range(5):  # a few products of the recursion, each against the reference
        M, _ = _gains(P_prev, info, None, F, Q)
        want = _next_G_mu(M, F, G_mu, drive)
        got, ok = k.mu_gain_step(P_prev, info, F, Q, G_mu, drive)
        P_pred = F[:, None] * P_prev * F[None, :] + np.diag(Q)
        cond = np.linalg.cond(np.eye(F.size) + P_pred @ info)
        assert ok and cond > 10.0
        tol = 1e2 * cond * EPS * np.abs(want).max()
        np.testing.assert_allclose(got, want, rtol=0, atol=tol)
        G_mu = want
    half, Ja = c["half"], c["Ja"]
    var, avar = k.term_variances(G_mu, half, Ja, 10)
    H = G_mu @ half
    Ha = Ja @ H[:10]
    np.testing.assert_allclose(var, np.sum(H * H, axis=1), rtol=1e-13)
    np.testing.assert_allclose(avar, np.sum(Ha * Ha, axis=1), rtol=1e-12)
    # P_pred = diag(2, 2, 2): A = I + P_pred info has a zero first column
    P3, F3, Q3 = np.diag([4.0, 4.0, 4.0]), np.array([0.5, 0.5, 1.0]), np.array([1.0, 1.0, -2.0])
    info3 = np.diag([-0.5, 1.0, 1.0])
    G3 = np.ones((3, 2))
    got, ok = k.mu_gain_step(P3, info3, F3, Q3, G3, np.eye(3, 2))
    assert not ok and got is G3


def test_transition_kernel_is_the_numpy_steps_bit_for_bit() -> None:
    """``drift`` gives ``x * b + a + z * s`` of the first ``q`` columns exactly as the
    NumPy steps, and flags exactly the rows that left the box (``into_box`` reflects
    them)."""
    from formtwin.evolution import into_box

    rng = np.random.default_rng(7)
    x = rng.uniform(-1.0, 1.0, (500, 21))
    q = 18
    a, b, s = rng.normal(0, 0.1, q), rng.uniform(0.5, 1.0, q), rng.uniform(0.01, 0.3, q)
    lo, hi = np.full(21, -1.0), np.full(21, 1.0)
    z = rng.standard_normal((500, q))
    out = np.full_like(x, np.nan)
    left = k.drift(x, a, b, s, z, lo, hi, out)
    new = x[:, :q] * b
    new += a
    new += z * s
    np.testing.assert_array_equal(out[:, :q], new)
    assert np.isnan(out[:, q:]).all()
    want_left = np.any((new < lo[:q]) | (new > hi[:q]), axis=1)
    assert 0 < want_left.sum() < 500
    np.testing.assert_array_equal(left, want_left)
    out[left, :q] = into_box(out[left, :q], lo[:q], hi[:q])
    np.testing.assert_array_equal(out[:, :q], into_box(new, lo[:q], hi[:q]))
