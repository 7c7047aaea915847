"""Sensor messages on their own topic: the line's values besides the curve, late and in
any order.

Sensor (line -> formtwin), schema ``formtwin.sensor/1``::

    {"schema": "formtwin.sensor/1", "part_id": "P-000123", "sensor": "camera",
     "value": 86.41,                    # in the measured quantity's internal unit
                                        # (mm for thickness, degrees for an angle)
     "timestamp": "2026-11-21T23:59:59.9Z"}   # optional

Each value is one of the spec's ``[[sensor]]`` entries that the service fuses
(``[tracker] sensors``), of one product, keyed by ``(part_id, sensor)``. What happens to
it, each case stored once (table ``measurements``) in the same SQLite transaction as its
effect on the tracker:

* the product is one of the last ``L + 1`` the tracker stepped (``L``: the tracker's
  ``sensor_lag``): **fused** (:meth:`~formtwin.tracker.Tracker.fuse`), late and out of
  order alike; the next estimate lists it in ``measurements``;
* the product is older: **too_late**, stored and flagged, not fused;
* the product is not yet seen: **held**, and fused when its curve arrives: a state
  variable's (a strip gauge's thickness) into the product's step, before it
  (:mod:`formtwin.tracker.ahead`; listed by the product's own estimate), where the tracker
  allows it, else right after the step in its transaction (listed by the estimate after
  it); stored as fused in the stroke's transaction. At most :data:`HOLD_COUNT` values
  are held (one more is rejected, ``hold_full``), each for at most :data:`HOLD_PRODUCTS`
  products (then it is stored as **expired** with a ``hold_expired`` notice on the errors
  topic). Both bounds count messages and products, never wall time, so a restarted
  service decides exactly as an uninterrupted one;
* the same ``(part_id, sensor)`` again with the same value: acknowledged with the stored
  answer (``redelivered``), no second effect; with another value: rejected,
  ``duplicate_measurement``;
* an unknown sensor, a non-finite value, a malformed message, a product the gate kept out
  of the tracker, a value no particle explains: rejected with its reason
  (:data:`formtwin.service.messages.REASONS`).

The answer, schema ``formtwin.measurement/1`` on the results topic: the message's fields,
``status`` (fused, held, too_late), the product's step ``index`` when known, the fusion's
``log_evidence``, and for a sensor of the final angle the prediction the twin issued for
that product (``predicted_deg`` and the camera-calibrated ``interval90_deg``).

A restart restores the tracker from its checkpoint and replays the stored curves and, in
their original order, the fusions stored after it (:func:`formtwin.service.restore.
fused_after`), so the estimates continue bit for bit.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import sqlite3
from typing import Any

import numpy as np

from formtwin.service.messages import MessageError, dumps, error_message
from formtwin.service.readings import SENSOR_SCHEMA, Reading, parse_reading
from formtwin.service.store import Store
from formtwin.spec.sensors import final_output, value_refusal
from formtwin.tracker._fusion_kernels import load_kernels
from formtwin.tracker.ahead import refusal
from formtwin.tracker.fusion import FusionError

log = logging.getLogger(__name__)

MEASUREMENT_SCHEMA = "formtwin.measurement/1"

#: at most this many values are held for products not yet seen (a strip gauge upstream of
#: the die runs a few products ahead of the press; 64 covers two sensors 32 products ahead)
HOLD_COUNT = 64
#: a held value whose curve has not come after this many more products is expired
HOLD_PRODUCTS = 32

#: accepted products whose step index, setting and final-angle prediction a
#: :class:`SensorDesk` keeps in memory (older ones are read from the store)
RECENT = 64

MEASUREMENTS_DDL = """
CREATE TABLE IF NOT EXISTS measurements (
    id INTEGER PRIMARY KEY,
    part_id TEXT NOT NULL,
    sensor TEXT NOT NULL,
    value REAL NOT NULL,
    status TEXT NOT NULL,
    at_seq INTEGER NOT NULL,
    product INTEGER,
    u TEXT,
    received_at REAL NOT NULL,
    message TEXT NOT NULL,
    UNIQUE (part_id, sensor)
);
CREATE INDEX IF NOT EXISTS measurements_status_seq ON measurements (status, at_seq);
"""

def issue(tracker: Any, u: Any) -> dict[str, Any] | None:
    """The twin's prediction of the current product's measured final angle, issued right
    after its step (and again in the same place by a replay: it records the interval its
    camera value will score): ``{"predicted_deg", "interval90_deg"}``, or None when no
    sensor of the final angle is fused."""
    if not any(s.measures == final_output(tracker.spec) for s in fused_sensors(tracker)):
        return None
    final, (lo, hi) = tracker.issue_final(u)
    ok = all(math.isfinite(v) for v in (final, lo, hi))
    return {"predicted_deg": float(final) if ok else None,
            "interval90_deg": [float(lo), float(hi)] if ok else None}


def fused_sensors(tracker: Any) -> tuple[Any, ...]:
    """The spec's sensors the tracker fuses (none for a tracker without sensor fusion)."""
    return tuple(getattr(tracker, "sensors", ()))


