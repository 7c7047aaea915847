"""The study with sensors on the analytic stand-in (formtwin.study.sensor_study): the gauge
pins the thickness where the Kalman filter of its AR(1) says it can, the camera's readings
are the data's angles plus noise, the interval is issued for every tracked product, and
the camera-only EWMA predictor is what it says."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from formtwin.defaults import bundled_metamodel
from formtwin.metamodel import Metamodel
from formtwin.physics.analytic import AnalyticBending
from formtwin.spec import load_spec
from formtwin.study.run import StudySettings, _tasks, run_study
from formtwin.study.sensor_study import ewma_prediction, reported_std, sensor_run
from formtwin.tracker import TrackerConfig, build_tracker

SPEC = load_spec()


def _kalman_rmse(rho: float, sigma: float, noise: float) -> float:
    """Steady-state filtering std of an AR(1) (rho, stationary sigma) observed with noise."""
    p = sigma**2
    for _ in range(200):
        pred = rho**2 * p + (1 - rho**2) * sigma**2
        p = 1.0 / (1.0 / pred + 1.0 / noise**2)
    return math.sqrt(p)


def test_gauge_pins_the_thickness_and_the_camera_calibrates(
        tmp_path: Path, analytic_mm: tuple[Metamodel, Path]) -> None:
    sim = AnalyticBending(SPEC)  # the metamodel: the default fit of 600 of its runs
    mm, mm_path = analytic_mm
    settings = StudySettings(n_products=300, window=200, n_realisations=1, n_repetitions=1,
                             series=(1,), paper_repetitions=0, workers=1, seed=5,
                             tracker=TrackerConfig(n_particles=300))
    study = run_study(settings, tmp_path, mm, mm_path, sim)
    task = _tasks(settings, tmp_path, mm_path, tmp_path / "data")[0]
    curve, both = sensor_run(task, ()), sensor_run(task, ("gauge", "camera"))
    real = study.realisations[0]
    col, sigma = SPEC.state.index["thickness"], SPEC.state["thickness"].sigma
    err = {k: np.sqrt(np.mean((r["mean"][-200:, col] - real.x[-200:, col]) ** 2)) / sigma
           for k, r in (("curve", curve), ("both", both))}
    bound = _kalman_rmse(0.7, 1.0, 0.5)  # the gauge alone, in units of sigma: 0.42
    assert bound == pytest.approx(0.42, abs=0.01)
    assert err["both"] < 1.3 * bound < err["curve"], err
    cam = both["camera"] - real.angles["MM"][:, 1]
    assert abs(cam.std() - 0.2) < 4 * 0.2 / math.sqrt(2 * cam.size)
    np.testing.assert_array_equal(curve["camera"], both["camera"])  # the same readings
    lo, hi = both["final_lo"], both["final_hi"]
    assert not np.isnan(lo).any() and np.all(lo < hi)
    assert np.isfinite(lo).mean() > 0.95  # infinite only where ACI's alpha fell to <= 0
    assert both["rejected"] == 0


def test_ewma_prediction() -> None:
    y = np.array([1.0, np.nan, 3.0, 5.0])
    np.testing.assert_allclose(ewma_prediction(y, 0.5), [np.nan, 1.0, 1.0, 2.0])
    np.testing.assert_allclose(ewma_prediction(y, 1.0)[1:], [1.0, 1.0, 3.0])


def test_reported_std_adds_the_steps_floors_to_the_fused_cloud() -> None:
    """On the bundled metamodel with its calibration (constant floors, mu known: no other
    term), what the step added to the cloud's std is the floors; nothing fused, the
    reported std is the step's; after the gauge is fused the thickness' cloud narrows and
    the reported std is that cloud with the same floors."""
    mm = Metamodel.load(bundled_metamodel("bending"))
    config = TrackerConfig(n_particles=200, n_mc=300, seed=1, intervals="calibrated",
                           mu_known=True, sensors=("gauge",))
    tracker = build_tracker(mm, config)
    # never resampled: the tracker keeps the weighted cloud the step's estimate was made of
    kept = build_tracker(mm, dataclasses.replace(config, ess_threshold=0.0))
    assert tracker.floors is not None and tracker.floors.b.max() > 0
    b = tracker.floors.b
    col = mm.spec.state.index["thickness"]
    x = np.r_[mm.spec.state.mu_mid, 0.5 * (mm.spec.params.lo + mm.spec.params.hi)]
    for curve in mm.predict_curves(np.tile(x, (3, 1))):
        est = tracker.step(curve)
        cloud = tracker.posterior().std
        added = np.maximum(est.std**2 - cloud**2, 0.0)
        # nothing fused: the reported std is the step's estimate's
        np.testing.assert_allclose(reported_std(tracker.posterior().std, added), est.std,
                                   rtol=1e-9)
        # what the step adds to its own cloud is the floors, to rounding
        est_kept = kept.step(curve)
        cloud_kept = kept.posterior().std
        np.testing.assert_allclose(est_kept.std**2 - cloud_kept**2, b**2,
                                   atol=1e-12 * float(np.max(est_kept.std**2)))
    tracker.fuse(2, "gauge", float(x[col]))
    fused = tracker.posterior().std
    assert fused[col] < cloud[col]
    np.testing.assert_allclose(reported_std(fused, added),
                               np.sqrt(fused**2 + tracker.floors.b**2), rtol=0.02)
