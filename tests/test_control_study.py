"""The closed-loop control study end to end on the analytic stand-in as both plant and
model, target within reach: the oracle hits the target exactly (the plant's angle is
linear in u, so the three-point interpolation is exact), feedforward from the estimates
beats no control, the trims remove the open feedforward's bias, results are reused on a
second call; the measure of what the estimates know of the angle against known relations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from formtwin.defaults import analytic_model, physics_model
from formtwin.study.control import (
    FF_RHOS,
    FF_WEIGHTS,
    R2R_LAMS,
    ControlStudySettings,
    PlantAngles,
)
from formtwin.study.control_ff import ADAPTIVE
from formtwin.study.control_run import angle_drivers, estimate_worth, run_control_study
from formtwin.tracker import TrackerConfig


def test_plant_interpolation_is_exact_for_a_quadratic() -> None:
    u3 = np.array([-1.0, 0.5, 2.0])
    a3 = np.array([[3 + 2 * u - 0.5 * u * u for u in u3]])
    p = PlantAngles(u3, a3)
    assert p(0, 1.3) == pytest.approx(3 + 2.6 - 0.5 * 1.69, abs=1e-12)


def test_control_study_on_the_analytic_stand_in(tmp_path: Path) -> None:
    model = analytic_model()
    physics = physics_model("analytic", model.spec)
    settings = ControlStudySettings(
        products=60, datasets=2, burn_in=10, interp_check=5, workers=1, seed=5, target=91.5,
        angle_sd=0.05,
        tracker=TrackerConfig(n_particles=100, n_mc=1000, estimate_deviation=True))
    s = run_control_study(model, physics, settings, tmp_path)
    assert s["plant_interpolation_max_abs_error_deg"] < 1e-9
    assert s["oracle"]["std_deg"] < 1e-6 and abs(s["oracle"]["mean_error_deg"]) < 1e-6
    assert s["feedforward"]["std_deg"] < s["fixed"]["std_deg"]
    assert s["feedforward_angle"]["std_deg"] < s["fixed"]["std_deg"]
    # the trims bring the mean error near 0 where the open feedforward is biased (mu unknown)
    assert abs(s["feedforward"]["mean_error_deg"]) < 0.2 < s["feedforward_open"]["mean_error_deg"]
    assert s["r2r_lam"] in R2R_LAMS and s["full_lam"] in FF_RHOS[0.0]
    assert s["fffixed_weight"] in FF_WEIGHTS and s["ff_lam"] in FF_RHOS[s["ff_rho"]]
    assert s["fffixed_lam"] in FF_RHOS[s["fffixed_rho"]]
    # the service's weights are the best of the grid on all datasets by the mean ratio of
    # the std to fixed u's within each dataset; each dataset's the best on the others (leave
    # one out), and the controllers scored there are those: the feedforward (the learned
    # weight, ADAPTIVE in the grid) and the fixed-weight one, chosen apart
    t = s["tuning_std_deg"]
    grid, sds = np.array(t["ff_grid"]), np.array(t["ff_per_dataset"])
    ratio = sds / np.array(t["fixed_per_dataset"])[:, None]
    assert np.array(t["fixed_per_dataset"]) == pytest.approx(
        s["per_dataset_std_deg"]["fixed"], abs=1e-4)
    fixed, learned = grid[:, 1] != ADAPTIVE, grid[:, 1] == ADAPTIVE
    assert learned.sum() == sum(len(v) for v in FF_RHOS.values())
    only_fixed, only_learned = np.where(fixed, 0.0, np.inf), np.where(learned, 0.0, np.inf)
    assert list(grid[int(np.argmin(ratio.mean(0) + only_fixed))]) == [
        s["fffixed_lam"], s["fffixed_weight"], s["fffixed_rho"]]
    assert list(grid[int(np.argmin(ratio.mean(0) + only_learned))]) == [
        s["ff_lam"], ADAPTIVE, s["ff_rho"]]
    for k, w in enumerate(s["per_dataset_weights"]):
        others = np.delete(ratio, k, 0).mean(0)
        row = int(np.argmin(others + only_fixed))
        assert list(grid[row]) == [w["fffixed_lam"], w["fffixed_weight"], w["fffixed_rho"]]
        assert s["per_dataset_std_deg"]["feedforward_fixed"][k] == pytest.approx(
            sds[k, row], abs=1e-4)
        row = int(np.argmin(others + only_learned))
        assert list(grid[row]) == [w["ff_lam"], ADAPTIVE, w["ff_rho"]]
        assert s["per_dataset_std_deg"]["feedforward"][k] == pytest.approx(sds[k, row],
                                                                           abs=1e-4)
        r2r = np.array(t["r2r_per_dataset"]) / np.array(t["fixed_per_dataset"])[:, None]
        assert w["r2r_lam"] == R2R_LAMS[int(np.argmin(np.delete(r2r, k, 0).mean(0)))]
    # weight 0: the trim alone, the same (lam, rho)
    assert s["trim_only"]["products"] == s["feedforward"]["products"]
    r = s["within_dataset_std_ratio_ff_vs_fixed"]
    assert r["per_dataset"][0] == pytest.approx(
        s["per_dataset_std_deg"]["feedforward"][0] / s["per_dataset_std_deg"]["fixed"][0],
        abs=2e-3)
    assert -1 <= s["estimate_change_corr"] <= 1
    assert s["angle2_std_ratio_ff_vs_fixed"] == pytest.approx(
        s["feedforward"]["std_deg"] / s["fixed"]["std_deg"], rel=1e-3)
    assert 0 <= s["feedforward_interval_coverage"] <= 1
    assert (tmp_path / "control_study.png").stat().st_size > 10_000
    again = run_control_study(model, physics, settings, tmp_path)  # reused, identical
    assert json.dumps(again, sort_keys=True) == json.dumps(s, sort_keys=True)


def test_results_are_keyed_by_the_model_not_only_its_version() -> None:
    """A metamodel refitted on the same physics version must not reuse old results."""
    from types import SimpleNamespace

    from formtwin.study.control_run import result_key

    model = analytic_model()
    settings = ControlStudySettings(products=60, datasets=2)
    shifted = SimpleNamespace(spec=model.spec, predict_angles=model.predict_angles,
                              predict_curves=lambda X: model.predict_curves(X) + 1e-9)
    key = result_key(settings, 90.0, "v1", model)
    assert key == result_key(settings, 90.0, "v1", model)
    assert key != result_key(settings, 90.0, "v1", shifted)  # type: ignore[arg-type]
    assert key != result_key(settings, 90.1, "v1", model)
    # the same curves with another K_res (e.g. statistics of another rule): other results
    cov = SimpleNamespace(curve_cov=np.eye(3), angle_cov=np.eye(2))
    with_res = SimpleNamespace(spec=model.spec, predict_angles=model.predict_angles,
                               predict_curves=model.predict_curves, residuals=cov)
    other = SimpleNamespace(spec=model.spec, predict_angles=model.predict_angles,
                            predict_curves=model.predict_curves,
                            residuals=SimpleNamespace(curve_cov=2 * np.eye(3),
                                                      angle_cov=np.eye(2)))
    k_res = result_key(settings, 90.0, "v1", with_res)  # type: ignore[arg-type]
    assert k_res != key and k_res != result_key(settings, 90.0, "v1", other)  # type: ignore[arg-type]


def test_estimate_worth_against_known_relations() -> None:
    """Estimates that are the plant's angle halved plus a per-dataset offset: levels and
    changes correlate exactly, the plant's change is twice the estimate's."""
    rng = np.random.default_rng(0)
    results = []
    for off in (0.0, 3.0):
        a = 72.0 + np.cumsum(rng.normal(0, 0.05, 200))
        results.append({"angle_fixed": a, "nominal_mean": off + 0.5 * a})
    w = estimate_worth(results, burn_in=20)
    assert w["estimate_level_corr"] == pytest.approx(1.0)
    assert w["estimate_change_corr"] == pytest.approx(1.0)
    assert w["estimate_change_slope"] == pytest.approx(2.0, abs=1e-4)
    assert w["plant_change_std_deg"] == pytest.approx(2 * w["estimate_change_std_deg"], rel=1e-3)


def test_angle_drivers_against_a_linear_angle() -> None:
    """Angle = 2 x0 - x1 (x2 inert, constant): shares 2 std(x0) and -std(x1) in that order;
    an exact estimate of x0 correlates 1, a noise-only one of x1 about 0."""
    rng = np.random.default_rng(1)
    results = []
    for _ in range(2):
        x = np.c_[rng.normal(0, 1, 300), rng.normal(0, 0.5, 300), np.full(300, 3.0)]
        est = np.c_[x[:, 0], rng.normal(0, 1, 300), x[:, 2]]
        results.append({"inputs": x, "input_mean": est, "truth_nominal": 2 * x[:, 0] - x[:, 1]})
    d = angle_drivers(results, 10, ["a", "b", "c"])
    assert list(d) == ["a", "b"]  # c does not vary
    assert d["a"]["angle_std_deg"] == pytest.approx(2 * np.concatenate(
        [r["inputs"][10:, 0] - r["inputs"][10:, 0].mean() for r in results]).std(), abs=1e-4)
    assert d["b"]["angle_std_deg"] < 0
    assert d["a"]["estimate_level_corr"] == pytest.approx(1.0)
    assert d["a"]["estimate_change_corr"] == pytest.approx(1.0)
    assert abs(d["b"]["estimate_level_corr"]) < 0.15
