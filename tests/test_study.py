"""The study end to end on the analytic stand-in: pseudo-data, six series, metrics, report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from formtwin.dataset import DatasetError
from formtwin.metamodel import Metamodel
from formtwin.physics.analytic import AnalyticBending
from formtwin.spec import load_spec
from formtwin.study.metrics import normalised_rmse, normalisers, rmse
from formtwin.study.pseudodata import data_digest
from formtwin.study.report import write_report
from formtwin.study.run import StudySettings, run_study
from formtwin.tracker import TrackerConfig

SPEC = load_spec()


@pytest.fixture(scope="module")
def metamodel(analytic_mm: tuple[Metamodel, Path]) -> tuple[Metamodel, Path]:
    """The default metamodel of 600 runs of the stand-in (conftest's, shared with the
    sensor study's test) and its file."""
    return analytic_mm


def test_metrics_normalise_as_the_paper_says() -> None:
    assert rmse(np.array([[1.0, 0.0], [3.0, np.nan]]), np.array([[2.0, 1.0], [2.0, 5.0]])
                ).tolist() == [1.0, 1.0]
    scale = normalisers(SPEC)
    assert scale[0] == 6.0  # yield stress: sigma
    assert scale[9] == pytest.approx(35000 / np.sqrt(6))  # press stiffness: range / sqrt 6
    assert scale[10] == pytest.approx(0.4 / np.sqrt(6))  # deviation knot: range / sqrt 6
    n = 50
    truth = np.zeros((n, 18))
    est = truth + scale  # every component off by exactly its normaliser
    ang = np.c_[np.arange(n), 2 * np.arange(n)].astype(float)
    out = normalised_rmse(SPEC, est, truth, ang + ang[-20:].std(0), ang, window=20)
    np.testing.assert_allclose(out, 1.0)  # off by the std of the real angles in the window


def test_quick_study_end_to_end(metamodel: tuple[Metamodel, Path], tmp_path: Path) -> None:
    mm, mm_path = metamodel
    settings = StudySettings(n_products=100, window=50, n_realisations=2, n_repetitions=1,
                             tracker=TrackerConfig(n_particles=200), workers=2, seed=5)
    result = run_study(settings, tmp_path, mm, mm_path, AnalyticBending(SPEC))
    nrmse = result.nrmse
    assert nrmse.shape == (6, 2, 1, 20)
    no_dev = [0, 1, 3, 4]  # series 1, 2, 4, 5 do not estimate theta_d
    assert np.isnan(nrmse[no_dev, :, :, 10:18]).all()
    assert np.isfinite(nrmse[[2, 5], :, :, 10:18]).all()
    assert np.isfinite(nrmse[:, :, :, :10]).all() and np.isfinite(nrmse[:, :, :, 18:]).all()
    s1 = nrmse[0].mean(axis=(0, 1))
    # with a perfect model the punch end distance is well observed
    assert s1[6] < 0.6, s1
    # an unmodelled deviation (series 2) is worse than the perfect model (series 1)
    keep = np.r_[0:7, 18:20]
    assert nrmse[1][..., keep].mean() > nrmse[0][..., keep].mean()
    report = write_report(result, SPEC, tmp_path, sources={"metamodel": str(mm_path)})
    text = (tmp_path / "report.md").read_text()
    assert "Comparison with the paper" in text and "0.11" in text and "series 6" in text
    assert "| series | mean ESS | collapsed steps | fit ok | fit degraded | no fit |" in text
    assert report.read_text().startswith("<!DOCTYPE html>")
    for fig in ("fig4_nrmse.png", "fig5_series1.png", "fig6_series6.png",
                "fig_skill_coverage.png"):
        assert (tmp_path / fig).stat().st_size > 10_000
    # honest metrics for the adaptive default and the paper's likelihood on the same data
    assert result.skill.shape == result.coverage.shape == nrmse.shape
    assert result.ess.shape == result.log_evidence.shape == (6, 2, 1)
    assert np.all((result.coverage[:, :, :, :10] >= 0) & (result.coverage[:, :, :, :10] <= 1))
    assert np.all(np.isfinite(result.log_evidence)) and np.all(result.ess >= 1)
    assert result.paper["nrmse"].shape == (6, 2, 1, 20)
    assert "| 1 | paper |" in text and "| 1 | adaptive |" in text
    assert "| 2 | paper |" not in text  # the paper's likelihood runs in series 1, 5, 6
    assert np.isnan(result.paper["nrmse"][[1, 2, 3]]).all()
    assert not np.array_equal(result.paper["nrmse"], nrmse)
    assert (tmp_path / "nrmse.csv").read_text().count("\n") == 1 + 6 * 2
    digest = json.loads((tmp_path / "results.json").read_text())["data_digest"]
    assert digest == data_digest(result.realisations)
    assert f"pseudo-data digest FE | {digest['FE']}" in text
    # a second run reuses every cached piece and gives the same numbers
    again = run_study(settings, tmp_path, mm, mm_path, AnalyticBending(SPEC))
    assert again.timings["cached"] == 1.0
    assert again.timings["filter_runs_computed"] == result.timings["filter_runs_computed"]
    np.testing.assert_array_equal(again.nrmse, nrmse)


def test_study_is_reproducible_from_its_seed(metamodel: tuple[Metamodel, Path],
                                             tmp_path: Path) -> None:
    mm, mm_path = metamodel
    settings = StudySettings(n_products=40, window=20, n_realisations=1, n_repetitions=1,
                             tracker=TrackerConfig(n_particles=100), series=(3,), workers=1, seed=9)
    a = run_study(settings, tmp_path / "a", mm, mm_path, AnalyticBending(SPEC))
    b = run_study(settings, tmp_path / "b", mm, mm_path, AnalyticBending(SPEC))
    np.testing.assert_array_equal(a.nrmse[2], b.nrmse[2])
    # the pseudo-data's digest records that: equal for the same seed, and one ulp of one
    # force value of the physics data changes its source's digest and no other
    assert data_digest(a.realisations) == data_digest(b.realisations)
    r = b.realisations[0]
    r.curves["FE"][7, 3] = np.nextafter(r.curves["FE"][7, 3], np.inf)
    da, db = data_digest(a.realisations), data_digest(b.realisations)
    assert [s for s in da if da[s] != db[s]] == ["FE"]


def test_cached_runs_of_other_settings_are_made_again(metamodel: tuple[Metamodel, Path],
                                                     tmp_path: Path) -> None:
    """The study folder's cache reuses a run only if it was made from the same inputs:
    other tracker settings in the same folder run the filters again, and give the numbers
    of a fresh folder."""
    mm, mm_path = metamodel
    base = StudySettings(n_products=40, window=20, n_realisations=1, n_repetitions=1,
                         tracker=TrackerConfig(n_particles=100), series=(1,), workers=1,
                         seed=9, paper_repetitions=0)
    first = run_study(base, tmp_path / "a", mm, mm_path, AnalyticBending(SPEC))
    assert first.timings["filter_runs_computed"] == 1
    again = run_study(base, tmp_path / "a", mm, mm_path, AnalyticBending(SPEC))
    assert again.timings["cached"] == 1.0
    other = dataclasses.replace(base, tracker=TrackerConfig(n_particles=120))
    changed = run_study(other, tmp_path / "a", mm, mm_path, AnalyticBending(SPEC))
    assert changed.timings["filter_runs_computed"] == 1 and "cached" not in changed.timings
    fresh = run_study(other, tmp_path / "b", mm, mm_path, AnalyticBending(SPEC))
    np.testing.assert_array_equal(changed.nrmse[0], fresh.nrmse[0])
    assert not np.array_equal(changed.nrmse[0], first.nrmse[0])
    # another seed wants other pseudo-data: not the seed-9 file's, and the physics runs'
    # file of the folder holds another design (a clear error, not a silent reuse)
    with pytest.raises(DatasetError, match="fe_0.nc: holds a different design"):
        run_study(dataclasses.replace(other, seed=10), tmp_path / "a", mm, mm_path,
                  AnalyticBending(SPEC))


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match="window = 600"):
        StudySettings(n_products=500, window=600)
    with pytest.raises(ValueError, match=r"series \[9\]"):
        StudySettings(series=(1, 9))


