"""Sensor messages in the broker-free service core: every case of formtwin.sensor/1 (late,
out of order, duplicated, unknown, non-finite, malformed, held, expired, too late) with its
stored status or reason, the estimates against the tracker called directly, restarts."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from formtwin.defaults import load_model
from formtwin.measurement import MeasurementModel
from formtwin.service import sensors as desk
from formtwin.service.export import export_store
from formtwin.service.messages import dumps
from formtwin.service.processor import Outcome, Processor
from formtwin.service.runtime import ServiceSettings, measurement_path, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.tracker import TrackerConfig, build_tracker

#: a lag of 3: the camera (delay 1) may be up to 3 products late
SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3,
                                                 sensors=("gauge", "camera"), sensor_lag=3))
N = 14


@pytest.fixture(scope="module")
def stream(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[bytes], list[str], Any]:
    """Stroke payloads, part ids and the stream file's sensor values."""
    path = make_stream(tmp_path_factory.mktemp("stream") / "s.npz", N, seed=4,
                       sensors=("gauge", "camera"))
    strokes = read_stream(path)
    with np.load(path) as z:
        values = {"gauge": z["sensor_gauge"].copy(), "camera": z["sensor_camera"].copy()}
    return [dumps(s.to_message()) for s in strokes], [s.part_id for s in strokes], values


def reading(part_id: str, sensor: str, value: Any, **extra: Any) -> bytes:
    return dumps({"schema": "formtwin.sensor/1", "part_id": part_id, "sensor": sensor,
                  "value": value, **extra})


def play(proc: Processor, items: list[tuple[str, bytes]]) -> list[Outcome]:
    """``("s", stroke)`` or ``("m", sensor message)`` in order."""
    return [proc.handle(p) if k == "s" else proc.handle_sensor(p) for k, p in items]


def estimates(outs: list[Outcome]) -> list[dict[str, Any]]:
    return [o.message for o in outs if o.kind == "accepted"]


def rows(proc: Processor) -> list[tuple[Any, ...]]:
    return proc.store.query("SELECT part_id, sensor, value, status FROM measurements "
                            "ORDER BY id")


def scenario(pay: list[bytes], ids: list[str], values: dict[str, Any]
             ) -> list[tuple[str, bytes]]:
    """The camera one to three products late and out of order (product 0's and the last
    product's never come), the gauge after its curve or, for product 5, before it (held),
    and a camera value redelivered."""
    cameras = {2: [1], 4: [3, 2], 5: [4], 8: [7, 5, 6], 9: [8, 6]}
    items: list[tuple[str, bytes]] = []
    for k in range(N):
        if k == 5:
            items.append(("m", reading(ids[5], "gauge", float(values["gauge"][5]))))
        items.append(("s", pay[k]))
        if k != 5:
            items.append(("m", reading(ids[k], "gauge", float(values["gauge"][k]))))
        for j in cameras.get(k, [k - 1] if k >= 10 else []):
            items.append(("m", reading(ids[j], "camera", float(values["camera"][j]))))
    return items


def direct(tmp: Path, pay: list[bytes], items: list[tuple[str, bytes]]) -> list[Any]:
    """The same sequence on a tracker called directly (step, the interval issued, fuse),
    skipping what the service stores without fusing: the reference of the orchestration.
    A held gauge value enters its product's step (fused before it, from the second product
    on); a held camera value is fused after it."""
    model = load_model("analytic")
    tracker = build_tracker(model, SETTINGS.tracker,
                            MeasurementModel.load(measurement_path(tmp / "a.sqlite")))
    index: dict[str, int] = {}
    seen: set[tuple[str, str]] = set()
    held: dict[str, list[tuple[str, float]]] = {}
    out = []
    for kind, p in items:
        m = json.loads(p)
        if kind == "s":
            waiting = held.pop(m["part_id"], [])
            ahead = [(s, v) for s, v in waiting if s == "gauge" and tracker.n_steps > 0]
            for sensor, value in ahead:
                tracker.fuse(tracker.n_steps, sensor, value)
            est = tracker.step(np.array(m["force_N"]))
            tracker.issue_final(None)
            index[m["part_id"]] = tracker.n_steps - 1
            out.append(est.to_dict())
            for sensor, value in waiting:
                if (sensor, value) not in ahead:
                    tracker.fuse(tracker.n_steps - 1, sensor, value)
            continue
        key = (m["part_id"], m["sensor"])
        if key in seen:
            continue
        seen.add(key)
        if m["part_id"] not in index:
            held.setdefault(m["part_id"], []).append((m["sensor"], m["value"]))
        elif index[m["part_id"]] >= tracker.n_steps - 1 - 3:
            tracker.fuse(index[m["part_id"]], m["sensor"], m["value"])
    return out


