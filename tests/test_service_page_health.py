"""The model-mismatch banner in a real headless Chromium, the ESS axis, and the page token:
read-only without one, no binding beyond 127.0.0.1 without one."""

from __future__ import annotations

import json
import os
import re
import subprocess
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from service_fixtures import (
    REPO,
    Collector,
    Mosquitto,
    free_port,
    live_page,
    log_has,
    mosquitto,  # noqa: F401 - fixture
    require_browser,
    serve_cmd,
    start_serve,
    wait_for,
    wait_serving,
)

from formtwin.dataset import DoeDataset
from formtwin.defaults import analytic_model, bundled_doe
from formtwin.service.messages import Stroke, stroke_digest
from formtwin.service.mqtt import BrokerConfig, publish_strokes
from formtwin.service.plausibility import Plausibility

TOPIC = "plant/line1/press1/stroke"
#: set to write the screenshot shown in docs/explanation/health.md
SHOT = REPO / "docs" / "figures" / "service_mismatch_banner.png"


def physics_strokes(n: int) -> list[Stroke]:
    """Curves of the physics model (bundled DOE) that pass the plausibility checks of the
    analytic stand-in: well-formed, plausible, and not explained by the stand-in."""
    data = DoeDataset.load(bundled_doe("bending"))
    lim = Plausibility.from_model(analytic_model())
    curves = [c for c in data.curves[data.ok][:300] if lim.check(c) is None][:n]
    return [Stroke(part_id=f"PH-{i:04d}", cycle=i + 1, timestamp=float(i + 1),
                   force_N=np.asarray(c), angles_deg=None, digest=stroke_digest(c))
            for i, c in enumerate(curves)]


def test_mismatch_banner_in_chromium(mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    require_browser()
    port = free_port()
    log = tmp_path / "serve.log"
    proc = start_serve(serve_cmd(mosquitto, tmp_path / "a.sqlite", "--particles", "200",
                                 "--n-mc", "1000", "--http-port", str(port), "--no-monitor"),
                       log)
    broker = BrokerConfig.from_url(mosquitto.url)
    errors_topic = TOPIC.rsplit("/", 1)[0] + "/errors"
    collector = Collector(mosquitto.url, [errors_topic])
    try:
        wait_serving(proc, log)
        assert log_has(log, "plausibility: peak >=")
        publish_strokes(physics_strokes(12), broker, TOPIC)
        wait_for(lambda: any(m.get("reason") == "model_mismatch"
                             for m in collector.get(errors_topic)), 60, "model_mismatch")
        with live_page(f"http://127.0.0.1:{port}/", height=820) as (page, errors):
            page.wait_for_function("document.body.dataset.health === 'model_mismatch'",
                                   timeout=30_000)
            text = page.inner_text("#banner")
            assert "Model mismatch since product" in text
            assert "the model does not explain the force curves" in text
            assert "Expected:" in text and "chi-square with 101 degrees of freedom" in text
            assert "Seen:" in text and "Likely causes:" in text
            assert "a metamodel of another press" in text
            # the ESS axis runs 0 .. N, whatever the ESS (1 of 200 here)
            y_max = page.evaluate(
                "window.formtwinLive.charts.find(c => c.key === 'ess').plot.scales.y.max")
            assert y_max == 200
            assert not errors, errors
            page.screenshot(path=str(SHOT if os.environ.get("FORMTWIN_DOCS_SHOTS")
                                     else tmp_path / "banner.png"))
        notes = [m for m in collector.get(errors_topic) if m.get("reason") == "model_mismatch"]
        assert len(notes) == 1  # once per episode
        state = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state",
                                                  timeout=10).read())
        assert state["health"]["state"] == "model_mismatch"
        # read-only page: no token configured, state-changing requests are refused
        req = urllib.request.Request(f"http://127.0.0.1:{port}/api/alarms/1/ack",
                                     data=b"{}", method="POST")
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(req, timeout=10)
        assert err.value.code in (403, 404, 405)
    finally:
        collector.stop()
        proc.terminate()
        proc.wait(20)


def test_serve_check_exits_nonzero_with_the_message(mosquitto: Mosquitto,  # noqa: F811
                                                   tmp_path: Path) -> None:
    """`serve --check 20` on a model that does not explain the press: exit 1, the message."""
    log = tmp_path / "check.log"
    proc = start_serve(serve_cmd(mosquitto, tmp_path / "c.sqlite", "--particles", "100",
                                 "--n-mc", "1000", "--no-monitor", "--no-page", "--check",
                                 "20"), log)
    try:
        wait_serving(proc, log)
        publish_strokes(physics_strokes(20), BrokerConfig.from_url(mosquitto.url), TOPIC)
        code = proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert code == 1, text[-2000:]
    found = re.search(r"model_mismatch after (\d+) products: the model does not explain the "
                      r"force curves", text)
    assert found and int(found.group(1)) <= 10, text[-2000:]
    # and says what the sensor noise was (the analytic stand-in's spec gives none: 0 N)
    assert "sensor noise in use: 0 N (the default: no noise_sd" in text, text[-2000:]


def test_page_refuses_other_addresses_without_a_token(mosquitto: Mosquitto,  # noqa: F811
                                                      tmp_path: Path) -> None:
    cmd = serve_cmd(mosquitto, tmp_path / "b.sqlite", "--particles", "32", "--n-mc", "500",
                    "--no-monitor", "--http-host", "0.0.0.0", "--http-port", str(free_port()))
    env = {k: v for k, v in os.environ.items() if k != "FORMTWIN_PAGE_TOKEN"}
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env, cwd=REPO)
    assert out.returncode != 0
    assert "only with a page token" in out.stderr + out.stdout


def test_page_token_guards_state_changes() -> None:
    """The token check alone: read-only without a configured token, 403 with a missing or
    wrong one, through with the right one."""
    from types import SimpleNamespace

    from formtwin.service.web import token_ok

    for configured, sent, code in (("", None, 403), ("tok", "bad", 403), ("tok", None, 403),
                                   ("tok", "tok", None)):
        headers = {} if sent is None else {"x-formtwin-token": sent}
        refused = token_ok(SimpleNamespace(headers=headers), configured)  # type: ignore[arg-type]
        assert (None if refused is None else refused.status_code) == code
        if configured == "":
            assert refused is not None and b"read-only" in refused.body
