"""Monitoring in the service: control charts on every accepted estimate, alarms stored,
published and acknowledged.

:class:`ServiceMonitor` runs a :class:`~formtwin.monitoring.Monitor` (EWMA and CUSUM charts
on the state posterior means and the predicted angles, the model-mismatch CUSUM on the
filter's health: log-evidence increment and ESS against their in-control distribution). For
every accepted product the processor calls :meth:`ServiceMonitor.observe` *before* the
commit (after the service's model health, :mod:`formtwin.service.health`, whose opening
``model_mismatch`` episode becomes an alarm too, chart ``model_mismatch``): the chart
statistics, their limits and the product's alarms go into the estimate message
(``"monitoring"``), so they are stored in the same SQLite transaction as the
product and the tracker checkpoint, published with the estimate, and shown on the page.
After the commit, :meth:`ServiceMonitor.committed` copies the alarms into the ``alarms``
table (one row per alarm, unique per product, variable and chart) where they are
acknowledged.

Restart: the monitor's state is rebuilt by charting the stored estimates again in commit
order (the charts are deterministic), and any alarm of a stored estimate missing from the
``alarms`` table (a kill between the two writes) is added then. Nothing is lost.

The chart configuration is fixed with the store (``meta`` key ``monitor_config``, JSON):
either calibrated at the store's first start on simulated in-control runs of the service's
own model, measurement model and tracker settings (the spec's statistics mu, sigma, rho;
:func:`~formtwin.monitoring.calibrate.calibrate`), or a user's file
(:meth:`~formtwin.monitoring.MonitorConfig.to_json` format: in-control means, residual
sigmas, chart limits).
"""

from __future__ import annotations

import logging
import math
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.monitoring.calibrate import ChartDesign, calibrate, simulate_in_control
from formtwin.monitoring.monitor import ANGLES, Monitor, MonitorConfig
from formtwin.service.store import Store
from formtwin.tracker import Tracker

log = logging.getLogger(__name__)

_DDL = """
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY,
    seq INTEGER NOT NULL,
    part_id TEXT NOT NULL,
    product_index INTEGER NOT NULL,
    variable TEXT NOT NULL,
    chart TEXT NOT NULL,
    side TEXT NOT NULL,
    statistic REAL NOT NULL,
    limit_value REAL NOT NULL,
    raised_at REAL NOT NULL,
    acked_at REAL,
    ack_note TEXT,
    UNIQUE (seq, variable, chart)
);
"""


@dataclass(frozen=True)
class MonitorSource:
    """Where a new store's chart configuration comes from.

    Attributes
    ----------
    file : a :class:`MonitorConfig` JSON file (user-set limits); ``None``: calibrate.
    runs, products : simulated in-control runs used to calibrate (first start only).
    design : chart design (smoothing, reference values, in-control ARL per chart,
        warm-up and Phase I).
    seed : seed of the simulated runs.
    """

    file: str | None = None
    runs: int = 2
    products: int = 600
    design: ChartDesign = ChartDesign()
    seed: int = 0


def monitor_config(store: Store, tracker: Tracker, source: MonitorSource) -> MonitorConfig:
    """The store's chart configuration: the stored one, or a new one from ``source``
    (stored in the store's ``meta``)."""
    stored = store.get_meta("monitor_config")
    if stored is not None:
        return MonitorConfig.from_json(stored)
    if source.file is not None:
        try:
            config = MonitorConfig.from_json(Path(source.file).read_text(encoding="utf-8"))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"monitor config {source.file}: {exc}") from exc
    else:
        log.info("calibrating the charts on %d simulated in-control runs of %d products",
                 source.runs, source.products)
        runs = simulate_in_control(tracker.model, tracker.measurement, tracker.config,
                                   source.products, source.runs, source.seed)
        c = tracker.config
        mu = tracker.spec.state.mu_mid if c.mu is None else np.asarray(c.mu)
        config = calibrate(runs, tracker.spec.state.names, mu, source.design)
    store.set_meta("monitor_config", config.to_json())
    return config


def values_of(message: dict[str, Any], config: MonitorConfig) -> dict[str, float]:
    """The monitored values of an estimate message (``None`` -> NaN, i.e. worst health)."""
    mean = message.get("mean") or {}
    angles = message.get("angles_mean") or [None, None]
    raw: dict[str, Any] = {n: mean.get(n) for n in config.quantities if n not in ANGLES}
    raw.update({a: angles[k] for k, a in enumerate(ANGLES)})
    raw.update(loglik=message.get("loglik"), ess=message.get("ess"),
               fit=(message.get("fit") or {}).get("log10_p"))
    return {k: math.nan if v is None else float(v) for k, v in raw.items()}


