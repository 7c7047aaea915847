"""A recorded run with its sensor values (formtwin.tracker.recorded, ``formtwin track``):
each value fused when the line knew it, the estimates those of that schedule written out
by hand, refusals listed, bad input named; the stream files' sensor values (npz arrays, CSV
columns) and the command line end to end, where the gauge pays."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from formtwin.cli import main
from formtwin.defaults import analytic_model
from formtwin.service.streams import make_stream, read_readings, read_sensor_values
from formtwin.tracker import FusionError, Tracker, TrackerConfig, build_tracker, track_recorded
from formtwin.tracker.ahead import refusal


@functools.cache
def _model_and_likelihood() -> tuple[Any, Any]:
    tr = build_tracker(analytic_model(), TrackerConfig(n_particles=10, n_mc=1000,
                                                       estimate_deviation=False))
    return tr.model, tr.measurement


def _tracker(sensors: tuple[str, ...] = ("gauge", "camera"), **kw: Any) -> Tracker:
    model, measurement = _model_and_likelihood()
    return Tracker(model, measurement, TrackerConfig(
        n_particles=200, n_mc=1000, estimate_deviation=False, seed=4, sensors=sensors, **kw))


@functools.cache
def _stream(tmp: str) -> Path:
    return make_stream(Path(tmp) / "line.npz", 40, seed=2, deviation=False,
                       sensors=("gauge", "camera"))


@pytest.fixture
def stream(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _stream(str(tmp_path_factory.getbasetemp()))


def _data(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    with np.load(path) as z:
        return np.asarray(z["curves"]), {n: np.asarray(z[f"sensor_{n}"]) for n in ("gauge",
                                                                                  "camera")}


def test_no_values_is_the_tracker_run(stream: Path) -> None:
    curves, _ = _data(stream)
    a, b = _tracker(), _tracker()
    rec = track_recorded(a, curves, {})
    ref = b.run(curves)
    np.testing.assert_array_equal(rec.estimates.mean, ref.mean)
    np.testing.assert_array_equal(rec.estimates.std, ref.std)
    assert rec.fused == {} and rec.refused == []
    # a camera but no values: the model's final angle, its interval not yet calibrated
    assert rec.final is not None and np.isfinite(rec.final).all()


def test_values_enter_when_the_line_knew_them(stream: Path) -> None:
    """The gauge (state, delay 0) before its product's step from the second product on
    (after the first step: no parents before it), the camera (delay 1) after the next
    product's step, the last camera value at the end: the estimates and issued final
    angles of that schedule written out by hand, bit for bit."""
    curves, values = _data(stream)
    n = curves.shape[0]
    rec = track_recorded(_tracker(), curves, values)
    ref = _tracker()
    gauge = ref.sensors[0]
    means, finals = [], []
    for k in range(n):
        ahead = refusal(ref, gauge) is None
        if ahead:
            ref.fuse(k, "gauge", float(values["gauge"][k]))
        means.append(ref.step(curves[k]).mean)
        if not ahead:
            ref.fuse(k, "gauge", float(values["gauge"][k]))
        if k >= 1:
            ref.fuse(k - 1, "camera", float(values["camera"][k - 1]))
        final, (lo, hi) = ref.issue_final()
        finals.append((final, lo, hi))
    ref.fuse(n - 1, "camera", float(values["camera"][n - 1]))
    np.testing.assert_array_equal(rec.estimates.mean, np.array(means))
    np.testing.assert_array_equal(rec.final, np.array(finals))
    assert rec.fused == {"gauge": n, "camera": n} and rec.refused == []
    assert np.all(rec.final[:, 1] < rec.final[:, 0]) and np.all(rec.final[:, 0] < rec.final[:, 2])


def test_a_refused_value_is_listed_and_tracking_goes_on(stream: Path) -> None:
    curves, values = _data(stream)
    bad = {"gauge": values["gauge"].copy()}
    bad["gauge"][5] = 300.0  # um, not mm: outside the spec's range of thickness
    tracker = _tracker()
    rec = track_recorded(tracker, curves, bad)
    assert rec.fused == {"gauge": curves.shape[0] - 1}
    assert rec.refused == ["product 5, gauge: fuse: gauge value 300 mm: outside thickness's "
                           "range in the spec, [0.295, 0.305] mm"]
    assert tracker.n_steps == curves.shape[0] and np.isfinite(rec.estimates.mean).all()
    with pytest.raises(FusionError):
        _tracker().fuse(0, "gauge", math.nan)


def test_bad_values_are_named(stream: Path) -> None:
    curves, values = _data(stream)
    with pytest.raises(ValueError, match="camera: not among the sensors the tracker fuses"):
        track_recorded(_tracker(("gauge",)), curves, values)
    with pytest.raises(ValueError, match=r"values of gauge: shape \(3,\), expected \(40,\)"):
        track_recorded(_tracker(), curves, {"gauge": values["gauge"][:3]})


def test_csv_stream_carries_sensor_columns(tmp_path: Path) -> None:
    spec = analytic_model().spec
    n_t = spec.n_t
    head = ["part_id", "cycle", *[f"f{j}" for j in range(n_t)], "sensor_gauge", "sensor_camera"]
    rows = [["p1", "1", *["1.0"] * n_t, "0.3001", ""],
            ["p2", "2", *["2.0"] * n_t, "", "73.5"],
            ["p3", "3", *["3.0"] * n_t, "0.2995", "73.4"]]
    path = tmp_path / "line.csv"
    path.write_text("\n".join(",".join(r) for r in [head, *rows]) + "\n", encoding="utf-8")
    got = read_sensor_values(path)
    np.testing.assert_array_equal(got["gauge"], [0.3001, np.nan, 0.2995])
    np.testing.assert_array_equal(got["camera"], [np.nan, 73.5, 73.4])
    # replay: the gauge before its product's stroke, the camera (delay 1) after the next
    due = [(k, r.part_id, r.sensor) for k, r in read_readings(path, spec)]
    assert due == [(-1, "p1", "gauge"), (1, "p3", "gauge"), (2, "p2", "camera"),
                   (2, "p3", "camera")]
    other = tmp_path / "other.csv"  # a sensor the spec does not declare: its delay unknown
    other.write_text(path.read_text(encoding="utf-8").replace("sensor_camera", "sensor_thermo"),
                     encoding="utf-8")
    with pytest.raises(ValueError, match="sensor_thermo: not a sensor of spec"):
        read_readings(other, spec)
    rows[1][-1] = "abc"
    path.write_text("\n".join(",".join(r) for r in [head, *rows]) + "\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"row 3, column sensor_camera: 'abc' is not a number"):
        read_sensor_values(path)


def test_track_command_fuses_the_file_and_the_gauge_pays(
        stream: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``formtwin track --sensors gauge,camera`` on a stream with both: the thickness error
    falls far below the curve-only run's (a 0.5 um gauge against a ~6 um spread), and the
    camera's calibrated final-angle interval is written beside the estimates."""
    import csv

    base = ["track", "--metamodel", "analytic", "--curves", str(stream), "--particles", "200",
            "--no-estimate-deviation", "--seed", "1"]
    rows = {}
    for tag, extra in (("curve", []), ("both", ["--sensors", "gauge,camera"])):
        out = tmp_path / f"{tag}.csv"
        assert main([*base, *extra, "--out", str(out)]) == 0
        with open(out, encoding="utf-8") as fh:
            rows[tag] = list(csv.DictReader(fh))
    printed = capsys.readouterr().out
    assert "values of camera, gauge not fused (not in --sensors)" in printed
    assert "sensor values fused: gauge 40, camera 40" in printed
    with np.load(stream) as z:
        spec = analytic_model().spec
        truth = np.asarray(z["truth"])[:, spec.state.index["thickness"]]

    def rmse(tag: str) -> float:
        est = np.array([float(r["mean_thickness"]) for r in rows[tag]])
        return float(np.sqrt(np.mean((est[10:] - truth[10:]) ** 2)))

    assert rmse("both") < 0.4 * rmse("curve")  # 0.26 on this stream
    assert "final_interval90_lo_deg" in rows["both"][0]
    assert "final_interval90_lo_deg" not in rows["curve"][0]
