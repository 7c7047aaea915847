"""POD, RBF and the combined metamodel: exactness, tolerances, file round trip."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.defaults import analytic_dataset
from formtwin.metamodel import POD, RBF, Metamodel, loo_residuals
from formtwin.metamodel.kernels import monomial_powers, polynomial


@pytest.fixture(scope="module")
def data():  # type: ignore[no-untyped-def]
    return analytic_dataset(400, seed=3, failure_clearance=0.02)


@pytest.fixture(scope="module")
def model(data):  # type: ignore[no-untyped-def]
    return Metamodel(POD(n_modes=12), RBF(length_scales="box")).fit(data)


def _low_rank(sv: list[float], n: int = 60, n_t: int = 30, seed: int = 0) -> np.ndarray:
    """Curves (n, n_t) whose centred part has exactly the singular values ``sv``."""
    rng = np.random.default_rng(seed)
    left = rng.normal(size=(n, len(sv)))
    left -= left.mean(axis=0)
    left, _ = np.linalg.qr(left)
    right, _ = np.linalg.qr(rng.normal(size=(n_t, len(sv))))
    return left @ np.diag(sv) @ right.T + rng.normal(size=n_t)


def test_pod_with_all_modes_reconstructs_exactly() -> None:
    curves = np.random.default_rng(1).normal(size=(40, 25)) * 50.0
    pod = POD(n_modes=25).fit(curves)
    assert pod.n_modes == 25
    assert np.abs(pod.inverse_transform(pod.transform(curves)) - curves).max() < 1e-10
    assert np.allclose(pod.modes @ pod.modes.T, np.eye(25), atol=1e-12)


def test_pod_energy_criterion_picks_the_right_count() -> None:
    curves = _low_rank([10.0, 3.0, 1.0, 0.1])
    # cumulative energy shares: 100, 109, 110, 110.01 of 110.01
    assert POD(energy=0.90).fit(curves).n_modes == 1
    assert POD(energy=0.99).fit(curves).n_modes == 2
    assert POD(energy=0.9995).fit(curves).n_modes == 3
    assert POD(energy=0.99999).fit(curves).n_modes == 4
    pod = POD(energy=1.0).fit(curves)  # rank 4: never more modes than the data has
    assert pod.n_modes == 4
    assert pod.captured_energy == pytest.approx(1.0)


def test_pod_clips_requested_modes_to_rank() -> None:
    assert POD(n_modes=40).fit(_low_rank([5.0, 2.0])).n_modes == 2


def test_rbf_interpolates_its_centres() -> None:
    rng = np.random.default_rng(2)
    U = rng.random((150, 4))
    Y = np.column_stack([np.sin(4 * U[:, 0]) * U[:, 1], U[:, 2] ** 3 - U[:, 3]])
    for kernel in ("thin_plate_spline", "cubic", "gaussian", "multiquadric"):
        rbf = RBF(kernel, length_scales="box", epsilon=2.0, dtype=np.float64).fit(U, Y)
        assert np.abs(rbf.predict(U) - Y).max() < 1e-7, kernel


def test_rbf_reproduces_a_smooth_function() -> None:
    def f(U: np.ndarray) -> np.ndarray:
        return np.sin(2.0 * U[:, 0]) + U[:, 1] ** 2

    rng = np.random.default_rng(4)
    train, test = rng.random((400, 2)), rng.random((200, 2)) * 0.9 + 0.05
    rbf = RBF(length_scales="box", dtype=np.float64).fit(train, f(train))
    err = np.abs(rbf.predict(test)[:, 0] - f(test))
    # measured: max 1.0e-3 (near the edge of the sampled square), rms 1.3e-4
    assert err.max() < 2e-3 and np.sqrt(np.mean(err**2)) < 3e-4
    # float32 evaluation loses little
    fast = RBF(length_scales="box").fit(train, f(train))
    assert np.abs(fast.predict(test)[:, 0] - f(test)).max() < 3e-3


def test_rbf_reproduces_its_polynomial_tail_exactly() -> None:
    rng = np.random.default_rng(5)
    U = rng.random((80, 3))
    y = 2.0 + U @ np.array([1.0, -3.0, 0.5])
    rbf = RBF(length_scales="box", dtype=np.float64).fit(U, y)
    V = rng.random((20, 3))
    assert np.abs(rbf.predict(V)[:, 0] - (2.0 + V @ np.array([1.0, -3.0, 0.5]))).max() < 1e-8


@pytest.mark.parametrize(("kernel", "smoothing"), [("thin_plate_spline", 0.0),
                                                   ("gaussian", 1e-3), ("cubic", 0.1)])
def test_rippa_loo_equals_brute_force(kernel: str, smoothing: float) -> None:
    rng = np.random.default_rng(6)
    U = rng.random((40, 3))
    Y = np.column_stack([np.cos(3 * U[:, 0]) + U[:, 1], U[:, 2] * U[:, 0], U[:, 1] ** 2])
    Z = U * np.array([1.5, 0.7, 2.0])
    P = polynomial(U, monomial_powers(3, 1))
    fast = loo_residuals(Z, P, Y, kernel, smoothing)
    brute = np.empty_like(Y)
    for i in range(U.shape[0]):
        keep = np.arange(U.shape[0]) != i
        rbf = RBF(kernel, length_scales=np.array([1.5, 0.7, 2.0]), smoothing=smoothing,
                  dtype=np.float64).fit(U[keep], Y[keep])
        brute[i] = Y[i] - rbf.predict(U[i:i + 1])[0]
    assert np.allclose(fast, brute, rtol=1e-6, atol=1e-9)


def test_loo_length_scales_find_the_irrelevant_input() -> None:
    rng = np.random.default_rng(7)
    U = rng.random((150, 3))
    y = np.sin(3.0 * U[:, 0]) + 0.001 * U[:, 2]  # input 1 unused, input 2 nearly so
    rbf = RBF(n_tune=150).fit(U, y)
    assert rbf.scales[1] < 0.2 * rbf.scales[0]
    assert rbf.loo_rmse < RBF(length_scales="box", n_tune=150).fit(U, y).loo_rmse


def test_least_squares_centres_are_cheaper_and_still_accurate() -> None:
    rng = np.random.default_rng(8)
    U, V = rng.random((600, 3)), rng.random((200, 3))

    def f(U: np.ndarray) -> np.ndarray:
        return np.exp(-U[:, 0]) * np.cos(2 * U[:, 1]) + U[:, 2]

    rbf = RBF(length_scales="box", n_centres=150, dtype=np.float64).fit(U, f(U))
    assert rbf.centres.shape == (150, 3)
    err = rbf.predict(V)[:, 0] - f(V)
    assert np.sqrt(np.mean(err**2)) < 1e-2  # measured 5.5e-3


def test_metamodel_fits_only_successful_runs(data, model) -> None:  # type: ignore[no-untyped-def]
    assert 0 < int((~data.ok).sum()) < 100  # the stand-in failed some runs
    assert model.n_train == int(data.ok.sum())
    assert model.n_modes == 12
    assert model.model_version == data.model_version
    assert model.spec.n_inputs == 10


def test_predict_shapes_and_vectorisation(data, model) -> None:  # type: ignore[no-untyped-def]
    X = data.inputs[data.ok][:7]
    p = model.predict(X)
    assert p.curves.shape == (7, 101) and p.angles.shape == (7, 2) and p.outside.shape == (7,)
    one = model.predict(X[3])
    assert np.allclose(one.curves[0], p.curves[3], rtol=1e-5, atol=1e-3)
    assert np.allclose(one.angles[0], p.angles[3], rtol=1e-6, atol=1e-6)
    assert np.array_equal(model.predict_curves(X), p.curves)
    assert np.array_equal(model.predict_angles(X), p.angles)
    with pytest.raises(ValueError, match="expected \\(N, 10\\)"):
        model.predict(np.zeros((3, 9)))


def test_training_points_are_interpolated(data, model) -> None:  # type: ignore[no-untyped-def]
    ok = data.ok
    p = model.predict(data.inputs[ok])
    # angles: exact interpolation up to float32 evaluation
    assert np.abs(p.angles - data.angles[ok]).max() < 1e-2
    # curves: up to the 12-mode POD truncation
    pod = model.reduction
    trunc = pod.inverse_transform(pod.transform(data.curves[ok]))
    assert np.abs(p.curves - trunc).max() < 1e-4 * np.abs(trunc).max()


def test_outside_box_flag(model) -> None:  # type: ignore[no-untyped-def]
    spec = model.spec
    mid = 0.5 * (spec.inputs.lo + spec.inputs.hi)
    X = np.tile(mid, (4, 1))
    X[1, 3] = spec.inputs.hi[3] * 1.01
    X[2, 9] = spec.inputs.lo[9] - 1.0
    X[3] = spec.inputs.hi  # a corner is inside
    assert model.predict(X).outside.tolist() == [False, True, True, False]


def test_save_load_round_trip_without_pickle(tmp_path, data, model) -> None:  # type: ignore[no-untyped-def]
    path = model.save(tmp_path / "mm.npz")
    with np.load(path, allow_pickle=False) as npz:
        assert all(npz[k].dtype != object for k in npz.files)
        assert str(npz["model_version"]) == data.model_version
    back = Metamodel.load(path)
    X = data.inputs[:50]
    a, b = model.predict(X), back.predict(X)
    assert np.array_equal(a.curves, b.curves) and np.array_equal(a.angles, b.angles)
    assert back.spec.inputs.names == model.spec.inputs.names
    assert np.array_equal(back.spec.time, model.spec.time)
    assert back.n_modes == model.n_modes and back.model_version == model.model_version
    assert repr(back) == repr(model)


def test_load_rejects_other_files(tmp_path, model) -> None:  # type: ignore[no-untyped-def]
    np.savez(tmp_path / "x.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="format"):
        Metamodel.load(tmp_path / "x.npz")
    with np.load(model.save(tmp_path / "full.npz")) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "curves.weights"}
    np.savez(tmp_path / "cut.npz", **arrays)
    with pytest.raises(ValueError, match="no array 'weights'"):
        Metamodel.load(tmp_path / "cut.npz")
    (tmp_path / "y.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="not a formtwin metamodel"):
        Metamodel.load(tmp_path / "y.npz")


def test_bad_settings_fail_loudly() -> None:
    with pytest.raises(ValueError, match="unknown RBF kernel 'spline'"):
        RBF("spline")
    with pytest.raises(ValueError, match="degree >= 2"):
        RBF("quintic", degree=1)
    with pytest.raises(ValueError, match="energy"):
        POD(energy=1.5)
    with pytest.raises(RuntimeError, match="not fitted"):
        _ = Metamodel().spec


@pytest.mark.parametrize("kernel", ["thin_plate_spline", "cubic", "gaussian"])
def test_loo_gradient_matches_finite_differences(kernel: str) -> None:
    from scipy.optimize import approx_fprime

    from formtwin.metamodel import loo_objective

    rng = np.random.default_rng(9)
    U = rng.random((50, 4))
    Y = np.column_stack([np.sin(3 * U[:, 0]) + U[:, 1] ** 2, U[:, 2] * U[:, 3]])
    P = polynomial(U, monomial_powers(4, 1))
    x = rng.normal(size=4) * 0.3
    grad = loo_objective(x, U, P, Y, kernel, 1e-4)[1]
    fd = approx_fprime(x, lambda v: loo_objective(v, U, P, Y, kernel, 1e-4)[0], 1e-6)
    assert np.allclose(grad, fd, rtol=1e-4, atol=1e-5)
    # with the log smoothing as a last parameter
    x = np.append(x, np.log(1e-2))
    grad = loo_objective(x, U, P, Y, kernel)[1]
    fd = approx_fprime(x, lambda v: loo_objective(v, U, P, Y, kernel)[0], 1e-6)
    assert grad.shape == (5,) and np.allclose(grad, fd, rtol=1e-4, atol=1e-5)


def test_loo_smoothing_grows_with_noise() -> None:
    rng = np.random.default_rng(10)
    U = rng.random((200, 2))
    clean = np.sin(3.0 * U[:, 0]) + U[:, 1] ** 2
    y = clean + 0.05 * rng.normal(size=200)
    exact = RBF(smoothing="loo", n_tune=200).fit(U, clean)
    noisy = RBF(smoothing="loo", n_tune=200).fit(U, y)
    assert noisy.smoothing > 100.0 * exact.smoothing  # measured: 8.9e-4 vs 2.4e-6
    V = rng.random((300, 2))
    truth = np.sin(3.0 * V[:, 0]) + V[:, 1] ** 2
    plain = RBF(n_tune=200).fit(U, y)
    err = [np.sqrt(np.mean((m.predict(V)[:, 0] - truth) ** 2)) for m in (noisy, plain)]
    assert err[0] < 0.6 * err[1]  # measured: 0.023 vs 0.050


def test_float32_falls_back_to_float64_when_it_loses_accuracy() -> None:
    rng = np.random.default_rng(12)
    U, V = rng.random((1500, 3)), rng.random((300, 3))

    def f(U: np.ndarray) -> np.ndarray:
        return np.sin(4.0 * U[:, 0]) + 0.01 * U[:, 1]

    # a near-exact fit: float32 rounding (5e-4) would dominate the error (2e-6)
    rbf = RBF("cubic", length_scales=np.array([20.0, 0.05, 0.05]), n_centres=500).fit(U, f(U))
    assert rbf.dtype == np.float64
    assert np.sqrt(np.mean((rbf.predict(V)[:, 0] - f(V)) ** 2)) < 1e-5
    # a model whose error is far above float32 rounding stays float32
    coarse = RBF(length_scales="box", n_centres=30).fit(U, f(U))
    assert coarse.dtype == np.float32


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_fused_cubic_kernel_equals_numpy_bit_for_bit(dtype: type) -> None:
    """The one-pass cubic kernel of the RBF's hot path gives NumPy's five passes' numbers
    exactly (same float steps in the same precision), NaN and negative squared distances
    included; and an RBF predicts the same with it as with the NumPy passes."""
    from formtwin.metamodel._fused import cubic_from_gram
    from formtwin.metamodel.kernels import kernel_function

    rng = np.random.default_rng(5)
    Z = rng.random((64, 7)).astype(dtype)
    C = np.vstack([Z[:3], rng.random((90, 7))]).astype(dtype)  # some zero distances
    g = Z @ C.T
    zz, cc = np.einsum("ij,ij->i", Z, Z), np.einsum("ij,ij->i", C, C)
    g[5, 7] = np.nan
    g[1, 2] = 10.0  # a squared distance below zero, clipped
    ref = g.copy()
    ref *= -2.0
    ref += zz[:, None]
    ref += cc[None, :]
    assert (ref < 0).any()
    np.maximum(ref, 0.0, out=ref)
    ref = kernel_function("cubic")(ref)
    out = cubic_from_gram(g.copy(), zz, cc)
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, ref)  # NaN in the same place

    U = rng.random((300, 3))
    rbf = RBF(kernel="cubic", length_scales="box", n_centres=120, seed=1).fit(
        U, np.sin(3 * U[:, :2]))
    X = rng.random((257, 3))
    fused = rbf.predict(X)
    rbf.kernel = "cubic_reference"  # not the fused path: NumPy's passes, the same kernel
    try:
        from formtwin.metamodel import kernels

        kernels.KERNELS["cubic_reference"] = kernels.KERNELS["cubic"]
        np.testing.assert_array_equal(rbf.predict(X), fused)
    finally:
        kernels.KERNELS.pop("cubic_reference", None)
