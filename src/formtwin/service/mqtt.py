"""paho-mqtt plumbing: broker address, security options, the serving loop and replay.

Delivery guarantees. The service subscribes with QoS 1 on a persistent session (fixed
client id, ``clean_session=False``) and acknowledges a stroke only *after* its outcome is
committed to the store and the broker has acknowledged its answer (estimate or error;
paho's ``manual_ack``). A service killed at any instant therefore gets every
unacknowledged stroke again from the broker when it restarts; the store recognises the ones
it had already committed (same part id, same curve) and answers them with the stored
estimate instead of counting them twice. Answers are published with QoS 1: a kill can
double an answer but never lose one, and consumers de-duplicate by ``part_id``.

Sensor messages (:mod:`formtwin.service.sensors`) come on their own topic,
:attr:`Topics.sensors`, on the same session and with the same guarantees.

Only its own input topics. A persistent session keeps its subscriptions and queued
messages across runs: a session id once used on another topic (a ``serve --check`` on a
test topic, an older configuration) would deliver that topic's strokes to this service.
A message on any other topic than :attr:`Topics.inputs` is acknowledged (so the broker
drops it), never processed, counted in :attr:`MqttService.foreign`, and its topic is
unsubscribed from the session. ``serve --check`` runs on a clean session of its own id
(:func:`check_client_id`), which the broker discards when the check disconnects.
"""

from __future__ import annotations

import logging
import os
import ssl
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from formtwin.service.messages import Stroke, dumps
from formtwin.service.processor import Outcome, Processor
from formtwin.service.sensors import Reading

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BrokerConfig:
    """Where and how to connect.

    Parameters
    ----------
    host, port : broker address.
    tls : connect with TLS (``mqtts://`` URLs set it).
    ca_file, cert_file, key_file : CA bundle and client certificate/key (PEM) for TLS.
    username, password : broker credentials (the CLI reads the password from an
        environment variable or a file, never from the command line).
    keepalive : MQTT keepalive, s.
    """

    host: str = "127.0.0.1"
    port: int = 1883
    tls: bool = False
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    username: str | None = None
    password: str | None = None
    keepalive: int = 30

    @classmethod
    def from_url(cls, url: str, **kwargs: Any) -> BrokerConfig:
        """Parse ``mqtt://host:port`` or ``mqtts://host:port``.

        >>> BrokerConfig.from_url("mqtts://broker.local:8883").tls
        True
        """
        parts = urlsplit(url)
        if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
            raise ValueError(f"broker URL {url!r}: expected mqtt://HOST[:PORT] or "
                             "mqtts://HOST[:PORT]")
        if parts.username or parts.password:
            raise ValueError("broker URL must not carry credentials; use --username and "
                             "FORMTWIN_MQTT_PASSWORD / --password-file")
        tls_flag = bool(kwargs.pop("tls", False))
        tls = parts.scheme == "mqtts" or tls_flag
        port = parts.port or (8883 if tls else 1883)
        return cls(host=parts.hostname, port=port, tls=tls, **kwargs)


def make_client(cfg: BrokerConfig, client_id: str, *, persistent: bool = False,
                manual_ack: bool = False) -> mqtt.Client:
    """A paho client (MQTT 3.1.1, callback API v2) configured from ``cfg``."""
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id,
                         clean_session=not persistent, protocol=mqtt.MQTTv311,
                         manual_ack=manual_ack)
    if cfg.username is not None:
        client.username_pw_set(cfg.username, cfg.password)
    if cfg.tls:
        client.tls_set(ca_certs=cfg.ca_file, certfile=cfg.cert_file, keyfile=cfg.key_file,
                       cert_reqs=ssl.CERT_REQUIRED, tls_version=ssl.PROTOCOL_TLS_CLIENT)
    client.max_inflight_messages_set(100)
    client.max_queued_messages_set(0)
    return client


@dataclass(frozen=True)
class Topics:
    """Input, results, errors and alarms topics; by default siblings of the input topic.

    >>> Topics.from_input("plant/line1/press1/stroke").alarms
    'plant/line1/press1/alarms'
    """

    strokes: str
    results: str
    errors: str
    alarms: str = ""
    #: sensor messages (:mod:`formtwin.service.sensors`); "" : none
    sensors: str = ""

    @classmethod
    def from_input(cls, topic: str, results: str | None = None,
                   errors: str | None = None, alarms: str | None = None,
                   sensors: str | None = None) -> Topics:
        """Topics from the stroke topic and optional results/errors/alarms/sensor topics
        (default: siblings ``estimate``, ``errors``, ``alarms`` and ``sensor``)."""
        if not topic or any(c in topic for c in "#+\x00"):
            raise ValueError(f"topic {topic!r}: expected a plain topic without wildcards")
        base = topic.rsplit("/", 1)[0] + "/" if "/" in topic else ""
        return cls(topic, results or base + "estimate", errors or base + "errors",
                   alarms or base + "alarms", sensors or base + "sensor")

    @property
    def inputs(self) -> tuple[str, ...]:
        """The topics the service subscribes to: strokes, and sensor messages if any."""
        return (self.strokes, self.sensors) if self.sensors else (self.strokes,)


