"""The linear-Gaussian bound of what a chart can see of a step: the steady filter against
the textbook covariance-form Kalman filter, its limits (a perfectly observed state, one
state), the information inequality, the Jacobian on a linear model and the GLR delays."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.monitoring.bound import (
    curve_jacobian,
    glr_delays,
    steady_filter,
    step_in_filter,
)
from formtwin.monitoring.glr import glr_h


def _system(seed: int = 3, n_t: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                      np.ndarray]:
    """A random curve Jacobian (n_t, 3), a noise covariance, rho and sigma."""
    rng = np.random.default_rng(seed)
    jac = rng.standard_normal((n_t, 3)) * np.array([3.0, 1.0, 0.2])
    b = rng.standard_normal((n_t, n_t))
    return jac, b @ b.T / n_t + 0.5 * np.eye(n_t), np.array([0.7, 0.9, 0.8]), \
        np.array([1.0, 2.0, 0.5])


def test_steady_filter_matches_the_covariance_form_kalman_filter() -> None:
    """Riccati fixed point, and the mean response to a step: the filter run in its
    covariance form (gain P^- J^T S^-1) on the noise-free curves of the step."""
    jac, r, rho, sigma = _system()
    f = steady_filter(jac, r, rho, sigma)
    a, q = np.diag(rho), np.diag(sigma**2 * (1 - rho**2))
    pm = a @ f.posterior @ a + q
    np.testing.assert_allclose(f.predicted, pm, rtol=1e-9)
    s = jac @ pm @ jac.T + r
    k = pm @ jac.T @ np.linalg.inv(s)
    np.testing.assert_allclose(f.posterior, (np.eye(3) - k @ jac) @ pm, rtol=1e-8, atol=1e-12)
    j, delta = 1, 2.0 * sigma[1]
    resp = step_in_filter(f, j, delta, 40)
    m, share, own, full = np.zeros(3), [], [], []
    sd = np.sqrt((k @ s @ k.T)[j, j])
    for _ in range(40):
        nu = jac @ (delta * np.eye(3)[j]) - jac @ (a @ m)  # mean innovation
        full.append(nu @ np.linalg.solve(s, nu))
        own.append((k @ nu)[j] / sd)
        m = a @ m + k @ nu
        share.append(m[j] / delta)
    np.testing.assert_allclose(resp.share, share, rtol=1e-7)
    np.testing.assert_allclose(resp.own, own, rtol=1e-7)
    np.testing.assert_allclose(resp.full, full, rtol=1e-7)


def test_a_perfectly_observed_state_leaves_the_true_states_signature() -> None:
    """R -> 0: the estimate is the state; a step delta leaves delta / sqrt(q) at the change
    and delta (1 - rho) / sqrt(q) after (q the AR(1) innovation variance)."""
    rho, sigma = np.array([0.9]), np.array([1.5])
    f = steady_filter(np.ones((1, 1)), np.array([[1e-10]]), rho, sigma)
    resp = step_in_filter(f, 0, 3.0, 5)
    sq = np.sqrt(sigma[0] ** 2 * (1 - rho[0] ** 2))
    np.testing.assert_allclose(resp.own, [3.0 / sq] + [3.0 * 0.1 / sq] * 4, rtol=1e-4)
    np.testing.assert_allclose(resp.share, 1.0, rtol=1e-4)


def test_own_residual_carries_at_most_the_curves_information() -> None:
    """Cauchy-Schwarz: the state's own estimate residual is one projection of the
    innovations, so its noncentrality is at most all of theirs, lag by lag; with one
    state they are equal."""
    jac, r, rho, sigma = _system()
    f = steady_filter(jac, r, rho, sigma)
    for j in range(3):
        resp = step_in_filter(f, j, 2.0 * sigma[j], 60)
        assert np.all(resp.own**2 <= resp.full * (1 + 1e-9))
        assert resp.expected_glr(30) <= resp.expected_glr(30, full=True)
    one = steady_filter(jac[:, :1], r, rho[:1], sigma[:1])
    resp = step_in_filter(one, 0, 2.0, 60)
    np.testing.assert_allclose(resp.own**2, resp.full, rtol=1e-9)


class _Linear:
    """A process model whose curve is linear in its inputs."""

    def __init__(self, b: np.ndarray) -> None:
        self.b = b

    def predict_curves(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x) @ self.b.T + 1.0


def test_curve_jacobian_of_a_linear_model_is_its_matrix() -> None:
    b = np.random.default_rng(0).standard_normal((8, 5))
    jac = curve_jacobian(_Linear(b), np.linspace(0.1, 0.5, 5), np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(jac, b[:, :3], rtol=1e-10)


def test_glr_delays_see_a_large_jump_at_once_and_miss_no_change() -> None:
    big = glr_delays(np.r_[8.0, np.full(10, 0.5)], arl0=1e4, runs=200, horizon=50)
    assert np.all(big == 1.0)
    none = glr_delays(np.r_[1e-6, np.full(10, 1e-6)], arl0=1e5, runs=200, horizon=50)
    assert np.mean(none == 51.0) > 0.95


@pytest.mark.parametrize("shift", [0.6, 1.0])
def test_glr_delays_grow_as_the_shift_shrinks(shift: float) -> None:
    """A constant shift: the delay's median is near where the expected statistic at the
    true change time, (1 + n shift^2) / 2, reaches h (the maximum over change times and
    the noise make it earlier, never much later)."""
    d = glr_delays(np.full(5, shift), arl0=1e4, runs=300, horizon=150)
    n_expected = (2 * glr_h((1.0,), 200, 1e4) - 1) / shift**2
    assert 0.4 * n_expected < np.median(d) < 1.2 * n_expected
