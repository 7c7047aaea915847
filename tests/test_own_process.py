"""A process other than the demonstrator (examples/air_bend): the spec's own outputs, curve
axis, sensor noise and deviation kinds; the design export and FE import; the study on the
user's FE dataset (or its refusal); and docs/howto/own-process.md run line by line,
serve and replay through a private mosquitto included."""

from __future__ import annotations

import csv
import json
import os
import shlex
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from service_fixtures import (
    REPO,
    Mosquitto,
    doc_commands,
    log_has,
    mosquitto,  # noqa: F401 - fixture
    stored_count,
    wait_for,
)

from formtwin.dataset import curve_columns, export_design, import_csv
from formtwin.deviation import DeviationModel
from formtwin.spec import SpecError, load_spec, parse_spec

EXAMPLE = REPO / "examples" / "air_bend"
SPEC = EXAMPLE / "air_bend.toml"
DOC = REPO / "docs" / "howto" / "own-process.md"
MARK = "<!-- the block below is run by tests/test_own_process.py -->"
FORMTWIN = [sys.executable, "-c", "import sys; from formtwin.cli import main; sys.exit(main())"]


def fe_module():  # type: ignore[no-untyped-def]
    """The example's FE stand-in, imported from its file."""
    import importlib.util

    s = importlib.util.spec_from_file_location("fe_air_bend", EXAMPLE / "fe_air_bend.py")
    assert s is not None and s.loader is not None
    mod = importlib.util.module_from_spec(s)
    s.loader.exec_module(mod)
    return mod


def test_example_spec_has_its_own_outputs_axis_noise_and_deviation() -> None:
    spec = load_spec(SPEC)
    assert spec.output_names == ("bend_angle",) and not spec.outputs[0].uses_controls
    assert spec.axis == "stroke" and spec.axis_unit == "mm"
    assert spec.time[0] == 0.0 and spec.time[-1] == 8.0 and spec.n_t == 61
    assert spec.noise_sd == 10.0
    assert spec.deviation.kinds == ("force_scaling",)
    assert spec.deviation.names == ("force_scaling_1", "force_scaling_2", "force_scaling_3")
    assert len(spec.controls) == 0 and spec.n_run_inputs == 6
    demo = load_spec()  # the demonstrator declares its two angles, as the default has them
    assert demo.output_names == ("angle_stage1", "angle_stage2")
    assert [o.uses_controls for o in demo.outputs] == [False, True]
    assert demo.axis == "time" and demo.noise_sd == 0.0
    assert demo.deviation.kinds == ("force_scaling", "speed_scaling")


def _with(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new)


def test_spec_errors_name_the_field_and_no_deviation_means_identity() -> None:
    text = SPEC.read_text(encoding="utf-8")
    bad = {
        "curve.unit": _with(text, 'unit = "mm"\nt_start', 'unit = "N"\nt_start'),
        "curve.noise_sd": _with(text, "noise_sd = 10.0", "noise_sd = -1.0"),
        "deviation.kinds": _with(text, 'kinds = ["force_scaling"]', 'kinds = ["bending"]'),
        "uses_controls": _with(text, "uses_controls = false", 'uses_controls = "no"'),
        "used twice": _with(text, 'name = "bend_angle"', 'name = "yield_stress"'),
    }
    for field, t in bad.items():
        with pytest.raises(SpecError, match=field.replace(".", r"\.")):
            parse_spec(t, "air_bend.toml")
    start = text.index("[deviation]")
    spec = parse_spec(text[:start] + "[deviation]\nkinds = []\n", "none.toml")
    assert spec.deviation.kinds == () and len(spec.deviation.group) == 0
    g = DeviationModel.from_spec(spec)
    z = np.linspace(0.0, 1.0, spec.n_t) ** 2
    assert g.n_params == 0
    assert np.array_equal(g.apply(z, np.zeros((3, 0))), np.tile(z, (3, 1)))
    # force scaling only: g(z) = (1 + a(x)) z exactly, a piecewise linear through the knots
    g1 = DeviationModel.from_spec(load_spec(SPEC))
    td = np.array([[0.1, -0.05, 0.02]])
    a = np.interp(g1.time, g1.knots, td[0])
    np.testing.assert_allclose(g1.apply(z, td)[0], (1.0 + a) * z, rtol=1e-13, atol=1e-15)


