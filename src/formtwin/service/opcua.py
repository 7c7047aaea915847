"""The OPC UA source: a press's stroke nodes in, estimates out on MQTT.

:class:`OpcUaSource` subscribes (asyncua, data-change monitored items) to the nodes of
:class:`~formtwin.service.opcua_map.OpcUaMapping` in a thread of its own and turns every
complete stroke into a ``formtwin.stroke/1`` payload, and every value of a mapped sensor
(``[opcua.sensors]``) into a ``formtwin.sensor/1`` one. :class:`OpcUaService` hands each
payload to the same :meth:`~formtwin.service.processor.Processor.handle` (or
``handle_sensor``) as the MQTT source (same validation, rejection reasons, store and
estimates) and publishes the outcome on the same MQTT topics (QoS 1).

Reconnection. When the connection is lost (the server restarts, the network drops) the
source reconnects with a doubling wait between ``reconnect_min_s`` and ``reconnect_max_s``,
resolves the nodes again and subscribes again. A new subscription first reports the nodes'
current values, i.e. the last stroke again: the store recognises it (same part id, same
curve) and answers it with the stored estimate, flagged ``redelivered``, without counting it
twice. Strokes the press made while the connection was down are not recovered: data-change
subscriptions keep no history across a lost session (:attr:`StrokeAssembler.skipped` counts
the cycle counts that were jumped).
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as mqtt

from formtwin.service.messages import dumps
from formtwin.service.mqtt import BrokerConfig, Topics, make_client
from formtwin.service.opcua_map import OpcUaMapping, SensorAssembler, StrokeAssembler
from formtwin.service.processor import Outcome, Processor

log = logging.getLogger(__name__)

_NODEID_PREFIXES = ("ns=", "nsu=", "i=", "s=", "g=", "b=")


async def _resolve(client: Any, mapping: OpcUaMapping) -> dict[str, Any]:
    """The mapped nodes of a connected asyncua client: key -> Node."""
    from asyncua import ua

    ns = await client.get_namespace_index(mapping.namespace) if mapping.namespace else None

    def qualify(path: str) -> list[str]:
        parts = [p for p in path.split("/") if p]
        if ns is None or not parts:
            return parts
        return [p if ":" in p else f"{ns}:{p}" for p in parts]

    root = client.nodes.objects
    if mapping.root:
        root = await root.get_child(qualify(mapping.root))
    nodes: dict[str, Any] = {}
    for key, ref in mapping.active().items():
        if ref.startswith(_NODEID_PREFIXES):
            nid = ua.NodeId.from_string(ref)
            uri = getattr(nid, "NamespaceUri", None)
            if uri:
                nid = ua.NodeId(nid.Identifier, await client.get_namespace_index(uri),
                                nid.NodeIdType)
            nodes[key] = client.get_node(nid)
        else:
            nodes[key] = await root.get_child(qualify(ref))
    return nodes


def _requests(nodes: list[Any], queue_size: int) -> list[Any]:
    """Monitored-item requests: every write reported (``StatusValueTimestamp``, so a value
    written again is a new sample), up to ``queue_size`` values queued per publish."""
    from asyncua import ua
    from asyncua.ua.attribute_ids import AttributeIds

    out = []
    for handle, node in enumerate(nodes, start=1):
        params = ua.MonitoringParameters(
            ClientHandle=handle, SamplingInterval=0.0, QueueSize=queue_size,
            DiscardOldest=True,
            Filter=ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp))
        out.append(ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(NodeId=node.nodeid,
                                         AttributeId=AttributeIds.Value),
            MonitoringMode=ua.MonitoringMode.Reporting, RequestedParameters=params))
    return out


class _Handler:
    """asyncua subscription handler: every data change into the assembler."""

    def __init__(self, source: OpcUaSource, keys: dict[Any, str]) -> None:
        self.source, self.keys = source, keys

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        """A monitored node changed: record it; queue the stroke once it is complete."""
        key = self.keys.get(node.nodeid)
        if key is None:
            return
        dv = getattr(getattr(data, "monitored_item", None), "Value", None)
        stamp = getattr(dv, "SourceTimestamp", None) or getattr(dv, "ServerTimestamp", None)
        if key.startswith("sensor:"):
            reading = self.source.sensor_assembler.update(key, val)
            if reading is not None:
                self.source.strokes.put((True, reading))
            return
        asm = self.source.assembler
        asm.update(key, val, stamp)
        while (payload := asm.take()) is not None:
            self.source.strokes.put((False, payload))

    def status_change_notification(self, status: Any) -> None:
        """The server reported a subscription status (e.g. shutting down)."""
        log.info("OPC UA subscription status: %s", status)


class OpcUaSource:
    """Subscribe to a press's stroke nodes; queue each complete stroke's payload.

    Parameters
    ----------
    url : str
        ``opc.tcp://host:port[/path]`` of the press's server.
    mapping : OpcUaMapping
        Which nodes make a stroke.
    request_timeout : float
        Timeout of one OPC UA request, s.
    """

    def __init__(self, url: str, mapping: OpcUaMapping, request_timeout: float = 4.0) -> None:
        if not url.startswith("opc.tcp://"):
            raise ValueError(f"--source {url!r}: expected opc.tcp://HOST:PORT")
        self.url = url
        self.mapping = mapping
        self.request_timeout = request_timeout
        self.assembler = StrokeAssembler(mapping)
        self.sensor_assembler = SensorAssembler(mapping)
        #: ``(is a sensor message, payload)`` in the order the values came
        self.strokes: queue.Queue[tuple[bool, bytes]] = queue.Queue()
        self.connected = threading.Event()
        #: number of sessions established (1 + reconnects)
        self.sessions = 0
        self.last_error: str | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None

    def start(self) -> None:
        """Start the client thread (connects, subscribes and reconnects until stopped)."""
        ready = threading.Event()

        def main() -> None:
            async def run() -> None:
                self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
                ready.set()
                await self._serve()

            asyncio.run(run())

        self._thread = threading.Thread(target=main, daemon=True, name="formtwin-opcua")
        self._thread.start()
        ready.wait(10.0)

    def stop(self) -> None:
        """Disconnect and end the client thread."""
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(10.0)

    async def _serve(self) -> None:
        assert self._stop is not None
        delay = self.mapping.reconnect_min_s
        while not self._stop.is_set():
            try:
                await self._session()
                delay = self.mapping.reconnect_min_s
            except Exception as exc:  # unreachable, refused, nodes missing: retry
                self.last_error = f"{type(exc).__name__}: {exc}"[:300]
                log.warning("OPC UA %s: %s; retrying in %.1f s", self.url, self.last_error,
                            delay)
            self.connected.clear()
            try:
                await asyncio.wait_for(self._stop.wait(), delay)
            except TimeoutError:
                pass
            delay = min(2.0 * delay, self.mapping.reconnect_max_s)

    async def _session(self) -> None:
        """One connection: resolve, subscribe, wait for loss or stop."""
        from asyncua.client.client import Client

        assert self._stop is not None
        client = Client(self.url, timeout=self.request_timeout, watchdog_intervall=1.0)
        lost = asyncio.Event()

        async def on_lost(exc: Exception) -> None:
            self.last_error = f"connection lost: {exc!r}"[:300]
            lost.set()

        client.connection_lost_callback = on_lost
        m = self.mapping
        if m.security:  # sign or encrypt with this client's certificate
            client.application_uri = m.application_uri
            await client.set_security_string(m.security)
        if m.user:
            client.set_user(m.user)
            client.set_password(m.password())
        await client.connect()
        try:
            nodes = await _resolve(client, self.mapping)
            self.assembler.reset()
            self.sensor_assembler.reset()
            handler = _Handler(self, {n.nodeid: k for k, n in nodes.items()})
            sub = await client.create_subscription(self.mapping.publishing_interval_ms,
                                                   handler)
            results = await sub.create_monitored_items(
                _requests(list(nodes.values()), self.mapping.queue_size))
            for key, res in zip(nodes, results, strict=True):
                if not isinstance(res, int):
                    raise ConnectionError(f"monitoring node {key!r} refused: {res}")
            self.sessions += 1
            self.connected.set()
            log.info("OPC UA %s: subscribed to %d nodes (session %d)", self.url, len(nodes),
                     self.sessions)
            waits = [asyncio.ensure_future(e.wait()) for e in (lost, self._stop)]
            try:
                await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for w in waits:
                    w.cancel()
            if lost.is_set():
                log.warning("OPC UA %s: %s; reconnecting", self.url, self.last_error)
        finally:
            self.connected.clear()
            try:
                await client.disconnect()
            except Exception:  # the server is gone already
                log.debug("OPC UA disconnect failed", exc_info=True)


class OpcUaService:
    """Process the strokes of an :class:`OpcUaSource`; publish outcomes on MQTT.

    The interface of :class:`~formtwin.service.mqtt.MqttService` (``run``, ``handled``,
    ``busy_s``, ``connected``, ``publish_alarm``), so ``formtwin serve`` uses either.

    Parameters
    ----------
    processor : Processor
    source : OpcUaSource
    broker : BrokerConfig
        Where the estimates, errors and alarms go.
    topics : Topics
        Their topics (``topics.strokes`` is not subscribed).
    client_id : str
        MQTT client id of the publisher.
    """

    def __init__(self, processor: Processor, source: OpcUaSource, broker: BrokerConfig,
                 topics: Topics, client_id: str = "formtwin-serve") -> None:
        self.processor = processor
        self.source = source
        self.broker = broker
        self.topics = topics
        self.client = make_client(broker, client_id)
        self.connected = source.connected
        self.handled = 0
        self.busy_s = 0.0
        self._last: mqtt.MQTTMessageInfo | None = None

    def publish_alarm(self, message: dict[str, Any]) -> None:
        """Publish an alarm message on the alarms topic, QoS 1 (thread-safe)."""
        self.client.publish(self.topics.alarms or self.topics.errors, dumps(message), qos=1)

    def _publish(self, out: Outcome) -> None:
        for alarm in out.alarms:
            self.client.publish(self.topics.alarms or self.topics.errors, dumps(alarm), qos=1)
        for note in out.notices:
            self.client.publish(self.topics.errors, dumps(note), qos=1)
        topic = self.topics.errors if out.is_error else self.topics.results
        self._last = self.client.publish(topic, out.payload or dumps(out.message), qos=1)

    def _connect_broker(self, timeout: float) -> None:
        answered = threading.Event()
        refused: list[str] = []

        def on_connect(c: mqtt.Client, u: Any, f: Any, rc: Any, p: Any = None) -> None:
            if getattr(rc, "is_failure", False):
                refused.append(str(rc))
            answered.set()

        self.client.on_connect = on_connect
        self.client.connect_async(self.broker.host, self.broker.port, self.broker.keepalive)
        self.client.loop_start()
        if not answered.wait(timeout) or refused:
            raise ConnectionError(f"no connection to the broker at {self.broker.host}:"
                                  f"{self.broker.port} within {timeout:g} s"
                                  + (f": {refused[0]}" if refused else ""))

    def run(self, stop: threading.Event, timeout: float = 10.0,
            on_connected: Callable[[], None] | None = None) -> None:
        """Connect to the broker and the press, serve until ``stop`` is set.

        Raises
        ------
        ConnectionError
            If the broker or the OPC UA server cannot be reached within ``timeout`` s.
        RuntimeError
            If processing a stroke failed unexpectedly (e.g. the store's disk is full).
        """
        self.source.start()
        try:
            self._connect_broker(timeout)
            if not self.source.connected.wait(timeout):
                raise ConnectionError(f"no subscription on the OPC UA server {self.source.url}"
                                      f" within {timeout:g} s: {self.source.last_error}")
            if on_connected is not None:
                on_connected()
            while not stop.is_set():
                try:
                    sensor, payload = self.source.strokes.get(timeout=0.2)
                except queue.Empty:
                    continue
                t0 = time.perf_counter()
                handle = self.processor.handle_sensor if sensor else self.processor.handle
                try:
                    out = handle(payload, self.source.url)
                except Exception as exc:  # storage failure: stop the service
                    raise RuntimeError(f"processing failed, service stopped: {exc!r}") from exc
                self._publish(out)
                self.handled += 1
                self.busy_s += time.perf_counter() - t0
        finally:
            self.source.stop()
            if self._last is not None and self.client.is_connected():
                self._last.wait_for_publish(5.0)  # the answers in flight reach the broker
            self.client.disconnect()
            self.client.loop_stop()