def test_cli_quick_study_on_the_embedded_default(tmp_path: Path) -> None:
    """The CI smoke test of the main job: bundled physics DOE -> metamodel -> 6 series."""
    from formtwin.cli import main
    from formtwin.defaults import physics_model

    assert main(["study", "--quick", "--out", str(tmp_path), "--workers", "2"]) == 0
    text = (tmp_path / "report.md").read_text()
    assert f"bending ({physics_model('bending').version})" in text
    assert "## Sensors besides the curve" in text  # the sensor section, figures or how-to
    lines = (tmp_path / "nrmse.csv").read_text().splitlines()
    assert len(lines) == 1 + 6 * 2 * 1
    s1 = np.array([[float(v) for v in line.split(",")[3:]] for line in lines[1:3]])
    assert np.all(s1[:, 6] < 0.5), s1[:, 6]  # punch end distance is observable in series 1
    # the study ran on the bundled metamodel, and the shipped interval calibration belongs
    # to it: the default intervals find its floors, no fallback to the cloud; the report
    # says so on its first page
    from formtwin.defaults import bundled_metamodel
    from formtwin.metamodel import Metamodel
    from formtwin.tracker import TrackerConfig
    from formtwin.tracker import intervals as iv

    mm = Metamodel.load(bundled_metamodel("bending"))
    # the bundled file by its place in the package, no path of this machine
    assert f"formtwin/data/metamodel_bending.npz (bundled) (fit {mm.fit_id})" in text
    assert str(bundled_metamodel("bending")) not in text
    assert f"'calibrated_fit', calibrated for fit {mm.fit_id} (interval_calibration.json)" \
        in text.split("## Settings")[0]
    cal = json.loads(iv.CALIBRATION_PATH.read_text())
    assert iv.find_calibration(mm).data == cal, iv.find_calibration(mm).reason
    assert cal["model_version"] == mm.model_version
    for deviation in (False, True):
        floors = iv.Floors(mm, deviation, TrackerConfig().intervals == "calibrated_fit")
        assert floors.b[:7].max() > 0 and floors.b_angles.max() > 0


