"""Export a service store (products with estimates, rejections or sensor messages) to
Parquet or CSV.

>>> import tempfile, os
>>> from formtwin.service.store import Store
>>> d = tempfile.mkdtemp(); Store(os.path.join(d, "s.sqlite")).close()
>>> export_store(os.path.join(d, "s.sqlite"), os.path.join(d, "e.csv"))[1]
0
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from formtwin.service.sensors import MEASUREMENTS_DDL
from formtwin.service.store import Store


def product_table(store: Store, curves: bool = False) -> dict[str, list[Any]]:
    """Column name -> values, one row per stored product (in commit order); the outputs
    (``angle<k>_mean/_std/_measured``, k = 1.. in the spec's ``[[output]]`` order)."""
    cols: dict[str, list[Any]] = {}
    rows = list(store.products())
    names: list[str] = []
    n_out = 2  # an estimate without output names: the demonstrator's two angles
    for r in rows:
        if r.estimate is not None:
            names = list(r.estimate.get("mean", {}))
            n_out = len(r.estimate.get("output_names") or r.estimate.get("angles_mean")
                        or [None, None])
            break
    n_t = rows[0].curve.size if rows else 0
    camera = any((r.estimate or {}).get("final") for r in rows)

    def put(key: str, value: Any) -> None:
        cols.setdefault(key, []).append(value)

    for r in rows:
        e = r.estimate or {}
        put("seq", r.seq)
        put("part_id", r.part_id)
        put("cycle", r.cycle)
        put("timestamp", r.timestamp)
        put("received_at", r.received_at)
        put("status", r.status)
        put("index", e.get("index"))
        for n in names:
            put(f"mean_{n}", (e.get("mean") or {}).get(n))
        for n in names:
            put(f"std_{n}", (e.get("std") or {}).get(n))
        none = [None] * n_out
        am, asd = e.get("angles_mean") or none, e.get("angles_std") or none
        ma: list[Any] = none if r.measured_angles is None else r.measured_angles
        for k in range(n_out):
            put(f"angle{k + 1}_mean", am[k])
            put(f"angle{k + 1}_std", asd[k])
            put(f"angle{k + 1}_measured", ma[k])
        put("ess", e.get("ess"))
        put("collapsed", e.get("collapsed"))
        put("loglik", e.get("loglik"))
        fit = e.get("fit") or {}
        put("health", e.get("health"))
        put("fit_distance2", fit.get("distance2"))
        put("fit_quantile", fit.get("quantile"))
        put("model_mismatch", (e.get("flags") or {}).get("model_mismatch"))
        if camera:  # the final angle's prediction and interval issued for the camera
            final = e.get("final") or {}
            lo, hi = final.get("interval90_deg") or (None, None)
            put("final_predicted_deg", final.get("predicted_deg"))
            put("final_lo90_deg", lo)
            put("final_hi90_deg", hi)
        if curves:
            for j in range(n_t):
                put(f"f{j}", float(r.curve[j]))
    return cols


def rejection_table(store: Store) -> dict[str, list[Any]]:
    """Column name -> values, one row per recorded rejection."""
    rows = store.rejections()
    keys = ("id", "received_at", "reason", "detail", "part_id")
    return {k: [r[i] for r in rows] for i, k in enumerate(keys)}


def measurement_table(store: Store) -> dict[str, list[Any]]:
    """Column name -> values, one row per stored sensor message (in arrival order): part
    id, sensor, value, status, the product's step index, the seq of the product it
    followed, the fusion's log evidence and, for a camera, the prediction issued for its
    product (``predicted_deg``, ``lo90_deg``, ``hi90_deg``)."""
    store.ensure_tables(MEASUREMENTS_DDL)
    rows = store.query("SELECT id, received_at, part_id, sensor, value, status, product, "
                       "at_seq, message FROM measurements ORDER BY id")
    cols: dict[str, list[Any]] = {k: [] for k in (
        "id", "received_at", "part_id", "sensor", "value", "status", "index", "at_seq",
        "log_evidence", "predicted_deg", "lo90_deg", "hi90_deg")}
    for rid, t, pid, sensor, value, status, index, at, text in rows:
        msg = json.loads(text)
        lo, hi = msg.get("interval90_deg") or (None, None)
        for k, v in zip(cols, (rid, t, pid, sensor, value, status, index, at,
                               msg.get("log_evidence"), msg.get("predicted_deg"), lo, hi),
                        strict=True):
            cols[k].append(v)
    return cols


def export_store(store_path: str | Path, out: str | Path, curves: bool = False,
                 rejections: bool = False, measurements: bool = False) -> tuple[Path, int]:
    """Write the store's products (or rejections, or sensor messages) to ``out``
    (.parquet or .csv).

    Returns
    -------
    (path, number of rows)
    """
    sp, op = Path(store_path), Path(out)
    if not sp.exists():
        raise ValueError(f"{sp}: no such store")
    suffix = op.suffix.lower()
    if suffix not in (".parquet", ".csv"):
        raise ValueError(f"{op}: unknown export format {suffix!r} (expected .parquet or .csv)")
    store = Store(sp)
    try:
        table = rejection_table(store) if rejections else measurement_table(store) \
            if measurements else product_table(store, curves)
    finally:
        store.close()
    n = len(next(iter(table.values()), []))
    op.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.table(table), op)
    else:
        with open(op, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(list(table))
            w.writerows(zip(*table.values(), strict=True))
    return op, n
