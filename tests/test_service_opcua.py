"""The OPC UA source: a simulated press (a real asyncua server on 127.0.0.1) feeding
`formtwin serve --source opc.tcp://...`; estimates in the store and on MQTT, equal to the
MQTT source's; a server restart mid-run; bad values rejected with their reasons."""

from __future__ import annotations

import json
import os
import shlex
import signal
import sqlite3
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
from service_fixtures import (
    FORMTWIN,
    REPO,
    Collector,
    Mosquitto,
    free_port,
    log_has,
    mosquitto,  # noqa: F401 - fixture
    read_opcua_results,
    serve_cmd,
    start_serve,
    wait_for,
    wait_serving,
)

pytest.importorskip("asyncua")

from formtwin.service.messages import dumps  # noqa: E402
from formtwin.service.mqtt import BrokerConfig, Topics  # noqa: E402
from formtwin.service.opcua import OpcUaService, OpcUaSource  # noqa: E402
from formtwin.service.opcua_map import NODES, OpcUaMapping, StrokeAssembler  # noqa: E402
from formtwin.service.opcua_press import SimulatedPress  # noqa: E402
from formtwin.service.runtime import ServiceSettings, open_processor  # noqa: E402
from formtwin.service.streams import make_stream, read_stream  # noqa: E402
from formtwin.tracker import TrackerConfig  # noqa: E402

FAST = ["--particles", "64", "--n-mc", "1000", "--seed", "3", "--no-page", "--no-monitor"]
SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))
TOPIC = "plant/line1/press1/stroke"
RESULTS, ERRORS = "plant/line1/press1/estimate", "plant/line1/press1/errors"
QUICK = OpcUaMapping(reconnect_min_s=0.2, reconnect_max_s=1.0)


def test_mapping_defaults_and_errors_name_the_key(tmp_path: Path) -> None:
    m = OpcUaMapping()
    assert m.nodes["part_id"] == "PartInformation/PartId"  # OPC 40503-1 field names
    assert m.nodes["cycle_count"] == "PartInformation/CycleCount"
    assert set(m.nodes) == set(NODES)
    f = tmp_path / "map.toml"
    f.write_text('[opcua]\nroot = "Machines/Press7"\n[opcua.nodes]\n'
                 'part_id = "ns=3;s=Press7.PartId"\nstage2_setting = ""\n', encoding="utf-8")
    m = OpcUaMapping.from_toml(f)
    assert m.root == "Machines/Press7" and m.nodes["part_id"] == "ns=3;s=Press7.PartId"
    assert "stage2_setting" not in m.active() and m.nodes["force_curve"] == NODES[
        "force_curve"][0]
    f.write_text('[opcua.nodes]\nforce = "X"\n', encoding="utf-8")
    with pytest.raises(ValueError, match="'force': unknown node key"):
        OpcUaMapping.from_toml(f)
    f.write_text('[opcua]\npublishing_interval = 5\n', encoding="utf-8")
    with pytest.raises(ValueError, match="'publishing_interval': unknown key"):
        OpcUaMapping.from_toml(f)
    with pytest.raises(ValueError, match="part_id is required"):
        OpcUaMapping(nodes={"part_id": ""})
    with pytest.raises(ValueError, match="publishing_interval_ms = -1"):
        OpcUaMapping(publishing_interval_ms=-1)


def test_assembler_pairs_values_in_order_and_drops_an_incomplete_stroke() -> None:
    asm = StrokeAssembler(OpcUaMapping())

    def stroke(cycle: int, part: str, curve: list[float], tag: int | None = None) -> None:
        for key, value in (("part_id", part), ("stage2_setting", []),
                           ("force_curve", curve), ("force_cycle_count", tag or cycle),
                           ("cycle_count", cycle)):
            asm.update(key, value)

    stroke(1, "P-1", [1.0])
    stroke(2, "P-1", [2.0])  # the same part id again is still a value of its own
    docs = [json.loads(p) for p in iter(asm.take, None)]
    assert [(d["part_id"], d["cycle"], d["force_N"]) for d in docs] == [
        ("P-1", 1, [1.0]), ("P-1", 2, [2.0])]
    assert all("u" not in d for d in docs)  # an empty setting: the nominal one
    # the curve of cycle 3 was lost: the part information of cycle 3 is dropped
    for key, value in (("part_id", "P-3"), ("stage2_setting", 0.2), ("cycle_count", 3)):
        asm.update(key, value)
    stroke(4, "P-4", [4.0])
    doc = json.loads(asm.take() or b"")
    assert (doc["part_id"], doc["cycle"], doc["force_N"]) == ("P-4", 4, [4.0])
    assert asm.take() is None and asm.skipped == 1
    asm.update("force_curve", [5.0])  # a stroke in progress waits for its other values
    assert asm.take() is None