def test_design_export_fe_and_import_round_trip(tmp_path: Path) -> None:
    from formtwin.doe import paper_design

    spec = load_spec(SPEC)
    X = paper_design(spec, 20, seed=4)
    export_design(spec, X, tmp_path / "design.csv")
    fe = fe_module()
    assert fe.run_fe(tmp_path / "design.csv", tmp_path / "fe.csv") == len(X)
    data = import_csv(tmp_path / "fe.csv", spec, "closed-form")
    np.testing.assert_allclose(data.inputs, X, rtol=1e-11, atol=1e-12 * np.abs(X).max())
    assert data.angles.shape == (len(X), 1) and data.ok.all()
    # the FE grid (81 samples) interpolated onto the spec's 61: exact at the shared samples
    curves, angles = fe.air_bend(X, spec.time)
    np.testing.assert_allclose(data.angles[:, 0], angles, rtol=1e-8)
    shared = np.isin(np.round(spec.time, 9), np.round(fe.FE_STROKE, 9))
    np.testing.assert_allclose(data.curves[:, shared], curves[:, shared], rtol=1e-8)
    assert curve_columns(spec)[:2] == ["F@0", "F@0.1333333333"]
    # physical sense of the closed form: a stiffer press bends further (smaller angle)
    soft, stiff = X[:1].copy(), X[:1].copy()
    soft[0, 5], stiff[0, 5] = spec.params["tool_stiffness"].lo, spec.params["tool_stiffness"].hi
    assert fe.air_bend(stiff, spec.time)[1][0] < fe.air_bend(soft, spec.time)[1][0]


def test_dataset_simulator_reproduces_the_fe_runs_and_bending_physics_is_refused(
        tmp_path: Path) -> None:
    from formtwin.defaults import physics_model
    from formtwin.doe import paper_design
    from formtwin.study.fe_data import DatasetSimulator, check_physics

    spec = load_spec(SPEC)
    X = paper_design(spec, 40, seed=2)
    export_design(spec, X, tmp_path / "design.csv")
    fe_module().run_fe(tmp_path / "design.csv", tmp_path / "fe.csv")
    data = import_csv(tmp_path / "fe.csv", spec, "closed-form")
    sim = DatasetSimulator(data)
    curves, angles = sim.run_batch(data.inputs)
    scale = np.abs(data.curves).max()
    np.testing.assert_allclose(curves, data.curves, atol=1e-7 * scale)  # an interpolant
    np.testing.assert_allclose(angles, data.angles, atol=1e-7 * np.abs(data.angles).max())
    check_physics(sim, spec, "the FE dataset")  # runs: no error
    with pytest.raises((ValueError, KeyError)):
        check_physics(physics_model("bending", spec), spec, "the bending model")


