"""The estimates as OPC UA variables of formtwin's own server (``serve --opcua-results``).

A press line's PLC or SCADA that speaks OPC UA reads formtwin's estimates, the predicted
final angle and the suggested press setting from an asyncua server run by the service,
beside the MQTT topics (which stay the record: every estimate, alarm and error). Each
accepted product overwrites the variables (one source timestamp for all; ``Seq`` and
``PartId`` written last, so a client that subscribes to ``PartId`` reads a complete
product); a rejected or gated message sets ``LastError``. The address space (namespace
``urn:formtwin:results``), all values null until the first product::

    Objects/Formtwin
        PartId String, Seq Int64, Index Int64, CycleCount Int64
        Health String ("ok", "degraded", "no_fit"), ModelMismatch Boolean, Ess Double
        Estimate/<name>/Mean, Estimate/<name>/Std      Double, each of spec.augmented
        Outputs/<name>/Mean, Outputs/<name>/Std         Double, each of spec.outputs
        FinalAngle/Predicted, /Low90, /High90           Double, with a camera fused
        Control/Setpoint Double[] (the spec's controls, mm), Control/Limited Boolean,
        Control/PredictedDeg Double                     with a controller
        LastAlarm String (the alarm message, JSON), LastError String (reason: detail)

The service's thread only queues each product's values (no waiting); one task of the
server's event loop writes them in order (0.3-0.6 ms of CPU per product for the demonstrator's
18 variables and 2 outputs). Security: none (mode None, anonymous clients), or with a
certificate only signed and encrypted sessions, with users only those users.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from datetime import UTC
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from formtwin.service.opcua_server import LoopThread, make_server
from formtwin.service.processor import Outcome

log = logging.getLogger(__name__)

NAMESPACE = "urn:formtwin:results"


class ResultsServer:
    """An asyncua server at ``url`` (``opc.tcp://HOST:PORT[/PATH]``) holding the last
    product's estimate of a service with augmented variables ``names`` and outputs
    ``outputs`` (names), in a thread of its own. :meth:`on_outcome` is the processor's
    listener; ``listener`` (another one, e.g. the live page's) is called first.

    ``certificate`` (certificate and private key files): only Basic256Sha256
    SignAndEncrypt sessions; ``users`` (name -> password): only these users. Neither:
    security mode None, anonymous clients."""

    def __init__(self, url: str, names: tuple[str, ...], outputs: tuple[str, ...],
                 certificate: tuple[str, str] | None = None,
                 users: dict[str, str] | None = None) -> None:
        parts = urlsplit(url)
        if parts.scheme != "opc.tcp" or not parts.hostname or not parts.port:
            raise ValueError(f"--opcua-results {url!r}: expected opc.tcp://HOST:PORT[/PATH]")
        for f in certificate or ():
            if not Path(f).is_file():
                raise ValueError(f"--opcua-results-security: no such file {f!r}")
        self.certificate, self.users = certificate, users
        self.url, self.names, self.outputs = url, tuple(names), tuple(outputs)
        self.listener: Any = None
        self.written = 0  #: products written (for tests and the status line)
        self._loop = LoopThread("formtwin-opcua-results")
        self._server: Any = None
        self._queue: asyncio.Queue[list[tuple[str, Any, str]]] | None = None
        self._writer: asyncio.Task[None] | None = None
        self._nodes: dict[str, Any] = {}

    def start(self) -> ResultsServer:
        """Start the server in its thread; return self (``OSError`` if the port is taken)."""
        self._loop.start()
        try:
            self._loop.call(self._start())
        except Exception:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Write what is queued, stop the server and its thread."""
        if self._loop.loop is not None:
            self._loop.call(self._stop())
            self._loop.close()

    def on_outcome(self, out: Outcome) -> None:
        """Queue the outcome's values for the server (called by the processor)."""
        if self.listener is not None:
            self.listener(out)
        values = self.values(out)
        if values and self._loop.loop is not None and self._queue is not None:
            self._loop.post(self._queue.put_nowait, values)

    def values(self, out: Outcome) -> list[tuple[str, Any, str]]:
        """``(node key, value, OPC UA type)`` of an outcome, in the order they are written."""
        m = out.message
        if out.is_error:
            return [("LastError", f"{m.get('reason', out.kind)}: {m.get('detail', '')}"
                     f" (part {out.part_id})", "String")]
        if out.kind != "accepted":
            return []
        vals: list[tuple[str, Any, str]] = []
        for key in ("mean", "std"):
            d = m.get(key) or {}
            vals += [(f"Estimate/{n}/{key.title()}", _num(d.get(n)), "Double")
                     for n in self.names]
        for j, n in enumerate(self.outputs):
            for key, col in (("Mean", "angles_mean"), ("Std", "angles_std")):
                arr = m.get(col) or []
                vals.append((f"Outputs/{n}/{key}", _num(arr[j] if j < len(arr) else None),
                             "Double"))
        final = m.get("final")
        if final:
            lo, hi = final.get("interval90_deg") or (None, None)
            vals += [("FinalAngle/Predicted", _num(final.get("predicted_deg")), "Double"),
                     ("FinalAngle/Low90", _num(lo), "Double"),
                     ("FinalAngle/High90", _num(hi), "Double")]
        ctl = m.get("control")
        if ctl:
            vals += [("Control/Setpoint", [_num(v) for v in ctl.get("u") or []], "Double"),
                     ("Control/Limited", bool(ctl.get("limited")), "Boolean"),
                     ("Control/PredictedDeg", _num(ctl.get("final_angle_deg")), "Double")]
        for alarm in out.alarms:
            vals.append(("LastAlarm", json.dumps(alarm, allow_nan=False, default=str),
                         "String"))
        flags = m.get("flags") or {}
        vals += [("Health", str(m.get("health") or ""), "String"),
                 ("ModelMismatch", bool(flags.get("model_mismatch")), "Boolean"),
                 ("Ess", _num(m.get("ess")), "Double"),
                 ("Index", int(m.get("index", -1)), "Int64"),
                 ("CycleCount", int(m.get("cycle") or 0), "Int64"),
                 ("Seq", int(m.get("seq") or 0), "Int64"),
                 ("PartId", str(m.get("part_id") or ""), "String")]
        return vals

    # ------------------------------------------------------------------ the loop's side
    async def _start(self) -> None:
        from asyncua import ua

        server = await make_server(self.url, "formtwin estimates", self.certificate, self.users)
        ns = await server.register_namespace(NAMESPACE)
        root = await server.nodes.objects.add_object(ns, "Formtwin")
        folders: dict[str, Any] = {"": root}

        async def folder(path: str) -> Any:
            if path not in folders:
                above, _, name = path.rpartition("/")
                folders[path] = await (await folder(above)).add_object(ns, name)
            return folders[path]

        async def var(path: str, kind: str) -> None:
            above, _, leaf = path.rpartition("/")
            self._nodes[path] = await (await folder(above)).add_variable(
                ns, leaf, ua.Variant(),  # a built-in type's id is its variant type's number
                datatype=ua.NodeId(getattr(ua.VariantType, kind).value))

        for n in self.names:
            for key in ("Mean", "Std"):
                await var(f"Estimate/{n}/{key}", "Double")
        for n in self.outputs:
            for key in ("Mean", "Std"):
                await var(f"Outputs/{n}/{key}", "Double")
        for path, kind in (("FinalAngle/Predicted", "Double"), ("FinalAngle/Low90", "Double"),
                           ("FinalAngle/High90", "Double"), ("Control/Setpoint", "Double"),
                           ("Control/Limited", "Boolean"), ("Control/PredictedDeg", "Double"),
                           ("LastAlarm", "String"), ("LastError", "String"),
                           ("Health", "String"), ("ModelMismatch", "Boolean"),
                           ("Ess", "Double"), ("Index", "Int64"), ("CycleCount", "Int64"),
                           ("Seq", "Int64"), ("PartId", "String")):
            await var(path, kind)
        await server.start()
        self._server = server
        self._queue = asyncio.Queue()
        self._writer = asyncio.get_running_loop().create_task(self._write_forever())

    async def _write_forever(self) -> None:
        assert self._queue is not None
        while True:
            values = await self._queue.get()
            try:
                await self._write(values)
                self.written += 1
            except Exception:  # a client's problem must not stop the writes
                log.exception("OPC UA results: writing failed")
            finally:
                self._queue.task_done()

    async def _write(self, values: list[tuple[str, Any, str]]) -> None:
        from asyncua import ua

        now = ua.DateTime.now(UTC)
        for key, value, kind in values:
            dv = ua.DataValue(ua.Variant(value, getattr(ua.VariantType, kind)),
                              SourceTimestamp=now, ServerTimestamp=now)
            await self._server.write_attribute_value(self._nodes[key].nodeid, dv)

    async def _stop(self) -> None:
        if self._queue is not None and self._writer is not None:
            await self._queue.join()
            self._writer.cancel()
        if self._server is not None:
            await self._server.stop()
            self._server = None


def read_users(path: str | Path) -> dict[str, str]:
    """``user:password`` lines of a file (blank lines and ``#`` comments skipped);
    ``ValueError`` naming a line that is not one."""
    users: dict[str, str] = {}
    for i, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        name, sep, password = line.partition(":")
        if not sep or not name.strip() or not password:
            raise ValueError(f"{path}: line {i}: expected user:password")
        users[name.strip()] = password
    return users


def _num(v: Any) -> float:
    """A message's number as a Double (null: NaN)."""
    return math.nan if v is None else float(v)


__all__ = ["NAMESPACE", "ResultsServer", "read_users"]
