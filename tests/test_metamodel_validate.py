"""k-fold validation figures, plots and the ``formtwin metamodel`` CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from formtwin.cli import main
from formtwin.defaults import analytic_dataset
from formtwin.metamodel import POD, RBF, Metamodel, cross_validate, plot_validation, validate


class _Mean:
    """A broken approximation (an :class:`Approximation`): the training mean everywhere."""

    kind = "mean"

    def fit(self, U: np.ndarray, Y: np.ndarray) -> _Mean:
        self.mean = np.asarray(Y).mean(axis=0)
        return self

    def predict(self, U: np.ndarray) -> np.ndarray:
        return np.tile(self.mean, (U.shape[0], 1))

    def state(self) -> dict[str, np.ndarray]:
        return {"mean": self.mean}


@pytest.fixture(scope="module")
def data():  # type: ignore[no-untyped-def]
    return analytic_dataset(300, seed=11, failure_clearance=0.02)


def _small() -> Metamodel:
    return Metamodel(POD(n_modes=10), RBF(length_scales="box"))


def test_validate_figures_of_a_good_model(data) -> None:  # type: ignore[no-untyped-def]
    figs = validate(_small, data, k=4, seed=1)
    assert figs["n_runs"] == int(data.ok.sum()) and figs["k"] == 4
    # measured on this data (238 runs, unit-box TPS): curve 0.094, variation 0.34,
    # angles nRMSE 0.055 / 0.032
    assert figs["curve_rel_err"] < 0.12
    assert figs["curve_var_rel_err"] < 0.45
    assert max(figs["angle_nrmse"]) < 0.08
    assert figs["curve_rel_err_max"] >= figs["curve_rel_err_median"]
    assert len(figs["worst_curve_runs"]) == 3 and len(figs["angle_rmse_deg"]) == 2
    # a Metamodel instance works as well as a factory and is not changed
    template = _small()
    again = validate(template, data, k=4, seed=1)
    assert again["curve_rel_err"] == pytest.approx(figs["curve_rel_err"], rel=1e-6)
    assert template.curve_model is None


def test_loo_scales_beat_the_unit_box(data) -> None:  # type: ignore[no-untyped-def]
    box = validate(_small, data, k=4, seed=1)
    loo = validate(lambda: Metamodel(POD(n_modes=10), RBF(n_tune=300)), data, k=4, seed=1)
    # measured: curve 0.023 vs 0.094, angles 0.010 / 0.013 vs 0.055 / 0.032
    assert loo["curve_rel_err"] < 0.4 * box["curve_rel_err"]
    assert all(a < 0.5 * b for a, b in zip(loo["angle_nrmse"], box["angle_nrmse"], strict=True))


def test_validate_fails_a_broken_model(data) -> None:  # type: ignore[no-untyped-def]
    figs = validate(lambda: Metamodel(POD(n_modes=10), _Mean()), data, k=4)
    assert figs["curve_var_rel_err"] == pytest.approx(1.0, abs=0.05)
    assert min(figs["angle_nrmse"]) > 0.95
    with pytest.raises(ValueError, match="at least 2 folds"):
        validate(_small, data, k=1)


def test_folds_hold_every_run_out_once(data) -> None:  # type: ignore[no-untyped-def]
    cv = cross_validate(_small, data, k=3, seed=2)
    assert np.bincount(cv.fold).tolist() == [int(np.sum(cv.fold == j)) for j in range(3)]
    assert cv.predicted_curves.shape == cv.curves.shape == (int(data.ok.sum()), 101)
    assert np.all(np.isfinite(cv.predicted_curves))


def test_plots(tmp_path, data) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("matplotlib")
    cv = cross_validate(_small, data, k=3)
    paths = plot_validation(cv, tmp_path / "plots")
    assert [p.name for p in paths] == ["angles.png", "worst_curves.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_cli_fit_and_validate(tmp_path, data, capsys) -> None:  # type: ignore[no-untyped-def]
    ds = data.save(tmp_path / "doe.h5")
    out = tmp_path / "mm.npz"
    assert main(["metamodel", "fit", str(ds), "--out", str(out), "--modes", "8",
                 "--scales", "box"]) == 0
    assert "fitted 8 POD modes" in capsys.readouterr().out
    mm = Metamodel.load(out)
    assert mm.n_modes == 8 and mm.n_train == int(data.ok.sum())
    assert main(["metamodel", "validate", str(ds), "--k", "3", "--energy", "0.999",
                 "--scales", "box", "--json", str(tmp_path / "v.json")]) == 0
    text = capsys.readouterr().out
    assert "curve_rel_err" in text and "angle_nrmse" in text
    assert json.loads((tmp_path / "v.json").read_text())["k"] == 3
    assert main(["metamodel", "fit", str(tmp_path / "missing.h5"), "--out", str(out)]) == 2


def test_residual_model_keeps_the_lines_region() -> None:
    """``line=True``: only interior runs whose every state lies within 2 sigma of its mu
    range enter K_res; the statistics are exactly those of those rows (p18 proposal)."""
    from formtwin.metamodel.validate import CrossValidation, residual_model
    from formtwin.spec import load_spec

    spec = load_spec()
    st, box = spec.state, spec.run_inputs
    rng = np.random.default_rng(3)
    n, n_t = 2000, 5
    X = box.lo + rng.random((n, len(box))) * (box.hi - box.lo)
    near = np.all((X[:, :len(st.names)] >= st.mu_min - 2 * st.sigma)
                  & (X[:, :len(st.names)] <= st.mu_max + 2 * st.sigma), axis=1)
    X[:3] = box.lo  # corners: never used
    near[:3] = False
    r = rng.standard_normal((n, n_t)) * np.where(near, 1.0, 10.0)[:, None]
    cv = CrossValidation(spec, X, r, np.zeros((n, n_t)), np.zeros((n, 2)), np.zeros((n, 2)),
                         np.zeros(n, dtype=np.int64), 0.0)
    assert near.sum() >= 2 * n_t
    res = residual_model(cv)
    assert res.n == near.sum() and res.rows == "interior, line 2 sigma"
    np.testing.assert_allclose(res.curve_cov, r[near].T @ r[near] / near.sum())
    wide = residual_model(cv, line=False)
    assert wide.n == n - 3 and np.trace(wide.curve_cov) > 10 * np.trace(res.curve_cov)
    assert wide.rows == "interior"
