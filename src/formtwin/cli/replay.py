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
                   help="make a synthetic stream of N products from the analytic stand-in "
                   "(written to --write, then published)")
    p.add_argument("--write", default="out/stream.npz",
                   help="where --synthetic writes its stream (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of --synthetic")
    p.add_argument("--source", default="gFE",
                   help="NetCDF files with a source dimension: which source (default: gFE)")
    add_broker_options(p)
    p.add_argument("--topic", default=DEFAULT_TOPIC, help="stroke topic (default: %(default)s)")
    p.add_argument("--rate", type=float, default=2.0,
                   help="strokes per second; 0 = as fast as possible (default: %(default)s)")
    p.add_argument("--start", type=int, default=0, help="first product to publish")
    p.add_argument("--count", type=int, help="number of products to publish (default: all)")
    p.add_argument("--no-angles", action="store_true",
                   help="do not send the measured angles")
    p.set_defaults(run=_replay)


def _replay(args: argparse.Namespace) -> int:
    import dataclasses

    from formtwin.service.mqtt import publish_strokes
    from formtwin.service.streams import make_stream, read_stream

    if args.synthetic is not None:
        path = make_stream(args.write, args.synthetic, seed=args.seed)
        print(f"synthetic stream of {args.synthetic} products -> {path}")
    elif args.file:
        path = args.file
    else:
        raise ValueError("give a stream FILE or --synthetic N")
    strokes = read_stream(path, source=args.source)
    end = None if args.count is None else args.start + args.count
    strokes = strokes[args.start:end]
    if args.no_angles:
        strokes = [dataclasses.replace(s, angles_deg=None) for s in strokes]
    if args.rate < 0:
        raise ValueError(f"--rate {args.rate}: expected >= 0")
    broker = broker_config(args)
    rate = "full speed" if args.rate == 0 else f"{args.rate:g}/s"
    print(f"publishing {len(strokes)} strokes to {args.topic} on {broker.host}:{broker.port} "
          f"at {rate}", flush=True)
    import sys

    from tqdm import tqdm

    with tqdm(total=len(strokes), unit="stroke", disable=not sys.stderr.isatty()) as bar:
        n = publish_strokes(strokes, broker, args.topic, rate=args.rate,
                            on_sent=lambda s, t: bar.update(1))
    print(f"published {n} strokes")
    return 0