def test_late_out_of_order_held_and_duplicates_match_the_tracker_called_directly(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any]) -> None:
    pay, ids, values = stream
    items = scenario(pay, ids, values)
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    outs = play(proc, items)
    kinds = [o.kind for o in outs]
    assert kinds.count("accepted") == N and "rejected" not in kinds
    assert kinds.count("held") == 1 and kinds.count("redelivered") == 1
    got = estimates(outs)
    want = direct(tmp_path, pay, items)
    for g, w in zip(got, want, strict=True):  # bit for bit: the same calls in the same order
        assert g["mean"] == w["mean"] and g["loglik"] == w["loglik"], g["part_id"]
    # every (part, sensor) stored once, with its status
    stored = rows(proc)
    assert len(stored) == len({(r[0], r[1]) for r in stored}) == 2 * N - 2
    assert {r[3] for r in stored} == {"fused"}
    # which measurements went into each estimate: those fused after the previous one and,
    # last, the product's own held gauge value, fused into its step
    assert got[5]["measurements"][-1] == \
        {"part_id": ids[5], "sensor": "gauge", "value": float(values["gauge"][5])}
    assert got[6]["measurements"] == [
        {"part_id": ids[4], "sensor": "camera", "value": float(values["camera"][4])}]
    held_answer = next(o.message for o in outs if o.sensor_answers
                       and o.sensor_answers[0]["part_id"] == ids[5]).get("index")
    assert held_answer == got[5]["index"]
    listed = [(m["part_id"], m["sensor"]) for e in got for m in e["measurements"]]
    assert len(listed) == len(set(listed)) == 2 * N - 2 - 2  # the last two follow
    # the camera's answer carries the prediction issued for its product
    cam = next(o.message for o in outs if o.kind == "fused" and o.message["sensor"] ==
               "camera" and o.message["part_id"] == ids[3])
    assert cam["predicted_deg"] == got[3]["final"]["predicted_deg"]
    lo, hi = cam["interval90_deg"]
    assert lo < cam["predicted_deg"] < hi and math.isfinite(cam["log_evidence"])
    # the fusions moved the estimates: a run without sensor messages differs
    bare = open_processor(tmp_path / "b.sqlite", SETTINGS)
    plain = estimates(play(bare, [(k, p) for k, p in items if k == "s"]))
    assert plain[-1]["mean"] != got[-1]["mean"]
    assert plain[0]["mean"] == got[0]["mean"]  # nothing fused before the first step
    for p in (proc, bare):
        p.close()


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_rejections_have_their_reasons_and_leave_the_tracker_untouched(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any]) -> None:
    pay, ids, values = stream
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    play(proc, [("s", pay[0]), ("s", pay[1]),
                ("m", reading(ids[1], "gauge", float(values["gauge"][1])))])
    state = proc.tracker.state_bytes()
    good = json.loads(reading(ids[1], "camera", 80.0))
    bad = {
        "duplicate_measurement": reading(ids[1], "gauge", float(values["gauge"][1]) + 1e-3),
        "unknown_sensor": reading(ids[1], "thermometer", 20.0),
        "non_finite": reading(ids[1], "camera", 1.0).replace(b"1.0", b"NaN"),
        "bad_field": reading(ids[1], "camera", "86"),
        "malformed_json": b"{oops",
        "missing_field": dumps({k: v for k, v in good.items() if k != "value"}),
        "unknown_schema": dumps({**good, "schema": "formtwin.sensor/2"}),
        "oversized": b"{" + b" " * 70_000 + b"}",
        "fusion_rejected": reading(ids[0], "gauge", 300.0),  # um, not mm: out of range
    }
    outs = {r: proc.handle_sensor(p) for r, p in bad.items()}
    for reason, o in outs.items():
        assert o.kind == "rejected" and o.message["reason"] == reason, (reason, o.message)
        assert o.message["detail"] and o.is_error
    assert proc.tracker.state_bytes() == state
    assert proc.store.rejection_counts() == {r: 1 for r in bad}
    assert proc.handle_sensor(bad["unknown_sensor"]).kind == "rejected"  # counted once
    assert proc.store.counts()["rejected"] == len(bad)
    assert len(rows(proc)) == 1
    # refused whatever the particles: a value for a product not yet seen is not held
    o = proc.handle_sensor(reading("not-yet-seen", "gauge", 300.0))
    assert o.kind == "rejected" and o.message["reason"] == "fusion_rejected"
    assert "outside thickness's range in the spec" in o.message["detail"]
    assert len(rows(proc)) == 1 and proc.tracker.state_bytes() == state
    proc.close()