def _stand_in_files(folder: Path) -> None:
    """Files where the study's tasks expect a metamodel and 5 realisations (their keys
    hash the contents)."""
    for name in ("mm.npz", *(f"realisation_{k}.nc" for k in range(5))):
        (folder / name).write_bytes(name.encode())


def test_the_study_counts_its_filter_runs(tmp_path: Path) -> None:
    """What `formtwin study` announces is what it runs (default: 6 series x 5 datasets x 5
    repetitions, plus the paper's likelihood once per dataset in series 1, 5 and 6)."""
    from formtwin.study.run import StudySettings, _tasks

    assert StudySettings().n_filter_runs == 165
    _stand_in_files(tmp_path)
    for kw in ({}, {"paper_repetitions": 0}, {"series": (2, 3, 5)},
               {"paper_repetitions": 2, "n_repetitions": 3}):
        st = StudySettings(**kw)  # type: ignore[arg-type]
        assert st.n_filter_runs == len(_tasks(st, tmp_path, tmp_path / "mm.npz", tmp_path))


def test_the_papers_runs_are_eq_12_whatever_the_tracker_compares(tmp_path: Path) -> None:
    """The study's paper-likelihood runs use eq. 12 as written (paper covariance, curves
    compared in model space), also when the tracker compares in measurement space."""
    from formtwin.study.run import StudySettings, _tasks
    from formtwin.tracker import TrackerConfig

    st = StudySettings(tracker=TrackerConfig(compare="measurement"))
    _stand_in_files(tmp_path)
    tasks = _tasks(st, tmp_path, tmp_path / "mm.npz", tmp_path)
    paper = [t for t in tasks if t.tracker.likelihood == "paper"]
    mine = [t for t in tasks if t.tracker.likelihood != "paper"]
    assert paper and all(t.tracker.compare == "model" for t in paper)
    assert mine and all(t.tracker.compare == "measurement" for t in mine)