def _count(store: Path, status: str = "accepted") -> int:
    if not store.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1.0) as db:
            return int(db.execute("SELECT COUNT(*) FROM products WHERE status = ?",
                                  (status,)).fetchone()[0])
    except sqlite3.Error:
        return 0


def test_serve_from_opcua_with_a_server_restart(mosquitto: Mosquitto,  # noqa: F811
                                                tmp_path: Path) -> None:
    strokes = read_stream(make_stream(tmp_path / "s.npz", 8, seed=4))
    store, log = tmp_path / "a.sqlite", tmp_path / "serve.log"
    col = Collector(mosquitto.url, [RESULTS, ERRORS])
    press = SimulatedPress(free_port()).start()
    mapping = tmp_path / "press.toml"  # the defaults, reconnecting within a second
    mapping.write_text("[opcua]\nreconnect_min_s = 0.2\nreconnect_max_s = 1.0\n",
                       encoding="utf-8")
    out_url = f"opc.tcp://127.0.0.1:{free_port()}/formtwin"  # the estimates as OPC UA too
    proc = start_serve(serve_cmd(mosquitto, store, "--source", press.url, "--opcua-map",
                                 str(mapping), "--topic", TOPIC, "--connect-timeout", "30",
                                 "--opcua-results", out_url, *FAST), log)
    try:
        wait_serving(proc, log)
        def answered(s: object) -> bool:
            return any(r["part_id"] == s.part_id for r in col.get(RESULTS))  # type: ignore[attr-defined]

        for i, s in enumerate(strokes[:5]):
            if i == 4:  # the press's server restarts mid-run (empty address space)
                press.restart(down_s=0.5)
            press.write(s)  # the first after the restart: reported on resubscription
            wait_for(lambda s=s: answered(s), 30, f"the estimate of {s.part_id}")
        for s in strokes[5:]:  # a burst within one publishing interval: queued, not lost
            press.write(s)
        wait_for(lambda: answered(strokes[-1]), 30, "the estimates of the burst")
        assert _count(store) == len(strokes) and _count(store, "rejected") == 0
        text = log.read_text(encoding="utf-8")
        assert "connection lost" in text and "reconnecting" in text
        results = col.get(RESULTS)
        first = [r for r in results if not r["flags"]["redelivered"]]  # type: ignore[index]
        assert [r["part_id"] for r in first] == [s.part_id for s in strokes]
        # a redelivery (the last stroke reported again on resubscription) is answered
        # from the store: the same estimate, never a second product
        for r in results:
            if r["flags"]["redelivered"]:  # type: ignore[index]
                same = next(f for f in first if f["part_id"] == r["part_id"])
                assert r["mean"] == same["mean"] and r["seq"] == same["seq"]
        assert col.get(ERRORS) == []
        # the estimates equal the MQTT source's: the same messages handled in-process
        ref = open_processor(tmp_path / "ref.sqlite", SETTINGS)
        want = [ref.handle(dumps(s.to_message())).message for s in strokes]
        ref.close()
        assert [m["mean"] for m in want] == [r["mean"] for r in first]
        assert [m["std"] for m in want] == [r["std"] for r in first]
        # the service's own OPC UA server holds the last product's estimate
        names = list(first[-1]["mean"])  # type: ignore[arg-type]
        got = read_opcua_results(out_url, ["PartId", "Seq", *[f"Estimate/{n}/Mean" for n in names]])
        assert got["PartId"] == strokes[-1].part_id and got["Seq"] == first[-1]["seq"]
        assert [got[f"Estimate/{n}/Mean"] for n in names] == \
            [first[-1]["mean"][n] for n in names]  # type: ignore[index]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        press.close()
        col.stop()


