"""Which OPC UA nodes make a stroke, and how their values become a stroke message.

The mapping (a TOML file, section ``[opcua]``, see docs/reference/opcua.md) names the press's nodes
by browse path below a root object or by NodeId. Its defaults follow OPC 40503-1 "OPC UA for
Metal Forming" (Release 1.00) where the companion specification has a name:

* ``PartInformation/CycleCount`` and ``PartInformation/PartId``: the two fields of its
  ``CyclicPartInformationDataType`` (cycle count and part id of the last produced part),
  exposed as child variables;
* ``StrokeForce/AnalogSignal`` and ``StrokeForce/CycleCount``: a ``CyclicProcessValueType``-like
  object whose ``AnalogSignal`` holds the stage-1 force curve. OPC 40503-1 has no node for a
  sampled force curve (its ``AnalogSignal`` is a scalar number), so formtwin uses this browse
  path for a Double array of the spec's samples, N; its ``CycleCount`` ties the curve to its
  stroke (the specification's "transactional context");
* ``Stage2Setting/Setpoint``: the stage-2 press setting as the ``Setpoint`` of a
  ``CyclicProcessValueType``-like object, in the spec's internal unit (mm).

Sensors besides the curve (``[opcua.sensors]``, sensor name -> browse path of an object):
each sensor object holds ``PartId`` (String) and ``AnalogSignal`` (Double, the value in
the measured quantity's internal unit), the press writing the part id first; each value
makes one ``formtwin.sensor/1`` payload (:class:`SensorAssembler`) for
:meth:`~formtwin.service.processor.Processor.handle_sensor`. OPC 40503-1 has no sensor
node of a part, so the layout mirrors its ``CyclicProcessValueType`` as the force curve's.

The press writes every mapped node once per stroke, the cycle counts last. formtwin
monitors each node with a queue (``queue_size``) and the ``StatusValueTimestamp`` trigger,
so every write is reported, in order, even when the value repeats (the same part id, the
same setting) and when several strokes fall into one publishing interval. The k-th values
of the nodes make the k-th stroke; the curve's ``CycleCount`` must equal the part
information's ``CycleCount`` (else the older side is dropped as an incomplete stroke and
counted with the cycle counts jumped in :attr:`StrokeAssembler.skipped`).

>>> m = OpcUaMapping()
>>> asm = StrokeAssembler(m)
>>> for key, value in [("part_id", "P-7"), ("stage2_setting", 0.1), ("force_curve", [0.0, 1.0]),
...                    ("force_cycle_count", 7)]:
...     asm.update(key, value)
>>> asm.take() is None  # the part information's cycle count has not arrived
True
>>> asm.update("cycle_count", 7)
>>> import json; doc = json.loads(asm.take()); doc["part_id"], doc["cycle"], doc["u"]
('P-7', 7, 0.1)
"""

from __future__ import annotations

import json
import logging
import math
import os
import tomllib
from collections import deque
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from formtwin.service.messages import STROKE_SCHEMA
from formtwin.service.sensors import SENSOR_SCHEMA

log = logging.getLogger(__name__)

#: the nodes of a stroke: key -> (default browse path, required, meaning)
NODES: dict[str, tuple[str, bool, str]] = {
    "cycle_count": ("PartInformation/CycleCount", True,
                    "cycle count of the last stroke (UInt32/UInt64); its change assembles a "
                    "stroke (OPC 40503-1 CyclicPartInformationDataType.CycleCount)"),
    "part_id": ("PartInformation/PartId", True,
                "part id of the last stroke (String; OPC 40503-1 "
                "CyclicPartInformationDataType.PartId)"),
    "force_curve": ("StrokeForce/AnalogSignal", True,
                    "stage-1 punch force on the spec's time grid (Double array, N); no node "
                    "in OPC 40503-1, formtwin's browse path"),
    "force_cycle_count": ("StrokeForce/CycleCount", False,
                          "cycle count of the force curve ('' : none, the curve is not "
                          "checked against the part information's)"),
    "stage2_setting": ("Stage2Setting/Setpoint", False,
                       "stage-2 press setting u (Double or Double array, mm; '' : none, the "
                       "nominal setting)"),
}


