"""The metamodel's closed-form derivatives: the RBF's gradient against an interpolated
linear function (exact) and against central differences of its float64 evaluation; the
metamodel's curve Jacobian and angle gradient through the scaler and the POD modes; the
tracker's Jacobian of the compared curve built from them."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.defaults import analytic_dataset
from formtwin.measurement import MeasurementModel
from formtwin.metamodel import POD, RBF, Metamodel
from formtwin.metamodel.kernels import monomial_powers, polynomial, polynomial_gradient
from formtwin.tracker import TrackerConfig
from formtwin.tracker.ssm import BendingSSM


def _central(f, x: np.ndarray, h: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Central differences (..., d) of ``f`` at the row ``x`` (1, d) with steps ``h`` (d,)."""
    cols = []
    for i in range(x.shape[1]):
        e = np.zeros_like(x)
        e[0, i] = h[i]
        cols.append((f(x + e) - f(x - e)) / (2.0 * h[i]))
    return np.stack(cols, axis=-1)


def test_polynomial_gradient_is_the_monomials_derivative() -> None:
    """Degree 2 in 3 inputs: central differences are exact for quadratics (to rounding)."""
    powers = monomial_powers(3, 2)
    U = np.array([[0.2, 0.7, 0.45]])
    g = polynomial_gradient(U, powers)[0]  # (d, q)
    fd = _central(lambda u: polynomial(u, powers)[0], U, np.full(3, 1e-3))  # (q, d)
    np.testing.assert_allclose(g, fd.T, atol=1e-10)
    lin = polynomial_gradient(U, monomial_powers(3, 1))[0]
    np.testing.assert_array_equal(lin, np.c_[np.zeros(3), 2.0 * np.eye(3)])


@pytest.mark.parametrize("kernel", ["cubic", "thin_plate_spline", "quintic"])
def test_rbf_of_a_linear_function_has_its_gradient(kernel: str) -> None:
    """A polynomial tail reproduces a linear function exactly (the kernel weights solve
    to 0), so the gradient is its slope ``a`` per unit-box input, to the solve's
    rounding."""
    rng = np.random.default_rng(1)
    U = rng.random((60, 3))
    a = np.array([[1.5, -2.0], [0.25, 0.0], [3.0, 1.0]])
    rbf = RBF(kernel, degree=2 if kernel == "quintic" else 1, length_scales="box",
              dtype=np.float64).fit(U, U @ a + 0.5)
    x = np.array([[0.3, 0.6, 0.5], [0.55, 0.4, 0.6]])
    value, grad = rbf.value_and_gradient(x)
    np.testing.assert_allclose(value, rbf.predict(x), atol=1e-9)
    np.testing.assert_allclose(grad, np.broadcast_to(a, grad.shape), atol=1e-6)


@pytest.mark.parametrize("kernel", ["cubic", "thin_plate_spline"])
def test_rbf_gradient_matches_central_differences_of_its_evaluation(kernel: str) -> None:
    """Least-squares RBF with per-dimension scales, evaluated in float64: central
    differences with step 1e-5 are within ~h^2 |f'''| + eps |f| / h of the gradient."""
    rng = np.random.default_rng(2)
    U = rng.random((300, 4))
    Y = np.c_[np.sin(3.0 * U[:, 0]) * U[:, 1], np.exp(U[:, 2] - U[:, 3] ** 2)]
    rbf = RBF(kernel, n_centres=120, dtype=np.float64, n_tune=200).fit(U, Y)
    x = np.array([[0.4, 0.3, 0.8, 0.55]])
    _, grad = rbf.value_and_gradient(x)
    fd = _central(lambda u: rbf.predict(u)[0], x, np.full(4, 1e-5))  # (k, d)
    scale = float(np.abs(grad).max())
    np.testing.assert_allclose(grad[0], fd.T, atol=1e-6 * scale)
    assert scale > 0.1  # the test is not of a flat function


@pytest.fixture(scope="module")
def small_mm() -> Metamodel:
    """A float64 metamodel of the analytic stand-in (float64: central differences of its
    evaluation are then accurate to ~1e-8 of the derivative)."""
    return Metamodel(POD(n_modes=6), RBF("cubic", n_centres=120, dtype=np.float64,
                                         n_tune=200)).fit(analytic_dataset(240, seed=5))