def test_bad_values_are_rejected_with_their_reasons_and_the_service_goes_on(
        mosquitto: Mosquitto, tmp_path: Path) -> None:  # noqa: F811
    strokes = read_stream(make_stream(tmp_path / "s.npz", 3, seed=5))
    good = [{"part_id": s.part_id, "cycle": s.cycle, "force_N": s.force_N.tolist(),
             "u": None} for s in strokes]
    curve = good[0]["force_N"]
    assert isinstance(curve, list)
    bad = {  # reason -> values written by the press
        "wrong_length": {"part_id": "B-1", "cycle": 10, "force_N": curve[:50]},
        "non_finite": {"part_id": "B-2", "cycle": 11, "force_N": [np.nan, *curve[1:]]},
        "missing_field": {"part_id": None, "cycle": 12, "force_N": curve},
    }
    good[1]["cycle"], good[2]["cycle"] = 20, 21  # after the bad ones, in order
    col = Collector(mosquitto.url, [RESULTS, ERRORS])
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    stop = threading.Event()
    with SimulatedPress(free_port()) as press:
        service = OpcUaService(proc, OpcUaSource(press.url, QUICK),
                               BrokerConfig.from_url(mosquitto.url),
                               Topics.from_input(TOPIC), client_id="opcua-test")
        runner = threading.Thread(target=service.run, args=(stop, 30.0), daemon=True)
        runner.start()
        try:
            wait_for(service.connected.is_set, 30, "the OPC UA subscription")
            sequence = [good[0], *bad.values(), good[1], good[2]]
            for k, values in enumerate(sequence, start=1):
                press.write(values)
                wait_for(lambda k=k: service.handled >= k, 30, f"stroke {k} handled")
        finally:
            stop.set()
            runner.join(20)
        # a new session (the service restarted) is first told the press's last stroke
        # again: answered from the store, not counted twice
        stop = threading.Event()
        again = OpcUaService(proc, OpcUaSource(press.url, QUICK),
                             BrokerConfig.from_url(mosquitto.url), Topics.from_input(TOPIC),
                             client_id="opcua-test-2")
        runner = threading.Thread(target=again.run, args=(stop, 30.0), daemon=True)
        runner.start()
        try:
            wait_for(lambda: again.handled >= 1, 30, "the last stroke reported again")
        finally:
            stop.set()
            runner.join(20)
    wait_for(lambda: len(col.get(ERRORS)) == len(bad) and len(col.get(RESULTS)) == 4, 10,
             "the answers on MQTT")
    errors = col.get(ERRORS)
    assert [e["reason"] for e in errors] == list(bad)
    # NaN is refused while the JSON is read, before the part id (as on MQTT)
    assert [e["part_id"] for e in errors] == ["B-1", None, None]
    assert "expected 101" in str(errors[0]["detail"])
    results = col.get(RESULTS)
    assert [r["part_id"] for r in results] == [g["part_id"] for g in (*good, good[2])]
    assert [r["flags"]["redelivered"] for r in results] == [False] * 3 + [True]  # type: ignore[index]
    assert results[3]["mean"] == results[2]["mean"] and proc.redelivered == 1
    counts = proc.store.counts()
    assert counts["accepted"] == 3 and counts["rejected"] == 3
    assert sorted(proc.store.rejection_counts()) == sorted(bad)
    proc.close()
    col.stop()


def test_docs_simulated_press_block_runs_as_written(mosquitto: Mosquitto,  # noqa: F811
                                                    tmp_path: Path) -> None:
    text = (REPO / "docs" / "reference" / "opcua.md").read_text(encoding="utf-8")
    mark = "<!-- the block below is run by tests/test_service_opcua.py -->"
    block = text.split(mark, 1)[1].split("```sh\n", 1)[1].split("```", 1)[0]
    press_line, serve_line = [line for line in block.splitlines() if line.strip()]
    port = str(free_port())

    def argv(line: str) -> list[str]:
        words = shlex.split(line.replace(":4840/", f":{port}/").replace(
            "mqtt://127.0.0.1:1883", mosquitto.url))
        assert words[0] == "formtwin", line
        return [*FORMTWIN, *words[1:]]

    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    with open(tmp_path / "press.log", "wb") as fh:
        press = subprocess.Popen(argv(press_line), cwd=tmp_path, env=env, stdout=fh,
                                 stderr=subprocess.STDOUT)
    try:  # the press first, as the page says
        wait_for(lambda: log_has(tmp_path / "press.log", "waiting for a subscription"), 60,
                 "the simulated press")
        out = subprocess.run(argv(serve_line), cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=120)
        assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
        assert "check passed: the model explains the first 20 products" in out.stdout
        assert press.wait(60) == 0, (tmp_path / "press.log").read_text()[-3000:]
    finally:
        if press.poll() is None:
            press.kill()


