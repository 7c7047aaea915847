"""A simulated press serving its strokes over OPC UA (asyncua server; demo, tests, benchmark).

The address space follows :class:`~formtwin.service.opcua_map.OpcUaMapping`'s defaults::

    Objects/Press                      (namespace urn:formtwin:press)
        PartInformation/CycleCount     UInt32   written last for each stroke
        PartInformation/PartId         String
        StrokeForce/AnalogSignal       Double[n_t], N
        StrokeForce/CycleCount         UInt32
        Stage2Setting/Setpoint         Double or Double[], mm
        <sensor>/PartId, <sensor>/AnalogSignal   String, Double: a sensor's value of a
                                       part (``sensors``; mapped by ``[opcua.sensors]``)

All values are null until the first stroke. :meth:`SimulatedPress.write` writes one stroke
in the order a press would (part id, setting, curve, the curve's cycle count, then the part
information's cycle count); :meth:`SimulatedPress.restart` stops the server and starts an
empty one on the same port, as a press restarting its OPC UA server would.
"""

from __future__ import annotations

import asyncio
from datetime import UTC
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from formtwin.service.messages import Stroke
from formtwin.service.opcua_server import LoopThread, make_server

NAMESPACE = "urn:formtwin:press"


def self_signed(key: str, certificate: str, uri: str, server: bool = False) -> None:
    """Write a private key (PEM) and a self-signed certificate (DER) for application ``uri``
    (a server's or a client's), e.g. for a press that encrypts, in tests and trials."""
    import socket

    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    usage = [ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]
    asyncio.run(setup_self_signed_certificate(
        Path(key), Path(certificate), uri, socket.gethostname(), usage,
        {"countryName": "NL", "organizationName": "formtwin"}))


