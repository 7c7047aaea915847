"""Child of ``bench_service.py``: the MQTT part of ``formtwin serve`` alone, its floor.

:class:`formtwin.service.mqtt.MqttService` (the service's paho client: persistent session,
QoS 1 in and out, each message acknowledged after the broker holds its answer) with a
processor that does nothing but read the message's part id and answer with a payload of
the real answer's size (an estimate for a stroke, a ``formtwin.measurement/1`` answer for a
sensor message). The CPU time per product of this process, measured by the parent over the
same messages as the service, is what paho and the service's MQTT plumbing cost with no
processing: the part of ``serve_overhead_cpu_ms`` no processor change can remove.
"""

from __future__ import annotations

import argparse
import signal
import threading
from typing import Any

import orjson

from formtwin.service.mqtt import BrokerConfig, MqttService, Topics
from formtwin.service.processor import Outcome


class Answerer:
    """A processor that answers every message with a fixed-size payload."""

    def __init__(self, estimate_bytes: int, answer_bytes: int) -> None:
        self.estimate_bytes = estimate_bytes
        self.answer_bytes = answer_bytes

    def _answer(self, payload: bytes, schema: str, size: int, kind: str) -> Outcome:
        part_id = str(orjson.loads(payload)["part_id"])
        head = orjson.dumps({"schema": schema, "part_id": part_id, "status": kind})
        pad = b',"pad":"' + b"x" * max(0, size - len(head) - 9) + b'"}'
        return Outcome(kind, {"part_id": part_id}, part_id, payload=head[:-1] + pad)

    def handle(self, payload: bytes, topic: str = "") -> Outcome:
        """A stroke: an estimate-sized answer."""
        return self._answer(payload, "formtwin.estimate/1", self.estimate_bytes, "accepted")

    def handle_sensor(self, payload: bytes, topic: str = "") -> Outcome:
        """A sensor message: an answer of a measurement answer's size."""
        return self._answer(payload, "formtwin.measurement/1", self.answer_bytes, "fused")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--topic", required=True)
    ap.add_argument("--estimate-bytes", type=int, required=True)
    ap.add_argument("--answer-bytes", type=int, required=True)
    args = ap.parse_args()
    proc: Any = Answerer(args.estimate_bytes, args.answer_bytes)
    service = MqttService(proc, BrokerConfig(port=args.port), Topics.from_input(args.topic),
                          client_id="bench-mqtt-floor")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    service.run(stop, on_connected=lambda: print("connected and subscribed", flush=True))


if __name__ == "__main__":
    main()