def test_study_without_physics_for_the_spec_exits_nonzero_naming_what_is_missing(
        tmp_path: Path) -> None:
    from formtwin.defaults import analytic_dataset  # noqa: F401 - a metamodel is needed
    from formtwin.doe import paper_design
    from formtwin.metamodel import POD, RBF, Metamodel

    spec = load_spec(SPEC)
    X = paper_design(spec, 60, seed=1)
    export_design(spec, X, tmp_path / "design.csv")
    fe_module().run_fe(tmp_path / "design.csv", tmp_path / "fe.csv")
    data = import_csv(tmp_path / "fe.csv", spec, "closed-form")
    Metamodel(POD(n_modes=5), RBF(length_scales="box")).fit(data).save(tmp_path / "mm.npz")
    out = subprocess.run([*FORMTWIN, "study", "--metamodel", str(tmp_path / "mm.npz"),
                          "--out", str(tmp_path / "st"), "--quick"], capture_output=True,
                         text=True, timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert out.returncode != 0
    assert "--fe-data" in out.stderr and "air_bend" in out.stderr, out.stderr[-2000:]
    assert not (tmp_path / "st" / "runs").exists()  # refused before any filter run



def argv_of(line: str, broker: str) -> list[str]:
    """The argv of a documented line, run with this interpreter."""
    argv = shlex.split(line.replace("mqtt://127.0.0.1:1883", broker).rstrip(" &"))
    if argv[0] == "python":
        return [sys.executable, *argv[1:]]
    assert argv[0] == "formtwin", line
    return [*FORMTWIN, *argv[1:]]


def test_howto_chain_runs_as_documented(mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    """Every command of the how-to, in a scratch folder with the repository's examples
    and sources linked in: spec, DOE export/import, metamodel, track, study series 5/6 on
    the example's own FE dataset, serve + replay through mosquitto, export."""
    lines = doc_commands(DOC, MARK)
    for name in ("src", "examples"):
        (tmp_path / name).symlink_to(REPO / name)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1",
               PYTHONPATH=str(REPO / "src"))
    outputs: dict[str, str] = {}
    serve = None
    log = tmp_path / "serve.log"
    t0 = time.monotonic()
    try:
        for line in lines:
            argv = argv_of(line, mosquitto.url)
            if line.rstrip().endswith("&"):  # the service, in the background
                with open(log, "wb") as fh:
                    proc = subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=fh,
                                            stderr=subprocess.STDOUT)
                serve = proc
                wait_for(lambda p=proc: log_has(log, "connected and subscribed")
                         or p.poll() is not None, 120, lambda: log.read_text()[-2000:])
                assert proc.poll() is None, log.read_text()[-3000:]
                continue
            if argv[3:4] == ["export"]:  # the service has stored every product: stop it
                assert serve is not None
                wait_for(lambda: stored_count(tmp_path / "out/ab/line.sqlite") >= 80, 120,
                         lambda: log.read_text()[-2000:])
                serve.terminate()
                assert serve.wait(60) == 0, log.read_text()[-3000:]
            out = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True,
                                 timeout=600)
            assert out.returncode == 0, f"{line}\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}"
            outputs[line.split()[1]] = out.stdout
    finally:
        if serve is not None and serve.poll() is None:
            serve.kill()
    elapsed = time.monotonic() - t0
    ab = tmp_path / "out" / "ab"
    assert "bend_angle" in outputs["spec"] and "stroke" in outputs["spec"]
    est = list(csv.DictReader(open(ab / "estimates.csv", encoding="utf-8")))
    assert len(est) == 80 and "mean_sheet_thickness" in est[0] and "angle1_mean" in est[0]
    assert "angle2_mean" not in est[0]
    ok = sum(r["health"] == "ok" for r in est)
    assert ok >= 60, f"only {ok} of 80 curves fit with the spec's sensor noise"
    # the spec's own sensors: the bound of each set, and both fused from the line's file
    bound = json.loads((ab / "sensors" / "sensors.json").read_text(encoding="utf-8"))
    assert bound["output"] == "bend_angle"
    assert {"curve", "gauge_2um", "camera_0.1deg", "all"} <= set(bound["bound"])
    b = {k: v["states"]["sheet_thickness"] for k, v in bound["bound"].items()}
    assert b["gauge_2um"] < 0.5 * b["curve"]
    fused = list(csv.DictReader(open(ab / "estimates_sensors.csv", encoding="utf-8")))
    assert len(fused) == 80 and "gauge 80, camera 80" in outputs["track"]

    line = list(csv.DictReader(open(ab / "line.csv", encoding="utf-8")))
    gauge = np.array([float(r["sensor_gauge"]) for r in line])

    def off(rows: list[dict[str, str]]) -> float:  # rms distance from the gauge's values
        mean = np.array([float(r["mean_sheet_thickness"]) for r in rows])
        return float(np.sqrt(np.mean((mean[10:] - gauge[10:]) ** 2)))

    assert off(fused) < 0.3 * off(est)  # the thickness follows the 2 um gauge
    lo, hi = (np.array([float(r[f"final_interval90_{k}_deg"]) for r in fused[1:]])
              for k in ("lo", "hi"))
    assert np.all(lo < hi) and np.all(hi - lo < 2.0)
    # the study on the example's own FE dataset: finite numbers, no paper, no bending model
    nrmse = list(csv.DictReader(open(ab / "study" / "nrmse.csv", encoding="utf-8")))
    assert {r["series"] for r in nrmse} == {"5", "6"}
    assert all(np.isfinite(float(r["bend_angle"])) and np.isfinite(float(r["yield_stress"]))
               for r in nrmse)
    report = (ab / "study" / "report.md").read_text(encoding="utf-8")
    assert "Process air_bend" in report and "fe.h5" in report
    assert "paper reports" not in report and "corotational" not in report
    assert "bending model" not in report
    # served: one row per product, the example's names, its single output
    rows = list(csv.DictReader(open(ab / "line_estimates.csv", encoding="utf-8")))
    assert len(rows) == 80 and rows[0]["part_id"] == "AB-00001"
    with sqlite3.connect(ab / "line.sqlite") as db:  # the sensors' values fused, none refused
        fused_rows = db.execute("SELECT COUNT(*) FROM measurements WHERE status = 'fused'"
                                ).fetchone()[0]
        refused = db.execute("SELECT COUNT(*) FROM rejections").fetchone()[0]
    assert fused_rows >= 150 and refused == 0
    assert "mean_tool_stiffness" in rows[0] and "angle1_measured" in rows[0]
    assert "angle2_mean" not in rows[0]
    assert abs(float(rows[0]["angle1_measured"]) - float(rows[0]["angle1_mean"])) < 2.0
    assert elapsed < 600


