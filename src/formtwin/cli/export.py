"""``formtwin export``: write a service store's products and estimates as Parquet or CSV."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    """Add the ``export`` command to the subparsers ``sub``."""
    p = sub.add_parser("export", help="export a serve store to Parquet or CSV",
                       description="One row per stored product: part id, cycle, timestamp, "
                       "status, posterior mean and std of every estimated quantity, predicted "
                       "and measured angles, ESS, loglik. Optionally the rejections or the "
                       "sensor messages.")
    p.add_argument("store", help="SQLite store written by formtwin serve")
    p.add_argument("out", help="output file: .parquet or .csv")
    p.add_argument("--curves", action="store_true", help="also write the force samples")
    p.add_argument("--rejections", action="store_true",
                   help="export the rejected messages instead of the products")
    p.add_argument("--measurements", action="store_true",
                   help="export the sensor messages instead of the products: part id, "
                   "sensor, value, status (fused, held, too_late, expired), product index, "
                   "log evidence, the prediction issued for a camera's product")
    p.set_defaults(run=_export)


def _export(args: argparse.Namespace) -> int:
    from formtwin.service.export import export_store

    if args.rejections and args.measurements:
        raise ValueError("--rejections and --measurements: give one")
    path, n = export_store(args.store, args.out, curves=args.curves,
                           rejections=args.rejections, measurements=args.measurements)
    print(f"wrote {n} rows to {path}")
    return 0
