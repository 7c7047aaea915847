"""``formtwin replay``: publish a stream file's curves as strokes (the demo's press)."""

from __future__ import annotations

import argparse
from typing import Any

from formtwin.cli.serve import DEFAULT_TOPIC, add_broker_options, broker_config


def register(sub: Any) -> None:
    """Add the ``replay`` command to the subparsers ``sub``."""
    p = sub.add_parser("replay", help="publish a stream of force curves to MQTT as strokes",
                       description="Publish each product of FILE (.npz, .nc or .csv; see "
                       "formtwin.service.streams) as a formtwin.stroke/1 message, QoS 1.")
    p.add_argument("file", nargs="?", help="stream file (omit with --synthetic N)")
    p.add_argument("--synthetic", type=int, metavar="N",
                   help="make a synthetic stream of N products (written to --write, then "
                   "published) from the model the service runs: give the same --metamodel "
                   "FILE or --analytic as to formtwin serve")
    model = p.add_mutually_exclusive_group()
    model.add_argument("--metamodel", help="with --synthetic: the metamodel file the service "
                       "runs (serve --metamodel)")
    model.add_argument("--analytic", action="store_true", help="with --synthetic: the "
                       "closed-form stand-in (serve --analytic)")
    p.add_argument("--draw-from", choices=("model", "physics"), default="model",
                   help="with --synthetic: draw the curves from the model itself, or from the "
                   "physics model the metamodel was fitted on (refused if the installed "
                   "physics has another version) (default: %(default)s)")
    p.add_argument("--write", default="out/stream.npz",
                   help="where --synthetic writes its stream (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of --synthetic")
    p.add_argument("--noise", type=float, default=2.0, metavar="N",
                   help="with --synthetic: std of the Gaussian sensor noise, N; give the "
                   "service the same (serve --sensor-noise) (default: %(default)s)")
    p.add_argument("--source", default="gFE",
                   help="NetCDF files with a source dimension: which source (default: gFE)")
    add_broker_options(p)
    p.add_argument("--topic", default=DEFAULT_TOPIC, help="stroke topic (default: %(default)s)")
    p.add_argument("--sensor-topic", help="topic of the sensor messages (default: sibling "
                   "'sensor' of --topic)")
    p.add_argument("--sensors", default="", metavar="NAMES",
                   help="with --synthetic: draw these of the spec's sensors (comma-separated, "
                   "e.g. gauge,camera) for every product; a stream file's sensor values "
                   "(sensor_<name>) are sent anyway, each after the stroke its delay puts "
                   "it behind (a state variable's without delay, a gauge's, before its "
                   "own stroke)")
    p.add_argument("--no-sensors", action="store_true", help="do not send sensor messages")
    p.add_argument("--spec", metavar="TOML",
                   help="the process spec whose [[sensor]] delays place a stream file's "
                   "sensor values (default: the bundled demonstrator's)")
    p.add_argument("--press", metavar="URL",
                   help="opc.tcp://HOST:PORT[/PATH]: instead of publishing to MQTT, be a "
                   "simulated OPC UA press there (docs/reference/opcua.md): wait for "
                   "formtwin serve --source to subscribe, then write the strokes into the "
                   "press's nodes")
    p.add_argument("--rate", type=float, default=2.0,
                   help="strokes per second; 0 = as fast as possible (default: %(default)s)")
    p.add_argument("--start", type=int, default=0, help="first product to publish")
    p.add_argument("--count", type=int, help="number of products to publish (default: all)")
    p.add_argument("--no-angles", action="store_true",
                   help="do not send the measured angles")
    p.set_defaults(run=_replay)


def synthetic_model(metamodel: str | None, analytic: bool, draw_from: str) -> tuple[Any, str]:
    """The process model a synthetic stream is drawn from, and its description.

    The stream must come from the model the service runs (``serve --metamodel FILE`` or
    ``--analytic``), or from the physics that model was fitted on; any other pairing gives
    curves that no particle explains, so it is refused with the reason.
    """
    from formtwin.defaults import PHYSICS, analytic_model, load_model, physics_model
    from formtwin.simulator import SimulatorModel

    if analytic:
        return analytic_model(), "the analytic stand-in (serve --analytic)"
    if metamodel is None:
        raise ValueError("--synthetic needs the model the service runs: --metamodel FILE (the "
                         "file given to formtwin serve --metamodel) or --analytic (serve "
                         "--analytic); a stream from another model is one the service "
                         "cannot explain")
    mm = load_model(metamodel)
    if draw_from == "model":
        return mm, f"the metamodel {metamodel}"
    version = str(getattr(mm, "model_version", ""))
    name = version.split("-")[0]
    if name not in PHYSICS:
        raise ValueError(f"--draw-from physics: the metamodel {metamodel} was fitted on "
                         f"physics {version!r}, which formtwin does not have (known: "
                         f"{', '.join(PHYSICS)}); draw from the metamodel instead")
    sim = physics_model(name, mm.spec)
    if sim.version != version:
        raise ValueError(f"--draw-from physics: the metamodel {metamodel} was fitted on "
                         f"{version!r}, the installed {name} physics is {sim.version!r}: its "
                         "curves would not be the ones the metamodel learnt; refit the "
                         "metamodel on a DOE of this physics or draw from the metamodel")
    return SimulatorModel(sim), f"the {sim.version} physics (metamodel {metamodel})"