class ServiceMonitor:
    """The charts of a running service and its ``alarms`` table.

    Parameters
    ----------
    store : the service's store (the ``alarms`` table is created in its file).
    config : the chart configuration (see :func:`monitor_config`).
    """

    def __init__(self, store: Store, config: MonitorConfig) -> None:
        self.config = config
        self.path = store.path
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), isolation_level=None,
                                   check_same_thread=False, timeout=30.0)
        self._db.executescript(_DDL)
        self.monitor = Monitor(config)
        self._saved: dict[str, Any] | None = None
        self.recovered = 0
        for row in store.products(status="accepted"):  # rebuild the charts' state
            if row.estimate is None:
                continue
            self.monitor.update_values(values_of(row.estimate, config),
                                       int(row.estimate.get("index", row.seq - 1)))
            mon = row.estimate.get("monitoring")
            if mon and mon.get("alarms"):
                self.recovered += self._insert(row.seq, row.part_id, mon["alarms"],
                                               row.received_at)
        if self.recovered:
            log.warning("%d alarms of stored products added to the alarms table",
                        self.recovered)

    def close(self) -> None:
        """Close the table's connection."""
        with self._lock:
            self._db.close()

    # ------------------------------------------------------------------ processor hooks
    def observe(self, message: dict[str, Any]) -> dict[str, Any]:
        """Chart one accepted estimate message; return its ``"monitoring"`` entry:
        ``phase`` (warmup, phase1, charting), ``charts`` (quantity -> chart -> [statistic,
        limit], sigma units) and ``alarms`` (list of dicts). :meth:`rollback` undoes it."""
        self._saved = self.monitor.state()
        index = int(message.get("index", self.monitor.n))
        alarms = self.monitor.update_values(values_of(message, self.config), index)
        c = self.config
        n = self.monitor.n  # this product's phase: its charts ran only when charting
        phase = ("warmup" if n <= c.warmup else "phase1" if n <= c.warmup + c.phase1
                 else "charting")
        charts = {n: {k: [_num(v[0]), _num(v[1])] for k, v in d.items()}
                  for n, d in self.monitor.last.items()}
        out = [{**a.to_dict(), "statistic": _num(a.statistic), "limit": _num(a.limit)}
               for a in alarms]
        health = message.get("model_health") or {}
        if health.get("event") == "opened":  # the service's model-health episode opens
            out.append({"variable": "model_health", "chart": "model_mismatch",
                        "index": index, "statistic": float(health.get("failing", 0)),
                        "limit": _num(float((health.get("rule") or {}).get("k", math.nan))),
                        "side": "high"})
        return {"phase": phase, "charts": charts, "alarms": out}

    def rollback(self) -> None:
        """Undo the last :meth:`observe` (its product was not committed)."""
        if self._saved is not None:
            self.monitor = Monitor(self.config, self._saved)
            self._saved = None

    def committed(self, seq: int, part_id: str, entry: dict[str, Any],
                  now: float | None = None) -> list[dict[str, Any]]:
        """Store the alarms of a committed product; return them with their ids (the
        alarms-topic messages)."""
        self._saved = None
        alarms = entry.get("alarms") or []
        if not alarms:
            return []
        t = time.time() if now is None else now
        self._insert(seq, part_id, alarms, t)
        return [a for a in self.alarms(since_seq=seq - 1) if a["seq"] == seq]

    # ------------------------------------------------------------------ the table
    def _insert(self, seq: int, part_id: str, alarms: list[dict[str, Any]],
                now: float) -> int:
        with self._lock:
            cur = self._db.executemany(
                "INSERT OR IGNORE INTO alarms(seq, part_id, product_index, variable, chart, "
                "side, statistic, limit_value, raised_at) VALUES (?,?,?,?,?,?,?,?,?)",
                [(seq, part_id, int(a["index"]), str(a["variable"]), str(a["chart"]),
                  str(a["side"]), _real(a["statistic"]), _real(a["limit"]), now)
                 for a in alarms])
            return int(cur.rowcount)

    def alarms(self, since_seq: int = 0, unacked: bool = False, limit: int = 1000
               ) -> list[dict[str, Any]]:
        """Stored alarms of products after ``since_seq`` (newest ``limit``, oldest first)."""
        sql = ("SELECT id, seq, part_id, product_index, variable, chart, side, statistic, "
               "limit_value, raised_at, acked_at, ack_note FROM alarms WHERE seq > ?")
        if unacked:
            sql += " AND acked_at IS NULL"
        sql += " ORDER BY id DESC LIMIT ?"
        with self._lock:
            rows = self._db.execute(sql, (since_seq, int(limit))).fetchall()
        keys = ("id", "seq", "part_id", "index", "variable", "chart", "side", "statistic",
                "limit", "raised_at", "acked_at", "ack_note")
        return [{k: _num(v) if isinstance(v, float) else v
                 for k, v in zip(keys, r, strict=True)} for r in reversed(rows)]

    def acknowledge(self, alarm_id: int, note: str = "", now: float | None = None
                    ) -> dict[str, Any]:
        """Acknowledge an alarm; return it. ``KeyError`` for an unknown id; acknowledging
        twice keeps the first acknowledgement."""
        t = time.time() if now is None else now
        with self._lock:
            self._db.execute("UPDATE alarms SET acked_at = ?, ack_note = ? WHERE id = ? AND "
                             "acked_at IS NULL", (t, note[:200], int(alarm_id)))
            row = self._db.execute("SELECT seq FROM alarms WHERE id = ?",
                                   (int(alarm_id),)).fetchone()
        if row is None:
            raise KeyError(f"no alarm with id {alarm_id}")
        return next(a for a in self.alarms(since_seq=int(row[0]) - 1) if a["id"] == alarm_id)

    def limits(self) -> dict[str, Any]:
        """What the page draws: the charted quantities, their charts and chart settings."""
        c = self.config
        return {"quantities": list(c.quantities), "health": list(c.health),
                "ewma": {"lam": c.ewma.lam, "L": c.ewma.L},
                "cusum": {"k": c.cusum.k, "h": c.cusum.h},
                "mismatch": {"k": c.mismatch.k, "h": c.mismatch.h},
                "warmup": c.warmup, "phase1": c.phase1,
                "means": {n: m for n, m in self.monitor.means.items()}}


def _num(v: float) -> float | None:
    """JSON-safe number."""
    return float(v) if math.isfinite(v) else None


def _real(v: Any) -> float:
    """A stored statistic (None -> NaN)."""
    return math.nan if v is None else float(v)


__all__ = ["MonitorSource", "ServiceMonitor", "monitor_config", "values_of"]
