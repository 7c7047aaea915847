"""Versioned JSON messages between the press and formtwin, and their validation.

Stroke (press -> formtwin), schema ``formtwin.stroke/1``::

    {"schema": "formtwin.stroke/1", "part_id": "P-000123", "cycle": 123,
     "timestamp": "2026-11-21T23:59:59.123Z",
     "force_N": [101 numbers: stage-1 punch force on the spec's time grid, N],
     "angles_deg": [a1, a2],            # optional, measured outputs (one per spec output,
                                        # in its unit; the demonstrator's two angles)
     "u": 0.05}                         # optional, the product's press setting(s) in
                                        # internal units (mm): a number or one per control;
                                        # absent: the nominal setting

Estimate (formtwin -> results topic), schema ``formtwin.estimate/1``: the part id, cycle and
timestamp of the stroke, the tracker step index, the names of the 18 estimated quantities with
their posterior mean and std, predicted angles with std (at the stroke's setting ``u``, echoed
as ``u`` when the stroke gave one), ESS, loglik and flags.

Error (formtwin -> errors topic), schema ``formtwin.error/1``: a reason code from
:data:`REASONS`, a human-readable detail, the part id when known.

>>> lim = Limits(n_t=3)
>>> s = parse_stroke(b'{"schema": "formtwin.stroke/1", "part_id": "a", "cycle": 1, '
...                  b'"timestamp": 0, "force_N": [0, 10.5, 2]}', lim)
>>> s.part_id, s.force_N.tolist()
('a', [0.0, 10.5, 2.0])
>>> try:
...     parse_stroke(b'{"schema": "formtwin.stroke/1", "part_id": "a", "cycle": 1, '
...                  b'"timestamp": 0, "force_N": [0, NaN, 2]}', lim)
... except MessageError as e:
...     print(e.reason)
non_finite
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeVar

import numpy as np
import orjson
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

STROKE_SCHEMA = "formtwin.stroke/1"
ESTIMATE_SCHEMA = "formtwin.estimate/1"
ERROR_SCHEMA = "formtwin.error/1"

#: every reason a message can be rejected for, with its meaning
REASONS: dict[str, str] = {
    "oversized": "message larger than the configured maximum",
    "malformed_json": "payload is not UTF-8 JSON, or not a JSON object",
    "unknown_schema": "schema field missing or not a version this service understands",
    "missing_field": "a required field is absent",
    "bad_field": "a field has the wrong type or an invalid value",
    "wrong_length": "force curve does not have the spec's number of samples",
    "non_finite": "NaN or infinity in the force curve or angles",
    "negative_force": "force below the allowed negative tolerance",
    "absurd_force": "force above the configured maximum",
    "no_stroke": "peak force below the floor derived from the spec's ranges (no stroke, "
                 "unplugged sensor)",
    "clipped_sensor": "a run of samples at one value at the top of the curve (clipped or "
                      "saturated sensor, flat curve)",
    "peak_outside_window": "the force peak lies outside the time window the model allows "
                           "(trigger or time base wrong)",
    "duplicate_part_id": "part id already stored with a different curve",
    "out_of_order": "cycle count not greater than the last accepted cycle",
    "tracker_rejected": "the tracker refused the curve",
    "outlier_gated": "curve gated as a single outlier (robust mode); state not updated",
    "unknown_sensor": "sensor message for a sensor this service does not fuse",
    "duplicate_measurement": "sensor value of a (part id, sensor) already stored with "
                             "another value",
    "hold_full": "sensor value for a product not yet seen, and the hold is full",
    "hold_expired": "held sensor value whose product did not come in time (a notice)",
    "fusion_rejected": "the tracker refused the sensor value (outside the spec's range of "
                       "its state variable, or no particle explains it)",
    "product_gated": "sensor value of a product gated as an outlier (not in the tracker)",
}

_PART_ID_MAX = 128
#: largest cycle count the store holds (SQLite INTEGER: signed 64 bit)
CYCLE_MAX = 2**63 - 1


class MessageError(ValueError):
    """A stroke or sensor message was rejected; ``reason`` is a key of :data:`REASONS`."""

    def __init__(self, reason: str, detail: str, part_id: str | None = None) -> None:
        if reason not in REASONS:
            raise KeyError(f"unknown rejection reason {reason!r}")
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
        self.part_id = part_id


@dataclass(frozen=True)
class Limits:
    """What a stroke message may contain.

    Parameters
    ----------
    n_t : int
        Number of force samples (the spec's time grid).
    max_bytes : int
        Largest accepted payload, bytes.
    min_force_N : float
        Most negative force sample accepted (sensor offset tolerance), N.
    max_force_N : float
        Largest force sample accepted, N.
    n_outputs : int
        Number of values of ``angles_deg`` (the spec's outputs).
    """

    n_t: int
    max_bytes: int = 65536
    min_force_N: float = -50.0
    max_force_N: float = 1.0e4
    n_outputs: int = 2


@dataclass(frozen=True)
class Stroke:
    """One validated stroke: ``force_N`` has shape ``(n_t,)``, ``angles_deg`` ``(n_outputs,)``
    or None,
    ``u`` the press settings ``(n_controls,)`` or None (nominal)."""

    part_id: str
    cycle: int
    timestamp: str
    force_N: FloatArray
    angles_deg: FloatArray | None
    digest: str
    u: FloatArray | None = None

    def to_message(self) -> dict[str, Any]:
        """The stroke as a ``formtwin.stroke/1`` JSON object."""
        msg: dict[str, Any] = {"schema": STROKE_SCHEMA, "part_id": self.part_id,
                               "cycle": self.cycle, "timestamp": self.timestamp,
                               "force_N": [float(v) for v in self.force_N]}
        if self.angles_deg is not None:
            msg["angles_deg"] = [float(v) for v in self.angles_deg]
        if self.u is not None:
            msg["u"] = [float(v) for v in self.u]
        return msg


def stroke_digest(force_N: FloatArray) -> str:
    """SHA-256 of the curve's float64 bytes: tells a redelivery from a clash of part ids."""
    return hashlib.sha256(np.ascontiguousarray(force_N, dtype="<f8").tobytes()).hexdigest()


def _reject_constant(name: str) -> float:
    raise MessageError("non_finite", f"JSON literal {name} is not a finite number")


#: ``json.loads(text, parse_constant=...)`` makes a decoder per call; this one is made once
_DECODER = json.JSONDecoder(parse_constant=_reject_constant)


#: 2^63: a float this large may be an integer orjson read as a float (beyond 64 bits)
LONG_INT = 2.0**63


def loads(payload: bytes, fast: bool = True) -> Any:
    """A message's JSON document; ``fast``: orjson's parser (about ten times the standard
    library's speed, the same numbers: both round every decimal correctly), else the
    standard library's (NaN and Infinity raise ``non_finite``).

    They differ only where orjson refuses what the standard library reads (NaN, lone
    surrogates, integers beyond 64 bits, which orjson reads as floats). The parsers of
    the messages therefore read fast first and read again with the standard library when
    the message is rejected, or a number could be such an integer (:data:`LONG_INT`): a
    rejected message gets the same reason and detail as ever, an accepted one the same
    values.

    Raises
    ------
    MessageError
        ``non_finite`` for a NaN or Infinity literal (not ``fast``).
    ValueError, RecursionError
        For a payload that is not JSON (bad UTF-8 included).
    """
    if fast:
        return orjson.loads(payload)
    return _DECODER.decode(payload.decode("utf-8"))


_Doc = TypeVar("_Doc")


def read_fast_then_exact(parse: Callable[[bool], _Doc | None]) -> _Doc:
    """``parse(fast=True)``; ``parse(fast=False)`` (the standard library's read, see
    :func:`loads`) where the fast read was rejected (a :class:`MessageError`) or says it
    may differ (None): a rejected message gets the standard read's reason and detail."""
    try:
        out = parse(True)
    except MessageError:
        out = None
    if out is None:
        out = parse(False)
        assert out is not None  # only a fast read gives None
    return out


#: the types of a JSON number (``bool``, a subclass of ``int``, is not one)
_NUMBER_TYPES = frozenset((int, float))


def _number_list(doc: dict[str, Any], key: str, part_id: str) -> FloatArray:
    value = doc[key]
    if not isinstance(value, list):
        raise MessageError("bad_field", f"{key} must be a list of numbers, got "
                           f"{type(value).__name__}", part_id)
    if not set(map(type, value)) <= _NUMBER_TYPES:  # JSON gives exactly int and float
        i, v = next((i, v) for i, v in enumerate(value) if type(v) not in _NUMBER_TYPES)
        raise MessageError("bad_field", f"{key}[{i}] must be a number, got {v!r:.40}",
                           part_id)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except OverflowError:
        raise MessageError("non_finite", f"{key} holds an integer too large for float64",
                           part_id) from None
    if not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise MessageError("non_finite", f"{key}[{bad}] is {arr[bad]}", part_id)
    return arr


def _valid_part_id(raw: Any) -> bool:
    return isinstance(raw, str) and 0 < len(raw) <= _PART_ID_MAX and raw.isprintable()


def _valid_timestamp(ts: Any) -> bool:
    if isinstance(ts, bool):
        return False
    if isinstance(ts, int):  # an int of any size: compare as int (no float overflow)
        return 0 <= ts <= CYCLE_MAX
    if isinstance(ts, float):
        return math.isfinite(ts) and ts >= 0
    if isinstance(ts, str) and 0 < len(ts) <= 64:
        try:
            datetime.fromisoformat(ts)
        except ValueError:
            return False
        return True
    return False


def parse_stroke(payload: bytes, limits: Limits) -> Stroke:
    """Parse and validate one stroke payload.

    Parameters
    ----------
    payload : bytes
        The raw MQTT payload.
    limits : Limits
        Sizes and force bounds.

    Returns
    -------
    Stroke

    Raises
    ------
    MessageError
        With a reason from :data:`REASONS` naming the field, the value and what was expected.
    """
    if len(payload) > limits.max_bytes:
        raise MessageError("oversized", f"{len(payload)} bytes > limit {limits.max_bytes}")
    return read_fast_then_exact(lambda fast: _stroke(payload, limits, fast))


def _stroke(payload: bytes, limits: Limits, fast: bool) -> Stroke | None:
    """:func:`parse_stroke` after the size check, the JSON read ``fast`` or not; None
    where a fast read may differ from the standard library's (:data:`LONG_INT`)."""
    try:
        doc = loads(payload, fast)
    except MessageError:
        raise
    except (ValueError, RecursionError) as exc:  # bad UTF-8, bad JSON, 5000-digit integers
        raise MessageError("malformed_json", f"{type(exc).__name__}: {exc}"[:200]) from None
    if not isinstance(doc, dict):
        raise MessageError("malformed_json", f"top level is {type(doc).__name__}, not object")
    schema = doc.get("schema")
    if schema != STROKE_SCHEMA:
        raise MessageError("unknown_schema",
                           f"schema {schema!r:.60}, expected {STROKE_SCHEMA!r}")
    raw_id = doc.get("part_id")
    part_id = raw_id if _valid_part_id(raw_id) else None  # only a valid id goes into errors
    for key in ("part_id", "cycle", "timestamp", "force_N"):
        if key not in doc:
            raise MessageError("missing_field", f"field {key!r} is required", part_id)
    if part_id is None:
        raise MessageError("bad_field", f"part_id must be a printable string of 1.."
                           f"{_PART_ID_MAX} characters, got {raw_id!r:.60}")
    cycle = doc["cycle"]
    if isinstance(cycle, bool) or not isinstance(cycle, int) or not 0 <= cycle <= CYCLE_MAX:
        raise MessageError("bad_field", f"cycle must be an integer in 0..2^63-1, got "
                           f"{cycle!r:.40}", part_id)
    ts = doc["timestamp"]
    if fast and isinstance(ts, float) and abs(ts) >= LONG_INT:
        return None
    if not _valid_timestamp(ts):
        raise MessageError("bad_field", f"timestamp must be an ISO 8601 string or epoch "
                           f"seconds >= 0, got {ts!r:.40}", part_id)
    force = _number_list(doc, "force_N", part_id)
    if force.size != limits.n_t:
        raise MessageError("wrong_length", f"force_N has {force.size} samples, expected "
                           f"{limits.n_t}", part_id)
    lo, hi = int(force.argmin()), int(force.argmax())
    if force[lo] < limits.min_force_N:
        raise MessageError("negative_force", f"force_N[{lo}] = {force[lo]:.6g} N < "
                           f"{limits.min_force_N:g} N", part_id)
    if force[hi] > limits.max_force_N:
        raise MessageError("absurd_force", f"force_N[{hi}] = {force[hi]:.6g} N > "
                           f"{limits.max_force_N:g} N", part_id)
    angles = None
    if doc.get("angles_deg") is not None:
        angles = _number_list(doc, "angles_deg", part_id)
        if angles.size != limits.n_outputs:
            raise MessageError("wrong_length", f"angles_deg has {angles.size} values, "
                               f"expected {limits.n_outputs} (the spec's outputs)", part_id)
    u = None
    if doc.get("u") is not None:
        raw = doc["u"]
        if isinstance(raw, bool) or not isinstance(raw, int | float | list):
            raise MessageError("bad_field", f"u must be a number or a list of numbers, got "
                               f"{raw!r:.40}", part_id)
        u = _number_list({"u": raw if isinstance(raw, list) else [raw]}, "u", part_id)
    return Stroke(part_id=part_id, cycle=cycle, timestamp=str(ts), force_N=force,
                  angles_deg=angles, digest=stroke_digest(force), u=u)


def estimate_message(stroke: Stroke, estimate: dict[str, Any], seq: int,
                     flags: dict[str, bool]) -> dict[str, Any]:
    """The ``formtwin.estimate/1`` message for an accepted stroke.

    ``estimate`` is the tracker's ``Estimate.to_dict()``; ``seq`` the store's product number.
    """
    msg: dict[str, Any] = {"schema": ESTIMATE_SCHEMA, "part_id": stroke.part_id,
                           "cycle": stroke.cycle, "timestamp": stroke.timestamp, "seq": seq}
    msg.update({k: v for k, v in estimate.items() if k not in msg})
    msg["flags"] = dict(flags)
    if stroke.angles_deg is not None:
        msg["measured_angles_deg"] = [float(v) for v in stroke.angles_deg]
    if stroke.u is not None:
        msg["u"] = [float(v) for v in stroke.u]
    return msg


def error_message(err: MessageError, topic: str, received_at: float) -> dict[str, Any]:
    """The ``formtwin.error/1`` message for a rejection."""
    return {"schema": ERROR_SCHEMA, "reason": err.reason, "detail": err.detail,
            "part_id": err.part_id, "topic": topic, "received_at": received_at}


def _scalar(obj: Any) -> Any:
    """A NumPy scalar as the Python number the standard library's encoder wrote."""
    if isinstance(obj, np.generic) and obj.dtype.kind in "biuf":
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def dumps(msg: dict[str, Any]) -> bytes:
    """Compact JSON bytes (orjson: the shortest decimal that reads back as the same
    float64, as :func:`repr` gives, ~15 times the standard library's speed on an estimate).
    A non-finite number is written ``null`` (not JSON; the messages' convention, as
    :meth:`formtwin.estimates.Estimate.to_dict` makes it). What orjson cannot write (an
    integer beyond 64 bits) the standard library writes."""
    try:
        return orjson.dumps(msg, default=_scalar, option=orjson.OPT_NON_STR_KEYS)
    except orjson.JSONEncodeError:
        return json.dumps(msg, separators=(",", ":"), allow_nan=False,
                          default=_scalar).encode("utf-8")