def refuse(store: Store, err: MessageError, payload: bytes, topic: str, now: float
           ) -> dict[str, Any]:
    """Record a rejected message (once per payload) and return its error message."""
    digest = hashlib.sha256(payload).hexdigest()
    fresh = store.add_rejection(payload_digest=digest, reason=err.reason, detail=err.detail,
                                part_id=err.part_id, received_at=now)
    log.warning("rejected message on %s (%s): %s%s", topic, err.reason, err.detail,
                "" if fresh else " [redelivered, counted once]")
    return error_message(err, topic, now)


class SensorDesk:
    """The sensor messages' part of the processor (called under its lock).

    Parameters
    ----------
    store : Store
        The service's store (the ``measurements`` table is created in it).
    tracker : Tracker
        The service's tracker; its ``config.sensors`` are the sensors fused.
    max_bytes : int
        Largest accepted payload, bytes.
    """

    def __init__(self, store: Store, tracker: Any, max_bytes: int = 65536) -> None:
        store.ensure_tables(MEASUREMENTS_DDL)
        self.store = store
        self.tracker = tracker
        self.max_bytes = max_bytes
        self.sensors = {s.name: s for s in fused_sensors(tracker)}
        if self.sensors:  # at the start, not at the first sensor message
            load_kernels()
        self.lag = int(getattr(getattr(tracker, "ssm", None), "lag_depth", 0))
        row = store.query("SELECT COALESCE(MAX(seq), 0) FROM products WHERE status = "
                          "'accepted'")
        #: seq of the last accepted product (the fusions after it go into the next estimate)
        self.last_accepted = int(row[0][0])
        #: part id -> (step index, setting, final-angle prediction) of the last
        #: :data:`RECENT` accepted products committed here: what a sensor message needs of
        #: its product, without reading and decoding the stored estimate
        self.recent: dict[str, tuple[int, Any, dict[str, Any] | None]] = {}
        self._pending: tuple[str, int, Any, dict[str, Any] | None] | None = None
        #: the values fused since the last accepted product (``at_seq >= last_accepted``,
        #: in ``at_seq, id`` order): the next estimate's ``measurements``, kept here as
        #: they are committed (read from the store once, at the start)
        self._since: list[dict[str, Any]] = self._fused_since(self.last_accepted)
        #: the held values :meth:`at_product` fused for the product being committed
        self._pending_since: list[dict[str, Any]] = []
        #: held row id -> (sensor, value, log evidence) of the values :meth:`before_step`
        #: fused into the current step, and their part id
        self._ahead: dict[int, tuple[str, float, float]] = {}
        self._ahead_part = ""
        #: the answers (``formtwin.measurement/1``) of the held values :meth:`at_product`
        #: decided for the product being committed (fused or rejected): the live page's
        self.held_answers: list[dict[str, Any]] = []
        #: values stored as held (the store's count, kept here: most products have none,
        #: and :meth:`at_product` then reads nothing); after the product being committed
        self._held = int(store.query("SELECT COUNT(*) FROM measurements WHERE status = "
                                     "'held'")[0][0])
        self._held_after = self._held

    @property
    def active(self) -> bool:
        """Whether the tracker fuses any sensor."""
        return bool(self.sensors)

    # ----------------------------------------------------------------- a sensor message
    def handle(self, payload: bytes, topic: str, now: float, last_seq: int
               ) -> tuple[str, dict[str, Any]]:
        """Process one sensor payload; ``last_seq`` is the seq of the last stored product.
        Returns ``(kind, message)``: kind ``fused``, ``held``, ``too_late``, ``redelivered``
        (the stored answer) or ``rejected`` (the error message)."""
        try:
            r = parse_reading(payload, tuple(self.sensors), self.max_bytes)
        except MessageError as err:
            return "rejected", refuse(self.store, err, payload, topic, now)
        old = self.store.query("SELECT value, message FROM measurements WHERE part_id = ? "
                               "AND sensor = ?", (r.part_id, r.sensor))
        if old:
            if float(old[0][0]) == r.value:
                msg = dict(json.loads(old[0][1]), redelivered=True)
                return "redelivered", msg
            return "rejected", refuse(self.store, MessageError(
                "duplicate_measurement", f"{r.sensor} of part {r.part_id!r} already stored "
                f"with value {float(old[0][0])!r}, now {r.value!r}", r.part_id),
                payload, topic, now)
        bad = value_refusal(self.tracker.spec, self.sensors[r.sensor], r.value)
        if bad is not None:  # refused whatever the particles: not held either
            return "rejected", refuse(self.store, MessageError(
                "fusion_rejected", f"fuse: {r.sensor} {bad}", r.part_id), payload, topic, now)
        known = self._product(r.part_id)
        if known is None:
            return self._hold(r, payload, topic, now, last_seq)
        if isinstance(known, str):  # gated
            return "rejected", refuse(self.store, MessageError(
                "product_gated", f"part {r.part_id!r} was gated as an outlier: not in the "
                "tracker, its sensor values are not fused", r.part_id), payload, topic, now)
        index, u, final = known
        newest = int(self.tracker.n_steps) - 1
        msg = self._answer(r, index, {"final": final})
        if index < newest - self.lag:
            msg["status"] = "too_late"
            msg["detail"] = (f"product {index} is more than L = {self.lag} products before "
                             f"the newest ({newest}): stored, not fused")
            self._insert(r, "too_late", last_seq, index, u, now, msg)
            log.warning("%s of part %s too late: %s", r.sensor, r.part_id, msg["detail"])
            return "too_late", msg
        try:
            with self.store.transaction() as cur:
                msg["log_evidence"] = self._fuse(r.sensor, r.value, index, u)
                msg["status"] = "fused"
                self._insert(r, "fused", last_seq, index, u, now, msg, cur)
        except MessageError as err:
            return "rejected", refuse(self.store, err, payload, topic, now)
        self._since.append({"part_id": r.part_id, "sensor": r.sensor, "value": r.value})
        return "fused", msg

    def _product(self, part_id: str) -> tuple[int, Any, dict[str, Any] | None] | str | None:
        """``(step index, setting, final-angle prediction)`` of a stored accepted product
        (from :attr:`recent` or the store), ``"gated"`` for another stored one, None for a
        product not yet seen."""
        got = self.recent.get(part_id)
        if got is not None:
            return got
        prod = self.store.product(part_id)
        if prod is None:
            return None
        if prod.status != "accepted" or prod.estimate is None:
            return "gated"
        e = prod.estimate
        return int(e["index"]), e.get("u"), e.get("final")

    def _fuse(self, sensor: str, value: float, index: int, u: Any) -> float:
        """Fuse into the tracker; a refusal becomes ``fusion_rejected`` (tracker untouched)."""
        try:
            return float(self.tracker.fuse(index, sensor, value, u=_setting(u)))
        except FusionError as exc:
            raise MessageError("fusion_rejected", str(exc)[:300]) from None

    def _answer(self, r: Reading, index: int | None, estimate: dict[str, Any] | None
                ) -> dict[str, Any]:
        msg: dict[str, Any] = {"schema": MEASUREMENT_SCHEMA, "part_id": r.part_id,
                               "sensor": r.sensor, "value": r.value, "index": index}
        if r.timestamp is not None:
            msg["timestamp"] = r.timestamp
        if self.sensors[r.sensor].measures == final_output(self.tracker.spec) \
                and estimate is not None:
            final = estimate.get("final") or {}
            msg["predicted_deg"] = final.get("predicted_deg")
            msg["interval90_deg"] = final.get("interval90_deg")
        return msg

    def _hold(self, r: Reading, payload: bytes, topic: str, now: float, last_seq: int
              ) -> tuple[str, dict[str, Any]]:
        held = self._held
        if held >= HOLD_COUNT:
            return "rejected", refuse(self.store, MessageError(
                "hold_full", f"part {r.part_id!r} not yet seen and {held} values already "
                f"held (at most {HOLD_COUNT})", r.part_id), payload, topic, now)
        msg = dict(self._answer(r, None, None), status="held")
        self._insert(r, "held", last_seq, None, None, now, msg)
        self._held = self._held_after = held + 1
        return "held", msg

    def _insert(self, r: Reading, status: str, at_seq: int, index: int | None, u: Any,
                now: float, msg: dict[str, Any], cur: sqlite3.Cursor | None = None) -> None:
        sql = ("INSERT INTO measurements(part_id, sensor, value, status, at_seq, product, u, "
               "received_at, message) VALUES (?,?,?,?,?,?,?,?,?)")
        args = (r.part_id, r.sensor, r.value, status, at_seq, index,
                None if u is None else json.dumps(u), now, dumps(msg).decode())
        (self.store.execute if cur is None else cur.execute)(sql, args)

    # ----------------------------------------------------------------- a product's commit
    def since_last(self) -> list[dict[str, Any]]:
        """The values fused after the last accepted estimate and those fused into the
        current step (:meth:`before_step`): what went into the current estimate."""
        return [dict(m) for m in self._since] + [
            {"part_id": self._ahead_part, "sensor": n, "value": v}
            for n, v, _ in self._ahead.values()]

    def before_step(self, part_id: str) -> bool:
        """Fuse into the coming step the values held for ``part_id`` that can enter it (a
        state variable's, :mod:`formtwin.tracker.ahead`), in their order; a value the
        tracker refuses stays held (:meth:`at_product` fuses it after the step or rejects
        it). Returns whether any was fused (the tracker is then no longer as before)."""
        self._ahead, self._ahead_part = {}, part_id
        if not self._held:
            return False
        rows = self.store.query("SELECT id, sensor, value FROM measurements WHERE status = "
                                "'held' AND part_id = ? ORDER BY id", (part_id,))
        for rid, sensor, value in rows:
            if refusal(self.tracker, self.sensors[str(sensor)]) is None:
                try:
                    inc = float(self.tracker.fuse(int(self.tracker.n_steps), str(sensor),
                                                  float(value)))
                except FusionError:
                    continue
                self._ahead[int(rid)] = (str(sensor), float(value), inc)
        return bool(self._ahead)

    def _fused_since(self, seq: int) -> list[dict[str, Any]]:
        """The stored values fused at or after product ``seq``, in their order."""
        rows = self.store.query("SELECT part_id, sensor, value FROM measurements WHERE "
                                "status = 'fused' AND at_seq >= ? ORDER BY at_seq, id",
                                (seq,))
        return [{"part_id": str(p), "sensor": str(s), "value": float(v)} for p, s, v in rows]

    def at_product(self, cur: sqlite3.Cursor, seq: int, part_id: str, index: int, u: Any,
                   final: dict[str, Any] | None) -> list[dict[str, Any]]:
        """In the transaction of accepted product ``seq`` (already stepped, its estimate
        issued with the final-angle prediction ``final``): fuse the values held for it,
        expire the held values older than :data:`HOLD_PRODUCTS` products; return the
        notices for the errors topic."""
        notices: list[dict[str, Any]] = []
        self._pending = (part_id, int(index), u, final)
        self._pending_since, self.held_answers = [], []
        self._held_after = self._held
        if not self._held:
            return notices
        held = cur.execute("SELECT id, sensor, value, message FROM measurements WHERE "
                           "status = 'held' AND part_id = ? ORDER BY id", (part_id,)).fetchall()
        est = {"final": final}
        for rid, sensor, value, text in held:
            msg = dict(json.loads(text), index=index)
            at = seq
            if self.sensors[str(sensor)].measures == final_output(self.tracker.spec):
                msg.update({k: v for k, v in self._answer(
                    Reading(part_id, str(sensor), float(value)), index, est).items()
                    if k in ("predicted_deg", "interval90_deg")})
            try:
                if int(rid) in self._ahead:  # fused into the step: replayed before it
                    msg["log_evidence"], msg["status"], at = self._ahead[int(rid)][2], \
                        "fused", seq - 1
                    msg["in_step"] = True
                else:
                    msg["log_evidence"] = self._fuse(str(sensor), float(value), index, u)
                    msg["status"] = "fused"
                    self._pending_since.append({"part_id": part_id, "sensor": str(sensor),
                                                "value": float(value)})
            except MessageError as err:
                msg["status"], msg["detail"] = "rejected", err.detail
                notices.append(error_message(MessageError(
                    "fusion_rejected", f"held {sensor} of part {part_id!r}: {err.detail}",
                    part_id), "held", 0.0))
            cur.execute("UPDATE measurements SET status = ?, at_seq = ?, product = ?, u = ?, "
                        "message = ? WHERE id = ?",
                        (msg["status"], at, index, None if u is None else json.dumps(u),
                         dumps(msg).decode(), rid))
            self.held_answers.append(msg)
        old = cur.execute("SELECT id, part_id, sensor, message FROM measurements WHERE "
                          "status = 'held' AND at_seq <= ? ORDER BY id",
                          (seq - HOLD_PRODUCTS,)).fetchall()
        for rid, pid, sensor, text in old:
            cur.execute("UPDATE measurements SET status = 'expired', message = ? WHERE id = ?",
                        (dumps(dict(json.loads(text), status="expired")).decode(), rid))
            notices.append(error_message(MessageError(
                "hold_expired", f"{sensor} of part {pid!r} held for {HOLD_PRODUCTS} "
                "products without its curve: stored as expired, not fused", str(pid)),
                "held", 0.0))
        self._held_after = self._held - len(held) - len(old)
        return notices

    def committed(self, seq: int) -> None:
        """Accepted product ``seq`` is in (with what :meth:`at_product` saw of it)."""
        self.last_accepted = seq
        self._held, self._ahead = self._held_after, {}
        self._since, self._pending_since = self._pending_since, []
        if self._pending is not None:
            part_id, *known = self._pending
            self.recent[part_id] = (known[0], known[1], known[2])
            self._pending = None
            while len(self.recent) > RECENT:
                del self.recent[next(iter(self.recent))]


def _setting(u: Any) -> Any:
    """A product's press setting as the tracker gets it: None (nominal) or float64."""
    return None if u is None else np.asarray(u, dtype=np.float64)

__all__ = ["HOLD_COUNT", "HOLD_PRODUCTS", "MEASUREMENT_SCHEMA", "SENSOR_SCHEMA", "Reading",
           "SensorDesk", "issue", "parse_reading"]