def test_spec_reference_lists_every_key_the_reader_accepts() -> None:
    """docs/reference/spec.md: one section per table, its table's first column naming the
    keys (several per row separated by commas), the same sets as formtwin.spec.KEYS."""
    import re

    from formtwin.spec import KEYS, UNITS

    text = (REPO / "docs" / "reference" / "spec.md").read_text(encoding="utf-8")
    documented: dict[str, set[str]] = {}
    for part in re.split(r"\n## ", text)[1:]:
        table = re.match(r"`\[+(\w+)\]+`", part)
        if table is None:  # a section about something else (the bundled spec)
            continue
        keys = documented.setdefault(table.group(1), set())
        for row in re.findall(r"^\| (`[^|]+) \|", part, flags=re.M):
            keys.update(re.findall(r"`(\w+)`", row))
    top = set(re.findall(r"`\[+(\w+)\]+`", text.split("\n## ", 1)[0]))
    assert top == set(KEYS["<top>"])
    assert documented == {k: set(v) for k, v in KEYS.items() if k != "<top>"}
    units = set(re.findall(r"`([^`]+)`", text.split("| unit in the file |", 1)[1]
                           .split("\n\n", 1)[0].split("\n", 2)[2]))
    assert units >= set(UNITS)


def _publish(url: str, topic: str, payloads: list[bytes]) -> None:
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"pub-{time.time_ns()}")
    c.connect("127.0.0.1", int(url.rsplit(":", 1)[1]))
    c.loop_start()
    for info in [c.publish(topic, p, qos=1) for p in payloads]:
        info.wait_for_publish(10)
    c.disconnect()
    c.loop_stop()


def _strokes(tmp_path: Path, name: str, n: int, seed: int) -> tuple[list[bytes], set[str]]:
    from formtwin.service.messages import dumps
    from formtwin.service.streams import make_stream, read_stream

    strokes = read_stream(make_stream(tmp_path / f"{name}.npz", n, seed=seed))
    return [dumps(s.to_message()) for s in strokes], {s.part_id for s in strokes}


def _stored_ids(store: Path) -> list[str]:
    with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1.0) as db:
        return [r[0] for r in db.execute("SELECT part_id FROM products ORDER BY seq")]


