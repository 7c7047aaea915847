"""The closed-loop study with the line's real sensors on the analytic stand-in as both
plant and model: the camera's noise enters what the controllers read and nothing else, the
exact camera reproduces the control study's EWMA, the oracle hits the target, the gauge
fused before the setting is chosen sharpens the feedforward's prediction."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.defaults import analytic_model, physics_model
from formtwin.study.control import (
    R2R_LAMS,
    ControlStudySettings,
    plant_run,
    r2r,
    r2r_gain,
    study_controllers,
)
from formtwin.study.control_ff import ADAPTIVE, track_and_choose
from formtwin.study.control_sensors import (
    GRID,
    SensorControlSettings,
    loo_ratios,
    reference_limit,
    run_sensor_control,
    sensor_dataset,
    sensor_draws,
)
from formtwin.tracker import TrackerConfig

TARGET = 91.5


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    model = analytic_model()
    physics = physics_model("analytic", model.spec)
    base = ControlStudySettings(products=40, datasets=2, burn_in=5, interp_check=0, workers=1,
                                seed=3, target=TARGET,
                                tracker=TrackerConfig(n_particles=60, n_mc=500,
                                                      estimate_deviation=True))
    settings = SensorControlSettings(base=base, camera_noises=(0.0, 0.2), sets=("curve",))
    folder = tmp_path_factory.mktemp("sensor_control")
    gain = r2r_gain(model, np.random.default_rng(base.seed))
    out = sensor_dataset(model, physics, settings, 0, folder, TARGET, gain)
    return {"model": model, "physics": physics, "base": base, "folder": folder,
            "gain": gain, "out": out}


def test_exact_camera_is_the_control_studys_ewma(case: dict) -> None:
    m, base, out = case["model"], case["base"], case["out"]
    run, _, ok, plant = plant_run(m.spec, case["physics"], base, 0, case["folder"])
    act, _, nominal = study_controllers(m, base, TARGET)
    for row, lam in enumerate(R2R_LAMS):
        u = r2r(plant, ok, run.n, TARGET, case["gain"], lam, act, nominal, 1)
        ref = np.where(ok, [plant(i, u[i]) for i in range(run.n)], np.nan)
        np.testing.assert_allclose(out["angle_r2r_0"][row], ref, rtol=0, atol=1e-9)
    # the analytic plant is the model: on target wherever the actuator's step allows
    a = out["angle_oracle"]
    assert np.mean(np.abs(a[np.isfinite(a)] - TARGET) < 1e-6) > 0.9


def test_camera_noise_reaches_the_ewma_one_product_late(case: dict) -> None:
    out, base = case["out"], case["base"]
    z, _ = sensor_draws(base.seed, 0, base.products)
    row = R2R_LAMS.index(1.0)  # the EWMA of weight 1 cancels the last reading, noise and all
    diff = out["angle_r2r_1"][row] - out["angle_r2r_0"][row]
    ok = np.isfinite(diff[1:])
    # the noise of product i - 1's reading moves product i's angle against it
    assert np.corrcoef(diff[1:][ok], -z[:-1][ok])[0, 1] > 0.9
    assert np.nanstd(diff) == pytest.approx(0.2, rel=0.35)
    # the feedforward's rows: one per (lam, rho) and noise, its trim reads the same camera
    assert out["angle_curve_0"].shape == out["angle_curve_1"].shape == (len(GRID),
                                                                        base.products)
    assert not np.allclose(out["angle_curve_0"], out["angle_curve_1"], equal_nan=True)


def test_gauge_fused_before_the_choice_sharpens_the_thickness(case: dict) -> None:
    m, base = case["model"], case["base"]
    run, curves, ok, plant = plant_run(m.spec, case["physics"], base, 0, case["folder"])
    _, ff, nominal = study_controllers(m, base, TARGET)
    thick = m.spec.state.index["thickness"]
    _, z = sensor_draws(base.seed, 0, run.n)
    gauge = run.x[:, thick] + 0.5e-3 * z  # mm: the spec's 0.5 um
    errors = []
    for sensors, readings in (((), None), (("gauge",), {"gauge": gauge})):
        config = TrackerConfig(n_particles=200, n_mc=500, estimate_deviation=True, seed=3,
                               sensors=sensors)
        p = track_and_choose(m, config, curves, ok, plant, ff, [(0.0, 1.0, 0.0)], nominal,
                             readings=readings)
        errors.append(np.sqrt(np.nanmean((p.input_mean[10:, thick] - run.x[10:, thick]) ** 2)))
    # a 0.5 um reading of a 1 um in-run spread: the posterior error at most ~0.45 um
    assert errors[1] < 0.6e-3 < errors[0]


def test_the_predictive_feedforward_runs_beside_and_on_the_camera_fused_posterior(
        case: dict) -> None:
    out, n = case["out"], case["base"].products
    for key in ("angle_curve_predictive_0", "angle_curve_predictive_1", "angle_curve_fused",
                "reference_curve", "reference_curve_fused"):
        assert out[key].shape == (n,) and np.isfinite(out[key][out["ok"]]).all()
    # the same camera values (0.2 deg), the same controller: fusing them into the particles
    # changes the posterior and so the settings
    assert not np.allclose(out["angle_curve_fused"], out["angle_curve_predictive_1"])
    # before the first camera value both passes choose on the same posterior
    assert out["reference_curve_fused"][0] == out["reference_curve"][0]
    a = out["angle_curve_predictive_0"][case["base"].burn_in:]
    assert np.nanstd(a) < np.nanstd(out["angle_fixed"][case["base"].burn_in:])


def test_the_camera_in_the_filter_serves_one_controller(case: dict) -> None:
    m, base = case["model"], case["base"]
    run, curves, ok, plant = plant_run(m.spec, case["physics"], base, 0, case["folder"])
    _, ff, nominal = study_controllers(m, base, TARGET)
    with pytest.raises(ValueError, match="camera in the filter: one controller \\(got 2\\)"):
        track_and_choose(m, base.tracker, curves, ok, plant, ff,
                         [(0.1, ADAPTIVE, 0.0), (0.1, 1.0, 0.0)], nominal, camera="camera")


def test_reference_limit_is_the_residual_of_the_best_line() -> None:
    rng = np.random.default_rng(5)
    results, r = [], 0.6
    for _ in range(3):
        y = rng.standard_normal(2000)
        c = r * y + np.sqrt(1 - r**2) * rng.standard_normal(2000)
        results.append({"reference_s": np.r_[np.nan, c], "angle_fixed": np.r_[0.0, y]})
    fixed, ewma = np.ones(3), np.full((3, 2), 2.0)
    got = reference_limit(results, "s", 0, 1, fixed, ewma)
    corr = [np.corrcoef(q["reference_s"][1:], q["angle_fixed"][1:])[0, 1] for q in results]
    np.testing.assert_allclose(got["corr"], np.round(corr, 3))
    assert got["ff_vs_ewma_median"] == pytest.approx(
        np.median(np.sqrt(1 - np.square(corr))) / 2.0, abs=1e-4)
    assert got["ff_vs_ewma_median"] == pytest.approx(0.4, abs=0.02)  # sqrt(1 - 0.36) / 2


def test_noise_of_the_wrong_shape_is_refused(case: dict) -> None:
    m, base = case["model"], case["base"]
    run, curves, ok, plant = plant_run(m.spec, case["physics"], base, 0, case["folder"])
    _, ff, nominal = study_controllers(m, base, TARGET)
    with pytest.raises(ValueError, match=r"noise: shape \(1, 3\), expected \(2, 40\)"):
        track_and_choose(m, base.tracker, curves, ok, plant, ff,
                         [(0.1, ADAPTIVE, 0.0), (0.1, 1.0, 0.0)], nominal,
                         noise=np.zeros((1, 3)))


def test_leave_one_out_choice_scores_each_dataset_with_the_others_weights() -> None:
    rng = np.random.default_rng(0)
    ff, ew, fixed = rng.random((4, 5)) + 0.5, rng.random((4, 3)) + 0.5, rng.random(4) + 1
    ratio, a, b = loo_ratios(ff, ew, fixed)
    for k in range(4):
        others = [j for j in range(4) if j != k]
        assert a[k] == int(np.argmin((ff[others] / fixed[others, None]).mean(0)))
        assert b[k] == int(np.argmin((ew[others] / fixed[others, None]).mean(0)))
        assert ratio[k] == ff[k, a[k]] / ew[k, b[k]]


def test_unknown_set_is_named() -> None:
    with pytest.raises(ValueError, match="sets = \\['camera'\\]: unknown"):
        SensorControlSettings(sets=("camera",))


def test_the_summary_scores_every_feedforward_against_the_ewma(case: dict) -> None:
    base = case["base"]
    settings = SensorControlSettings(base=base, camera_noises=(0.0, 0.2), sets=("curve",))
    s = run_sensor_control(case["model"], case["physics"], settings, case["folder"] / "sum")
    cell = s["curve"]["0.2"]
    for part in (cell, cell["predictive"], s["curve"]["fused"]):
        assert len(part["ff_vs_ewma"]["per_dataset"]) == base.datasets
        assert part["ff_vs_ewma"]["median"] == pytest.approx(
            np.median(part["ff_vs_ewma"]["per_dataset"]), abs=2e-3)
    assert s["curve"]["fused"]["camera_deg"] == 0.2
    limit = s["curve"]["fused"]["reference_limit"]
    assert len(limit["corr"]) == base.datasets and all(-1 <= r <= 1 for r in limit["corr"])
    # a second call reuses the stored datasets: the same numbers
    assert run_sensor_control(case["model"], case["physics"], settings,
                              case["folder"] / "sum") == s