def test_too_late_is_stored_flagged_and_not_fused(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any]) -> None:
    pay, ids, values = stream
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    play(proc, [("s", p) for p in pay[:6]])
    state = proc.tracker.state_bytes()
    o = proc.handle_sensor(reading(ids[1], "camera", float(values["camera"][1])))
    assert o.kind == "too_late" and o.message["status"] == "too_late" and not o.is_error
    assert "L = 3" in o.message["detail"] and o.message["index"] == 1
    assert proc.tracker.state_bytes() == state
    assert proc.handle_sensor(reading(ids[1], "camera", float(values["camera"][1]))
                              ).kind == "redelivered"
    ok = proc.handle_sensor(reading(ids[2], "camera", float(values["camera"][2])))
    assert ok.kind == "fused"  # 3 products back: the oldest the tracker keeps
    assert [r[3] for r in rows(proc)] == ["too_late", "fused"]
    nxt = proc.handle(pay[6]).message
    assert nxt["measurements"] == [{"part_id": ids[2], "sensor": "camera",
                                    "value": float(values["camera"][2])}]
    proc.close()


def held_in_store(proc: Any) -> int:
    """Values stored as held."""
    return int(proc.store.query("SELECT COUNT(*) FROM measurements WHERE status = "
                                "'held'")[0][0])


def test_hold_is_bounded_in_count_and_age(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any],
        monkeypatch: pytest.MonkeyPatch) -> None:
    pay, ids, values = stream
    monkeypatch.setattr(desk, "HOLD_COUNT", 3)
    monkeypatch.setattr(desk, "HOLD_PRODUCTS", 4)
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    early = [proc.handle_sensor(reading(f"never-{i}", "gauge", 0.3)).kind for i in range(3)]
    assert early == ["held"] * 3
    full = proc.handle_sensor(reading(ids[2], "gauge", float(values["gauge"][2])))
    assert full.kind == "rejected" and full.message["reason"] == "hold_full"
    assert proc.sensors._held == held_in_store(proc) == 3
    outs = play(proc, [("s", p) for p in pay[:4]])
    assert proc.sensors._held == held_in_store(proc) == 0
    notices = [n for o in outs for n in o.notices]
    assert [o.kind for o in outs] == ["accepted"] * 4
    assert [n["reason"] for n in notices] == ["hold_expired"] * 3  # at the 4th product
    assert "never-0" in notices[0]["detail"]
    assert [r[3] for r in rows(proc)] == ["expired"] * 3
    again = proc.handle_sensor(reading("never-0", "gauge", 0.3))  # answered as stored
    assert again.kind == "redelivered" and again.message["status"] == "expired"
    # room again: a value held now is fused when its curve comes
    assert proc.handle_sensor(reading(ids[4], "gauge", float(values["gauge"][4]))).kind \
        == "held"
    got = proc.handle(pay[4])
    assert rows(proc)[-1][3] == "fused"  # into its step: listed by its own estimate
    assert got.message["measurements"][-1]["part_id"] == ids[4]
    proc.close()


@pytest.mark.parametrize("k", [1, 4])
def test_restart_at_every_point_continues_bit_for_bit(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any], k: int) -> None:
    """A restart after any message (checkpoints every k products, fusions after them
    replayed) gives the estimates and answers of an uninterrupted run."""
    pay, ids, values = stream
    items = scenario(pay, ids, values)
    ref = open_processor(tmp_path / "ref.sqlite", SETTINGS, checkpoint_every=k)
    want = [o.message for o in play(ref, items)]
    ref.close()
    store = tmp_path / "k.sqlite"
    got = []
    rng = np.random.default_rng(k)
    cuts = sorted(rng.choice(len(items), 6, replace=False).tolist()) + [len(items)]
    start = 0
    for cut in cuts:
        proc = open_processor(store, SETTINGS, checkpoint_every=k)
        got += [o.message for o in play(proc, items[start:cut])]
        proc.close()
        start = cut
    drop = ("received_at",)
    assert [{a: b for a, b in m.items() if a not in drop} for m in got] == \
        [{a: b for a, b in m.items() if a not in drop} for m in want]


