"""`formtwin serve` against a real mosquitto on 127.0.0.1: bad input on the errors topic,
SIGKILL at random moments without loss or doubles, username/password over TLS."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from service_fixtures import (
    FORMTWIN,
    REPO,
    Collector,
    Mosquitto,
    mosquitto,  # noqa: F401 - fixture
    replay_with_kills,
    require_binary,
    serve_cmd,
    start_serve,
    stored_count,
    wait_for,
    wait_serving,
)

from formtwin.service.messages import dumps
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.tracker import TrackerConfig

FAST = ["--particles", "64", "--n-mc", "1000", "--seed", "3", "--no-page"]
SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))
TOPIC = "plant/line1/press1/stroke"
RESULTS, ERRORS = "plant/line1/press1/estimate", "plant/line1/press1/errors"


def publish(url: str, payloads: list[bytes]) -> None:
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"pub-{time.time_ns()}")
    c.connect("127.0.0.1", int(url.rsplit(":", 1)[1]))
    c.loop_start()
    infos = [c.publish(TOPIC, p, qos=1) for p in payloads]
    for i in infos:
        i.wait_for_publish(10)
    c.disconnect()
    c.loop_stop()


def stop(proc: subprocess.Popen[bytes]) -> int:
    proc.send_signal(signal.SIGTERM)
    return proc.wait(20)


def test_serve_publishes_estimates_and_rejects_bad_input(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    strokes = read_stream(make_stream(tmp_path / "s.npz", 12, seed=2))
    good = [dumps(s.to_message()) for s in strokes]
    base = json.loads(good[0])
    bad = {
        "malformed_json": b"{oops",
        "unknown_schema": dumps({**base, "schema": "formtwin.stroke/9"}),
        "missing_field": dumps({k: v for k, v in base.items() if k != "cycle"}),
        "wrong_length": dumps({**base, "part_id": "L", "force_N": base["force_N"][:50]}),
        "non_finite": good[0].replace(b'"force_N":[', b'"force_N":[NaN,').replace(
            base["part_id"].encode(), b"NF"),
        "negative_force": dumps({**base, "part_id": "N", "force_N": [-1e3] * 101}),
        "absurd_force": dumps({**base, "part_id": "A", "force_N": [1e7] * 101}),
        "oversized": b"{" + b" " * 70_000 + b"}",
        "duplicate_part_id": dumps({**base, "force_N": [f + 1.0 for f in base["force_N"]]}),
        "out_of_order": dumps({**base, "part_id": "late", "cycle": 0}),
    }
    col = Collector(mosquitto.url, [RESULTS, ERRORS])
    log = tmp_path / "serve.log"
    proc = start_serve(serve_cmd(mosquitto, tmp_path / "a.sqlite", *FAST), log)
    try:
        wait_serving(proc, log)
        publish(mosquitto.url, good[:6] + list(bad.values()) + good[6:])
        wait_for(lambda: len(col.get(RESULTS)) >= 12 and len(col.get(ERRORS)) >= len(bad),
                 60, "12 estimates and all errors")
        assert proc.poll() is None, "the service must keep running"
        errors = col.get(ERRORS)
        assert sorted(e["reason"] for e in errors) == sorted(bad)  # type: ignore[type-var]
        assert all(e["schema"] == "formtwin.error/1" and e["detail"] for e in errors)
        results = col.get(RESULTS)
        assert [r["part_id"] for r in results] == [s.part_id for s in strokes]
        r = results[-1]
        assert r["schema"] == "formtwin.estimate/1" and r["index"] == 11
        assert len(r["mean"]) == 18  # type: ignore[arg-type]
        assert len(r["angles_mean"]) == 2 and r["ess"] > 0  # type: ignore[arg-type,operator]
        assert r["measured_angles_deg"] == pytest.approx(strokes[-1].angles_deg.tolist())  # type: ignore[union-attr]
        # the stored estimates equal an in-process run on the good strokes only
        ref = open_processor(tmp_path / "ref.sqlite", SETTINGS)
        want = [ref.handle(p).message for p in good]
        assert [m["mean"] for m in want] == [m["mean"] for m in results]
        ref.close()
        ref.store.close()
        assert stop(proc) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        col.stop()


def test_sigkill_restarts_lose_nothing_and_double_nothing(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    n = 800  # four kills at random products, one more during a restart
    stream = make_stream(tmp_path / "s.npz", n, seed=5)
    store, log = tmp_path / "kill.sqlite", tmp_path / "serve.log"
    cmd = serve_cmd(mosquitto, store, *FAST)
    col = Collector(mosquitto.url, [RESULTS, ERRORS])
    rng = np.random.default_rng(11)
    thresholds = sorted(int(t) for t in rng.choice(np.arange(100, n - 100), 4, replace=False))
    proc = None
    try:
        proc, kills, _ = replay_with_kills(
            cmd, log, stream, mosquitto.url, thresholds, rng,
            done=lambda: stored_count(store) >= n, progress=lambda: stored_count(store),
            timeout=200)
        assert stored_count(store) == n, f"{stored_count(store)} of {n} stored after {kills} kills"
        got_ids = lambda: {r["part_id"] for r in col.get(RESULTS)}  # noqa: E731
        ids = {s.part_id for s in read_stream(stream)}
        wait_for(lambda: len(got_ids()) == n, 30,
                 lambda: f"an estimate for every product; missing {sorted(ids - got_ids())[:9]}"
                         f" (collector disconnects {col.disconnects}, errors {col.errors})")
        assert stop(proc) == 0
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        col.stop()
    assert kills >= 5
    # nothing lost, nothing doubled, and bit for bit what an uninterrupted run stores
    with sqlite3.connect(store) as db:
        rows = db.execute("SELECT seq, part_id, estimate FROM products ORDER BY seq").fetchall()
        assert db.execute("SELECT COUNT(*) FROM rejections").fetchone()[0] == 0
    strokes = read_stream(stream)
    assert [r[0] for r in rows] == list(range(1, n + 1))
    assert [r[1] for r in rows] == [s.part_id for s in strokes]
    ref = open_processor(tmp_path / "ref.sqlite", SETTINGS)
    keep = ("part_id", "index", "mean", "std", "angles_mean", "angles_std", "ess", "loglik")
    for (_, pid, est), s in zip(rows, strokes, strict=True):
        want = ref.handle(dumps(s.to_message())).message
        have = json.loads(est)
        assert {k: have[k] for k in keep} == {k: want[k] for k in keep}, pid
    ref.close()
    ref.store.close()
    # redelivered estimates (at least once on the results topic) equal the stored ones
    by_id: dict[str, list[dict[str, object]]] = {}
    for r in col.get(RESULTS):
        by_id.setdefault(str(r["part_id"]), []).append(r)
    for msgs in by_id.values():
        assert all({k: m[k] for k in keep} == {k: msgs[0][k] for k in keep} for m in msgs)
    print(f"kill test: {n} products, {kills} SIGKILLs, "
          f"{sum(len(v) - 1 for v in by_id.values())} results redelivered")


def test_password_and_tls(tmp_path: Path) -> None:
    require_binary("openssl")
    passwd = require_binary("mosquitto_passwd", ("/usr/bin/mosquitto_passwd",))
    d = tmp_path

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    ssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
        "-keyout", "ca.key", "-out", "ca.crt", "-subj", "/CN=formtwin-test-ca", "-days", "1")
    ssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
        "-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=127.0.0.1")
    (d / "ext").write_text("subjectAltName=IP:127.0.0.1\n")
    ssl("x509", "-req", "-in", "server.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
        "-CAcreateserial", "-out", "server.crt", "-days", "1", "-extfile", "ext")
    subprocess.run([passwd, "-b", "-c", str(d / "passwd"), "alice", "s3cret"], check=True)
    user = "user root\n" if os.geteuid() == 0 else ""  # keep read access to tmp_path
    tls = Mosquitto(d, anonymous=False, extra_conf=(
        f"{user}cafile {d / 'ca.crt'}\ncertfile {d / 'server.crt'}\n"
        f"keyfile {d / 'server.key'}\npassword_file {d / 'passwd'}\n"))
    try:
        url = f"mqtts://127.0.0.1:{tls.port}"
        stream = make_stream(d / "s.npz", 3, seed=1)
        base = [*FORMTWIN, "replay", str(stream), "--broker", url,
                "--rate", "0", "--username", "alice"]

        def replay(password: str, *extra: str) -> subprocess.CompletedProcess[str]:
            env = dict(os.environ, FORMTWIN_MQTT_PASSWORD=password)
            return subprocess.run(base + list(extra), cwd=REPO, env=env, text=True,
                                  capture_output=True, timeout=60)

        ok = replay("s3cret", "--ca-file", str(d / "ca.crt"))
        assert ok.returncode == 0 and "published 3 strokes" in ok.stdout, ok.stderr
        wrong = replay("wrong", "--ca-file", str(d / "ca.crt"))
        assert wrong.returncode == 2 and "Not authorized" in wrong.stderr
        untrusted = replay("s3cret")  # the broker's CA is not trusted by default
        assert untrusted.returncode == 2 and "CERTIFICATE_VERIFY_FAILED" in untrusted.stderr
    finally:
        tls.stop()


def test_storage_failure_stops_without_ack_and_restart_gets_the_stroke(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    import threading

    from formtwin.service.mqtt import BrokerConfig, MqttService, Topics

    strokes = read_stream(make_stream(tmp_path / "s.npz", 3, seed=6))
    broker = BrokerConfig.from_url(mosquitto.url)
    topics = Topics.from_input(TOPIC)
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    real_commit = proc.store.commit_product

    def disk_full(**kw: object) -> int:
        raise sqlite3.OperationalError("database or disk is full")

    proc.store.commit_product = disk_full  # type: ignore[method-assign]
    svc = MqttService(proc, broker, topics, client_id="formtwin-fail-test")
    errors: list[BaseException] = []
    stop_ev = threading.Event()

    def serve() -> None:
        try:
            svc.run(stop_ev)
        except RuntimeError as e:
            errors.append(e)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    wait_for(svc.connected.is_set, 20, "in-process service to subscribe")
    publish(mosquitto.url, [dumps(s.to_message()) for s in strokes])
    t.join(20)
    assert errors and "disk is full" in str(errors[0].__cause__)
    assert proc.store.counts()["accepted"] == 0
    # the restarted service (same session id) gets every stroke again and stores them once
    proc.close()
    proc.store.close()
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    assert proc.store.commit_product.__func__ is real_commit.__func__  # type: ignore[attr-defined]
    svc = MqttService(proc, broker, topics, client_id="formtwin-fail-test")
    stop_ev = threading.Event()
    t = threading.Thread(target=svc.run, args=(stop_ev,), daemon=True)
    t.start()
    wait_for(lambda: proc.store.counts()["accepted"] == 3, 30, "the 3 strokes after restart")
    stop_ev.set()
    t.join(20)
    assert [r.part_id for r in proc.store.products()] == [s.part_id for s in strokes]
    proc.close()
    proc.store.close()


def test_service_reconnects_after_a_broker_restart(tmp_path: Path) -> None:
    strokes = read_stream(make_stream(tmp_path / "s.npz", 60, seed=8))
    payloads = [dumps(s.to_message()) for s in strokes]
    store, log = tmp_path / "a.sqlite", tmp_path / "serve.log"
    (tmp_path / "b1").mkdir()
    broker = Mosquitto(tmp_path / "b1")
    proc = start_serve(serve_cmd(broker, store, *FAST), log)
    try:
        wait_serving(proc, log)
        publish(broker.url, payloads[:5])
        wait_for(lambda: stored_count(store) == 5, 30, "5 products before the restart")
        broker.proc.kill()  # the broker dies (and, without persistence, forgets the session)
        broker.proc.wait(5)
        broker.stop()
        (tmp_path / "b2").mkdir()
        broker = Mosquitto(tmp_path / "b2", port=broker.port)
        k = 5
        deadline = time.monotonic() + 60
        while stored_count(store) == 5 and time.monotonic() < deadline:
            publish(broker.url, [payloads[k]])  # lost until the service has resubscribed
            k += 1
            time.sleep(0.5)
        n0 = stored_count(store)
        assert n0 > 5, "the service did not come back after the broker restart"
        publish(broker.url, payloads[k:k + 10])
        last = strokes[k + 9].part_id

        def has_last() -> bool:
            with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1.0) as db:
                return db.execute("SELECT 1 FROM products WHERE part_id=?",
                                  (last,)).fetchone() is not None

        wait_for(has_last, 30, "10 more products")
        assert stored_count(store) >= n0 + 10
        assert proc.poll() is None
        assert stop(proc) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        broker.stop()
