"""Monitoring on the live page, in a real headless Chromium against a running `formtwin
serve` with user-set limits: a control chart per monitored variable with its limits, the
signals marked on the charts, the alarm episodes listed, published on the alarms topic, and
acknowledged on the page (with the page token; without it the service refuses)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from service_fixtures import (
    Collector,
    Mosquitto,
    free_port,
    live_page,
    mosquitto,  # noqa: F401 - fixture
    require_browser,
    serve_cmd,
    start_serve,
    wait_for,
    wait_serving,
)

from formtwin.monitoring.glr import Glr
from formtwin.monitoring.incontrol import InControl
from formtwin.monitoring.monitor import MonitorConfig
from formtwin.service.mqtt import BrokerConfig, publish_strokes
from formtwin.service.streams import make_stream, read_stream

TOPIC = "plant/line1/press1/stroke"
ALARMS = "plant/line1/press1/alarms"


def test_page_shows_charts_and_alarms_and_acknowledges(mosquitto: Mosquitto,  # noqa: F811
                                                       tmp_path: Path) -> None:
    require_browser()
    # user-set limits: thickness in control at 300 um with a residual sigma of 1 nm (the
    # estimates are out of control), the stage-2 angle about its Phase-I level
    config = MonitorConfig({"thickness": InControl(mean=300.0, sigma=1e-3),
                            "angle_stage2": InControl(mean=None, sigma=1e-3)},
                           warmup=2, phase1=3,
                           glr={"thickness": Glr((1.0, 0.3), h=20.0, window=50)})
    (tmp_path / "limits.json").write_text(config.to_json())
    strokes = read_stream(make_stream(tmp_path / "s.npz", 20, seed=4))
    port = free_port()
    log = tmp_path / "serve.log"
    cmd = serve_cmd(mosquitto, tmp_path / "a.sqlite", "--particles", "64", "--n-mc", "1000",
                    "--http-port", str(port), "--monitor-config", str(tmp_path / "limits.json"),
                    "--page-token", "tok-123")
    proc = start_serve(cmd, log)
    collector = Collector(mosquitto.url, [ALARMS])
    try:
        wait_serving(proc, log)
        assert f"live page: http://127.0.0.1:{port}/?token=tok-123" in log.read_text()
        assert f"alarms -> {ALARMS}" in log.read_text()
        publish_strokes(strokes, BrokerConfig.from_url(mosquitto.url), TOPIC)
        wait_for(lambda: len(collector.get(ALARMS)) >= 3, 30, "alarms on the alarms topic")
        with live_page(f"http://127.0.0.1:{port}/?token=tok-123", height=1400) as (page, errors):
            page.wait_for_function("Number(document.body.dataset.points || 0) >= 20 && "
                                   "Number(document.body.dataset.alarms || 0) >= 3",
                                   timeout=30_000)
            # one control chart per monitored variable, with its limits and signals
            keys = page.evaluate("window.formtwinLive.charts.map(c => c.key)")
            assert "chart:thickness" in keys and "chart:angle_stage2" in keys
            assert "glr:thickness" in keys and "glr:angle_stage2" not in keys
            chart = page.evaluate(
                "window.formtwinLive.charts.find(c => c.key === 'chart:thickness')"
                ".plot.data")
            seqs, stat, upper, lower, marks = chart
            charted = [i for i, v in enumerate(upper) if v is not None]
            assert len(charted) == 20 - 5  # after warm-up and Phase I
            assert all(lower[i] == -upper[i] and stat[i] is not None for i in charted)
            signals = _get(port, "api/signals")
            marked = {seqs[i] for i, v in enumerate(marks) if v is not None}
            assert marked == {a["seq"] for a in signals if a["variable"] == "thickness"}
            assert marked
            # the GLR chart: its statistic with its one limit, marked where it signalled
            seqs_g, stat_g, upper_g, lower_g, marks_g = page.evaluate(
                "window.formtwinLive.charts.find(c => c.key === 'glr:thickness').plot.data")
            assert [v for v in upper_g if v is not None] == [20.0] * (20 - 5)
            assert all(v is None for v in lower_g)
            assert {seqs_g[i] for i, v in enumerate(marks_g) if v is not None} == {
                a["seq"] for a in signals if a["variable"] == "thickness" and a["chart"] == "glr"}
            assert any(a["chart"] == "glr" for a in signals)
            # the list: one episode per chart and variable, many signals each, raised once
            # on the alarms topic
            episodes = _get(port, "api/alarms")
            n_alarms = int(page.get_attribute("body", "data-alarms") or 0)
            assert n_alarms == len(episodes) < len(signals)
            assert len({(e["variable"], e["chart"]) for e in episodes}) == len(episodes)
            assert any(e["signals"] > 1 for e in episodes)
            assert sorted(m["id"] for m in collector.get(ALARMS) if m["event"] == "raised") == \
                [e["id"] for e in episodes]
            assert page.inner_text("#n-alarms") == str(n_alarms)
            active = sum(e["state"] == "active" for e in episodes)
            assert page.inner_text("#n-active") == str(active) and active
            busiest = max(episodes, key=lambda e: e["signals"])
            row = page.inner_text(f".alarm[data-id='{busiest['id']}']")
            assert f"{busiest['signals']} signals" in row and busiest["state"] in row
            # acknowledge the newest episode on the page
            newest = episodes[-1]["id"]
            page.click(f".alarm[data-id='{newest}'] button")
            page.wait_for_function(
                f"document.querySelector(\".alarm[data-id='{newest}']\")"
                ".classList.contains('acked')", timeout=10_000)
            assert page.inner_text("#n-alarms") == str(n_alarms - 1)
            acked = [a for a in _get(port, "api/alarms") if a["acked_at"] is not None]
            assert [a["id"] for a in acked] == [newest]
            assert acked[0]["ack_note"] == "acknowledged on the live page"
            # ... and published on the alarms topic for whoever else watches the line
            wait_for(lambda: any(m["event"] == "acknowledged" for m in collector.get(ALARMS)),
                     10, "the acknowledgement on the alarms topic")
            ack_msgs = [m for m in collector.get(ALARMS) if m["event"] == "acknowledged"]
            assert [(m["id"], m["acked_at"]) for m in ack_msgs] == [(newest, acked[0]["acked_at"])]
            assert not errors, errors
            page.screenshot(path=str(tmp_path / "alarms.png"), full_page=True)
        # without the token the service refuses to acknowledge
        req = urllib.request.Request(f"http://127.0.0.1:{port}/api/alarms/"
                                     f"{episodes[0]['id']}/ack", method="POST", data=b"")
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(req, timeout=10)
        assert err.value.code == 403
    finally:
        collector.stop()
        proc.terminate()
        proc.wait(20)


def _get(port: int, path: str) -> list[dict[str, object]]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/{path}", timeout=10) as r:
        return list(json.loads(r.read()))
