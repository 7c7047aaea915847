"""Sensor messages through a real mosquitto: `formtwin replay` sends a stream's gauge and
camera values on the sensor topic between its strokes, `formtwin serve` is SIGKILLed at
random moments, and the store ends bit for bit as an uninterrupted run's."""

from __future__ import annotations

import json
import signal
import sqlite3
from pathlib import Path

import numpy as np
from service_fixtures import (
    Collector,
    Mosquitto,
    mosquitto,  # noqa: F401 - fixture
    replay_with_kills,
    serve_cmd,
    stored_count,
    wait_for,
)

from formtwin.service.messages import dumps
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import interleave, make_stream, read_readings, read_stream
from formtwin.tracker import TrackerConfig

FAST = ["--particles", "64", "--n-mc", "1000", "--seed", "3", "--no-page",
        "--sensors", "gauge,camera"]
SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3,
                                                 sensors=("gauge", "camera")))
RESULTS, ERRORS = "plant/line1/press1/estimate", "plant/line1/press1/errors"


def measured(store: Path) -> int:
    """Sensor messages in a service's store (0 while it does not exist or is locked)."""
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1.0) as db:
            return int(db.execute("SELECT COUNT(*) FROM measurements").fetchone()[0])
    except sqlite3.Error:
        return 0


def test_sigkill_with_sensor_messages_loses_nothing_and_doubles_nothing(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    n = 300
    stream = make_stream(tmp_path / "s.npz", n, seed=6, sensors=("gauge", "camera"))
    store, log = tmp_path / "kill.sqlite", tmp_path / "serve.log"
    cmd = serve_cmd(mosquitto, store, *FAST)
    col = Collector(mosquitto.url, [RESULTS, ERRORS])
    rng = np.random.default_rng(12)
    thresholds = sorted(int(t) for t in rng.choice(np.arange(50, n - 50), 4, replace=False))
    proc = None
    try:
        proc, kills, out = replay_with_kills(
            cmd, log, stream, mosquitto.url, thresholds, rng,
            done=lambda: stored_count(store) >= n and measured(store) >= 2 * n,
            progress=lambda: stored_count(store), timeout=240)
        assert f"and {2 * n} sensor messages" in out
        assert stored_count(store) == n and measured(store) == 2 * n, \
            f"{stored_count(store)} products, {measured(store)} sensor values after {kills} kills"
        wait_for(lambda: len({(r["part_id"], r.get("sensor")) for r in col.get(RESULTS)})
                 == 3 * n, 30, lambda: "an answer for every stroke and sensor message "
                 f"(collector disconnects {col.disconnects}, errors {col.errors})")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        col.stop()
    assert kills >= 5
    with sqlite3.connect(store) as db:
        rows = db.execute("SELECT part_id, estimate FROM products ORDER BY seq").fetchall()
        meas = db.execute("SELECT part_id, sensor, value, status, at_seq, product, message "
                          "FROM measurements ORDER BY id").fetchall()
        assert db.execute("SELECT COUNT(*) FROM rejections").fetchone()[0] == 0
    # the reference: the same messages in the same order, in process, never interrupted
    strokes = read_stream(stream)
    ref = open_processor(tmp_path / "ref.sqlite", SETTINGS)
    want = [ref.handle(dumps(m.to_message())).message if hasattr(m, "force_N")
            else ref.handle_sensor(dumps(m.to_message())).message
            for m in interleave(strokes, read_readings(stream))]
    want_meas = ref.store.query("SELECT part_id, sensor, value, status, at_seq, product, "
                                "message FROM measurements ORDER BY id")
    ref.close()
    keep = ("part_id", "index", "mean", "std", "angles_mean", "angles_std", "ess", "loglik",
            "measurements", "final")
    estimates = [m for m in want if m["schema"] == "formtwin.estimate/1"]
    assert [r[0] for r in rows] == [s.part_id for s in strokes]
    for (pid, est), w in zip(rows, estimates, strict=True):
        have = json.loads(est)
        assert {k: have[k] for k in keep} == {k: w[k] for k in keep}, pid
    assert [tuple(r) for r in meas] == [tuple(r) for r in want_meas]
    assert {r[3] for r in meas} == {"fused"}
    # every gauge value (before its stroke: in its own estimate; the first product's after
    # its step, in the next) and every camera value but the last two (after the last stroke)
    assert sum(len(e["measurements"]) for e in estimates) == 2 * n - 2
