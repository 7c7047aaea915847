"""The study report's sensor section from a sensor benchmark's figures: the figure is drawn,
the table holds each series' row per sensor set with its numbers, a file without the
tables or no file gives the paragraph saying how to make them."""

from __future__ import annotations

import json
from pathlib import Path

from formtwin.study.sensor_report import SETS, load_sensor_figures, sensor_blocks


def _figures() -> dict:
    tables = {k: {s: {n: 0.5 + 0.1 * i + 0.01 * int(s) for i, n in enumerate(SETS)}
                  for s in ("1", "5", "6")}
              for k in ("final_nrmse", "state_nrmse", "state_coverage90", "final_coverage90")}
    return {**tables, "settings": {"series": [1, 5, 6], "datasets": 5, "products": 1000,
                                   "n_particles": 500},
            "ff_vs_ewma_within_curve": 0.7}


def test_section_from_the_benchmarks_figures(tmp_path: Path) -> None:
    path = tmp_path / "bench_sensors.json"
    path.write_text(json.dumps({"figures": _figures()}))
    figures = load_sensor_figures(path)
    assert figures is not None
    blocks = sensor_blocks(figures, tmp_path, str(path))
    assert (tmp_path / "fig_sensors.png").stat().st_size > 0
    table = next(b for b in blocks if b[0] == "table")
    rows = table[2]
    assert len(rows) == 3 * len(SETS)
    # series 5, the gauge (third set): 0.5 + 0.2 + 0.05 in every column
    assert rows[len(SETS) + 2] == ["5", SETS["gauge"], "0.75", "0.75", "0.75", "0.75"]
    assert any("feedforward / run-to-run EWMA" in b[1] and "0.7" in b[1]
               for b in blocks if b[0] == "p")


def test_without_figures_the_section_says_how_to_make_them(tmp_path: Path) -> None:
    assert load_sensor_figures(tmp_path / "absent.json") is None
    (tmp_path / "other.json").write_text(json.dumps({"figures": {"final_nrmse": {}}}))
    assert load_sensor_figures(tmp_path / "other.json") is None
    blocks = sensor_blocks(None, tmp_path, "")
    assert "bench_sensors.py" in blocks[-1][1]
    assert not (tmp_path / "fig_sensors.png").exists()


def test_the_state_coverage_column_says_which_intervals_it_scores(tmp_path: Path) -> None:
    old = sensor_blocks(_figures(), tmp_path, "old.json")
    new = sensor_blocks({**_figures(), "state_coverage90_cloud": {}}, tmp_path, "new.json")
    heads = [next(b for b in blocks if b[0] == "table")[1][4] for blocks in (old, new)]
    assert heads == ["state coverage (cloud)", "state coverage"]
    text = [" ".join(b[1] for b in blocks if b[0] == "p") for blocks in (old, new)]
    assert "no calibrated floors" in text[0] and "default 90 % intervals" in text[1]