class SimulatedPress:
    """An asyncua server on ``host:port`` holding the last stroke (in a thread of its own).

    Parameters
    ----------
    port : int
        TCP port (the caller picks a free one).
    host : str
        Bind address.
    path : str
        Path of the endpoint URL.
    sensors : tuple of str
        Sensor objects to serve (browse names below ``Press``), written by
        :meth:`write_sensor`.
    certificate : (str, str), optional
        The server's certificate and private key files: then it accepts only
        Basic256Sha256 SignAndEncrypt connections (:func:`self_signed` makes a pair).
    users : dict, optional
        User name -> password: then it accepts only these users (no anonymous session).
    """

    def __init__(self, port: int, host: str = "127.0.0.1", path: str = "/formtwin/press",
                 sensors: tuple[str, ...] = (), certificate: tuple[str, str] | None = None,
                 users: dict[str, str] | None = None) -> None:
        self.certificate, self.users = certificate, users
        self.sensors = tuple(sensors)
        self.host, self.port = host, port
        self.url = f"opc.tcp://{host}:{port}{path}"
        self._loop = LoopThread("formtwin-sim-press")
        self._server: Any = None
        self._nodes: dict[str, Any] = {}

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> SimulatedPress:
        """Start the event loop thread (once) and the server; return self."""
        self._loop.start()
        self._call(self._start())
        return self

    def stop(self) -> None:
        """Stop the server (the thread keeps running for a restart)."""
        if self._server is not None:
            self._call(self._server.stop())
            self._server = None

    def restart(self, down_s: float = 0.0) -> None:
        """Stop the server, stay down ``down_s`` seconds, start an empty one."""
        import time

        self.stop()
        time.sleep(down_s)
        self._call(self._start())

    def close(self) -> None:
        """Stop the server and the thread."""
        self.stop()
        self._loop.close()

    def __enter__(self) -> SimulatedPress:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, coro: Any, timeout: float = 30.0) -> Any:
        return self._loop.call(coro, timeout)

    async def _start(self) -> None:
        from asyncua import ua

        server = await make_server(self.url, "formtwin simulated press", self.certificate,
                                   self.users)
        ns = await server.register_namespace(NAMESPACE)
        press = await server.nodes.objects.add_object(ns, "Press")
        info = await press.add_object(ns, "PartInformation")
        force = await press.add_object(ns, "StrokeForce")
        setting = await press.add_object(ns, "Stage2Setting")
        VT = ua.VariantType

        async def var(parent: Any, name: str, kind: Any) -> Any:  # null until a stroke
            return await parent.add_variable(ns, name, ua.Variant(),
                                             datatype=ua.NodeId(kind.value))

        self._nodes = {
            "cycle_count": await var(info, "CycleCount", VT.UInt32),
            "part_id": await var(info, "PartId", VT.String),
            "force_curve": await var(force, "AnalogSignal", VT.Double),
            "force_cycle_count": await var(force, "CycleCount", VT.UInt32),
            "stage2_setting": await var(setting, "Setpoint", VT.Double),
        }
        for name in self.sensors:
            obj = await press.add_object(ns, name)
            self._nodes[f"{name}:part_id"] = await var(obj, "PartId", VT.String)
            self._nodes[f"{name}:value"] = await var(obj, "AnalogSignal", VT.Double)
        await server.start()
        self._server = server

    @classmethod
    def from_url(cls, url: str, sensors: tuple[str, ...] = ()) -> SimulatedPress:
        """The press at ``opc.tcp://HOST:PORT[/PATH]`` (with ``sensors``' objects)."""
        parts = urlsplit(url)
        if parts.scheme != "opc.tcp" or not parts.hostname or not parts.port:
            raise ValueError(f"press URL {url!r}: expected opc.tcp://HOST:PORT[/PATH]")
        return cls(parts.port, parts.hostname, parts.path, sensors)

    def monitored(self) -> int:
        """Number of monitored items clients hold on the server (0: nobody subscribed)."""
        service = getattr(getattr(self._server, "iserver", None), "subscription_service",
                          None)
        subs = list(getattr(service, "subscriptions", {}).values())
        return sum(len(getattr(s.monitored_item_srv, "_monitored_items", {})) for s in subs)

    # ------------------------------------------------------------------ strokes
    def write(self, stroke: Stroke | dict[str, Any]) -> None:
        """Write one stroke: a :class:`Stroke`, or a dict with keys ``part_id``, ``cycle``,
        ``force_N``, ``u`` (a part id of None is written as ``''``, a setting of None as
        an empty array: the nominal setting;
        a bad value is written as given, to test the service's validation)."""
        if isinstance(stroke, Stroke):
            stroke = {"part_id": stroke.part_id, "cycle": stroke.cycle,
                      "force_N": [float(v) for v in stroke.force_N],
                      "u": None if stroke.u is None else [float(v) for v in stroke.u]}
        self._call(self._write(stroke))

    async def _write(self, s: dict[str, Any]) -> None:
        from asyncua import ua

        VT = ua.VariantType
        u = s.get("u")
        if isinstance(u, list) and len(u) == 1:
            u = u[0]
        now = ua.DateTime.now(UTC)  # one acquisition time for the stroke's values
        values = (("part_id", s.get("part_id"), VT.String), ("stage2_setting", u, VT.Double),
                  ("force_curve", s.get("force_N"), VT.Double),
                  ("force_cycle_count", s.get("cycle"), VT.UInt32),
                  ("cycle_count", s.get("cycle"), VT.UInt32))
        for key, value, kind in values:  # the server's own write, as a PLC's
            if value is None:  # a press without a part id / setting for the stroke
                value = "" if key == "part_id" else []
            dv = ua.DataValue(ua.Variant(value, kind), SourceTimestamp=now,
                              ServerTimestamp=now)
            await self._server.write_attribute_value(self._nodes[key].nodeid, dv)

    def write_sensor(self, sensor: str, part_id: str, value: float) -> None:
        """Write one value of sensor object ``sensor`` (its part id first, as a press)."""
        self._call(self._write_sensor(sensor, part_id, value))

    async def _write_sensor(self, sensor: str, part_id: str, value: float) -> None:
        from asyncua import ua

        now = ua.DateTime.now(UTC)
        for key, v, kind in ((f"{sensor}:part_id", part_id, ua.VariantType.String),
                             (f"{sensor}:value", value, ua.VariantType.Double)):
            dv = ua.DataValue(ua.Variant(v, kind), SourceTimestamp=now, ServerTimestamp=now)
            await self._server.write_attribute_value(self._nodes[key].nodeid, dv)