class MqttService:
    """Subscribe to strokes, process them, publish outcomes, acknowledge after commit.

    Parameters
    ----------
    processor : Processor
    broker : BrokerConfig
    topics : Topics
    client_id : str
        Fixed id of the persistent session (keep it across restarts).
    """

    def __init__(self, processor: Processor, broker: BrokerConfig, topics: Topics,
                 client_id: str = "formtwin-serve", persistent: bool = True) -> None:
        self.processor = processor
        self.topics = topics
        self.client_id = client_id
        self.client = make_client(broker, client_id, persistent=persistent, manual_ack=True)
        #: messages on other topics than the stroke topic: acknowledged, not processed
        self.foreign = 0
        self._dropped: set[str] = set()
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        self.client.on_subscribe = self._on_subscribe
        self.client.on_publish = self._on_publish
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[int, int]] = {}
        self.client.on_disconnect = self._on_disconnect
        self.connected = threading.Event()
        self._answered = threading.Event()
        self.refused: str | None = None
        self.fatal: BaseException | None = None
        self.broker = broker
        self.handled = 0
        self.busy_s = 0.0

    def publish_alarm(self, message: dict[str, Any]) -> None:
        """Publish an alarm message (an acknowledgement from the live page) on the alarms
        topic, QoS 1 (paho queues it while the broker is away; thread-safe)."""
        self.client.publish(self.topics.alarms or self.topics.errors, dumps(message), qos=1)

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, rc: Any,
                    props: Any = None) -> None:
        if getattr(rc, "is_failure", False):
            log.error("broker refused the connection: %s", rc)
            self.refused = str(rc)
            self._answered.set()
            return
        client.subscribe([(t, 1) for t in self.topics.inputs])
        log.info("connected to %s:%d, subscribing to %s", self.broker.host, self.broker.port,
                 ", ".join(self.topics.inputs))

    def _on_subscribe(self, client: mqtt.Client, userdata: Any, mid: int, rcs: Any,
                      props: Any = None) -> None:
        if any(getattr(rc, "is_failure", False) for rc in rcs):
            log.error("broker refused the subscription to %s: %s", self.topics.inputs, rcs)
            self.refused = f"subscription refused: {rcs}"
            self._answered.set()
            return
        self.connected.set()
        self._answered.set()

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, rc: Any,
                       props: Any = None) -> None:
        self.connected.clear()
        with self._lock:  # the broker redelivers unacknowledged strokes after a reconnect
            self._pending.clear()
        if getattr(rc, "is_failure", True):
            log.warning("disconnected from broker (%s); paho reconnects", rc)
        else:
            log.info("disconnected from broker (%s)", rc)

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: mqtt.MQTTMessage) -> None:
        if self.fatal is not None:
            return  # stopping: leave the stroke unacknowledged for the next start
        if msg.topic not in self.topics.inputs:  # an old subscription of a persistent session
            if msg.qos > 0:
                client.ack(msg.mid, msg.qos)
            if self.foreign == 0 or msg.topic not in self._dropped:
                log.warning("ignoring messages on %s (not an input topic %s: an earlier "
                            "subscription of session %s); unsubscribing", msg.topic,
                            ", ".join(self.topics.inputs), self.client_id)
                client.unsubscribe(msg.topic)
                self._dropped.add(msg.topic)
            self.foreign += 1
            return
        t0 = time.perf_counter()
        try:
            handle = self.processor.handle_sensor if msg.topic == self.topics.sensors \
                else self.processor.handle
            out: Outcome = handle(bytes(msg.payload), msg.topic)
            for alarm in out.alarms:  # before the answer: acknowledged once it is in
                client.publish(self.topics.alarms or self.topics.errors, dumps(alarm), qos=1)
            for note in out.notices:  # model_mismatch: once per episode, errors topic
                client.publish(self.topics.errors, dumps(note), qos=1)
            topic = self.topics.errors if out.is_error else self.topics.results
            info = client.publish(topic, out.payload or dumps(out.message), qos=1)
        except Exception as exc:  # storage failure: never acknowledge, stop the service
            log.exception("processing a stroke failed; stopping without acknowledging it")
            self.fatal = exc
            return
        if msg.qos > 0:
            # acknowledge the stroke only once the broker holds our answer: a kill before
            # that makes the broker redeliver the stroke, and the store answers it again
            with self._lock:
                self._pending[info.mid] = (msg.mid, msg.qos)
        self.handled += 1
        self.busy_s += time.perf_counter() - t0

    def _on_publish(self, client: mqtt.Client, userdata: Any, mid: int, rc: Any = None,
                    props: Any = None) -> None:
        with self._lock:
            stroke = self._pending.pop(mid, None)
        if stroke is not None:
            client.ack(*stroke)

    def run(self, stop: threading.Event, timeout: float = 10.0,
            on_connected: Callable[[], None] | None = None) -> None:
        """Connect and serve until ``stop`` is set; ``on_connected()`` runs once subscribed.

        Raises
        ------
        ConnectionError
            If the broker cannot be reached within ``timeout`` seconds.
        RuntimeError
            If processing a message failed unexpectedly (e.g. the store's disk is full): the
            stroke is not acknowledged, the service stops, and a restart (by a supervisor)
            gets the stroke again.
        """
        self.client.connect_async(self.broker.host, self.broker.port, self.broker.keepalive)
        self.client.loop_start()
        try:
            self._answered.wait(timeout)
            if self.refused is not None:
                raise ConnectionError(f"broker {self.broker.host}:{self.broker.port} refused "
                                      f"the connection: {self.refused}")
            if not self.connected.is_set():
                raise ConnectionError(f"no connection to the broker at {self.broker.host}:"
                                      f"{self.broker.port} within {timeout:g} s")
            if on_connected is not None:
                on_connected()
            while not stop.wait(0.2) and self.fatal is None:
                pass
            if self.fatal is not None:
                raise RuntimeError(f"processing failed, service stopped: {self.fatal!r}") \
                    from self.fatal
        finally:
            self.client.disconnect()
            self.client.loop_stop()