def test_source_options_are_checked_before_the_start(tmp_path: Path) -> None:
    from argparse import Namespace

    from formtwin.cli.source import opcua_source

    assert opcua_source(Namespace(source=None, opcua_map=None)) is None  # MQTT
    with pytest.raises(ValueError, match="--opcua-map needs --source"):
        opcua_source(Namespace(source=None, opcua_map="press.toml"))
    with pytest.raises(ValueError, match="expected opc.tcp://HOST:PORT"):
        opcua_source(Namespace(source="mqtt://press:1883", opcua_map=None))
    f = tmp_path / "press.toml"
    f.write_text('[opcua]\nqueue_size = 0\n', encoding="utf-8")
    with pytest.raises(ValueError, match="queue_size = 0: expected an integer >= 1"):
        opcua_source(Namespace(source="opc.tcp://press:4840", opcua_map=str(f)))
    src = opcua_source(Namespace(source="opc.tcp://press:4840", opcua_map=None))
    assert src.mapping == OpcUaMapping() and src.url == "opc.tcp://press:4840"
    from formtwin.cli.source import opcua_results

    none = Namespace(opcua_results=None, opcua_results_security=None, opcua_results_users=None)
    assert opcua_results(none, None) is None
    with pytest.raises(ValueError, match="need --opcua-results URL"):
        opcua_results(Namespace(**{**vars(none), "opcua_results_users": "u.txt"}), None)
    with pytest.raises(ValueError, match="expected CERT,KEY"):
        opcua_results(Namespace(**{**vars(none), "opcua_results": "opc.tcp://h:4841",
                                   "opcua_results_security": "cert.der"}), None)


def test_sensor_nodes_are_fused_as_sensor_messages(mosquitto: Mosquitto,  # noqa: F811
                                                   tmp_path: Path) -> None:
    """A gauge and a camera mapped by [opcua.sensors]: the values the press writes become
    sensor messages, fused as the same messages over MQTT are (same estimates, same rows),
    and a new session's report of the last values again is answered once."""
    from formtwin.service.sensors import Reading
    from formtwin.service.streams import interleave, read_readings

    path = make_stream(tmp_path / "s.npz", 6, seed=4, sensors=("gauge", "camera"))
    messages = interleave(read_stream(path), read_readings(path))
    settings = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3,
                                                     sensors=("gauge", "camera")))
    mapping = OpcUaMapping(reconnect_min_s=0.2, reconnect_max_s=1.0,
                           sensors={"gauge": "StripGauge", "camera": "FlapCamera"})
    objects = {"gauge": "StripGauge", "camera": "FlapCamera"}
    proc = open_processor(tmp_path / "a.sqlite", settings)
    outs: list[object] = []
    proc.on_outcome = outs.append
    stop = threading.Event()
    with SimulatedPress(free_port(), sensors=tuple(objects.values())) as press:
        service = OpcUaService(proc, OpcUaSource(press.url, mapping),
                               BrokerConfig.from_url(mosquitto.url), Topics.from_input(TOPIC),
                               client_id="opcua-sensors")
        runner = threading.Thread(target=service.run, args=(stop, 30.0), daemon=True)
        runner.start()
        try:
            wait_for(service.connected.is_set, 30, "the OPC UA subscription")
            for k, m in enumerate(messages, start=1):
                if isinstance(m, Reading):
                    press.write_sensor(objects[m.sensor], m.part_id, m.value)
                else:
                    press.write(m)
                wait_for(lambda k=k: service.handled >= k, 30, f"message {k} handled")
        finally:
            stop.set()
            runner.join(20)
        stop = threading.Event()  # a new session: the last values are reported again
        again = OpcUaService(proc, OpcUaSource(press.url, mapping),
                             BrokerConfig.from_url(mosquitto.url), Topics.from_input(TOPIC),
                             client_id="opcua-sensors-2")
        runner = threading.Thread(target=again.run, args=(stop, 30.0), daemon=True)
        runner.start()
        try:
            wait_for(lambda: again.handled >= 3, 30, "the last values reported again")
        finally:
            stop.set()
            runner.join(20)
    kinds = [o.kind for o in outs]  # type: ignore[attr-defined]
    # the 6 strokes accepted; each gauge value held (it comes before its stroke, then goes
    # into the stroke's step); each camera value fused (the last one after the last stroke)
    assert [kinds[:len(messages)].count(k) for k in ("accepted", "held", "fused")] == [6] * 3
    assert kinds[len(messages):] == ["redelivered"] * 3  # stroke, gauge and camera
    rows = proc.store.query("SELECT part_id, sensor, value, status FROM measurements "
                            "ORDER BY id")
    ref = open_processor(tmp_path / "ref.sqlite", settings)
    want = [ref.handle(dumps(m.to_message())) if not isinstance(m, Reading)
            else ref.handle_sensor(dumps(m.to_message())) for m in messages]
    assert rows == ref.store.query("SELECT part_id, sensor, value, status FROM measurements "
                                   "ORDER BY id")
    got = [o.message for o in outs[:len(messages)]]  # type: ignore[attr-defined]
    assert [g.get("mean") for g in got] == [w.message.get("mean") for w in want]
    ref.close()
    proc.close()


