"""Learning the statistics mu (``TrackerConfig(learn_mu=True)``, study series 7 and 8).

On the analytic stand-in, data drawn with mu at ``mu_max``: the learned mu of the punch end
distance (well observed in the force curve) moves from the prior's mid-range toward the
truth, and the learned-mu tracker tracks that variable better than one assuming the
mid-range mu (series 4). Plus: checkpoints with learn_mu continue bit for bit, the 18-name
Estimate API is unchanged, and the study knows series 7 and 8 without changing its default.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.production import draw_production_run
from formtwin.spec import ProcessSpec
from formtwin.study.run import StudySettings
from formtwin.study.series import PAPER_SERIES, SERIES
from formtwin.tracker import Tracker, TrackerConfig

N_PRODUCTS = 400


@pytest.fixture(scope="module")
def mm(model: AnalyticModel) -> MeasurementModel:
    """K_MC with the mid-range mu, as in series 4 and 6."""
    return MeasurementModel.from_monte_carlo(model, mu=None, n=2000,
                                             rng=np.random.default_rng(2))


def _data(spec: ProcessSpec, model: AnalyticModel, seed: int) -> dict[str, np.ndarray]:
    # mu at one end of [mu_min, mu_max]: the mid-range guess is off by half
    run = draw_production_run(spec, N_PRODUCTS, np.random.default_rng(seed),
                              mu=spec.state.mu_max.copy(), deviation=False)
    return {"mu": run.mu, "X": run.inputs, "curves": model.predict_curves(run.inputs)}


def test_learned_mu_moves_to_the_truth_and_beats_the_midrange(
        spec: ProcessSpec, model: AnalyticModel, mm: MeasurementModel) -> None:
    st = spec.state
    k = st.index["punch_end_distance"]
    half = slice(N_PRODUCTS // 2, None)
    rmse = {False: [], True: []}
    mu_err = []
    for seed in (11, 12):
        d = _data(spec, model, seed)
        for learn in (False, True):
            cfg = TrackerConfig(n_particles=400, estimate_deviation=False, seed=4,
                                learn_mu=learn)
            est = Tracker(model, mm, cfg).run(d["curves"])
            err = est.mean[half, k] - d["X"][half, k]
            rmse[learn].append(float(np.sqrt(np.mean(err**2)) / st.sigma[k]))
            if learn:
                assert est.mu_mean is not None and est.mu_std is not None
                assert est.mu_mean.shape == (N_PRODUCTS, 7)
                assert np.all((est.mu_mean >= st.lo) & (est.mu_mean <= st.hi))
                mu_err.append(abs(est.mu_mean[-1, k] - d["mu"][k]) / st.sigma[k])
            else:
                assert est.mu_mean is None
    mid_err = abs(st.mu_mid[k] - st.mu_max[k]) / st.sigma[k]  # 2 sigma
    assert mid_err == pytest.approx(2.0)
    # learned mu ends nearer the truth than the mid-range guess, in each dataset
    assert max(mu_err) < 0.75 * mid_err, mu_err
    # and tracks the variable better on average
    assert np.mean(rmse[True]) < np.mean(rmse[False]), rmse


def test_checkpoint_restore_with_learn_mu_is_bit_for_bit(
        tmp_path: Path, spec: ProcessSpec, model: AnalyticModel,
        mm: MeasurementModel) -> None:
    curves = _data(spec, model, 5)["curves"][:12]
    cfg = TrackerConfig(n_particles=100, seed=5, learn_mu=True)
    a = Tracker(model, mm, cfg)
    a.run(curves[:6])
    path = a.checkpoint(tmp_path / "ck.npz")
    rest_a = a.run(curves[6:])
    b = Tracker.restore(path, model, mm)
    assert b.config == cfg and b.config.learn_mu
    rest_b = b.run(curves[6:])
    for f in ("mean", "std", "angles_mean", "angles_std", "ess", "loglik", "mu_mean",
              "mu_std"):
        np.testing.assert_array_equal(getattr(rest_a, f), getattr(rest_b, f))
    assert a.particles is not None and a.particles.shape == (100, 32)
    np.testing.assert_array_equal(a.particles, b.particles)
    # a config saved before learn_mu existed restores with it off
    old = json.loads(cfg.to_json())
    del old["learn_mu"]
    assert not TrackerConfig.from_json(json.dumps(old)).learn_mu


def test_estimate_api_keeps_18_names(spec: ProcessSpec, model: AnalyticModel,
                                     mm: MeasurementModel) -> None:
    curve = _data(spec, model, 6)["curves"][0]
    on = Tracker(model, mm, TrackerConfig(n_particles=50, learn_mu=True)).step(curve)
    off = Tracker(model, mm, TrackerConfig(n_particles=50)).step(curve)
    assert on.names == off.names == spec.augmented.names and on.mean.shape == (18,)
    assert on.mu_mean is not None and on.mu_std is not None and on.mu_mean.shape == (7,)
    d_on, d_off = on.to_dict(), off.to_dict()
    assert set(d_on) - set(d_off) == {"mu_mean", "mu_std"} and len(d_on["mu_mean"]) == 7
    assert "mu_mean" not in d_off
    json.dumps(d_on)


def test_study_knows_series_7_and_8_but_runs_the_papers_six_by_default() -> None:
    assert StudySettings().series == PAPER_SERIES == (1, 2, 3, 4, 5, 6)
    s7, s8 = SERIES[6], SERIES[7]
    assert (s7.number, s7.data, s7.deviation, s7.learn_mu) == (7, "MM", False, True)
    assert (s8.number, s8.data, s8.deviation, s8.learn_mu) == (8, "gFE", True, True)
    assert not s7.mu_known and "mu learned" in s7.label
    assert all(s.number == i + 1 for i, s in enumerate(SERIES))
    assert StudySettings(series=(1, 4, 7)).series == (1, 4, 7)
    with pytest.raises(ValueError, match="unknown"):
        StudySettings(series=(9,))


def test_a_study_of_series_4_and_7_runs_and_reports(
        tmp_path: Path, spec: ProcessSpec, analytic_mm: tuple[Any, Path]) -> None:
    from formtwin.physics.analytic import AnalyticBending
    from formtwin.study.report import write_report
    from formtwin.study.run import run_study

    mm, mm_path = analytic_mm  # the session's fit of the analytic stand-in (600 runs)
    settings = StudySettings(n_products=40, window=20, n_realisations=1, n_repetitions=1,
                             tracker=TrackerConfig(n_particles=100), series=(4, 7), workers=1,
                             seed=3)
    result = run_study(settings, tmp_path / "study", mm, mm_path, AnalyticBending(spec))
    assert result.nrmse.shape == (7, 1, 1, 20)
    assert np.isfinite(result.nrmse[[3, 6], ..., :10]).all()
    assert np.isnan(result.nrmse[[0, 1, 2, 4, 5]]).all()
    with np.load(result.run_paths[(7, 0, 0)], allow_pickle=False) as run:
        assert run["mu_mean"].shape == (40, 7)
    write_report(result, spec, tmp_path / "study", sources={})
    text = (tmp_path / "study" / "report.md").read_text()
    assert "mu learned" in text and "Learned mu (series 7)" in text