def test_export_carries_the_sensor_messages(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any]) -> None:
    pay, ids, values = stream
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    play(proc, scenario(pay, ids, values)[:12])
    want = rows(proc)
    proc.close()
    path, n = export_store(tmp_path / "a.sqlite", tmp_path / "m.csv", measurements=True)
    import csv

    with open(path, newline="") as fh:
        table = list(csv.DictReader(fh))
    assert n == len(table) == len(want)
    assert [(r["part_id"], r["sensor"], float(r["value"]), r["status"]) for r in table] == \
        [(a, b, c, d) for a, b, c, d in want]
    _, n_products = export_store(tmp_path / "a.sqlite", tmp_path / "p.csv")
    with open(tmp_path / "p.csv", newline="") as fh:
        products = list(csv.DictReader(fh))
    assert n_products == len(products) and float(products[0]["final_lo90_deg"]) < \
        float(products[0]["final_predicted_deg"]) < float(products[0]["final_hi90_deg"])


def test_a_gated_products_values_are_rejected(tmp_path: Path) -> None:
    path = make_stream(tmp_path / "s.npz", 26, seed=1)
    pay = [json.loads(dumps(s.to_message())) for s in read_stream(path)]
    odd = dict(pay[25], part_id="odd", force_N=[3.0 * f + 300.0 for f in pay[25]["force_N"]])
    proc = open_processor(tmp_path / "a.sqlite", replace(SETTINGS, gate_k=50.0))
    play(proc, [("s", dumps(m)) for m in pay[:24]])
    assert proc.handle(dumps(odd)).message["reason"] == "outlier_gated"
    state = proc.tracker.state_bytes()
    o = proc.handle_sensor(reading("odd", "gauge", 0.3))
    assert o.kind == "rejected" and o.message["reason"] == "product_gated"
    assert proc.tracker.state_bytes() == state and rows(proc) == []
    proc.close()


def test_a_value_fused_into_a_gated_step_is_undone(tmp_path: Path) -> None:
    """A gauge value held for a product enters its step; when the gate keeps the product
    out, the step and the value are undone together (the tracker as before the stroke) and
    the value stays held, then expires as any held value of a product never fused."""
    path = make_stream(tmp_path / "s.npz", 26, seed=1)
    pay = [json.loads(dumps(s.to_message())) for s in read_stream(path)]
    odd = dict(pay[24], part_id="odd", force_N=[3.0 * f + 300.0 for f in pay[24]["force_N"]])
    proc = open_processor(tmp_path / "a.sqlite", replace(SETTINGS, gate_k=50.0))
    play(proc, [("s", dumps(m)) for m in pay[:24]])
    assert proc.handle_sensor(reading("odd", "gauge", 0.3)).kind == "held"
    before = proc.tracker.state_bytes()
    assert proc.handle(dumps(odd)).message["reason"] == "outlier_gated"
    assert proc.tracker.state_bytes() == before
    assert [r[3] for r in rows(proc)] == ["held"]
    assert proc.handle(dumps(pay[25])).kind == "accepted"  # nothing of the value in it
    assert proc.tracker.fused.ahead == {} and [r[3] for r in rows(proc)] == ["held"]
    proc.close()


