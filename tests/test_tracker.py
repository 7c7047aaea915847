"""Tracker on the analytic stand-in: real-number accuracy, checkpoints, bad input, collapse."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.production import draw_production_run
from formtwin.spec import ProcessSpec
from formtwin.tracker import Estimates, Tracker, TrackerConfig


@pytest.fixture(scope="module")
def series1(spec: ProcessSpec, model: AnalyticModel) -> dict[str, np.ndarray]:
    """Paper series 1 on the stand-in: data from the filter's own model, mu known."""
    run = draw_production_run(spec, 150, np.random.default_rng(11), deviation=False)
    X = run.inputs
    return {"mu": run.mu, "X": X, "curves": model.predict_curves(X),
            "angles": model.predict_angles(X)}


@pytest.fixture(scope="module")
def mm(model: AnalyticModel, series1: dict[str, np.ndarray]) -> MeasurementModel:
    return MeasurementModel.from_monte_carlo(model, mu=series1["mu"], n=3000,
                                             rng=np.random.default_rng(2))


def test_series1_estimates_punch_end_distance_and_press_stiffness(
        spec: ProcessSpec, model: AnalyticModel, mm: MeasurementModel,
        series1: dict[str, np.ndarray]) -> None:
    cfg = TrackerConfig(n_particles=500, mu=tuple(series1["mu"]), estimate_deviation=False,
                        seed=3)
    est = Tracker(model, mm, cfg).run(series1["curves"])
    assert isinstance(est, Estimates) and len(est) == 150
    X, half = series1["X"], slice(75, None)
    idx = spec.augmented.index

    def nrmse(name: str, scale: float) -> float:
        err = est.mean[half, idx[name]] - X[half, idx[name]]
        return float(np.sqrt(np.mean(err**2)) / scale)

    st, pa = spec.state, spec.params
    j = pa.index["press_stiffness"]
    # paper Fig. 4 normalisation; a random/broken estimator scores ~1 or more
    assert nrmse("punch_end_distance", st["punch_end_distance"].sigma) < 0.3
    assert nrmse("press_stiffness", (pa.hi[j] - pa.lo[j]) / np.sqrt(6)) < 0.2
    assert nrmse("vertical_alignment", 0.02 / np.sqrt(6)) < 0.2
    ang = np.sqrt(np.mean((est.angles_mean[half, 0] - series1["angles"][half, 0]) ** 2))
    assert ang / series1["angles"][:, 0].std() < 1.0
    # the posterior std is a sane error bar: truth mostly inside mean +- 3 std
    k = idx["punch_end_distance"]
    inside = np.abs(est.mean[half, k] - X[half, k]) < 3 * est.std[half, k] + 1e-12
    assert inside.mean() > 0.8
    assert np.all(est.ess >= 1) and not est.collapsed.any()
    assert np.all(est.mean[:, 10:] == 0) and np.all(est.std[:, 10:] == 0)


def test_checkpoint_restore_continues_bit_for_bit(
        tmp_path: Path, model: AnalyticModel, mm: MeasurementModel,
        series1: dict[str, np.ndarray]) -> None:
    curves = series1["curves"][:12]
    cfg = TrackerConfig(n_particles=100, seed=5, resampling="stratified")
    a = Tracker(model, mm, cfg)
    a.run(curves[:6])
    path = a.checkpoint(tmp_path / "ck.npz")
    rest_a = a.run(curves[6:])
    b = Tracker.restore(path, model, mm)
    assert b.n_steps == 6 and b.config == cfg
    rest_b = b.run(curves[6:])
    for f in ("mean", "std", "angles_mean", "angles_std", "ess", "loglik"):
        np.testing.assert_array_equal(getattr(rest_a, f), getattr(rest_b, f))
    np.testing.assert_array_equal(a.particles, b.particles)
    np.testing.assert_array_equal(rest_b.index, np.arange(6, 12))
    # a fresh (never stepped) tracker round-trips too
    c = Tracker(model, mm, cfg)
    c.checkpoint(tmp_path / "fresh.npz")
    d = Tracker.restore(tmp_path / "fresh.npz", model, mm)
    np.testing.assert_array_equal(c.step(curves[0]).mean, d.step(curves[0]).mean)
    np.savez(tmp_path / "junk.npz", a=np.zeros(2))
    with pytest.raises(ValueError, match="not a tracker checkpoint"):
        Tracker.restore(tmp_path / "junk.npz", model, mm)


