"""The live page in a real headless Chromium (Debian's, driven by Playwright) against a
running `formtwin serve`: points appear and grow as strokes arrive; rejections are counted."""

from __future__ import annotations

import os
import re
import signal
import threading
import time
import urllib.request
from pathlib import Path

from service_fixtures import (
    Mosquitto,
    free_port,
    live_page,
    log_has,
    mosquitto,  # noqa: F401 - fixture
    require_browser,
    serve_cmd,
    start_serve,
    wait_serving,
)

from formtwin.service.mqtt import BrokerConfig, publish_strokes
from formtwin.service.streams import make_stream, read_stream

TOPIC = "plant/line1/press1/stroke"
#: the live page in its normal state, shown in docs/explanation/service.md; written with
#: FORMTWIN_DOCS_SHOTS=1 set
SHOT = Path(__file__).resolve().parent.parent / "docs" / "figures" / "service_live_page.png"


def test_live_page_in_chromium(mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    require_browser()
    strokes = read_stream(make_stream(tmp_path / "s.npz", 50, seed=4))
    port = free_port()
    log = tmp_path / "serve.log"
    # the settings of test_service_mqtt's services: the session's chart calibration is theirs
    cmd = serve_cmd(mosquitto, tmp_path / "a.sqlite", "--particles", "64", "--n-mc", "1000",
                    "--seed", "3", "--http-port", str(port))
    proc = start_serve(cmd, log)
    broker = BrokerConfig.from_url(mosquitto.url)
    try:
        wait_serving(proc, log)
        assert log_has(log, f"live page: http://127.0.0.1:{port}/")
        publish_strokes(strokes[:5], broker, TOPIC)
        with live_page(f"http://127.0.0.1:{port}/", height=900) as (page, errors):
            page.wait_for_function("Number(document.body.dataset.points || 0) >= 5",
                                   timeout=30_000)
            first = int(page.inner_text("#n-points"))
            assert page.locator("canvas").count() >= 21  # 18 variables, 2 angles, ESS
            page.wait_for_function(
                "document.getElementById('conn').textContent === 'live'", timeout=10_000)
            # strokes arriving while the page is open: points appear and grow
            feeder = threading.Thread(target=publish_strokes, daemon=True, kwargs=dict(
                strokes=strokes[5:40], broker=broker, topic=TOPIC, rate=20.0))
            feeder.start()
            page.wait_for_function("Number(document.body.dataset.points) >= 15",
                                   timeout=30_000)
            mid = int(page.inner_text("#n-points"))
            page.wait_for_function("Number(document.body.dataset.points) >= 40",
                                   timeout=30_000)
            feeder.join(10)
            last = int(page.inner_text("#n-points"))
            assert first < mid < last == 40
            assert page.inner_text("#last-part") == strokes[39].part_id
            # the chart holds the data: the ESS chart has 40 x values
            n_x = page.evaluate("window.formtwinLive.charts.at(-1).plot.data[0].length")
            assert n_x == 40
            if os.environ.get("FORMTWIN_DOCS_SHOTS"):
                page.screenshot(path=str(SHOT))
            _publish_raw(mosquitto.url, b"{not json")
            page.wait_for_function(
                "document.getElementById('n-rejected').textContent === '1'",
                timeout=20_000)
            assert "malformed_json: 1" in page.inner_text("#reasons")
            assert page.inner_text("#n-accepted") == "40"
            # the service is killed and restarted: the open page reloads and goes on
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
            log2 = tmp_path / "serve2.log"
            proc = start_serve(cmd, log2)
            wait_serving(proc, log2)
            publish_strokes(strokes[40:50], broker, TOPIC)
            page.wait_for_function("Number(document.body.dataset.resets || 0) >= 1 && "
                                   "Number(document.body.dataset.points) >= 50",
                                   timeout=40_000)
            assert page.inner_text("#n-accepted") == "50"
            assert page.inner_text("#n-rejected") == "1"
            assert page.inner_text("#last-part") == strokes[49].part_id
            assert not errors, errors
            page.screenshot(path=str(tmp_path / "live.png"))
        state = urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=10).read()
        assert re.search(rb'"accepted":\s*50', state)
    finally:
        proc.terminate()
        proc.wait(20)


def _publish_raw(url: str, payload: bytes) -> None:
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"raw-{time.time_ns()}")
    c.connect("127.0.0.1", int(url.rsplit(":", 1)[1]))
    c.loop_start()
    c.publish(TOPIC, payload, qos=1).wait_for_publish(10)
    c.disconnect()
    c.loop_stop()