def test_a_press_that_encrypts_and_asks_for_a_user(tmp_path: Path) -> None:
    """A press accepting only Basic256Sha256 SignAndEncrypt and one user: the source with
    the mapping's certificate, user and password file subscribes and assembles a stroke;
    with a wrong password or without security it does not, and says why."""
    from formtwin.service.opcua_press import self_signed

    certs = {}
    for who, uri in (("press", "urn:freeopcua:python:server"), ("client", "urn:formtwin:client")):
        certs[who] = (str(tmp_path / f"{who}_cert.der"), str(tmp_path / f"{who}_key.pem"))
        self_signed(certs[who][1], certs[who][0], uri, server=who == "press")
    (tmp_path / "pw.txt").write_text("s3cret\n", encoding="utf-8")
    (tmp_path / "bad.txt").write_text("wrong\n", encoding="utf-8")
    conf = tmp_path / "press.toml"

    def mapping(**keys: str) -> OpcUaMapping:
        conf.write_text("[opcua]\nreconnect_min_s = 0.2\nreconnect_max_s = 0.5\n"
                        + "".join(f'{k} = "{v}"\n' for k, v in keys.items()), encoding="utf-8")
        return OpcUaMapping.from_toml(conf)

    secure = {"security": "Basic256Sha256,SignAndEncrypt,client_cert.der,client_key.pem",
              "user": "press"}
    stroke = read_stream(make_stream(tmp_path / "s.npz", 1, seed=2))[0]
    with SimulatedPress(free_port(), certificate=certs["press"],
                        users={"press": "s3cret"}) as press:
        source = OpcUaSource(press.url, mapping(**secure, password_file="pw.txt"))
        source.start()
        try:
            wait_for(source.connected.is_set, 30, f"the secure session ({source.last_error})")
            press.write(stroke)
            sensor, payload = source.strokes.get(timeout=10)
            assert not sensor and json.loads(payload)["part_id"] == stroke.part_id
        finally:
            source.stop()
        for keys, why in (({**secure, "password_file": "bad.txt"}, "BadUserAccessDenied"),
                          ({}, "No matching endpoints")):
            source = OpcUaSource(press.url, mapping(**keys))
            source.start()
            try:
                wait_for(lambda s=source: s.last_error is not None, 30, "the refusal")
                assert why in str(source.last_error) and not source.connected.is_set()
            finally:
                source.stop()
    with pytest.raises(ValueError, match="security mode 'Encrypt'"):
        OpcUaMapping(security=f"Basic256Sha256,Encrypt,{certs['client'][0]},"
                              f"{certs['client'][1]}")
    with pytest.raises(ValueError, match="no such file"):
        OpcUaMapping(security="Basic256Sha256,SignAndEncrypt,nope.der,nope.pem")
    with pytest.raises(ValueError, match="password_file needs a user"):
        OpcUaMapping(password_file=str(tmp_path / "pw.txt"))