def check_client_id(client_id: str) -> str:
    """The session id of ``serve --check``: its own (``<client_id>-check-<pid>``), on a
    clean session, so the check neither takes over nor leaves behind a persistent session
    of the service."""
    return f"{client_id}-check-{os.getpid()}"


def publish_strokes(strokes: Iterable[Stroke | Reading], broker: BrokerConfig, topic: str,
                    rate: float = 0.0, client_id: str = "",
                    on_sent: Callable[[Stroke, float], None] | None = None,
                    max_seconds: float | None = None, sensor_topic: str = "") -> int:
    """Publish strokes with QoS 1 (``rate`` per second; 0 = as fast as possible), and
    the sensor readings among them, in their order, on ``sensor_topic``.

    Returns the number of strokes published. ``on_sent(stroke, t_publish)`` is called
    after each stroke's publish (the benchmark measures latency from there).
    """
    client = make_client(broker, client_id or f"formtwin-replay-{time.time_ns()}")
    answered = threading.Event()
    refused: list[str] = []

    def on_connect(c: mqtt.Client, u: Any, f: Any, rc: Any, p: Any = None) -> None:
        if getattr(rc, "is_failure", False):
            refused.append(str(rc))
        answered.set()

    client.on_connect = on_connect
    client.connect(broker.host, broker.port, broker.keepalive)
    client.loop_start()
    n = 0
    try:
        if not answered.wait(10.0):
            raise ConnectionError(f"no connection to {broker.host}:{broker.port}")
        if refused:
            raise ConnectionError(f"broker {broker.host}:{broker.port} refused the "
                                  f"connection: {refused[0]}")
        t0 = time.perf_counter()
        last = None
        for s in strokes:
            if isinstance(s, Reading):
                if not sensor_topic:
                    raise ValueError("sensor readings to publish, but no sensor topic")
                last = client.publish(sensor_topic, dumps(s.to_message()), qos=1)
                continue
            if rate > 0:
                delay = t0 + n / rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            if max_seconds is not None and time.perf_counter() - t0 > max_seconds:
                break
            t = time.perf_counter()
            last = client.publish(topic, dumps(s.to_message()), qos=1)
            if on_sent is not None:
                on_sent(s, t)
            n += 1
        if last is not None:
            last.wait_for_publish(timeout=60.0)
    finally:
        client.disconnect()
        client.loop_stop()
    return n