def test_a_failed_store_or_fusion_leaves_nothing_behind(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The fused value and its row are one transaction: a storage error after the fusion
    restores the tracker (and propagates: the service stops unacknowledged); an unexpected
    error in the fusion rejects the message and the service goes on."""
    import sqlite3

    pay, ids, values = stream
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS, checkpoint_every=3)
    play(proc, [("s", p) for p in pay[:5]])
    state = proc.tracker.state_bytes()
    msg = reading(ids[4], "gauge", float(values["gauge"][4]))
    real = proc.sensors._insert

    def full_disk(*a: Any, **k: Any) -> None:
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(proc.sensors, "_insert", full_disk)
    with pytest.raises(sqlite3.OperationalError):
        proc.handle_sensor(msg)
    assert proc.tracker.state_bytes() == state and rows(proc) == []
    monkeypatch.setattr(proc.sensors, "_insert", real)

    def broken(*a: Any, **k: Any) -> float:
        raise KeyError("a bug")

    monkeypatch.setattr(proc.tracker, "fuse", broken)
    out = proc.handle_sensor(msg)
    assert out.kind == "rejected" and out.message["reason"] == "fusion_rejected"
    assert proc.tracker.state_bytes() == state and rows(proc) == []
    monkeypatch.undo()
    assert proc.handle_sensor(msg).kind == "fused"  # the same value, now stored once
    assert len(rows(proc)) == 1
    proc.close()


def test_a_streams_sensor_values_and_their_places(tmp_path: Path) -> None:
    """make_stream draws each sensor as its quantity plus the sensor's noise; replay sends
    a value after the stroke its delay puts it behind (the last stroke at the latest), the
    gauge's before its own stroke (it reads the strip before the press)."""
    from formtwin.service.sensors import Reading
    from formtwin.service.streams import interleave, read_readings
    from formtwin.spec import load_spec

    spec = load_spec()
    n = 400
    path = make_stream(tmp_path / "s.npz", n, seed=0, sensors=("gauge", "camera"))
    with np.load(path) as z:
        names = [str(v) for v in z["names"]]
        thickness = z["truth"][:, names.index("thickness")]
        err = {"gauge": z["sensor_gauge"] - thickness,
               "camera": z["sensor_camera"] - z["angles"][:, 1]}
    for name, e in err.items():  # the noise's mean and std, within 5 standard errors
        sd = spec.sensor(name).noise
        assert abs(e.mean()) < 5 * sd / np.sqrt(n)
        assert abs(e.std() / sd - 1) < 5 / np.sqrt(2 * n)
    strokes = read_stream(path)
    messages = interleave(strokes[10:20], read_readings(path), start=10)
    at = {(m.part_id, m.sensor): i for i, m in enumerate(messages) if isinstance(m, Reading)}
    pos = {s.part_id: i for i, s in enumerate(messages) if not isinstance(s, Reading)}
    assert at[(strokes[10].part_id, "gauge")] == 0  # before the first stroke sent
    for s in strokes[10:19]:
        k = strokes.index(s)
        if k > 10:
            assert pos[strokes[k - 1].part_id] < at[(s.part_id, "gauge")] < pos[s.part_id]
        assert at[(s.part_id, "camera")] > pos[strokes[k + 1].part_id]
    assert (strokes[9].part_id, "gauge") not in at  # due before stroke 9: not sent
    assert (strokes[9].part_id, "camera") in at  # product 9's camera comes after stroke 10
    assert (strokes[19].part_id, "camera") not in at  # due after stroke 20: not sent


def test_the_measurements_kept_in_memory_are_the_stored_ones(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any]) -> None:
    """The values fused since the last estimate, kept as they are committed (held ones
    fused with their stroke included), equal the store's after every message, and a
    processor opened on the store reads the same ones."""
    pay, ids, values = stream
    items = scenario(pay, ids, values)
    store = tmp_path / "a.sqlite"
    proc = open_processor(store, SETTINGS)
    seen = 0
    for k, p in items:
        play(proc, [(k, p)])
        kept = proc.sensors.since_last()
        assert kept == proc.sensors._fused_since(proc.sensors.last_accepted)
        assert proc.sensors._held == held_in_store(proc)  # the count kept in memory
        seen = max(seen, len(kept))
    proc.close()
    assert seen >= 2  # the scenario lists more than one value in an estimate
    again = open_processor(store, SETTINGS)
    assert again.sensors.since_last() == kept
    again.close()


def test_a_held_value_fused_with_its_stroke_reaches_the_live_page(
        tmp_path: Path, stream: tuple[list[bytes], list[str], Any]) -> None:
    """The page feed carries a held value's answer when its stroke fuses it (status fused,
    with the prediction issued for a camera's product), right after the product's point,
    as a reload would show it from the store."""
    from formtwin.service.web import LiveFeed

    pay, ids, values = stream
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    feed = LiveFeed(proc.tracker_names(), sensors=("gauge", "camera"))
    proc.on_outcome = feed.on_outcome
    cam = float(values["camera"][2])
    items = [("s", pay[0]), ("s", pay[1]), ("m", reading(ids[2], "camera", cam)),
             ("m", reading(ids[2], "gauge", float(values["gauge"][2]))), ("s", pay[2])]
    outs = play(proc, items)
    assert [o.kind for o in outs] == ["accepted", "accepted", "held", "held", "accepted"]
    events = [e for _, e in feed.since(0)[1]]
    point = next(i for i, e in enumerate(events) if e["type"] == "point"
                 and e["part_id"] == ids[2])
    after = events[point + 1:point + 3]
    assert [(e["type"], e["sensor"], e["status"]) for e in after] == \
        [("sensor", "camera", "fused"), ("sensor", "gauge", "fused")]
    final = outs[-1].message["final"]
    assert after[0]["value"] == cam and after[0]["index"] == 2
    assert after[0]["predicted_deg"] == final["predicted_deg"]
    assert after[0]["interval90_deg"] == final["interval90_deg"]
    # what a reloaded page reads from the store: the same answers
    fresh = LiveFeed(proc.tracker_names(), sensors=("gauge", "camera"))
    fresh.seed(proc.store)
    assert fresh.last_values["camera"] == feed.last_values["camera"]
    assert list(fresh._finals) == list(feed._finals)
    proc.close()
