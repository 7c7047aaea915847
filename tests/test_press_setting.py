"""The press setting ``u`` (the spec's control inputs): spec, metamodel, tracker, messages,
service. Known to the tracker, never estimated: it moves the final angle only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel, analytic_dataset
from formtwin.metamodel import POD, RBF, Metamodel
from formtwin.physics.analytic import _GAIN_U
from formtwin.service.messages import Limits, MessageError, dumps, parse_stroke
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.spec import ProcessSpec, SpecError, parse_spec
from formtwin.tracker import Tracker, TrackerConfig, build_measurement


def test_spec_reads_controls_with_nominal_and_bounds(spec: ProcessSpec) -> None:
    u = spec.controls["stage2_depth"]
    assert (u.lo, u.hi, u.nominal, u.internal_unit) == (-0.1, 0.1, 0.0, "mm")
    assert spec.run_inputs.names == (*spec.inputs.names, "stage2_depth")
    assert spec.augmented.names[:10] == spec.inputs.names  # never estimated
    bad = spec.text.replace("nominal = 0.0", "nominal = 300.0")
    with pytest.raises(SpecError, match=r"control\[0\] 'stage2_depth'.nominal = 300.0"):
        parse_spec(bad)
    no_controls = spec.text[:spec.text.index("[[control]]")] + spec.text[
        spec.text.index("[deviation]"):]
    plain = parse_spec(no_controls)
    assert plain.run_inputs.names == plain.inputs.names and plain.n_run_inputs == 10


def test_run_columns_appends_nominal_or_given_settings(spec: ProcessSpec) -> None:
    X = np.tile(spec.inputs.lo, (3, 1))
    np.testing.assert_array_equal(spec.run_columns(X)[:, 10], 0.0)
    np.testing.assert_array_equal(spec.run_columns(X, 0.05)[:, 10], 0.05)
    np.testing.assert_array_equal(spec.run_columns(X, [0.01, 0.02, 0.03])[:, 10],
                                  [0.01, 0.02, 0.03])
    full = spec.run_columns(X, 0.05)
    assert spec.run_columns(full) is full
    with pytest.raises(ValueError, match="expected a scalar"):
        spec.run_columns(X, [0.1, 0.2])
    with pytest.raises(ValueError, match=r"expected \(N, 10\)"):
        spec.run_columns(X[:, :9])


@pytest.fixture(scope="module")
def metamodel() -> Metamodel:
    return Metamodel(POD(n_modes=8), RBF(length_scales="box")).fit(analytic_dataset(600, 4))


def test_metamodel_final_angle_follows_u_and_curves_do_not(metamodel: Metamodel,
                                                           spec: ProcessSpec) -> None:
    X = analytic_dataset(20, seed=9).inputs[:, :10]
    lo, hi = metamodel.predict_angles(X, -0.1), metamodel.predict_angles(X, 0.1)
    np.testing.assert_array_equal(lo[:, 0], hi[:, 0])  # stage 1 happens before u acts
    # the stand-in's final angle is linear in u with slope _GAIN_U deg/mm
    np.testing.assert_allclose((hi[:, 1] - lo[:, 1]) / 0.2, _GAIN_U, rtol=0.05)
    np.testing.assert_array_equal(metamodel.predict_curves(X),
                                  metamodel.predict_curves(spec.run_columns(X, 0.1)))
    grid = np.array([-0.1, 0.0, 0.1])
    a = metamodel.final_angle(X, grid)
    assert a.shape == (20, 3)
    # the same float32 model on batches of another size: BLAS blocks the sums differently,
    # so the two agree to the rounding of an m-term float32 sum (~sqrt(m) eps32, margin 4),
    # not bit for bit (1.6e-8 relative seen between two x86-64 CPUs)
    m = metamodel.angle_models[1].centres.shape[0]
    rtol = 4 * np.sqrt(m) * float(np.finfo(np.float32).eps)
    for k, u in enumerate(grid):
        np.testing.assert_allclose(a[:, k], metamodel.predict_angles(X, u)[:, 1], rtol=rtol)
    assert metamodel.outside(X, 0.2).all() and not metamodel.outside(X, 0.1).any()


def test_tracker_predicts_angles_at_the_given_setting(spec: ProcessSpec) -> None:
    model = AnalyticModel(spec)
    config = TrackerConfig(n_particles=300, n_mc=2000, seed=2, estimate_deviation=False)
    measurement = build_measurement(model, config)
    centre = spec.run_columns(0.5 * (spec.inputs.lo + spec.inputs.hi))
    curve = model.predict_curves(centre)[0]
    a, b = (Tracker(model, measurement, config) for _ in range(2))
    ea, eb = a.step(curve), b.step(curve, 0.05)
    np.testing.assert_array_equal(ea.mean, eb.mean)  # u does not act on the estimate
    assert ea.angles_mean[0] == eb.angles_mean[0]
    assert eb.angles_mean[1] - ea.angles_mean[1] == pytest.approx(0.05 * _GAIN_U, rel=1e-6)
    fa = b.final_angle(np.array([0.0, 0.05]))
    assert fa.shape == (300, 2)
    np.testing.assert_allclose(fa[:, 1] - fa[:, 0], 0.05 * _GAIN_U, rtol=1e-9)
    before = b.state_bytes()
    for bad, words in ((0.5, r"stage2_depth = 500 um, expected a value in \[-100, 100\] um"),
                       ([0.0, 0.0], "u has 2 values, expected 1"),
                       (float("nan"), "stage2_depth = nan")):
        with pytest.raises(ValueError, match=words):
            b.step(curve, bad)
    assert b.state_bytes() == before  # refused: nothing changed


def test_stroke_message_carries_an_optional_setting() -> None:
    lim = Limits(n_t=3)
    base = {"schema": "formtwin.stroke/1", "part_id": "a", "cycle": 1,
            "timestamp": "2026-11-23T10:00:00Z",
            "force_N": [0, 1, 2]}
    assert parse_stroke(json.dumps(base).encode(), lim).u is None
    s = parse_stroke(json.dumps({**base, "u": 0.05}).encode(), lim)
    assert s.u is not None and s.u.tolist() == [0.05]
    assert parse_stroke(dumps(s.to_message()), lim).u.tolist() == [0.05]  # type: ignore[union-attr]
    for bad, reason in (("deep", "bad_field"), ([True], "bad_field"), (True, "bad_field")):
        with pytest.raises(MessageError) as err:
            parse_stroke(json.dumps({**base, "u": bad}).encode(), lim)
        assert err.value.reason == reason


def test_service_uses_the_stroke_setting_and_rejects_a_bad_one(tmp_path: Path) -> None:
    stream = make_stream(tmp_path / "s.npz", 3, seed=1)
    strokes = list(read_stream(stream))
    settings = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))
    proc = open_processor(tmp_path / "a.sqlite", settings)
    msgs = []
    for s, u in zip(strokes[:2], (None, 0.05), strict=True):
        m = s.to_message()
        if u is not None:
            m["u"] = u
        out = proc.handle(dumps(m))
        assert out.kind == "accepted"
        msgs.append(out.message)
    assert "u" not in msgs[0] and msgs[1]["u"] == [0.05]
    m = strokes[2].to_message()
    m["u"] = 1.0  # 1 mm: outside the control's bounds
    out = proc.handle(dumps(m))
    assert out.kind == "rejected" and "stage2_depth = 1000 um" in out.message["detail"]


def test_stream_file_carries_each_products_setting(tmp_path: Path) -> None:
    path = tmp_path / "s.npz"
    np.savez(path, curves=np.ones((3, 101)), u=np.array([[0.0], [0.05], [-0.02]]))
    assert [s.u.tolist() for s in read_stream(path)] == [[0.0], [0.05], [-0.02]]  # type: ignore[union-attr]
    np.savez(path, curves=np.ones((2, 101)))
    assert [s.u for s in read_stream(path)] == [None, None]
