"""A sensor message (schema ``formtwin.sensor/1``, :mod:`formtwin.service.sensors`) parsed
and validated: :func:`parse_reading` gives a :class:`Reading` or a
:class:`~formtwin.service.messages.MessageError` naming the field, the value and what was
expected."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from formtwin.service.messages import LONG_INT, MessageError, loads, read_fast_then_exact

SENSOR_SCHEMA = "formtwin.sensor/1"

_PART_ID_MAX = 128


@dataclass(frozen=True)
class Reading:
    """One validated sensor message: ``value`` in internal units."""

    part_id: str
    sensor: str
    value: float
    timestamp: str | None = None

    def to_message(self) -> dict[str, Any]:
        """The reading as a ``formtwin.sensor/1`` JSON object."""
        msg: dict[str, Any] = {"schema": SENSOR_SCHEMA, "part_id": self.part_id,
                               "sensor": self.sensor, "value": self.value}
        if self.timestamp is not None:
            msg["timestamp"] = self.timestamp
        return msg


def parse_reading(payload: bytes, sensors: tuple[str, ...], max_bytes: int = 65536
                  ) -> Reading:
    """Parse and validate one sensor payload; ``sensors`` are the names the service fuses.

    Raises
    ------
    MessageError
        ``oversized``, ``malformed_json``, ``unknown_schema``, ``missing_field``,
        ``bad_field``, ``non_finite`` or ``unknown_sensor``, naming the field, the value and
        what was expected.
    """
    if len(payload) > max_bytes:
        raise MessageError("oversized", f"{len(payload)} bytes > limit {max_bytes}")
    return read_fast_then_exact(lambda fast: _reading(payload, sensors, fast))


def _reading(payload: bytes, sensors: tuple[str, ...], fast: bool) -> Reading | None:
    """:func:`parse_reading` after the size check, the JSON read ``fast`` or not; None
    where a fast read may differ from the standard library's (:data:`LONG_INT`)."""
    try:
        doc = loads(payload, fast)
    except MessageError:
        raise
    except (ValueError, RecursionError) as exc:
        raise MessageError("malformed_json", f"{type(exc).__name__}: {exc}"[:200]) from None
    if not isinstance(doc, dict):
        raise MessageError("malformed_json", f"top level is {type(doc).__name__}, not object")
    if doc.get("schema") != SENSOR_SCHEMA:
        raise MessageError("unknown_schema", f"schema {doc.get('schema')!r:.60}, expected "
                           f"{SENSOR_SCHEMA!r}")
    raw = doc.get("part_id")
    part_id = raw if isinstance(raw, str) and 0 < len(raw) <= _PART_ID_MAX \
        and raw.isprintable() else None
    for key in ("part_id", "sensor", "value"):
        if key not in doc:
            raise MessageError("missing_field", f"field {key!r} is required", part_id)
    if part_id is None:
        raise MessageError("bad_field", f"part_id must be a printable string of 1.."
                           f"{_PART_ID_MAX} characters, got {raw!r:.60}")
    sensor, value = doc["sensor"], doc["value"]
    if not isinstance(sensor, str):
        raise MessageError("bad_field", f"sensor must be a string, got {sensor!r:.40}",
                           part_id)
    if sensor not in sensors:
        raise MessageError("unknown_sensor", f"sensor {sensor!r:.60} is not fused by this "
                           f"service (tracker sensors: {', '.join(sensors) or 'none'})",
                           part_id)
    if type(value) not in (int, float):
        raise MessageError("bad_field", f"value must be a number, got {value!r:.40}", part_id)
    try:
        v = float(value)
    except OverflowError:
        raise MessageError("non_finite", "value is an integer too large for float64",
                           part_id) from None
    if not math.isfinite(v):
        raise MessageError("non_finite", f"value is {v}", part_id)
    ts = doc.get("timestamp")
    if fast and isinstance(ts, float) and abs(ts) >= LONG_INT:
        return None
    return Reading(part_id, sensor, v, None if ts is None else str(ts)[:64])


__all__ = ["SENSOR_SCHEMA", "Reading", "parse_reading"]
