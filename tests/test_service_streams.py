"""Stream files for `formtwin replay`: npz, NetCDF (with a source dimension and failures),
CSV; and the replay/export command lines' error messages."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from formtwin.cli import main
from formtwin.production import draw_production_run
from formtwin.service.streams import make_stream, read_stream
from formtwin.spec import load_spec


def test_npz_stream_roundtrip(tmp_path: Path) -> None:
    path = make_stream(tmp_path / "s.npz", 5, seed=2)
    strokes = read_stream(path)
    assert [s.cycle for s in strokes] == [1, 2, 3, 4, 5]
    assert strokes[0].part_id == "P002-0000001" and strokes[0].force_N.shape == (101,)
    assert strokes[0].angles_deg is not None
    with np.load(path, allow_pickle=False) as z:
        assert z["truth"].shape == (5, 18)
        mu = z["mu"]  # the line's state means: the first draw of the stream's seed
    spec = load_spec()
    line = draw_production_run(spec, 5, np.random.default_rng(np.random.SeedSequence([2, 7])))
    assert np.array_equal(mu, line.mu)
    assert np.all((spec.state.mu_min <= mu) & (mu <= spec.state.mu_max))
    # the same seed makes the same stream
    again = read_stream(make_stream(tmp_path / "t.npz", 5, seed=2))
    assert all(a.digest == b.digest for a, b in zip(strokes, again, strict=True))


def test_netcdf_stream_selects_source_and_skips_failures(tmp_path: Path) -> None:
    xr = pytest.importorskip("xarray")
    curves = np.arange(2 * 4 * 101, dtype=float).reshape(2, 4, 101)
    ok = np.array([[True, True, True, True], [True, False, True, True]])
    ds = xr.Dataset({"curves": (("source", "product", "time"), curves),
                     "angles": (("source", "product", "angle"), np.ones((2, 4, 2))),
                     "ok": (("source", "product"), ok)},
                    coords={"source": ["MM", "gFE"]})
    ds.to_netcdf(tmp_path / "r.nc", engine="h5netcdf")
    strokes = read_stream(tmp_path / "r.nc", source="gFE")
    assert [s.cycle for s in strokes] == [1, 3, 4]
    assert np.array_equal(strokes[1].force_N, curves[1, 2])
    assert len(read_stream(tmp_path / "r.nc", source="MM")) == 4


def test_csv_stream(tmp_path: Path) -> None:
    path = tmp_path / "s.csv"
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["part_id", "cycle"] + [f"f{j}" for j in range(101)])
        w.writerow(["A", 7] + [1.0] * 101)
        w.writerow(["B", 9] + [2.0] * 101)
    strokes = read_stream(path)
    assert [(s.part_id, s.cycle) for s in strokes] == [("A", 7), ("B", 9)]
    assert strokes[1].force_N.tolist() == [2.0] * 101 and strokes[0].angles_deg is None
    from formtwin.service.messages import Limits, dumps, parse_stroke

    for s in strokes:  # what replay publishes is a valid stroke message
        assert parse_stroke(dumps(s.to_message()), Limits(n_t=101)).digest == s.digest


def test_cli_errors_name_the_problem(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(tmp_path / "missing.npz")]) == 2
    assert "no such stream file" in capsys.readouterr().err
    (tmp_path / "x.txt").write_text("hi")
    assert main(["replay", str(tmp_path / "x.txt")]) == 2
    assert "unknown stream format" in capsys.readouterr().err
    assert main(["replay", str(make_stream(tmp_path / "s.npz", 2)), "--broker",
                 "http://127.0.0.1:1"]) == 2
    assert "expected mqtt://" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "none.sqlite"), str(tmp_path / "o.csv")]) == 2
    assert "no such store" in capsys.readouterr().err
