"""The final angle's discrepancy learned from the camera (formtwin.tracker.angle_discrepancy)
against closed forms: a static hypothesis is the conjugate Normal-inverse-gamma regression
of all values so far, its evidence the Student-t marginal likelihood of the data; the
Occam factor keeps the model as it is when it is right, a wrong model is corrected."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import gammaln

from formtwin.tracker.angle_discrepancy import HYPOTHESES, PRIOR_DOF, PRIOR_SD, AngleDiscrepancy


def _nig(X: np.ndarray, y: np.ndarray, m0: np.ndarray, V0: np.ndarray, n0: float,
         s0: float) -> tuple[np.ndarray, float]:
    """Posterior mean (p,) of the coefficients of y = X b + e, e ~ N(0, v), with the
    prior b | v ~ N(m0, v V0 / s0), v ~ IG(n0 / 2, n0 s0 / 2), and the log marginal
    likelihood of y (a multivariate Student-t), by the batch formulas."""
    n = y.size
    V0s = V0 / s0  # the prior covariance in units of v
    P0 = np.linalg.inv(V0s)
    Pn = P0 + X.T @ X
    Vn = np.linalg.inv(Pn)
    mn = Vn @ (P0 @ m0 + X.T @ y)
    a0, b0 = n0 / 2, n0 * s0 / 2
    an = a0 + n / 2
    bn = b0 + 0.5 * (y @ y + m0 @ P0 @ m0 - mn @ Pn @ mn)
    logml = (gammaln(an) - gammaln(a0) + a0 * math.log(b0) - an * math.log(bn)
             + 0.5 * (np.linalg.slogdet(Vn)[1] - np.linalg.slogdet(V0s)[1])
             - 0.5 * n * math.log(2 * math.pi))
    return mn, float(logml)


@pytest.mark.parametrize("h", [i for i, (b, s, d) in enumerate(HYPOTHESES) if d == 1.0 and s])
def test_static_hypothesis_is_the_conjugate_regression(h: int) -> None:
    """With delta = 1 and both coefficients learned, the sequential updates give the batch
    NIG posterior mean, and the sum of the one-step log predictive densities is the exact
    log marginal likelihood (to rounding)."""
    rng = np.random.default_rng(4)
    s0 = 0.05
    d = AngleDiscrepancy(noise_var=s0)
    m = 88.0 + 0.1 * rng.standard_normal(60)
    y = 87.7 + 0.4 * (m - 88.0) + 0.2 * rng.standard_normal(60)
    before = d.logw.copy()
    for mk, yk in zip(m, y, strict=True):
        d.update(float(mk), float(yk))
    ref = m[0]
    X = np.c_[np.ones(m.size), m - ref]
    mn, exact = _nig(X, y - ref, np.array([0.0, 1.0]), np.diag(np.square(PRIOR_SD)),
                     PRIOR_DOF, s0)
    np.testing.assert_allclose(d.a[h], mn, rtol=0, atol=1e-9)
    # the evidence: relative log weights against the model-as-it-is (a closed form too)
    null = (gammaln((PRIOR_DOF + m.size) / 2) - gammaln(PRIOR_DOF / 2)
            + PRIOR_DOF / 2 * math.log(PRIOR_DOF * s0)
            - (PRIOR_DOF + m.size) / 2 * math.log(PRIOR_DOF * s0 + np.sum((y - m) ** 2))
            - m.size / 2 * math.log(math.pi))
    got = (d.logw[h] - before[h]) - (d.logw[0] - before[0])
    assert got == pytest.approx(exact - null, abs=1e-8)


def test_a_right_model_is_kept_and_a_wrong_one_corrected() -> None:
    """Values of a right model with 0.2 deg noise: the model as it is keeps most weight and
    the prediction moves by far less than the noise; a model 0.3 deg low that follows
    only half of the true variation is corrected (bias and slope), and the state survives
    its list of numbers."""
    rng = np.random.default_rng(0)
    a = 88.0 + 0.1 * rng.standard_normal(1000)
    right, wrong = AngleDiscrepancy(0.04), AngleDiscrepancy(0.04)
    for k in range(999):
        right.issue(k, float(a[k]))
        right.update_product(k, float(a[k] + 0.2 * rng.standard_normal()))
        wrong.issue(k, float(88.0 + 2.0 * (a[k] - 88.0) - 0.3))
        wrong.update_product(k, float(a[k] + 0.2 * rng.standard_normal()))
    assert right.weights()[0] > 0.5
    assert abs(right.predict(88.1)[0] - 88.1) < 0.02
    assert wrong.weights()[0] < 1e-6
    ref, b0, b1 = wrong.coefficients()
    assert ref + b0 + b1 * (87.7 - ref) == pytest.approx(88.0, abs=0.03)
    assert b1 == pytest.approx(0.5, abs=0.1)
    again = AngleDiscrepancy(0.04)
    again.set_state(wrong.state())
    assert again == wrong and again.predict(88.2) == wrong.predict(88.2)
    with pytest.raises(ValueError, match="noise_var"):
        AngleDiscrepancy(0.0)


def test_the_mapping_is_the_coefficients_and_the_variance() -> None:
    """:meth:`AngleDiscrepancy.mapping` (one evaluation of the weights) gives exactly
    :meth:`coefficients` and :meth:`variance`."""
    d = AngleDiscrepancy(noise_var=0.04)
    rng = np.random.default_rng(3)
    for _ in range(60):
        a = 88.0 + 0.1 * rng.standard_normal()
        d.update(a, 0.4 + 0.8 * a + 0.2 * rng.standard_normal() - 0.8 * 88.0 + 88.0)
        assert d.mapping() == (*d.coefficients(), d.variance())


def test_the_update_is_the_einsum_formulation() -> None:
    """The covariance update (one pass, Numba: the gain's two-term sums and the outer
    product written out) gives the ``np.einsum`` formulation's numbers (the same two-term
    sums and products: equal to a few ulp on any BLAS, bit for bit where the sums are done
    in the same order)."""
    rng = np.random.default_rng(5)
    d = AngleDiscrepancy(noise_var=0.04)
    for _ in range(300):
        a = 88.0 + 0.3 * rng.standard_normal()
        y = 88.3 + 0.7 * (a - 88.0) + 0.2 * rng.standard_normal()
        ref = a if math.isnan(d.ref) else d.ref  # the forecast, as the update makes it
        F = np.array([1.0, a - ref])
        R = d.C / d._delta[:, None, None]
        f = ref + d.a @ F
        Q = np.einsum("i,hij,j->h", F, R, F) + d.S
        e = y - f
        S1 = d.S + d.S / (d.n + 1.0) * (e * e / Q - 1.0)
        A = np.einsum("hij,j->hi", R, F) / Q[:, None]
        C = (S1 / d.S)[:, None, None] * (R - np.einsum("hi,hj->hij", A, A) * Q[:, None, None])
        a_new = d.a + A * e[:, None]
        d.update(a, y)
        eps = np.finfo(float).eps
        np.testing.assert_allclose(d.a, a_new, rtol=8 * eps, atol=0)
        np.testing.assert_allclose(d.C, C, rtol=64 * eps, atol=64 * eps * np.abs(C).max())


def test_predict_is_the_mixture_formula_to_rounding() -> None:
    """:meth:`AngleDiscrepancy.predict` (one pass, Numba) is the hypotheses' Student-t
    mixture of the NumPy formula (forecast ``ref + a F``, ``F^T (C / delta) F + S``, the
    variances ``Q n / max(n - 2, 1)``, the weights ``exp(logw)`` normalised) to rounding,
    from the prior through 300 updates of a drifting, wrong model."""
    rng = np.random.default_rng(5)
    d = AngleDiscrepancy(noise_var=0.05)
    for k in range(300):
        angle = 88.0 + 0.5 * float(rng.standard_normal())
        mean, var = d.predict(angle)
        ref = angle if math.isnan(d.ref) else d.ref
        F = np.array([1.0, angle - ref])
        f = ref + d.a @ F
        Q = np.einsum("i,hij,j->h", F, d.C / d._delta[:, None, None], F) + d.S
        w = np.exp(d.logw - d.logw.max())
        w /= w.sum()
        v = Q * d.n / np.maximum(d.n - 2.0, 1.0)
        m = float(w @ f)
        assert mean == pytest.approx(m, rel=1e-13, abs=1e-13), k
        assert var == pytest.approx(float(w @ (v + (f - m) ** 2)), rel=1e-11), k
        d.update(angle, 0.3 + 1.01 * angle + 0.01 * k + 0.2 * float(rng.standard_normal()))


def _numpy_update(d: AngleDiscrepancy, model_angle: float, value: float) -> float:
    """The update's NumPy formula (the discount-evolved covariance, the Student-t density,
    the conjugate update and the weights), applied to ``d``."""
    if math.isnan(d.ref):
        d.ref = float(model_angle)
    F = np.array([1.0, model_angle - d.ref])
    R = d.C / d._delta[:, None, None]
    f = d.ref + d.a @ F
    Q = np.einsum("i,hij,j->h", F, R, F) + d.S
    e, n = float(value) - f, d.n
    ll = (gammaln((n + 1) / 2) - gammaln(n / 2) - 0.5 * np.log(n * math.pi * Q)
          - (n + 1) / 2 * np.log1p(e * e / (n * Q)))
    n1 = n + 1.0
    S1 = d.S + d.S / n1 * (e * e / Q - 1.0)
    A = np.einsum("hij,j->hi", R, F) / Q[:, None]
    d.a = d.a + A * e[:, None]
    d.C = (S1 / d.S)[:, None, None] * (R - A[:, :, None] * A[:, None, :] * Q[:, None, None])
    d.S, d.n = S1, n1
    total = d.logw + ll
    top = float(total.max())
    norm = top + math.log(float(np.exp(total - top).sum()))
    d.logw = total - norm
    return norm


def test_update_is_the_numpy_formula_to_rounding() -> None:
    """:meth:`AngleDiscrepancy.update` (one pass, Numba) is the NumPy formula to rounding,
    one update at a time from the same state, through 300 updates of a drifting, wrong
    model (the evidence, and every array of the state)."""
    rng = np.random.default_rng(6)
    d = AngleDiscrepancy(noise_var=0.05)
    eps = np.finfo(float).eps
    for k in range(300):
        angle = 88.0 + 0.5 * float(rng.standard_normal())
        value = 0.3 + 1.01 * angle + 0.01 * k + 0.2 * float(rng.standard_normal())
        ref = AngleDiscrepancy(0.05)
        ref.set_state(d.state())
        want = _numpy_update(ref, angle, value)
        got = d.update(angle, value)
        assert got == pytest.approx(want, rel=1e3 * eps, abs=1e3 * eps), k
        for x, y in ((d.a, ref.a), (d.C, ref.C), (d.S, ref.S), (d.n, ref.n), (d.logw, ref.logw)):
            np.testing.assert_allclose(x, y, rtol=1e3 * eps, atol=1e3 * eps * np.abs(y).max())
        d.set_state(ref.state())  # on from the reference's state: no drift between them