def test_curve_jacobian_and_angle_gradient_match_central_differences(
        small_mm: Metamodel) -> None:
    """Through the scaler ((x - lo) / (hi - lo)) and the POD modes: the Jacobian per
    internal unit of each input, and the angles' gradient at a press setting."""
    spec = small_mm.spec
    lo, hi = spec.inputs.lo, spec.inputs.hi
    X = lo + (hi - lo) * np.linspace(0.3, 0.7, spec.n_inputs)[None, :]
    h = 1e-5 * (hi - lo)
    curves, jac = small_mm.curve_jacobian(X)
    np.testing.assert_allclose(curves, small_mm.predict_curves(X),
                               atol=1e-9 * float(np.abs(curves).max()))
    fd = _central(lambda x: small_mm.predict_curves(x)[0], X, h)  # (n_t, n_in)
    np.testing.assert_allclose(jac[0], fd, atol=1e-6 * float(np.abs(jac).max()))
    u = 0.5 * (spec.controls.lo + spec.controls.hi) + 0.1 * (spec.controls.hi
                                                              - spec.controls.lo)
    ga = small_mm.angle_gradient(X, u)
    fda = _central(lambda x: small_mm.predict_angles(x, u)[0], X, h)  # (n_out, n_in)
    assert ga.shape == (1, spec.n_outputs, spec.n_inputs)
    np.testing.assert_allclose(ga[0], fda, atol=1e-6 * float(np.abs(ga).max()))


@pytest.mark.parametrize(("compare", "deviation"), [("measurement", True), ("model", True),
                                                    ("measurement", False)])
def test_tracker_jacobian_from_the_gradient_matches_forward_differences(
        small_mm: Metamodel, compare: str, deviation: bool) -> None:
    """The sandwich's Jacobian of the compared curve (``g`` of the model curve, or the
    model curve against ``g^-1`` of the measured one): the exact path against forward
    differences of the full residuals in every column, with steps of 1e-6 of the range
    in ``[x, theta]`` (float64 model: error ~h |f''| + eps |f| / h) and the same steps
    in ``theta_d`` (there both are differences of ``g`` of the same curve)."""
    mm = MeasurementModel.from_monte_carlo(small_mm, n=500, rng=np.random.default_rng(0))
    ssm = BendingSSM(small_mm, mm, TrackerConfig(compare=compare,
                                                 estimate_deviation=deviation))
    c = ssm.sample_initial(1, np.random.default_rng(3))[0]
    if deviation:
        c[ssm.n_in:ssm.n_aug] = np.linspace(-0.1, 0.12, ssm.n_aug - ssm.n_in)
    y = small_mm.predict_curves(c[None, :ssm.n_in])[0]
    m = ssm.n_varying
    step = 1e-6 * (ssm._hi[:m] - ssm._lo[:m])
    step[ssm.n_in:] = 1e-3
    assert small_mm.differentiable
    exact = ssm._exact_jacobian(c, step[ssm.n_in:], y)
    fd = ssm._jacobian(c, step, y)
    # the sandwich's path takes it (steps from sigma and the spread)
    got, steps = ssm._cloud_jacobian(c, np.full(m - ssm.n_x, 0.01), y, exact=True)
    np.testing.assert_array_equal(got, ssm._exact_jacobian(c, steps[ssm.n_in:], y))
    assert exact.shape == fd.shape == (small_mm.spec.n_t, m)
    col = np.abs(exact).max(axis=0)
    assert np.all(col > 0)
    assert np.all(np.abs(exact - fd).max(axis=0) <= 1e-4 * col + 1e-9 * np.abs(y).max())


def test_cubic_kernel_and_slope_in_one_pass_are_the_numpy_formulas() -> None:
    """``cubic_value_slope`` (the cubic RBF's gradient, Numba) against the NumPy steps of
    the other kernels' path: ``phi = r^3`` and ``S = 2 phi'(r^2) (z - c)``, to ``d eps``
    of their scale, for several points at once."""
    from formtwin.metamodel._fused import cubic_value_slope
    from formtwin.metamodel.kernels import KERNEL_SLOPES, kernel_function

    rng = np.random.default_rng(12)
    Z, C = rng.random((3, 10)) * 2.0, rng.random((200, 10)) * 2.0
    phi, S = cubic_value_slope(Z, C)
    D = Z[:, None, :] - C[None]
    r2 = np.einsum("nmd,nmd->nm", D, D)
    eps = 10 * np.finfo(float).eps
    np.testing.assert_allclose(phi, kernel_function("cubic")(r2), rtol=eps)
    want = (D * (2.0 * KERNEL_SLOPES["cubic"](r2))[:, :, None]).transpose(0, 2, 1)
    np.testing.assert_allclose(S, want, rtol=0, atol=eps * np.abs(want).max())
