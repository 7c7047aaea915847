"""Deviation model g and its inverse: identity, exactness, round trips, monotone time."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from formtwin.deviation import DeviationModel
from formtwin.spec import load_spec

SPEC = load_spec()
G = DeviationModel.from_spec(SPEC)
T = SPEC.time


def bump(t: np.ndarray) -> np.ndarray:
    """A smooth force-like curve, flat (zero) near both ends of the window."""
    return 500.0 * np.exp(-(((t + 0.02) / 0.012) ** 2)) + 200.0 * np.exp(
        -(((t + 0.04) / 0.007) ** 2))


def test_zero_theta_d_is_the_identity() -> None:
    z = bump(T)
    np.testing.assert_allclose(G.apply(z, np.zeros(8))[0], z, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(G.invert(z, np.zeros(8))[0], z, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(G.model_time(np.zeros(8))[0], T, atol=1e-15)


def test_constant_speed_scaling_is_a_time_stretch_about_zero() -> None:
    theta_d = np.r_[np.zeros(4), np.full(4, 0.1)]
    np.testing.assert_allclose(G.model_time(theta_d)[0], 1.1 * T, atol=1e-15)
    np.testing.assert_allclose(G.real_time(theta_d)[0], T / 1.1, atol=1e-15)
    z = np.where(np.abs(T) < 0.07, np.cos(T * 20), np.cos(0.07 * 20))
    np.testing.assert_allclose(G.apply(z, theta_d)[0][20:], np.interp(1.1 * T, T, z)[20:],
                               atol=1e-12)


def test_model_time_matches_numerical_integral_of_piecewise_linear_b() -> None:
    theta_d = np.r_[np.zeros(4), [0.2, -0.15, 0.1, -0.2]]
    fine = np.linspace(T[0], T[-1], 200_001)
    b = np.interp(fine, SPEC.deviation.knots, theta_d[4:])
    cum = np.concatenate([[0], np.cumsum(0.5 * (2 + b[1:] + b[:-1]) * np.diff(fine))])
    tau_ref = np.interp(T, fine, cum - np.interp(0.0, fine, cum))
    np.testing.assert_allclose(G.model_time(theta_d)[0], tau_ref, atol=1e-10)


theta_d_strategy = arrays(np.float64, 8, elements=st.floats(-0.2, 0.2))


@settings(max_examples=60, deadline=None)
@given(theta_d_strategy)
def test_tau_is_monotone_and_inverse_is_exact(theta_d: np.ndarray) -> None:
    tau = G.model_time(theta_d)[0]
    assert np.all(np.diff(tau) > 0)
    assert tau[np.argmin(np.abs(T))] == pytest.approx(0.0, abs=1e-15)  # anchored at t = 0
    # real_time inverts model_time: tau(t(s)) = s at the grid's model times
    t_of_s = G.real_time(theta_d)[0]
    dense = np.linspace(-0.2, 0.2, 40_001)
    G_dense = DeviationModel(dense, SPEC.deviation.knots)
    np.testing.assert_allclose(np.interp(t_of_s, dense, G_dense.model_time(theta_d)[0]), T,
                               atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(theta_d_strategy)
def test_inverse_undoes_g_to_interpolation_accuracy(theta_d: np.ndarray) -> None:
    fine_t = np.linspace(T[0], T[-1], 1001)  # fine grid: interpolation error O(dt^2)
    g = DeviationModel(fine_t, SPEC.deviation.knots)
    z = bump(fine_t)
    back = g.invert(g.apply(z, theta_d), theta_d)[0]
    assert np.max(np.abs(back - z)) < 1e-3 * z.max()


def test_one_curve_against_many_parameter_sets_is_vectorised() -> None:
    rng = np.random.default_rng(0)
    thetas = rng.uniform(-0.2, 0.2, (500, 8))
    z = bump(T)
    many = G.invert(z, thetas)
    assert many.shape == (500, 101)
    for k in (0, 137, 499):
        np.testing.assert_allclose(many[k], G.invert(z, thetas[k])[0], rtol=1e-14)
    per_row = G.apply(np.tile(z, (500, 1)), thetas)
    np.testing.assert_allclose(per_row, G.apply(z, thetas), rtol=1e-14)


def test_force_scaling_interpolates_between_knots() -> None:
    theta_d = np.r_[[0.0, 0.2, -0.2, 0.1], np.zeros(4)]
    a = G.force_scaling(theta_d)[0]
    np.testing.assert_allclose(a[[0, -1]], [0.0, 0.1])
    mid = np.argmin(np.abs(T - (SPEC.deviation.knots[1] + SPEC.deviation.knots[2]) / 2))
    assert a[mid] == pytest.approx(0.0, abs=0.01)


def test_bad_theta_d_is_rejected() -> None:
    with pytest.raises(ValueError, match="7 columns, expected 8"):
        G.apply(bump(T), np.zeros(7))
    with pytest.raises(ValueError, match="above -1"):
        G.apply(bump(T), np.r_[np.zeros(4), [-1.0, 0, 0, 0]])


def test_plot_deviation_writes_a_figure(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from formtwin.cli import main

    out = tmp_path / "deviation.png"
    assert main(["plot", "deviation", "--out", str(out)]) == 0
    assert out.stat().st_size > 20_000


def test_row_interpolation_matches_numpy_interp_per_row() -> None:
    """g on many curves at once equals np.interp of each curve at its own model times
    (edge value outside the window), and one curve broadcast to all rows equals it too."""
    rng = np.random.default_rng(3)
    theta_d = rng.uniform(-0.2, 0.2, (40, 8))
    curves = bump(T) * rng.uniform(0.5, 1.5, (40, 1)) + rng.normal(0.0, 5.0, (40, T.size))
    tau = G.model_time(theta_d)
    a = G.force_scaling(theta_d)
    ref = np.array([(1 + a[k]) * np.interp(tau[k], T, curves[k]) for k in range(40)])
    np.testing.assert_allclose(G.apply(curves, theta_d), ref, rtol=1e-12, atol=1e-9)
    one = np.array([(1 + a[k]) * np.interp(tau[k], T, curves[0]) for k in range(40)])
    np.testing.assert_allclose(G.apply(curves[:1], theta_d), one, rtol=1e-12, atol=1e-9)


def test_fused_apply_equals_the_numpy_steps_bit_for_bit() -> None:
    """``g`` of curves (N, n_t) with their own theta_d (the tracker's call) takes one Numba
    pass; it equals the NumPy steps (force scaling, model time, row interpolation) exactly,
    also for times that leave the window (clipped) and at the bounds of theta_d."""
    g = DeviationModel.from_spec(load_spec())
    rng = np.random.default_rng(11)
    n = 300
    td = rng.uniform(-0.2, 0.2, (n, g.n_params))
    td[0] = 0.2
    td[1] = -0.2
    td[2, :4] = 0.0
    curves = np.cumsum(rng.standard_normal((n, g.time.size)), axis=1) * 40.0
    ref = (1.0 + g.force_scaling(td)) * g._interp_rows(curves, g.model_time(td))
    out = g.apply(curves, td)
    np.testing.assert_array_equal(out, ref)
    tq = g.model_time(td)
    assert (tq < g.time[0]).any() and (tq > g.time[-1]).any()  # the clipped ends are used
    # one curve for all rows (and non-finite theta_d) keep the NumPy path
    np.testing.assert_array_equal(g.apply(curves[0], td[:5]),
                                  (1.0 + g.force_scaling(td[:5]))
                                  * g._interp_rows(curves[0], g.model_time(td[:5])))