@dataclass(frozen=True)
class OpcUaMapping:
    """The mapping of a press's OPC UA nodes to a stroke (TOML section ``[opcua]``).

    Parameters
    ----------
    namespace : str
        Namespace URI of browse names written without an ``N:`` index prefix.
    root : str
        Browse path from the Objects folder to the press object (``/``-separated).
    nodes : dict
        Key of :data:`NODES` -> browse path below ``root`` (``PartInformation/PartId``),
        NodeId (``ns=2;s=Press.PartId``, ``nsu=URI;i=5``) or ``''`` for an optional node
        the press does not have.
    sensors : dict
        Sensor name (the spec's ``[[sensor]]``) -> browse path below ``root`` of the
        object holding its ``PartId`` and ``AnalogSignal`` (none by default).
    publishing_interval_ms : float
        Requested publishing interval of the subscription, ms.
    queue_size : int
        Values each monitored node queues between two publishes (strokes per publishing
        interval the service can take without loss).
    reconnect_min_s, reconnect_max_s : float
        First and largest wait between connection attempts, s (doubling in between).
    security : str
        ``POLICY,MODE,CERTIFICATE,PRIVATE_KEY[,SERVER_CERTIFICATE]`` for a press that signs
        or encrypts (asyncua's security string: a policy of :data:`POLICIES`, ``Sign`` or
        ``SignAndEncrypt``, this client's certificate (DER or PEM; its subject alternative
        name holds ``application_uri``) and private key); ``''``: none.
    user, password_file : str
        A user name for the press's user authentication and the file holding its
        password (else ``$FORMTWIN_OPCUA_PASSWORD``); ``''``: anonymous.
    application_uri : str
        This client's application URI (in its certificate).
    """

    namespace: str = "urn:formtwin:press"
    root: str = "Press"
    nodes: dict[str, str] = field(default_factory=lambda: {k: v[0] for k, v in NODES.items()})
    sensors: dict[str, str] = field(default_factory=dict)
    publishing_interval_ms: float = 20.0
    queue_size: int = 1000
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 10.0
    security: str = ""
    user: str = ""
    password_file: str = ""
    application_uri: str = "urn:formtwin:client"

    def __post_init__(self) -> None:
        unknown = sorted(set(self.nodes) - set(NODES))
        if unknown:
            raise ValueError(f"[opcua.nodes] {unknown[0]!r}: unknown node key, expected one "
                             f"of {', '.join(NODES)}")
        merged = {k: v[0] for k, v in NODES.items()} | dict(self.nodes)
        for key, path in merged.items():
            if not isinstance(path, str):
                raise ValueError(f"[opcua.nodes] {key} = {path!r}: expected a browse path "
                                 "or NodeId string")
            if NODES[key][1] and not path:
                raise ValueError(f"[opcua.nodes] {key} is required: expected a browse path "
                                 "or NodeId, got ''")
        object.__setattr__(self, "nodes", merged)
        for name, path in self.sensors.items():
            if not isinstance(path, str) or not path:
                raise ValueError(f"[opcua.sensors] {name} = {path!r}: expected the browse "
                                 "path of the sensor's object")
        for name in ("publishing_interval_ms", "reconnect_min_s", "reconnect_max_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not math.isfinite(value) or value <= 0:
                raise ValueError(f"[opcua] {name} = {value!r}: expected a number > 0")
        if isinstance(self.queue_size, bool) or not isinstance(self.queue_size, int) \
                or self.queue_size < 1:
            raise ValueError(f"[opcua] queue_size = {self.queue_size!r}: expected an integer "
                             ">= 1")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError(f"[opcua] reconnect_max_s = {self.reconnect_max_s} < "
                             f"reconnect_min_s = {self.reconnect_min_s}")
        _check_security(self)

    @classmethod
    def from_toml(cls, path: str | Path) -> OpcUaMapping:
        """Read the ``[opcua]`` section of a TOML file (absent keys keep their defaults)."""
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
        section = doc.get("opcua")
        if not isinstance(section, dict):
            raise ValueError(f"{path}: no [opcua] section")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(section) - known)
        if unknown:
            raise ValueError(f"{path}: [opcua] {unknown[0]!r}: unknown key, expected one of "
                             f"{', '.join(sorted(known))}")
        base = Path(path).parent  # files named in the section: relative to it
        if section.get("password_file"):
            section["password_file"] = str(base / section["password_file"])
        if section.get("security"):
            parts = [p.strip() for p in str(section["security"]).split(",")]
            section["security"] = ",".join(parts[:2] + [str(base / f) for f in parts[2:]])
        return cls(**section)

    def password(self) -> str:
        """The user's password: the file's first line, else ``$FORMTWIN_OPCUA_PASSWORD``."""
        if self.password_file:
            return Path(self.password_file).read_text(encoding="utf-8").splitlines()[0]
        return os.environ.get("FORMTWIN_OPCUA_PASSWORD", "")

    def active(self) -> dict[str, str]:
        """The configured nodes (optional ones set to ``''`` left out), and each sensor's
        two as ``sensor:<name>:part_id`` and ``sensor:<name>:value``."""
        out = {k: v for k, v in self.nodes.items() if v}
        for name, path in self.sensors.items():
            out[f"sensor:{name}:part_id"] = f"{path}/PartId"
            out[f"sensor:{name}:value"] = f"{path}/AnalogSignal"
        return out


