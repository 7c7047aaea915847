"""Monitoring in the service (broker-free): charts on every accepted estimate, alarms in the
store and in the message, restart without losing or doubling an alarm, rollback of a failed
commit, calibration fixed with the store, and the page's alarm routes with the token."""

from __future__ import annotations

import json
import sqlite3
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from formtwin.monitoring.calibrate import ChartDesign
from formtwin.monitoring.incontrol import InControl
from formtwin.monitoring.monitor import Monitor, MonitorConfig
from formtwin.service.alarms import MonitorSource, ServiceMonitor, monitor_config, values_of
from formtwin.service.messages import dumps
from formtwin.service.processor import Processor
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.spec import load_spec
from formtwin.tracker import TrackerConfig

SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))


@pytest.fixture(scope="module")
def payloads(tmp_path_factory: pytest.TempPathFactory) -> list[bytes]:
    path = make_stream(tmp_path_factory.mktemp("stream") / "s.npz", 40, seed=1)
    return [dumps(s.to_message()) for s in read_stream(path)]


def tight_config() -> MonitorConfig:
    """User-set limits so tight that the stream is out of control: the thickness estimate's
    in-control sigma is a thousandth of a micrometre, the angle's level from Phase I."""
    q = {"thickness": InControl(mean=300.0, sigma=1e-3),
         "angle_stage2": InControl(mean=None, sigma=1e-3)}
    return MonitorConfig(q, warmup=2, phase1=3)


def attach(proc: Processor, config: MonitorConfig) -> ServiceMonitor:
    mon = ServiceMonitor(proc.store, config)
    proc.monitor = mon
    return mon


def close(proc: Processor) -> None:
    proc.close()


def test_alarms_are_charted_stored_and_survive_a_restart(tmp_path: Path,
                                                         payloads: list[bytes]) -> None:
    config = tight_config()
    # the reference: one uninterrupted service
    ref = open_processor(tmp_path / "ref.sqlite", SETTINGS)
    ref_mon = attach(ref, config)
    ref_out = [ref.handle(p) for p in payloads]
    assert all(o.kind == "accepted" for o in ref_out)
    phases = [o.message["monitoring"]["phase"] for o in ref_out]
    assert phases[:2] == ["warmup"] * 2 and phases[2:5] == ["phase1"] * 3
    assert set(phases[5:]) == {"charting"}
    # the product's signals (per product) and its episodes (one per chart while it signals)
    every = [{**a, "seq": o.seq} for o in ref_out for a in o.message["monitoring"]["alarms"]]
    alarms = [a for a in every if a["chart"] != "model_mismatch"]
    assert len(alarms) > 5  # out of control by construction
    assert {a["variable"] for a in alarms} <= {"thickness", "angle_stage2"}
    stored = ref_mon.signals()
    assert [(a["seq"], a["variable"], a["chart"]) for a in stored] == \
        [(a["seq"], a["variable"], a["chart"]) for a in every]
    episodes = ref_mon.alarms()
    assert len(episodes) == len({(a["variable"], a["chart"]) for a in every}) < len(every)
    for ep in episodes:  # each episode's signals are its chart's, counted and linked
        mine = [a for a in stored if a["episode_id"] == ep["id"]]
        assert mine and {(a["variable"], a["chart"]) for a in mine} == {
            (ep["variable"], ep["chart"])}
        assert (ep["raised_seq"], ep["last_seq"], ep["signals"]) == (
            mine[0]["seq"], mine[-1]["seq"], len(mine))
        assert ep["ratio"] == pytest.approx(max(abs(a["statistic"]) / a["limit"]
                                                for a in mine))
    # published: the raises, an update at most once per clear-after products, no storm
    published = [a for o in ref_out for a in o.alarms]
    assert sorted(a["id"] for a in published if a["event"] == "raised") == \
        [e["id"] for e in episodes]
    assert len(published) < len(every) / 2
    # the message carries the chart statistics: the EWMA statistic beyond its limit
    for o in ref_out:
        for a in o.message["monitoring"]["alarms"]:
            if a["chart"] == "model_mismatch":
                continue
            stat, lim = o.message["monitoring"]["charts"][a["variable"]][a["chart"]]
            assert abs(stat) > lim and a["limit"] == lim
    # the same charts from the stored values alone (the monitor is a function of them)
    offline = Monitor(config)
    again = [a.to_dict() for o in ref_out for a in offline.update_values(
        values_of(o.message, config), o.message["index"])]
    assert again == [{k: a[k] for k in again[0]} for a in alarms]

    # a service stopped after 23 products, then a restart: same charts, same signals and
    # episodes, none doubled, none lost
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    mon = attach(proc, config)
    for p in payloads[:23]:
        proc.handle(p)
    n_before = len(mon.signals())
    assert n_before >= 1
    close(proc)
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    mon = attach(proc, config)
    assert len(mon.signals()) == n_before
    rest = [proc.handle(p) for p in payloads[23:]]
    assert [o.message for o in rest] == [o.message for o in ref_out[23:]]
    assert [o.alarms for o in rest] == [o.alarms for o in ref_out[23:]]
    assert mon.monitor.state() == ref_mon.monitor.state()
    assert mon.episodes.state() == ref_mon.episodes.state()
    strip = [{k: a[k] for k in ("seq", "variable", "chart", "side", "statistic", "episode_id")}
             for a in mon.signals()]
    assert strip == [{k: a[k] for k in strip[0]} for a in stored]
    untimed = ("raised_at", "updated_at", "cleared_at")
    assert [{k: v for k, v in e.items() if k not in untimed} for e in mon.alarms()] == \
        [{k: v for k, v in e.items() if k not in untimed} for e in ref_mon.alarms()]
    # acknowledging an episode: stored with its note, kept on a second acknowledgement
    first = mon.alarms()[0]
    acked = mon.acknowledge(first["id"], "seen", now=1000.0)
    assert acked["acked_at"] == 1000.0 and acked["ack_note"] == "seen"
    assert acked["state"] == "active"  # acknowledged, still signalling
    assert mon.acknowledge(first["id"], "again", now=2000.0)["acked_at"] == 1000.0
    assert first["id"] not in [a["id"] for a in mon.alarms(unacked=True)]
    with pytest.raises(KeyError, match="no alarm"):
        mon.acknowledge(10**6)
    close(proc)
    close(ref)