def _replay(args: argparse.Namespace) -> int:
    import dataclasses

    from formtwin.service.mqtt import Topics, publish_strokes
    from formtwin.service.streams import interleave, make_stream, read_readings, read_stream
    from formtwin.spec import load_spec

    if args.synthetic is not None:
        model, what = synthetic_model(args.metamodel, args.analytic, args.draw_from)
        print(f"drawing {args.synthetic} products from {what}", flush=True)
        path = make_stream(args.write, args.synthetic, seed=args.seed, model=model,
                           noise_N=args.noise, sensors=tuple(
                               n.strip() for n in args.sensors.split(",") if n.strip()))
        print(f"synthetic stream of {args.synthetic} products -> {path}")
    elif args.file:
        if args.metamodel or args.analytic:
            raise ValueError("--metamodel/--analytic choose the model of --synthetic; a "
                             "stream FILE is replayed as it is")
        path = args.file
    else:
        raise ValueError("give a stream FILE or --synthetic N")
    strokes = read_stream(path, source=args.source)
    end = None if args.count is None else args.start + args.count
    strokes = strokes[args.start:end]
    if args.no_angles:
        strokes = [dataclasses.replace(s, angles_deg=None) for s in strokes]
    spec = load_spec(args.spec) if args.spec else None
    readings = [] if args.no_sensors else read_readings(path, spec)
    if args.rate < 0:
        raise ValueError(f"--rate {args.rate}: expected >= 0")
    messages = interleave(strokes, readings, args.start)
    if args.press:
        return _replay_press(messages, args.press, args.rate)
    broker = broker_config(args)
    rate = "full speed" if args.rate == 0 else f"{args.rate:g}/s"
    topics = Topics.from_input(args.topic, sensors=args.sensor_topic)
    print(f"publishing {len(strokes)} strokes to {args.topic}"
          + (f" and {len(messages) - len(strokes)} sensor messages to {topics.sensors}"
             if len(messages) > len(strokes) else "")
          + f" on {broker.host}:{broker.port} at {rate}", flush=True)
    import sys

    from tqdm import tqdm

    with tqdm(total=len(strokes), unit="stroke", disable=not sys.stderr.isatty()) as bar:
        n = publish_strokes(messages, broker, args.topic, rate=args.rate,
                            on_sent=lambda s, t: bar.update(1), sensor_topic=topics.sensors)
    print(f"published {n} strokes")
    return 0


def _replay_press(messages: list[Any], url: str, rate: float) -> int:
    """Serve ``messages`` (strokes, and sensor values as the sensor objects named after
    their sensors) as a simulated OPC UA press at ``url`` (``--press``)."""
    import time

    from formtwin.service.opcua_press import SimulatedPress
    from formtwin.service.readings import Reading

    sensors = tuple(sorted({m.sensor for m in messages if isinstance(m, Reading)}))
    with SimulatedPress.from_url(url, sensors) as press:
        print(f"simulated press at {press.url}"
              + (f" with sensor objects {', '.join(sensors)}" if sensors else "")
              + "; waiting for a subscription", flush=True)
        while press.monitored() == 0:
            time.sleep(0.1)
        t0, i = time.perf_counter(), 0
        for m in messages:
            if isinstance(m, Reading):
                press.write_sensor(m.sensor, m.part_id, m.value)
                continue
            if rate > 0:
                time.sleep(max(0.0, t0 + i / rate - time.perf_counter()))
            press.write(m)
            i += 1
        print(f"wrote {i} strokes and {len(messages) - i} sensor values", flush=True)
        time.sleep(1.0)  # the last publishing interval reaches the subscriber
    return 0