def test_fresh_serve_after_check_stores_only_its_own_topic(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    """A check, then the service: `serve --check` on a test topic with the default client id,
    more strokes on that topic after it ended, an old persistent session of the default id
    still subscribed to a third topic with strokes queued; then a fresh `serve` with the
    default client id on the line's topic stores exactly the line's strokes."""
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    fast = ["--particles", "64", "--n-mc", "1000", "--seed", "3", "--no-page"]
    check_t, old_t, line_t = "test/press/stroke", "old/press/stroke", "plant/l1/press/stroke"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    check_log = tmp_path / "check.log"
    with open(check_log, "wb") as fh:
        check = subprocess.Popen([*FORMTWIN, "serve", "--analytic", "--broker", mosquitto.url,
                                  "--topic", check_t, "--store", str(tmp_path / "check.sqlite"),
                                  "--check", "3", *fast], stdout=fh,
                                 stderr=subprocess.STDOUT, env=env)
    try:
        wait_for(lambda: log_has(check_log, "connected and subscribed")
                 or check.poll() is not None, 120, lambda: check_log.read_text()[-2000:])
        payloads, _ = _strokes(tmp_path, "check", 8, 1)
        _publish(mosquitto.url, check_t, payloads)
        assert check.wait(120) == 0, check_log.read_text()[-3000:]
    finally:
        if check.poll() is None:
            check.kill()
    _publish(mosquitto.url, check_t, _strokes(tmp_path, "late", 4, 2)[0])
    # an old persistent session of the service's default id, subscribed to another topic
    old = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="formtwin-serve",
                      clean_session=False)
    old.connect("127.0.0.1", int(mosquitto.url.rsplit(":", 1)[1]))
    old.loop_start()
    old.subscribe(old_t, qos=1)
    time.sleep(0.5)
    old.disconnect()
    old.loop_stop()
    _publish(mosquitto.url, old_t, _strokes(tmp_path, "old", 5, 3)[0])

    store, log = tmp_path / "line.sqlite", tmp_path / "line.log"
    with open(log, "wb") as fh:
        serve = subprocess.Popen([*FORMTWIN, "serve", "--analytic", "--broker", mosquitto.url,
                                  "--topic", line_t, "--store", str(store), *fast],
                                 stdout=fh, stderr=subprocess.STDOUT, env=env)
    try:
        wait_for(lambda: log_has(log, "connected and subscribed") or serve.poll() is not None,
                 120, lambda: log.read_text()[-2000:])
        line, ids = _strokes(tmp_path, "line", 3, 4)
        _publish(mosquitto.url, line_t, line)
        wait_for(lambda: stored_count(store) >= 3, 60, lambda: log.read_text()[-2000:])
        time.sleep(1.5)  # anything else queued would have arrived by now
    finally:
        serve.terminate()
        serve.wait(30)
    stored = _stored_ids(store)
    assert len(stored) == 3 and set(stored) == ids
    assert log_has(log, f"ignoring messages on {old_t}")
    assert not log_has(log, check_t)


def test_tracker_runs_without_a_deviation_model(tmp_path: Path) -> None:
    """``[deviation] kinds = []``: theta_d is empty, the tracker estimates x and theta
    only, with and without estimate_deviation (the same filter: g is the identity)."""
    from formtwin.doe import paper_design
    from formtwin.metamodel import POD, RBF, Metamodel
    from formtwin.tracker import TrackerConfig, build_tracker

    text = SPEC.read_text(encoding="utf-8")
    spec = parse_spec(text[:text.index("[deviation]")] + "[deviation]\nkinds = []\n", "n.toml")
    fe = fe_module()
    X = paper_design(spec, 100, seed=5)
    curves, angles = fe.air_bend(X, spec.time)
    from formtwin.dataset import DoeDataset

    data = DoeDataset(spec=spec, inputs=X, curves=curves, angles=angles[:, None],
                      ok=np.ones(len(X), bool), reason=np.full(len(X), ""), model_version="cf")
    mm = Metamodel(POD(n_modes=8), RBF(length_scales="box")).fit(data)
    Xp, Y, _ = fe.production(30, 2, spec)
    runs = []
    for dev in (True, False):
        tr = build_tracker(mm, TrackerConfig(n_particles=150, n_mc=1000, seed=1,
                                             estimate_deviation=dev, sensor_noise=10.0))
        runs.append(tr.run(Y))
    for est in runs:
        assert est.mean.shape == (30, 6) and est.angles_mean.shape == (30, 1)
        assert np.all(np.isfinite(est.mean)) and np.sum(est.health == "ok") >= 20
    np.testing.assert_array_equal(runs[0].mean, runs[1].mean)
    # the die opening is well observed by the force level: inside 3 std of the truth
    j = spec.inputs.index["die_opening_offset"]
    assert abs(runs[0].mean[-1, j] - Xp[-1, j]) < 3 * runs[0].std[-1, j] + 1e-3