def test_a_failed_commit_leaves_charts_and_tables_as_before(tmp_path: Path,
                                                            payloads: list[bytes]) -> None:
    """A storage error inside the product's transaction, after its alarm rows were written:
    neither the product nor its alarms are stored, the charts are as before, and the same
    stroke again gives what an undisturbed service gives."""
    ref = open_processor(tmp_path / "ref.sqlite", SETTINGS)
    attach(ref, tight_config())
    want = [ref.handle(p) for p in payloads[:12]]
    assert want[-1].message["monitoring"]["alarms"]  # the product that fails signals
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    mon = attach(proc, tight_config())
    for p in payloads[:11]:
        proc.handle(p)
    before = json.dumps([mon.monitor.state(), mon.episodes.state()])
    n_alarms, episodes = len(mon.signals()), mon.alarms()
    real = mon.write

    def fail(*args: Any) -> list[dict[str, Any]]:
        real(*args)
        raise sqlite3.OperationalError("disk I/O error")

    mon.write = fail  # type: ignore[method-assign]
    with pytest.raises(sqlite3.OperationalError):
        proc.handle(payloads[11])
    assert json.dumps([mon.monitor.state(), mon.episodes.state()]) == before
    assert len(mon.signals()) == n_alarms and proc.store.counts()["accepted"] == 11
    assert mon.alarms() == episodes
    mon.write = real  # type: ignore[method-assign]
    again = proc.handle(payloads[11])
    assert again.kind == "accepted" and again.message == want[-1].message
    assert again.alarms == want[-1].alarms
    assert len(mon.signals()) == n_alarms + len(again.message["monitoring"]["alarms"])
    close(proc)
    close(ref)


def test_calibrated_charts_are_fixed_with_the_store(tmp_path: Path,
                                                    payloads: list[bytes]) -> None:
    """First start: charts calibrated on simulated in-control runs of the service's own
    tracker (state AR models about the tracker's mu); a restart reads them back, whatever
    source it is given."""
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    design = ChartDesign(warmup=5, phase1=10)
    cfg = monitor_config(proc.store, proc.tracker, MonitorSource(runs=1, products=300,
                                                                 design=design))
    spec = proc.tracker.spec  # type: ignore[attr-defined]
    assert set(cfg.quantities) == {*spec.state.names, "angle_stage1", "angle_stage2"}
    assert set(cfg.health) == {"loglik", "ess", "fit"}  # the fit: its log10 p-value
    np.testing.assert_allclose([cfg.quantities[n].mean for n in spec.state.names],
                               spec.state.mu_mid)
    assert (cfg.warmup, cfg.phase1) == (5, 10)
    other = MonitorSource(file=str(tmp_path / "missing.json"))
    assert monitor_config(proc.store, proc.tracker, other).to_json() == cfg.to_json()
    mon = ServiceMonitor(proc.store, cfg)
    proc.monitor = mon
    outs = [proc.handle(p) for p in payloads]
    charts = outs[-1].message["monitoring"]["charts"]
    assert set(charts) == set(cfg.quantities) | {"loglik", "ess", "fit"}
    assert charts["ess"]["mismatch"][1] == pytest.approx(cfg.mismatch.h)
    close(proc)
    with pytest.raises(ValueError, match="missing.json"):
        fresh = open_processor(tmp_path / "b.sqlite", SETTINGS)
        try:
            monitor_config(fresh.store, fresh.tracker, other)
        finally:
            fresh.store.close()