#: the security policies a press may ask for (asyncua's names)
POLICIES = ("Basic256Sha256", "Aes128Sha256RsaOaep", "Aes256Sha256RsaPss")


def _check_security(m: OpcUaMapping) -> None:
    """``ValueError`` naming the key of a security setting that cannot work."""
    for name in ("security", "user", "password_file", "application_uri"):
        if not isinstance(getattr(m, name), str):
            raise ValueError(f"[opcua] {name} = {getattr(m, name)!r}: expected a string")
    if m.security:
        parts = [p.strip() for p in m.security.split(",")]
        if len(parts) not in (4, 5):
            raise ValueError(f"[opcua] security = {m.security!r}: expected POLICY,MODE,"
                             "CERTIFICATE,PRIVATE_KEY[,SERVER_CERTIFICATE]")
        if parts[0] not in POLICIES:
            raise ValueError(f"[opcua] security policy {parts[0]!r}: expected one of "
                             f"{', '.join(POLICIES)}")
        if parts[1] not in ("Sign", "SignAndEncrypt"):
            raise ValueError(f"[opcua] security mode {parts[1]!r}: expected Sign or "
                             "SignAndEncrypt")
        for f in parts[2:]:
            if not Path(f).is_file():
                raise ValueError(f"[opcua] security: no such file {f!r}")
    if m.password_file and not m.user:
        raise ValueError("[opcua] password_file needs a user")
    if m.password_file and not Path(m.password_file).is_file():
        raise ValueError(f"[opcua] password_file: no such file {m.password_file!r}")


def _jsonable(value: Any) -> Any:
    """An OPC UA variant's Python value as JSON (arrays as lists, None stays None)."""
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