def test_state_bytes_continue_bit_for_bit_in_place_and_new(
        model: AnalyticModel, mm: MeasurementModel, series1: dict[str, np.ndarray]) -> None:
    curves = series1["curves"][:10]
    cfg = TrackerConfig(n_particles=80, seed=9)
    a = Tracker(model, mm, cfg)
    a.run(curves[:5])
    saved = a.state_bytes()
    want = a.run(curves[5:])
    b = Tracker.from_state_bytes(saved, model, mm)  # a new tracker
    a.load_state_bytes(saved)  # the same tracker, rewound in place
    for tr in (a, b):
        got = tr.run(curves[5:])
        for f in ("mean", "std", "angles_mean", "ess", "loglik"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
    assert a.state_bytes() == b.state_bytes()
    with pytest.raises(ValueError, match="bad magic"):
        Tracker.from_state_bytes(b"junk" * 10, model, mm)
    with pytest.raises(ValueError, match="bytes, expected"):
        a.load_state_bytes(saved[:-8])
    other = Tracker(model, mm, TrackerConfig(n_particles=81, seed=9))
    with pytest.raises(ValueError, match="saved with config"):
        other.load_state_bytes(saved)


def test_simulate_draws_the_run_the_model_assumes(model: AnalyticModel,
                                                  mm: MeasurementModel) -> None:
    cfg = TrackerConfig(mu=tuple(model.spec.state.mu_min), estimate_deviation=False)
    tr = Tracker(model, mm, cfg)
    run, curves = tr.ssm.simulate(400, np.random.default_rng(1))
    st = model.spec.state
    np.testing.assert_array_equal(run.mu, st.mu_min)
    assert np.all(run.theta_d == 0) and run.truth.shape == (400, 18)
    np.testing.assert_array_equal(curves, model.predict_curves(run.inputs))
    # the states scatter about mu with the spec's sigma (AR(1) stationary law, reflected)
    k = st.index["punch_end_distance"]
    assert abs(run.x[:, k].mean() - st.mu_min[k]) < 0.5 * st.sigma[k]
    # with the deviation estimated, the curves are g(model, theta_d)
    tr2 = Tracker(model, mm, TrackerConfig())
    run2, curves2 = tr2.ssm.simulate(5, np.random.default_rng(2))
    assert np.any(run2.theta_d != 0)
    np.testing.assert_allclose(
        curves2, tr2.ssm.deviation.apply(model.predict_curves(run2.inputs),
                                         np.tile(run2.theta_d, (5, 1))))


@pytest.mark.parametrize("bad,message", [
    (np.zeros(50), "50 samples, expected 101"),
    (np.zeros((1, 101)), r"shape \(1, 101\)"),
    (np.r_[np.zeros(100), np.nan], "non-finite"),
    (np.r_[np.zeros(100), np.inf], "non-finite"),
    (["a"] * 101, "dtype"),
    ("1,2,3", "str"),
    (np.zeros(101, dtype=complex), "dtype"),
    (None, "dtype"),
    ([[1.0, 2.0], [1.0]], "cannot be read|dtype"),
])
def test_malformed_curves_raise_and_leave_the_state(
        model: AnalyticModel, mm: MeasurementModel, series1: dict[str, np.ndarray],
        bad: object, message: str) -> None:
    tr = Tracker(model, mm, TrackerConfig(n_particles=50))
    tr.step(series1["curves"][0])
    before = (tr.particles.copy(), tr.filter.logw.copy(), tr.rng.bit_generator.state)
    with pytest.raises(ValueError, match=message):
        tr.step(bad)
    assert tr.n_steps == 1
    np.testing.assert_array_equal(tr.particles, before[0])
    np.testing.assert_array_equal(tr.filter.logw, before[1])
    assert tr.rng.bit_generator.state == before[2]


def test_weight_collapse_is_flagged_and_recovered(
        spec: ProcessSpec, mm: MeasurementModel, series1: dict[str, np.ndarray]) -> None:
    class Flaky(AnalyticModel):
        broken = False

        def predict_curves(self, X: np.ndarray) -> np.ndarray:
            out = super().predict_curves(X)
            return np.full_like(out, np.nan) if self.broken else out

    model = Flaky(spec)
    tr = Tracker(model, mm, TrackerConfig(n_particles=100, estimate_deviation=False))
    tr.run(series1["curves"][:5])
    model.broken = True
    e = tr.step(series1["curves"][5])
    assert e.collapsed and e.loglik == -np.inf
    assert np.all(np.isfinite(e.mean)) and np.all(np.isfinite(e.std))
    assert np.all(np.isfinite(e.angles_mean)) and e.ess == pytest.approx(100)
    json.dumps(e.to_dict(), allow_nan=False)  # JSON-safe: -inf -> null
    model.broken = False
    e2 = tr.step(series1["curves"][6])
    assert not e2.collapsed and np.isfinite(e2.loglik)


def test_estimate_values_and_config(model: AnalyticModel, mm: MeasurementModel,
                                    series1: dict[str, np.ndarray]) -> None:
    tr = Tracker(model, mm, TrackerConfig(n_particles=64, seed=1))
    e = tr.step(series1["curves"][0])
    assert e.index == 0 and len(e.names) == 18 and e.names[-1] == "speed_scaling_4"
    assert np.any(tr.particles[:, 10:] != 0)  # deviation estimated by default
    d = e.to_dict()
    assert set(d["mean"]) == set(e.names)
    assert e["punch_end_distance"] == d["mean"]["punch_end_distance"]
    json.dumps(d, allow_nan=False)
    cols = tr.run(series1["curves"][1:3]).columns()
    assert cols["index"].tolist() == [1, 2] and "std_press_stiffness" in cols
    with pytest.raises(ValueError, match="config.mu has 3 values, expected 7"):
        Tracker(model, mm, TrackerConfig(mu=(1.0, 2.0, 3.0)))
    with pytest.raises(ValueError, match="unknown resampling scheme"):
        Tracker(model, mm, TrackerConfig(resampling="nope"))
    cfg = dataclasses.replace(TrackerConfig(), mu=np.arange(7.0))
    assert cfg.mu == tuple(float(v) for v in range(7))
    assert TrackerConfig.from_json(cfg.to_json()) == cfg


def test_measurement_domain_comparison_runs_and_is_validated(
        model: AnalyticModel, mm: MeasurementModel, series1: dict[str, np.ndarray]) -> None:
    cfg = TrackerConfig(n_particles=64, compare="measurement")
    est = Tracker(model, mm, cfg).run(series1["curves"][:5])
    assert np.all(np.isfinite(est.mean)) and np.all(np.isfinite(est.loglik))
    assert TrackerConfig.from_json(cfg.to_json()).compare == "measurement"
    with pytest.raises(ValueError, match="known: model, measurement"):
        TrackerConfig(compare="real")


def test_blocks_of_particles_give_the_same_numbers(
        monkeypatch: pytest.MonkeyPatch, model: AnalyticModel, mm: MeasurementModel,
        series1: dict[str, np.ndarray]) -> None:
    import formtwin.tracker as tracker_mod

    curves = series1["curves"][:3]
    whole = Tracker(model, mm, TrackerConfig(n_particles=50, seed=2)).run(curves)
    monkeypatch.setattr(tracker_mod, "CHUNK", 7)
    blocks = Tracker(model, mm, TrackerConfig(n_particles=50, seed=2)).run(curves)
    np.testing.assert_allclose(blocks.mean, whole.mean, rtol=1e-12)
    np.testing.assert_allclose(blocks.angles_mean, whole.angles_mean, rtol=1e-12)


def test_regularised_filter_by_name_stays_in_bounds(
        spec: ProcessSpec, model: AnalyticModel, mm: MeasurementModel,
        series1: dict[str, np.ndarray]) -> None:
    tr = Tracker(model, mm, TrackerConfig(n_particles=100, filter="regularised",
                                          estimate_deviation=False))
    tr.run(series1["curves"][:5])
    x = tr.particles
    assert x is not None
    aug = spec.augmented
    assert np.all(x[:, 10:] == 0)  # theta_d not estimated: stays 0 after the kernel move
    assert np.all(x[:, :10] >= aug.lo[:10]) and np.all(x[:, :10] <= aug.hi[:10])
    with pytest.raises(ValueError, match="unknown filter"):
        Tracker(model, mm, TrackerConfig(filter="kalman"))


def test_a_failing_model_leaves_the_tracker_untouched(
        spec: ProcessSpec, mm: MeasurementModel, series1: dict[str, np.ndarray]) -> None:
    class Broken(AnalyticModel):
        fail = False

        def predict_curves(self, X: np.ndarray) -> np.ndarray:
            if self.fail:
                raise RuntimeError("model server down")
            return super().predict_curves(X)

    model = Broken(spec)
    a = Tracker(model, mm, TrackerConfig(n_particles=50, seed=4))
    b = Tracker(model, mm, TrackerConfig(n_particles=50, seed=4))
    a.step(series1["curves"][0])
    b.step(series1["curves"][0])
    model.fail = True
    with pytest.raises(RuntimeError):
        a.step(series1["curves"][1])
    model.fail = False
    assert a.n_steps == 1
    np.testing.assert_array_equal(a.step(series1["curves"][1]).mean,
                                  b.step(series1["curves"][1]).mean)


def test_angles_from_a_subsample_of_particles(
        model: AnalyticModel, mm: MeasurementModel, series1: dict[str, np.ndarray]) -> None:
    curves = series1["curves"][:20]
    cfg = TrackerConfig(n_particles=400, mu=tuple(series1["mu"]), estimate_deviation=False,
                        angle_particles=None)
    full = Tracker(model, mm, cfg).run(curves)
    sub = Tracker(model, mm, dataclasses.replace(cfg, angle_particles=100)).run(curves)
    # the subsample's draws shift the RNG stream, so the two runs agree only statistically:
    # compare the predicted angles against their posterior spread
    err = np.abs(sub.angles_mean[-10:] - full.angles_mean[-10:])
    assert np.all(err < 5 * full.angles_std[-10:] + 0.05)
    with pytest.raises(ValueError, match="angle_particles"):
        TrackerConfig(angle_particles=0)


def test_angles_skip_only_negligible_weight(
        model: AnalyticModel, mm: MeasurementModel, series1: dict[str, np.ndarray],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The lightest particles (weights summing to <= ANGLE_MASS) are not evaluated by the
    angle model: the angles' mean moves by at most ~2 ANGLE_MASS times their spread, their
    variance by ANGLE_MASS times (spread^2 + var), the states and the RNG stream not at all
    (the analytic model has no float32 rounding)."""
    from formtwin.tracker import core

    eps = core.ANGLE_MASS
    assert 0 < eps <= 1e-3
    curves = series1["curves"][:30]
    cfg = TrackerConfig(n_particles=400, mu=tuple(series1["mu"]), mu_known=True,
                        estimate_deviation=False)
    rows: list[int] = []
    predict = type(model).predict_angles

    def counting(self, X, u=None):  # type: ignore[no-untyped-def]
        rows.append(X.shape[0])
        return predict(self, X, u)

    monkeypatch.setattr(type(model), "predict_angles", counting)
    pruned = Tracker(model, mm, cfg).run(curves)
    assert sum(rows) < 400 * len(curves)  # some particles were skipped
    monkeypatch.setattr(core, "ANGLE_MASS", 0.0)
    rows.clear()
    full = Tracker(model, mm, cfg).run(curves)
    assert sum(rows) == 400 * len(curves)
    np.testing.assert_array_equal(pruned.mean, full.mean)
    np.testing.assert_array_equal(pruned.std, full.std)
    spread = np.ptp(full.angles_mean) + full.angles_std.max()
    np.testing.assert_allclose(pruned.angles_mean, full.angles_mean, rtol=0,
                               atol=2 * eps * spread)
    # std from the variance: |d std| <= |d var| / std
    np.testing.assert_allclose(pruned.angles_std, full.angles_std, rtol=0,
                               atol=eps * (spread**2 + full.angles_std.max() ** 2)
                               / full.angles_std.min())
    assert not np.array_equal(pruned.angles_mean, full.angles_mean)  # the cut is real
    w = np.array([0.6, 1e-12, 3e-10, 0.4 - 3.01e-10])
    assert core.heaviest(w, 1e-9).tolist() == [0, 3]
    assert core.heaviest(w, 0.0).tolist() == [0, 1, 2, 3]


def _heaviest_by_full_sort(w: np.ndarray, mass: float) -> list[int]:
    """The reference: stable sort of all weights, drop the lightest prefix summing to <= mass."""
    order = np.argsort(w, kind="stable")
    n_drop = int(np.searchsorted(np.cumsum(w[order]), mass, side="right"))
    return sorted(order[n_drop:].tolist())


def test_heaviest_sorts_only_the_light_weights_with_the_same_result() -> None:
    """``heaviest`` sorts only the weights <= mass; the kept set is the full sort's, ties
    (equal weights, a weight equal to mass) and all-dropped/none-dropped cases included."""
    from formtwin.tracker import core

    rng = np.random.default_rng(5)
    cases = [np.array([1e-10, 1e-10, 5e-10, 1.0 - 7e-10]), np.array([1e-9, 1.0 - 1e-9]),
             np.array([0.25, 0.25, 0.25, 0.25]), np.array([0.0, 0.0, 1.0])]
    for _ in range(200):
        w = np.exp(rng.normal(0.0, rng.uniform(1.0, 15.0), rng.integers(1, 60)))
        w[rng.random(w.size) < 0.2] = w[0]  # ties
        cases.append(w / w.sum())
    for w in cases:
        for mass in (0.0, 1e-9, 1e-3, 0.3, 1.0):
            assert core.heaviest(w, mass).tolist() == _heaviest_by_full_sort(w, mass)


def test_estimate_std_is_the_steps_std(model: AnalyticModel, mm: MeasurementModel,
                                       series1: dict[str, np.ndarray]) -> None:
    """The estimate's mean is the step's, bit for bit; its std (one pass with the
    intervals' covariance, ``tracker._kernels.cloud_moments``) is ``Step.std`` to the
    rounding of another summation order (``N eps`` relative; ``intervals="cloud"``:
    nothing added)."""
    tr = Tracker(model, mm, TrackerConfig(n_particles=200, mu=tuple(series1["mu"]),
                                          intervals="cloud", seed=4))
    steps = []
    step = tr.filter.step

    def keep(y):  # type: ignore[no-untyped-def]
        steps.append(step(y))
        return steps[-1]

    tr.filter.step = keep  # type: ignore[method-assign]
    for c in series1["curves"][:5]:
        e = tr.step(c)
        np.testing.assert_allclose(e.std, steps[-1].std()[:len(e.std)],
                                   rtol=200 * np.finfo(float).eps)
        np.testing.assert_array_equal(e.mean, steps[-1].mean()[:len(e.mean)])
