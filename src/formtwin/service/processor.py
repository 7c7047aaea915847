"""The broker-free core of the service: one payload in, one outcome out.

For every message :meth:`Processor.handle`

1. validates it (:func:`~formtwin.service.messages.parse_stroke`); a bad message is
   recorded as a rejection with its reason and the tracker is not touched;
2. looks its part id up in the store: the same curve again is a *redelivery* (the stored
   estimate is returned, nothing is counted twice), a different curve is a
   ``duplicate_part_id`` rejection; a cycle count not above the last one is ``out_of_order``;
3. steps the tracker (the values held for the part that can enter its step fused into
   it first: :meth:`~formtwin.service.sensors.SensorDesk.before_step`), optionally gates
   a single outlier (:class:`~formtwin.service.gate.OutlierGate`), and commits product,
   estimate, the product's alarm and model-health rows and, every ``checkpoint_every``
   accepted products, the tracker checkpoint in **one** SQLite transaction.

A process killed at any instant restarts from a store in which every product is either
fully in (and its redelivery is recognised) or not at all; the tracker is restored from the
last checkpoint and stepped again through the curves stored after it
(:func:`formtwin.service.restore.replay`: the steps are deterministic), so a product not
yet in is processed from the same tracker state, giving bit-for-bit the same estimate.
Sensor messages (:meth:`Processor.handle_sensor`) go to :mod:`formtwin.service.sensors`.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.service.gate import OutlierGate
from formtwin.service.health import ModelHealth
from formtwin.service.messages import (
    Limits,
    MessageError,
    Stroke,
    dumps,
    error_message,
    estimate_message,
    parse_stroke,
)
from formtwin.service.restore import replay
from formtwin.service.sensors import SensorDesk, issue, refuse
from formtwin.service.store import Store

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class EstimateLike(Protocol):
    """What the processor reads from the tracker's ``Estimate``."""

    @property
    def loglik(self) -> float:
        """Log-likelihood of the step's curve (for the outlier gate)."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """The estimate as JSON-ready values."""
        ...


class MonitorLike(Protocol):
    """What the processor needs of :class:`formtwin.service.alarms.ServiceMonitor`."""

    def observe(self, message: dict[str, Any]) -> dict[str, Any]:
        """Chart an estimate message before its commit; its ``"monitoring"`` entry."""
        ...

    def rollback(self) -> None:
        """Undo the last observe (the product was not committed)."""
        ...

    def write(self, cur: sqlite3.Cursor, seq: int, part_id: str, entry: dict[str, Any],
              now: float) -> list[dict[str, Any]]:
        """Write the product's alarm rows in its transaction; return the alarms' messages."""
        ...

    def committed(self) -> None:
        """The last observed product is in (its undo is dropped)."""
        ...


class TrackerLike(Protocol):
    """What the processor needs of :class:`formtwin.tracker.Tracker`."""

    def step(self, curve: FloatArray, u: Any = None) -> Any:
        """One curve in (setting ``u``, None: nominal), its estimate out (ValueError: untouched)."""
        ...

    def state_bytes(self) -> bytes:
        """The full state, bit for bit."""
        ...

    def load_state_bytes(self, data: bytes) -> None:
        """Continue from bytes made by :meth:`state_bytes`."""
        ...


@dataclass(frozen=True)
class Outcome:
    """Result of one message: ``kind`` is accepted, redelivered, gated or rejected;
    ``message`` goes to the results topic (accepted, redelivered) or the errors topic."""

    kind: str
    message: dict[str, Any]
    part_id: str | None = None
    seq: int | None = None
    alarms: tuple[dict[str, Any], ...] = ()  # alarm episodes' reported changes
    notices: tuple[dict[str, Any], ...] = ()  # model health, for the errors topic
    payload: bytes | None = None  # ``message`` as JSON, when already encoded (stored so)
    sensor_answers: tuple[dict[str, Any], ...] = ()  # of values held for it, fused with it

    @property
    def is_error(self) -> bool:
        """Whether the message was rejected or gated."""
        return self.kind in ("rejected", "gated")


class Processor:
    """Validate, step, gate and commit, one message at a time (thread-safe).

    Parameters
    ----------
    store : Store
        The durable store.
    tracker : TrackerLike
        The tracker at the last stored product: restored from the store's checkpoint and
        stepped through the products stored after it (:func:`replay`); on a store without
        a checkpoint, in its first state (stored then as the checkpoint of seq 0). A gated
        or failed step is undone by :func:`replay` too.
    limits : Limits
        Message validation limits.
    gate : OutlierGate or None
        Robust option for single outlier curves; None disables it.
    on_outcome : callable, optional
        Called with every :class:`Outcome` (the live page listens here).
    monitor : MonitorLike or None
        Control charts on the accepted estimates (:mod:`formtwin.service.alarms`): their
        statistics and alarms go into the estimate message before the commit.
    health : ModelHealth or None
        Model health (:class:`formtwin.service.health.ModelHealth`): its state goes into
        the estimate message (``model_health``, ``flags.model_mismatch``) before the commit,
        its notices (``model_mismatch``) to the errors topic.
    plausible : callable, optional
        Checks a parsed stroke before the tracker (:mod:`formtwin.service.plausibility`);
        raises :class:`MessageError` (no_stroke, clipped_sensor, peak_outside_window).
    checkpoint_every : int
        Store the tracker's state with every this many accepted products (1: each one).
        The tracker must already be at the last stored product (restored and replayed).
    """

    def __init__(self, store: Store, tracker: TrackerLike, limits: Limits,
                 gate: OutlierGate | None = None,
                 on_outcome: Callable[[Outcome], None] | None = None,
                 monitor: MonitorLike | None = None, health: ModelHealth | None = None,
                 plausible: Callable[[Stroke], None] | None = None,
                 checkpoint_every: int = 1) -> None:
        if checkpoint_every < 1:
            raise ValueError(f"checkpoint_every = {checkpoint_every}, expected >= 1")
        self.store = store
        self.checkpoint_every = checkpoint_every
        self.monitor = monitor
        self.health = health
        #: feedforward control (:class:`formtwin.service.control.ServiceController`): the
        #: suggested setting goes into the estimate message (``control``) before the commit
        self.controller: Any = None
        self.plausible = plausible
        self.tracker = tracker
        self.limits = limits
        self.gate = gate
        self.on_outcome = on_outcome
        self._lock = threading.Lock()
        # one BLAS thread while the processor is open: a step's model evaluations then cost
        # a counter, not a limit set and restored (two per product, ~0.5 ms; same numbers)
        self._blas: Any = single_blas_thread()
        self._last_cycle = store.last_cycle()
        self._next_seq = store.next_seq()  # this processor is the store's only writer
        if gate is not None:
            gate.history = store.recent_logliks(gate.window)
            gate.last_gated = store.last_status() == "gated"
        ck = store.checkpoint()
        if ck is None:
            store.execute("INSERT INTO checkpoint(id, seq, data) VALUES (1, 0, ?)",
                          (tracker.state_bytes(),))
        #: accepted products stored after the last stored checkpoint
        self._unsaved = int(store.query(
            "SELECT COUNT(*) FROM products WHERE status = 'accepted' AND seq > ?",
            (0 if ck is None else ck[0],))[0][0])
        self.redelivered = 0
        self.step_cpu_s = 0.0  #: CPU s (thread time) of the tracker steps made here
        #: the sensor messages' part (:mod:`formtwin.service.sensors`)
        self.sensors = SensorDesk(store, tracker, limits.max_bytes)

    def tracker_names(self) -> tuple[str, ...]:
        """Names of the estimated quantities (the tracker's, else the spec's)."""
        names = getattr(self.tracker, "names", None)
        if names is None:
            from formtwin.spec import load_spec

            return load_spec().augmented.names
        return tuple(str(n) for n in names)

    def close(self) -> None:
        """Close the store (a second close does nothing); give BLAS its threads back."""
        self.store.close()
        blas, self._blas = self._blas, None
        if blas is not None:
            blas.__exit__(None, None, None)

    def _rollback(self) -> None:
        replay(self.store, self.tracker)
        for m in (self.monitor, self.health, self.controller):
            if m is not None:
                m.rollback()

    def _reject(self, err: MessageError, payload: bytes, topic: str, now: float) -> Outcome:
        return Outcome("rejected", refuse(self.store, err, payload, topic, now), err.part_id)

    def _emit(self, out: Outcome) -> Outcome:
        if self.on_outcome is not None:
            try:
                self.on_outcome(out)
            except Exception:  # the page must never break the tracking
                log.exception("on_outcome listener failed")
        return out

    def handle(self, payload: bytes, topic: str = "", received_at: float | None = None
               ) -> Outcome:
        """Process one raw message and return its :class:`Outcome` (never raises for bad
        input; storage errors propagate after the tracker has been rolled back)."""
        now = time.time() if received_at is None else received_at
        with self._lock:
            return self._emit(self._handle(payload, topic, now))

    def handle_sensor(self, payload: bytes, topic: str = "",
                      received_at: float | None = None) -> Outcome:
        """Process one sensor message (:meth:`SensorDesk.handle`): kind fused, held,
        too_late, redelivered or rejected (never raises for bad input; storage errors
        propagate after the tracker has been restored)."""
        now = time.time() if received_at is None else received_at
        with self._lock:
            try:
                kind, msg = self.sensors.handle(payload, topic, now, self._next_seq - 1)
            except (sqlite3.Error, OSError, RuntimeError):  # storage: fatal for the service
                replay(self.store, self.tracker)
                raise
            except Exception as exc:  # never let a poison message stop the service
                log.exception("a sensor message failed; tracker restored, message rejected")
                replay(self.store, self.tracker)
                return self._emit(self._reject(MessageError(
                    "fusion_rejected", f"{type(exc).__name__}: {exc}"[:300]), payload, topic,
                    now))
            return self._emit(Outcome(kind, msg, msg.get("part_id")))

    def _handle(self, payload: bytes, topic: str, now: float) -> Outcome:
        try:
            stroke = parse_stroke(payload, self.limits)
        except MessageError as err:
            return self._reject(err, payload, topic, now)
        except Exception as exc:  # never let a poison message stop the service
            log.exception("validator failed on a message; rejecting it as malformed")
            return self._reject(MessageError("malformed_json", f"unparseable: "
                                             f"{type(exc).__name__}: {exc}"[:200]),
                                payload, topic, now)
        row = self.store.product(stroke.part_id)
        if row is not None:
            if row.digest == stroke.digest and row.estimate is not None:
                self.redelivered += 1
                msg = dict(row.estimate)
                msg["flags"] = dict(msg.get("flags", {}), redelivered=True)
                log.info("redelivered part %s: stored estimate returned", stroke.part_id)
                return Outcome("redelivered", msg, stroke.part_id, row.seq)
            if row.digest == stroke.digest:  # a redelivered gated product
                self.redelivered += 1
                gerr = MessageError("outlier_gated", "redelivered gated product",
                                    stroke.part_id)
                return Outcome("gated", error_message(gerr, topic, now), stroke.part_id,
                               row.seq)
            return self._reject(MessageError(
                "duplicate_part_id", f"part {stroke.part_id!r} already stored (seq "
                f"{row.seq}) with a different curve", stroke.part_id), payload, topic, now)
        if self._last_cycle is not None and stroke.cycle <= self._last_cycle:
            return self._reject(MessageError(
                "out_of_order", f"cycle {stroke.cycle} <= last accepted cycle "
                f"{self._last_cycle}", stroke.part_id), payload, topic, now)
        if self.plausible is not None:
            try:
                self.plausible(stroke)
            except MessageError as err:
                return self._reject(err, payload, topic, now)
        ahead = self.sensors.active and self.sensors.before_step(stroke.part_id)
        try:
            c0 = time.thread_time()
            est = self.tracker.step(stroke.force_N, stroke.u)
            self.step_cpu_s += time.thread_time() - c0
        except ValueError as exc:  # the tracker's contract: state untouched (but for the
            if ahead:  # values fused into the step: undone)
                self._rollback()
            return self._reject(MessageError("tracker_rejected", str(exc)[:300],
                                             stroke.part_id), payload, topic, now)
        except Exception as exc:  # unexpected: undo whatever the step did, reject the curve
            log.exception("tracker step failed on part %s; state restored", stroke.part_id)
            self._rollback()
            return self._reject(MessageError(
                "tracker_rejected", f"{type(exc).__name__}: {exc}"[:300], stroke.part_id),
                payload, topic, now)
        try:
            return self._commit(stroke, est, topic, now)
        except (sqlite3.Error, OSError, RuntimeError):  # storage: fatal for the service
            self._rollback()
            raise
        except Exception as exc:  # e.g. an estimate that is not storable: reject, go on
            log.exception("storing the estimate of part %s failed", stroke.part_id)
            self._rollback()
            return self._reject(MessageError(
                "tracker_rejected", f"estimate not storable: {type(exc).__name__}: {exc}"[:300],
                stroke.part_id), payload, topic, now)
        except BaseException:
            self._rollback()
            raise

    def _commit(self, stroke: Stroke, est: Any, topic: str, now: float) -> Outcome:
        loglik = float(est.loglik)
        gated = self.gate is not None and self.gate.is_outlier(loglik)
        angles = None if stroke.angles_deg is None else [float(a) for a in stroke.angles_deg]
        if gated:
            assert self.gate is not None
            thr = self.gate.threshold()
            self._rollback()
            seq = self.store.commit_product(
                part_id=stroke.part_id, cycle=stroke.cycle, timestamp=stroke.timestamp,
                status="gated", digest=stroke.digest, curve=stroke.force_N,
                measured_angles=angles, estimate=None, checkpoint=None, received_at=now)
            self.gate.record(loglik, gated=True)
            self._last_cycle = stroke.cycle
            self._next_seq = seq + 1
            err = MessageError("outlier_gated", f"loglik {loglik:.4g} < gate {thr:.4g}; "
                               "state not updated", stroke.part_id)
            log.warning("part %s gated as outlier: %s", stroke.part_id, err.detail)
            return Outcome("gated", error_message(err, topic, now), stroke.part_id, seq)
        flags = {"collapsed": bool(est.collapsed), "redelivered": False}
        msg = estimate_message(stroke, est.to_dict(), seq=-1, flags=flags)
        seq = self._next_seq
        msg["seq"] = seq
        u = None if stroke.u is None else [float(v) for v in stroke.u]
        if self.sensors.active:  # what went in, and the final angle's calibrated interval
            msg["measurements"] = self.sensors.since_last()
            msg["final"] = issue(self.tracker, stroke.u)
        if self.health is not None:
            msg["peak_force_N"] = float(np.max(stroke.force_N))
            msg["model_health"] = self.health.observe(msg, stroke.force_N)
            msg["flags"]["model_mismatch"] = msg["model_health"]["state"] == "model_mismatch"
        if self.controller is not None:
            msg["control"] = self.controller.observe(msg)
        if self.monitor is not None:
            msg["monitoring"] = self.monitor.observe(msg)
        alarms: list[dict[str, Any]] = []
        notices: list[dict[str, Any]] = []

        def within(cur: sqlite3.Cursor, seq: int) -> None:  # rows of the same transaction
            if self.monitor is not None:
                alarms[:] = self.monitor.write(cur, seq, stroke.part_id, msg["monitoring"], now)
            if self.health is not None:
                notices[:] = self.health.write(cur, seq, stroke.part_id, msg["model_health"],
                                               now)
            if self.sensors.active:
                notices.extend(self.sensors.at_product(cur, seq, stroke.part_id, msg["index"],
                                                       u, msg["final"]))

        save = self._unsaved + 1 >= self.checkpoint_every
        ckpt = self.tracker.state_bytes() if save else None
        payload = dumps(msg)  # once: stored and published as is
        got = self.store.commit_product(
            part_id=stroke.part_id, cycle=stroke.cycle, timestamp=stroke.timestamp,
            status="accepted", digest=stroke.digest, curve=stroke.force_N,
            measured_angles=angles, estimate=payload, checkpoint=ckpt,
            received_at=now, within=within)
        if got != seq:  # single writer: cannot happen unless the store is shared
            raise RuntimeError(f"store sequence {got} != expected {seq}: is another "
                               "service writing to the same store?")
        self._unsaved = 0 if save else self._unsaved + 1
        self.sensors.committed(seq)
        self._last_cycle = stroke.cycle
        self._next_seq = seq + 1
        if self.gate is not None:
            self.gate.record(loglik, gated=False)
        for m in (self.monitor, self.health):
            if m is not None:
                m.committed()
        return Outcome("accepted", msg, stroke.part_id, seq, tuple(alarms), tuple(notices),
                       payload, tuple(self.sensors.held_answers))
