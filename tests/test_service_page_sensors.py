"""The live page with sensor messages, in headless Chromium: the camera's measured final
angle against the predicted one with its calibrated interval, and the sensors' last values."""

from __future__ import annotations

from pathlib import Path

from service_fixtures import (
    Mosquitto,
    free_port,
    live_page,
    mosquitto,  # noqa: F401 - fixture
    require_browser,
    serve_cmd,
    start_serve,
    wait_serving,
)

from formtwin.service.mqtt import BrokerConfig, publish_strokes
from formtwin.service.streams import interleave, make_stream, read_readings, read_stream

TOPIC, SENSORS = "plant/line1/press1/stroke", "plant/line1/press1/sensor"


def test_page_shows_camera_against_prediction_and_last_values(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    require_browser()
    path = make_stream(tmp_path / "s.npz", 30, seed=4, sensors=("gauge", "camera"))
    strokes, readings = read_stream(path), read_readings(path)
    messages = interleave(strokes, readings)
    port = free_port()
    log = tmp_path / "serve.log"
    # the settings of test_service_sensors_mqtt's services: their chart calibration is shared
    cmd = serve_cmd(mosquitto, tmp_path / "a.sqlite", "--particles", "64", "--n-mc", "1000",
                    "--seed", "3", "--http-port", str(port), "--sensors", "gauge,camera")
    proc = start_serve(cmd, log)
    broker = BrokerConfig.from_url(mosquitto.url)
    try:
        wait_serving(proc, log)
        first = messages.index(strokes[10])
        publish_strokes(messages[:first], broker, TOPIC, sensor_topic=SENSORS)
        with live_page(f"http://127.0.0.1:{port}/", height=1400) as (page, errors):
            # loaded from the state: products 0..8's camera values (the 9th's comes later)
            page.wait_for_function("Number(document.body.dataset.finals || 0) >= 9",
                                   timeout=30_000)
            publish_strokes(messages[first:], broker, TOPIC, sensor_topic=SENSORS)
            page.wait_for_function("Number(document.body.dataset.finals || 0) >= 30",
                                   timeout=30_000)
            data = page.evaluate("window.formtwinLive.charts.find("
                                 "(c) => c.key === 'final').data")
            x, lo, pred, hi, meas = data
            assert x == list(range(30))
            assert all(a < p < b for a, p, b in zip(lo, pred, hi, strict=True))
            cams = {r.part_id: r.value for _, r in readings if r.sensor == "camera"}
            assert meas == [cams[s.part_id] for s in strokes]
            text = page.inner_text("#sensor-values")
            last_gauge = [r for _, r in readings if r.sensor == "gauge"][-1]
            assert "camera" in text and f"gauge {last_gauge.value:.4g}" in text, text
            assert strokes[-1].part_id in text
            assert not errors, errors
    finally:
        proc.terminate()
        proc.wait(20)
