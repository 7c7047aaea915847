"""The independent CalculiX check's points and figures (benchmarks/fe_independent.py; the
ccx runs themselves are in the benchmark)."""

from __future__ import annotations

import doctest
import importlib.util
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from formtwin.dataset import DoeDataset
from formtwin.defaults import bundled_doe

PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "fe_independent.py"


@pytest.fixture(scope="module")
def fi() -> ModuleType:
    spec = importlib.util.spec_from_file_location("fe_independent", PATH)
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_doctests(fi: ModuleType) -> None:
    res = doctest.testmod(fi)
    assert res.attempted >= 5 and res.failed == 0


def test_points_are_unseen_lhs_rows_one_per_stratum(fi: ModuleType) -> None:
    doe = DoeDataset.load(bundled_doe("bending"))
    names = tuple(doe.spec.run_inputs.names)
    n_corners = 2 ** len(names)
    pts = fi.independent_points(doe.inputs, names, n_corners, 12, seed=2026)
    assert [p["group"] for p in pts] == ["pinch"] * 8 + ["control"] * 4
    rows = [p["row"] for p in pts]
    assert len(set(rows)) == 12 and min(rows) >= n_corners
    pe = np.array([p["pe_um"] for p in pts])
    # one point in each 3.75-um stratum of 310-340 and each 17.5-um stratum of 340-410
    edges = np.r_[np.linspace(310, 340, 9)[:-1], np.linspace(340, 410, 5)]
    assert np.all(pe >= edges[:-1] - 1e-9) and np.all(pe <= edges[1:] + 1e-9)
    for p in pts:  # the rows themselves, not a copy of another row
        assert np.array_equal(p["x"], doe.inputs[p["row"]])
        assert p["pe_um"] == pytest.approx(1e3 * p["x"][names.index("punch_end_distance")])
    again = fi.independent_points(doe.inputs, names, n_corners, 12, seed=2026)
    assert [p["row"] for p in again] == rows
    other = fi.independent_points(doe.inputs, names, n_corners, 12, seed=7)
    assert [p["row"] for p in other] != rows


def test_summary_separates_groups_and_skips_failed_fe(fi: ModuleType) -> None:
    def fe(peak: float, a2: float, ok: bool = True) -> dict[str, object]:
        return {"ok": ok, "peak": peak, "plateau": 50.0, "angle1": 40.0, "angle2": a2}

    beam = {"peak": 110.0, "plateau": 50.0, "angle1": 41.0, "angle2": 72.0}
    pts = {"a": {"group": "pinch", "fe1": fe(100.0, 0.0), "fe2": fe(0.0, 71.0),
                 "beam": {"m": beam}},
           "b": {"group": "pinch", "fe1": fe(0.0, 0.0, ok=False), "fe2": fe(0.0, 74.0),
                 "beam": {"m": beam}},
           "c": {"group": "control", "fe1": fe(88.0, 0.0), "fe2": fe(0.0, 72.5),
                 "beam": {"m": beam}}}
    s = fi.summarise(pts, ("m",))
    p, c, a = s["pinch"]["m"], s["control"]["m"], s["all"]["m"]
    assert (p["points"], p["fe_failed"], p["fe_failed_final"]) == (2, 1, 0)
    assert p["peak_rel_err_max"] == pytest.approx(0.1)  # b's failed stage-1 run not used
    assert p["angle2_err_mean_deg"] == pytest.approx((1.0 - 2.0) / 2)
    assert p["angle2_err_max_deg"] == pytest.approx(2.0)
    assert c["peak_rel_err_max"] == pytest.approx(110 / 88 - 1)
    assert a["angle2_err_rms_deg"] == pytest.approx(np.sqrt((1 + 4 + 0.25) / 3))
    assert a["angle1_err_mean_deg"] == pytest.approx(1.0)
