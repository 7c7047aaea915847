"""The OPC UA source against the MQTT source: products/s, same run, N = 500 particles.

One private mosquitto on 127.0.0.1 and, in this process, a simulated press
(:class:`formtwin.service.opcua_press.SimulatedPress`, an asyncua server on 127.0.0.1). For each
source in turn a fresh ``formtwin serve`` subprocess (the bundled metamodel, page on, default
monitoring, its own store), ``N_WARM`` strokes paced one by one, then ``--n`` strokes at full
speed:

* MQTT: published with QoS 1 to the stroke topic (``publish_strokes``);
* OPC UA: written into the press's nodes (``SimulatedPress.write``; the service's monitored
  items queue them, ``serve --source opc.tcp://...``).

With ``--sensor-messages-per-product 1`` (the default) every product has one value of
``--sensor`` (default ``camera``: the final angle, one product late) besides its stroke,
sent after the stroke its delay puts it behind, and both services fuse it (``serve
--sensors camera``): over MQTT on the sensor topic, over OPC UA written into the press's
sensor object (``SimulatedPress.write_sensor``, mapped by ``[opcua.sensors]``).
``sensor_messages_per_product`` is recorded; 0 sends strokes only.

``products_per_s`` of a source: products divided by the time from the first stroke sent to
the last estimate received on the results topic (MQTT in both cases). ``opcua_over_mqtt`` is
the ratio of the two (target >= 0.8); ``serve_cpu_ms_per_product`` the serve
process's CPU time per product during the full-speed phase, which other jobs on the machine
disturb less than wall time (``opcua_over_mqtt_cpu`` = MQTT's CPU per product over OPC UA's).

Usage: ``python benchmarks/bench_opcua.py [--n 1000] [--particles 500] [--analytic]
[--sensor-messages-per-product 0|1] [--sensor NAME]``; writes
``benchmarks/results/bench_opcua.json``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench_service import Receiver, cpu_seconds, free_port  # the service benchmark's probes

from formtwin._bench import bundled_metamodel, write_result
from formtwin.defaults import analytic_model
from formtwin.service.mqtt import BrokerConfig, publish_strokes
from formtwin.service.opcua_press import SimulatedPress
from formtwin.service.sensors import Reading
from formtwin.service.streams import interleave, make_stream, read_readings, read_stream

NOISE_N = 2.0
N_WARM = 20
TOPIC = "plant/line1/press1/stroke"
RESULTS = "plant/line1/press1/estimate"
SENSORS = "plant/line1/press1/sensor"
#: the press's object of the sensor values (``[opcua.sensors]``)
SENSOR_OBJECT = "LineSensor"
CLI = [sys.executable, "-c", "import sys; from formtwin.cli import main; sys.exit(main())"]
TARGET = 0.8


def start_serve(cmd: list[str], log: Path) -> subprocess.Popen[bytes]:
    with open(log, "wb") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONUNBUFFERED="1"))
    deadline = time.monotonic() + 300
    while "connected and subscribed" not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise SystemExit(f"serve did not start:\n{log.read_text()[-3000:]}")
        time.sleep(0.1)
    return proc


def run_source(name: str, send: Callable[[list[Any]], float], serve: list[str],
               messages: list[Any], broker: BrokerConfig, tmp: Path) -> dict[str, float]:
    """Warm up, then the full-speed phase; products/s and serve CPU per product.
    ``messages``: strokes and the sensor readings among them."""
    proc = start_serve(serve, tmp / f"serve-{name}.log")
    rx = Receiver(broker)
    try:
        at = [k for k, m in enumerate(messages) if not isinstance(m, Reading)]
        for a, b in zip(at[:N_WARM], at[1:N_WARM + 1], strict=True):
            send(messages[a:b])  # a stroke and the values after it
            rx.wait([messages[a].part_id], 60)
        cpu0 = cpu_seconds(proc.pid)
        full = messages[at[N_WARM]:]
        t_first = send(full)
        ids = [s.part_id for s in full if not isinstance(s, Reading)]
        rx.wait(ids, 60 + 0.5 * len(ids))
        cpu = cpu_seconds(proc.pid) - cpu0
        t_last = max(rx.t[i] for i in ids)
    finally:
        rx.stop()
        proc.terminate()
        proc.wait(30)
    return {"products_per_s": len(ids) / (t_last - t_first),
            "serve_cpu_ms_per_product": 1e3 * cpu / len(ids)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1000, help="strokes of the full-speed phase")
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--analytic", action="store_true",
                    help="the closed-form stand-in instead of the bundled metamodel (a quick "
                    "check, not the product)")
    ap.add_argument("--sensor-messages-per-product", type=int, choices=(0, 1), default=1,
                    help="sensor messages per product besides the stroke (default: 1)")
    ap.add_argument("--sensor", default="camera",
                    help="the spec's sensor those messages carry (default: camera)")
    args = ap.parse_args()
    sensors = (args.sensor,) if args.sensor_messages_per_product else ()
    if args.analytic:
        stream_model, model_args = analytic_model(), ["--analytic"]
        model_info: dict[str, Any] = {"name": "analytic stand-in, not the product"}
    else:
        stream_model, mm_path, model_info = bundled_metamodel()
        model_args = ["--metamodel", str(mm_path)]
    mosq = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not os.path.exists(mosq):
        raise SystemExit("mosquitto not installed: make system-deps")
    tmp = Path(tempfile.mkdtemp(prefix="bench-opcua-"))
    port = free_port()
    (tmp / "m.conf").write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\n"
                                "persistence false\nmax_queued_messages 100000\n")
    stream = make_stream(tmp / "s.npz", N_WARM + 1 + args.n, seed=9, noise_N=NOISE_N,
                         model=stream_model, sensors=sensors)
    messages = interleave(read_stream(stream), read_readings(stream, stream_model.spec))
    (tmp / "map.toml").write_text(
        "[opcua.sensors]\n" + "".join(f'{n} = "{SENSOR_OBJECT}"\n' for n in sensors))
    broker = BrokerConfig.from_url(f"mqtt://127.0.0.1:{port}")
    mosquitto = subprocess.Popen([mosq, "-c", str(tmp / "m.conf")],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    press = SimulatedPress(free_port(), sensors=(SENSOR_OBJECT,) if sensors else ()).start()
    try:
        time.sleep(0.5)

        def serve(name: str, *extra: str) -> list[str]:
            return [*CLI, "serve", *model_args, "--broker", broker_url,
                    "--store", str(tmp / f"{name}.sqlite"), "--particles",
                    str(args.particles), "--sensor-noise", str(NOISE_N), "--http-port",
                    str(free_port()), "--topic", TOPIC,
                    *(["--sensors", ",".join(sensors)] if sensors else []), *extra]

        def send_mqtt(batch: list[Any]) -> float:
            t0 = time.perf_counter()
            publish_strokes(batch, broker, TOPIC, sensor_topic=SENSORS)
            return t0

        def send_opcua(batch: list[Any]) -> float:
            t0 = time.perf_counter()
            for s in batch:
                if isinstance(s, Reading):
                    press.write_sensor(SENSOR_OBJECT, s.part_id, s.value)
                else:
                    press.write(s)
            return t0

        broker_url = f"mqtt://127.0.0.1:{port}"
        mqtt = run_source("mqtt", send_mqtt, serve("mqtt"), messages, broker, tmp)
        opcua = run_source("opcua", send_opcua, serve(
            "opcua", "--source", press.url, "--opcua-map", str(tmp / "map.toml")),
            messages, broker, tmp)
    finally:
        press.close()
        mosquitto.terminate()
        mosquitto.wait(10)
    ratio = opcua["products_per_s"] / mqtt["products_per_s"]
    figures = {
        "opcua_over_mqtt": round(ratio, 3),
        "opcua_over_mqtt_cpu": round(mqtt["serve_cpu_ms_per_product"]
                                     / opcua["serve_cpu_ms_per_product"], 3),
        "mqtt_products_per_s": round(mqtt["products_per_s"], 1),
        "opcua_products_per_s": round(opcua["products_per_s"], 1),
        "mqtt_serve_cpu_ms_per_product": round(mqtt["serve_cpu_ms_per_product"], 3),
        "opcua_serve_cpu_ms_per_product": round(opcua["serve_cpu_ms_per_product"], 3),
        "n_products": args.n, "n_particles": args.particles,
        "sensor_messages_per_product": args.sensor_messages_per_product,
        "sensor_messages": list(sensors),
        "targets": {"opcua_over_mqtt": TARGET},
        "met": {"opcua_over_mqtt": ratio >= TARGET},
    }
    write_result("opcua", figures, model=model_info)
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
