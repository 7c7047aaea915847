"""Bring the service's tracker to the last stored product: checkpoint, then replay.

The store holds the tracker's checkpoint (written with every k-th accepted product, in its
transaction), the curves of the products after it and the sensor values fused after it
(:mod:`formtwin.service.sensors`), each with the product it followed. :func:`replay`
loads the checkpoint and steps the tracker through those curves and fusions in their
original order; the steps and fusions are deterministic, so the tracker ends in exactly the
state it had (at a restart, and to undo a gated or failed step).
"""

from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np

from formtwin.service.sensors import MEASUREMENTS_DDL, fused_sensors, issue
from formtwin.service.store import Store

log = logging.getLogger(__name__)


def replay(store: Store, tracker: Any) -> int:
    """Restore ``tracker`` from the store's last checkpoint (if any) and step it through
    the curves (and press settings) of the accepted products stored after it, with the
    final-angle predictions issued after each step and the sensor values fused after each
    product, in commit order; return how many products were stepped. An estimate the
    replay does not reproduce (its log-likelihood) is logged as an error."""
    ck = store.checkpoint()
    since = 0 if ck is None else ck[0]
    if ck is not None:
        tracker.load_state_bytes(ck[1])
        log.info("restored tracker from checkpoint of product seq %d", ck[0])
    active = bool(fused_sensors(tracker))
    fusions = fused_after(store, since) if active else {}
    replay_fusions(fusions.get(since, []), tracker)
    n = 0
    for row in store.products(since_seq=since):
        if row.status == "accepted":
            stored = row.estimate or {}
            u = stored.get("u")
            uu = None if u is None else np.asarray(u, dtype=np.float64)
            est = tracker.step(row.curve, uu)
            if active:
                issue(tracker, uu)
            n += 1
            if "loglik" in stored and float(est.loglik) != stored["loglik"]:
                log.error("replaying product seq %d gave loglik %r, stored %r: the tracker "
                          "does not continue bit for bit", row.seq, float(est.loglik),
                          stored["loglik"])
        replay_fusions(fusions.get(row.seq, []), tracker)
    if n:
        log.info("replayed %d products stored after the checkpoint", n)
    return n


def fused_after(store: Store, seq: int) -> dict[int, list[tuple[str, float, int, Any]]]:
    """The fusions stored after product ``seq`` (``at_seq >= seq``), by the product seq
    they follow, in their order: ``(sensor, value, product index, u)``."""
    store.ensure_tables(MEASUREMENTS_DDL)
    rows = store.query("SELECT at_seq, sensor, value, product, u FROM measurements WHERE "
                       "status = 'fused' AND at_seq >= ? ORDER BY at_seq, id", (seq,))
    out: dict[int, list[tuple[str, float, int, Any]]] = {}
    for at, sensor, value, product, u in rows:
        out.setdefault(int(at), []).append(
            (str(sensor), float(value), int(product), None if u is None else json.loads(u)))
    return out


def replay_fusions(group: list[tuple[str, float, int, Any]], tracker: Any) -> None:
    """Fuse a product's stored values again, in their order (a restart's replay); the next
    product's values (fused into its step) last, right before that step, as they were."""
    newest = int(tracker.n_steps) - 1 if group else 0
    for sensor, value, index, u in sorted(group, key=lambda g: g[2] > newest):
        tracker.fuse(index, sensor, value,
                     u=None if u is None else np.asarray(u, dtype=np.float64))


__all__ = ["fused_after", "replay", "replay_fusions"]