class StrokeAssembler:
    """Queue node values; make a ``formtwin.stroke/1`` payload per complete stroke.

    The payload goes to :meth:`formtwin.service.processor.Processor.handle` like an MQTT
    message, so the same validation and rejection reasons apply (a missing part id is
    ``missing_field``, NaN ``non_finite``, a curve of the wrong length ``wrong_length``).
    """

    def __init__(self, mapping: OpcUaMapping) -> None:
        self.mapping = mapping
        self.keys = tuple(k for k, v in mapping.nodes.items() if v)  # the stroke's nodes
        self.queues: dict[str, deque[tuple[Any, datetime | None]]] = {
            k: deque() for k in self.keys}
        self.last_cycle: Any = None
        #: strokes not assembled: cycle counts jumped (incomplete strokes dropped, strokes
        #: made while disconnected)
        self.skipped = 0

    def reset(self) -> None:
        """Forget queued values (a new session reports every node's current value)."""
        for q in self.queues.values():
            q.clear()

    def update(self, key: str, value: Any, stamp: datetime | None = None) -> None:
        """Queue the value of node ``key`` (its source timestamp ``stamp``, optional)."""
        self.queues[key].append((value, stamp))

    def _drop(self, keys: tuple[str, ...]) -> None:
        for k in keys:
            if k in self.queues:
                self.queues[k].popleft()

    def take(self) -> bytes | None:
        """The payload of the oldest complete stroke not yet taken, else None."""
        force_side = ("force_curve", "force_cycle_count")
        info_side = tuple(k for k in self.keys if k not in force_side)
        while all(self.queues[k] for k in self.keys):
            cycle, stamp = self.queues["cycle_count"][0]
            if "force_cycle_count" in self.queues:
                tag = self.queues["force_cycle_count"][0][0]
                if tag != cycle:  # one side lost a stroke: drop the older side's values
                    older_force = cycle is not None and (tag is None or (
                        isinstance(tag, int) and isinstance(cycle, int) and tag < cycle))
                    log.warning("curve of cycle %s with part information of cycle %s: "
                                "dropping the older", tag, cycle)
                    self._drop(force_side if older_force else info_side)
                    continue
            values = {k: self.queues[k].popleft()[0] for k in self.keys}
            if cycle is None:  # a node not yet written (a server just started)
                continue
            if isinstance(cycle, int) and isinstance(self.last_cycle, int) \
                    and cycle > self.last_cycle + 1:
                self.skipped += cycle - self.last_cycle - 1
                log.warning("cycle count jumped from %d to %d: strokes of the press not "
                            "received", self.last_cycle, cycle)
            self.last_cycle = cycle
            return self._payload(values, stamp)
        return None

    @staticmethod
    def _payload(values: dict[str, Any], stamp: datetime | None) -> bytes:
        stamp = stamp or datetime.now(UTC)
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=UTC)
        doc: dict[str, Any] = {"schema": STROKE_SCHEMA, "cycle": values["cycle_count"],
                               "timestamp": stamp.isoformat().replace("+00:00", "Z")}
        if values.get("part_id") not in (None, ""):
            doc["part_id"] = values["part_id"]
        if values.get("force_curve") is not None:
            doc["force_N"] = _jsonable(values["force_curve"])
        if values.get("stage2_setting") not in (None, []):  # empty: the nominal setting
            doc["u"] = _jsonable(values["stage2_setting"])
        # NaN is written as the JSON literal so the validator rejects it as non_finite
        return json.dumps(doc, separators=(",", ":")).encode("utf-8")


class SensorAssembler:
    """Pair each sensor's ``PartId`` and ``AnalogSignal`` values in order; make a
    ``formtwin.sensor/1`` payload per pair (null values, a server's first state, skipped)."""

    def __init__(self, mapping: OpcUaMapping) -> None:
        self.queues: dict[str, dict[str, deque[Any]]] = {
            n: {"part_id": deque(), "value": deque()} for n in mapping.sensors}

    def reset(self) -> None:
        """Forget queued values (a new session reports every node's current value)."""
        for q in self.queues.values():
            q["part_id"].clear()
            q["value"].clear()

    def update(self, key: str, value: Any) -> bytes | None:
        """Queue the value of node ``sensor:<name>:<part_id|value>``; the payload of the
        sensor's oldest complete pair, else None."""
        _, name, what = key.split(":", 2)
        q = self.queues[name]
        q[what].append(value)
        while q["part_id"] and q["value"]:
            part_id, value = q["part_id"].popleft(), q["value"].popleft()
            if part_id in (None, "") or value is None:
                continue
            return json.dumps({"schema": SENSOR_SCHEMA, "part_id": part_id, "sensor": name,
                               "value": _jsonable(value)},
                              separators=(",", ":")).encode("utf-8")
        return None