def test_charts_watch_the_line_means_the_service_is_told(tmp_path: Path) -> None:
    """``serve --mu``: the state charts' in-control means are the line's (a stream's means
    lie anywhere in [mu_min, mu_max]; charts about the mid-range would take the line's
    own offset for a shift)."""
    spec = load_spec()  # the analytic stand-in's
    mu = spec.state.mu_min + 0.8 * (spec.state.mu_max - spec.state.mu_min)
    told = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3,
                                                 mu=tuple(float(v) for v in mu)))
    proc = open_processor(tmp_path / "a.sqlite", told)
    cfg = monitor_config(proc.store, proc.tracker, MonitorSource(
        runs=1, products=200, design=ChartDesign(warmup=5, phase1=10, glr=False)))
    np.testing.assert_allclose([cfg.quantities[n].mean for n in spec.state.names], mu)
    close(proc)


def test_alarm_routes_need_the_page_token(tmp_path: Path, payloads: list[bytes]) -> None:
    from formtwin.service.alarm_api import add_alarm_routes
    from formtwin.service.web import LiveFeed, PageServer

    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    mon = attach(proc, tight_config())
    feed = LiveFeed(proc.tracker_names())
    proc.on_outcome = feed.on_outcome
    for p in payloads[:12]:
        proc.handle(p)
    page = PageServer(feed, port=0)
    add_alarm_routes(page.app, mon, feed, "s3cret")
    url = page.start()
    try:
        listed = json.loads(urllib.request.urlopen(url + "api/alarms", timeout=10).read())
        assert [a["id"] for a in listed] == [a["id"] for a in mon.alarms()] and listed
        aid = listed[0]["id"]

        def post(path: str, token: str | None) -> tuple[int, dict[str, Any]]:
            req = urllib.request.Request(url + path, method="POST", data=b'{"note": "ok"}',
                                         headers={"Content-Type": "application/json"})
            if token is not None:
                req.add_header("X-Formtwin-Token", token)
            try:
                with urllib.request.urlopen(req, timeout=10) as r:
                    return r.status, json.loads(r.read())
            except urllib.error.HTTPError as e:
                return e.code, json.loads(e.read())

        assert post(f"api/alarms/{aid}/ack", None)[0] == 403
        assert post(f"api/alarms/{aid}/ack", "wrong")[0] == 403
        assert mon.alarms(unacked=True)[0]["id"] == aid  # nothing changed
        code, body = post(f"api/alarms/{aid}/ack", "s3cret")
        assert code == 200 and body["acked_at"] is not None and body["ack_note"] == "ok"
        assert post("api/alarms/999999/ack", "s3cret")[0] == 404
        assert any(e.get("type") == "ack" for _, e in feed.since(0)[1])
        assert any(e.get("type") == "alarms" for _, e in feed.since(0)[1])
        signals = json.loads(urllib.request.urlopen(url + "api/signals", timeout=10).read())
        assert signals == mon.signals() and {a["episode_id"] for a in signals} == {
            a["id"] for a in listed}
        lim = json.loads(urllib.request.urlopen(url + "api/monitor", timeout=10).read())
        assert lim["quantities"] == ["thickness", "angle_stage2"]
    finally:
        page.stop()
        close(proc)


def test_model_health_episode_is_an_alarm(tmp_path: Path) -> None:
    """Physics curves (the bundled DOE) into a service on the analytic stand-in: the
    service's model-health episode opens once, and it is one acknowledgeable alarm
    (chart ``model_mismatch``, variable ``model_health``) on the product that opened it."""
    from formtwin.dataset import DoeDataset
    from formtwin.defaults import analytic_model, bundled_doe
    from formtwin.service.messages import STROKE_SCHEMA
    from formtwin.service.plausibility import Plausibility

    data = DoeDataset.load(bundled_doe("bending"))
    lim = Plausibility.from_model(analytic_model())
    phys = [c for c in data.curves[data.ok][:200] if lim.check(c) is None][:20]
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    mon = attach(proc, MonitorConfig({"thickness": InControl(mean=0.3, sigma=1.0)},
                                     warmup=0, phase1=0))
    outs = [proc.handle(dumps({"schema": STROKE_SCHEMA, "part_id": f"P-{i:05d}", "cycle": i,
                               "timestamp": float(i), "force_N": [float(v) for v in c]}))
            for i, c in enumerate(phys, 1)]
    opened = [o.seq for o in outs if any(n["reason"] == "model_mismatch" for n in o.notices)]
    health = [a for a in mon.alarms() if a["chart"] == "model_mismatch"]
    assert len(opened) == 1 and [a["raised_seq"] for a in health] == opened
    assert health[0]["variable"] == "model_health" and health[0]["side"] == "high"
    assert health[0]["statistic"] >= health[0]["limit"] > 0
    # every product of the model-health episode is a signal of its alarm episode; the
    # signal row is the opening product's
    state = [o.message["model_health"]["state"] for o in outs]
    assert health[0]["signals"] == state.count("model_mismatch")
    assert [a["seq"] for a in mon.signals() if a["chart"] == "model_mismatch"] == opened
    close(proc)
