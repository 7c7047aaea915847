"""``formtwin track`` end to end on the analytic stand-in."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from formtwin.cli import main
from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.spec import load_spec


@pytest.fixture(scope="module")
def curves() -> np.ndarray:
    spec = load_spec()
    mid = spec.inputs.lo + 0.5 * (spec.inputs.hi - spec.inputs.lo)
    noise = np.random.default_rng(0).standard_normal((8, 10))
    X = mid + 0.01 * (spec.inputs.hi - spec.inputs.lo) * noise
    return AnalyticModel(spec).predict_curves(X)


def test_track_npz_to_csv_with_checkpoint(tmp_path: Path, curves: np.ndarray) -> None:
    spec = load_spec()
    mm = MeasurementModel.from_monte_carlo(AnalyticModel(spec), n=1000)
    mpath = mm.save(tmp_path / "mm.npz")
    bad = curves.copy()
    bad[3, 5] = np.nan  # a failed run: skipped, row numbers kept
    np.savez(tmp_path / "c.npz", curves=bad)
    out = tmp_path / "est.csv"
    rc = main(["track", "--metamodel", "analytic", "--curves", str(tmp_path / "c.npz"),
               "--out", str(out), "--measurement", str(mpath), "--particles", "64",
               "--no-deviation", "--checkpoint", str(tmp_path / "ck.npz")])
    assert rc == 0
    rows = list(csv.DictReader(open(out, encoding="utf-8")))
    assert [int(r["index"]) for r in rows] == [0, 1, 2, 4, 5, 6, 7]
    assert float(rows[-1]["mean_press_stiffness"]) > 0 and "angle2_std" in rows[0]
    # the absolute fit of every product: the model's own curves are explained
    assert {r["health"] for r in rows} <= {"ok", "degraded"}
    assert all(0 <= float(r["fit_quantile"]) < 0.999 for r in rows)
    assert (tmp_path / "ck.npz").exists()


def test_track_csv_input_and_errors(tmp_path: Path, curves: np.ndarray,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "c.csv"
    np.savetxt(src, curves, delimiter=",", header=",".join(f"t{i}" for i in range(101)),
               comments="")
    out = tmp_path / "e.csv"
    assert main(["track", "--metamodel", "analytic", "--curves", str(src), "--out", str(out),
                 "--n-mc", "500", "--particles", "32"]) == 0
    assert len(list(csv.DictReader(open(out, encoding="utf-8")))) == 8
    assert "fit (the model's own check" in capsys.readouterr().out
    # curves of another process (3x the force): the command says the model does not fit
    np.savetxt(src, 3.0 * curves + 100.0, delimiter=",")
    assert main(["track", "--metamodel", "analytic", "--curves", str(src), "--out", str(out),
                 "--n-mc", "500", "--particles", "32"]) == 0
    assert "WARNING: the model does not explain 8 of 8 curves" in capsys.readouterr().out
    assert {r["health"] for r in csv.DictReader(open(out, encoding="utf-8"))} == {"no_fit"}
    np.savetxt(src, curves[:, :50], delimiter=",")
    assert main(["track", "--metamodel", "analytic", "--curves", str(src), "--out",
                 str(out)]) == 2
    assert "expected (n, 101)" in capsys.readouterr().err


def test_track_reads_a_study_realisation_by_source(tmp_path: Path, curves: np.ndarray) -> None:
    xr = pytest.importorskip("xarray")
    from formtwin.cli.track import read_curves

    stack = np.stack([curves, 2 * curves])
    ds = xr.Dataset({"curves": (("source", "product", "time"), stack)},
                    coords={"source": ["MM", "gMM"]})
    path = tmp_path / "real.nc"
    ds.to_netcdf(path, engine="h5netcdf")
    np.testing.assert_array_equal(read_curves(path, 101, "gMM"), 2 * curves)
    with pytest.raises(ValueError, match="pass --source, one of MM, gMM"):
        read_curves(path, 101)
    out = tmp_path / "e.csv"
    assert main(["track", "--metamodel", "analytic", "--curves", str(path), "--source", "MM",
                 "--out", str(out), "--n-mc", "500", "--particles", "32"]) == 0


def test_track_reads_a_doe_dataset(tmp_path: Path) -> None:
    pytest.importorskip("h5py")
    from formtwin.cli.track import read_curves
    from formtwin.defaults import analytic_dataset

    data = analytic_dataset(6, seed=0, failure_clearance=0.33)
    path = data.save(tmp_path / "doe.h5")
    curves = read_curves(Path(path), 101)
    assert curves.shape == (6, 101)
    np.testing.assert_array_equal(np.isnan(curves).any(axis=1), ~data.ok)


def test_track_predicts_angles_at_each_products_setting(tmp_path: Path) -> None:
    """Settings u come with a DOE dataset (its last run-input column) or from --u; the
    angles are predicted at them and the table says which u each row used."""
    pytest.importorskip("h5py")
    from formtwin.defaults import analytic_dataset

    data = analytic_dataset(6, seed=1)
    path = data.save(tmp_path / "doe.h5")
    common = ["--metamodel", "analytic", "--curves", str(path), "--n-mc", "500",
              "--particles", "64", "--no-deviation", "--seed", "3"]
    assert main(["track", *common, "--out", str(tmp_path / "a.csv")]) == 0
    rows = list(csv.DictReader(open(tmp_path / "a.csv", encoding="utf-8")))
    u_file = [float(r["u_stage2_depth"]) for r in rows]
    np.testing.assert_allclose(u_file, data.inputs[:, -1])
    assert main(["track", *common, "--u", "0", "--out", str(tmp_path / "b.csv")]) == 0
    nominal = list(csv.DictReader(open(tmp_path / "b.csv", encoding="utf-8")))
    assert [float(r["u_stage2_depth"]) for r in nominal] == [0.0] * 6
    # same curves, same seed: the state is the same, the final angle moves with u
    gaps = []
    for r, q in zip(rows, nominal, strict=True):
        assert r["mean_yield_stress"] == q["mean_yield_stress"]
        gaps.append(float(r["angle2_mean"]) - float(q["angle2_mean"]))
    assert np.corrcoef(gaps, u_file)[0, 1] > 0.9
    np.savetxt(tmp_path / "u.csv", np.full(6, 0.5))  # 0.5 mm: beyond the +-0.1 mm box
    assert main(["track", *common, "--u", str(tmp_path / "u.csv"),
                 "--out", str(tmp_path / "c.csv")]) == 2


def test_each_command_is_parsed_with_its_own_module_alone() -> None:
    """``main`` imports only the chosen command's module: for every command group, the
    parser built from it alone knows that command (its name maps back to the module), and
    the full parser has exactly these commands."""
    import argparse

    from formtwin.cli import COMMANDS, MODULE_OF, build_parser

    def names(p: argparse.ArgumentParser) -> list[str]:
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        return list(sub.choices)

    every = []
    for module in COMMANDS:
        (name,) = names(build_parser((module,)))
        assert MODULE_OF.get(name, name) == module
        every.append(name)
    assert names(build_parser()) == every
