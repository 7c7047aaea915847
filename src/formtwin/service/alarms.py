"""Monitoring in the service: control charts on every accepted estimate, alarms stored,
published and acknowledged.

:class:`ServiceMonitor` runs a :class:`~formtwin.monitoring.Monitor` (EWMA and CUSUM charts
on the state posterior means and the predicted angles, GLR charts for a level change of a
state variable, the model-mismatch CUSUM on the filter's health: log-evidence increment
and ESS against their in-control distribution). For
every accepted product the processor calls :meth:`ServiceMonitor.observe` *before* the
commit (after the service's model health, :mod:`formtwin.service.health`, whose opening
``model_mismatch`` episode becomes an alarm too, chart ``model_mismatch``): the chart
statistics, their limits and the product's alarms go into the estimate message
(``"monitoring"``), and :meth:`ServiceMonitor.write` puts them into the ``alarms`` table
(one row per alarm, unique per product, variable and chart, where they are acknowledged),
both in the SQLite transaction of the product and the tracker checkpoint
(:meth:`~formtwin.service.store.Store.commit_product`): a kill at any instant leaves a
product with all its alarm rows or neither. They are published with the estimate and shown
on the page.

Restart: the monitor's state is rebuilt by charting the stored estimates again in commit
order (the charts are deterministic).

The chart configuration is fixed with the store (``meta`` key ``monitor_config``, JSON):
either calibrated at the store's first start on simulated in-control runs of the service's
own model, measurement model and tracker settings
(:func:`~formtwin.monitoring.calibrate.in_control_runs`: the tracker's statistics mu,
sigma, rho, and measurement noise as the likelihood assumes it; the state charts watch
for departures from the tracker's mu, the line's means ``--mu`` or by default the spec's
mid-range, so a line running elsewhere alarms: give it its means;
:func:`~formtwin.monitoring.calibrate.calibrate`), or a user's file
(:meth:`~formtwin.monitoring.MonitorConfig.to_json` format: in-control means, residual
sigmas, chart limits).
"""

from __future__ import annotations

import logging
import math
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.monitoring.calibrate import ChartDesign, calibrate, in_control_runs
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
        runs = in_control_runs(tracker.model, tracker.measurement, tracker.config,
                               source.products, source.runs, source.seed, noise=True)
        c = tracker.config
        mu = tracker.spec.state.mu_mid if c.mu is None else np.asarray(c.mu)
        if c.mu is None:
            log.info("the line's state means are not given (--mu): the state charts watch "
                     "for departures from the spec's mid-range, where a line whose means "
                     "lie elsewhere in [mu_min, mu_max] raises alarms")
        # the true states too: the GLR charts follow how the estimates respond to a step
        config = calibrate([est for _, est in runs], tracker.spec.state.names, mu,
                           source.design, truths=[x for x, _ in runs])
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
        self.store = store
        store.ensure_tables(_DDL)
        self.monitor = Monitor(config)
        self._saved: dict[str, Any] | None = None
        for row in store.products(status="accepted"):  # rebuild the charts' state
            if row.estimate is None:
                continue
            self.monitor.update_values(values_of(row.estimate, config),
                                       int(row.estimate.get("index", row.seq - 1)))

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

    def write(self, cur: sqlite3.Cursor, seq: int, part_id: str, entry: dict[str, Any],
              now: float) -> list[dict[str, Any]]:
        """Insert the alarms of product ``seq`` with ``cur`` (inside the product's
        transaction); return them with their ids (the alarms-topic messages)."""
        out = []
        for a in entry.get("alarms") or []:
            row = (seq, part_id, int(a["index"]), str(a["variable"]), str(a["chart"]),
                   str(a["side"]), _real(a["statistic"]), _real(a["limit"]), now)
            cur.execute("INSERT INTO alarms(seq, part_id, product_index, variable, chart, "
                        "side, statistic, limit_value, raised_at) VALUES (?,?,?,?,?,?,?,?,?)",
                        row)
            out.append(_alarm((int(cur.lastrowid or 0), *row, None, None)))
        return out

    def committed(self) -> None:
        """The product of the last :meth:`observe` is in: forget its undo."""
        self._saved = None

    # ------------------------------------------------------------------ the table
    def alarms(self, since_seq: int = 0, unacked: bool = False, limit: int = 1000
               ) -> list[dict[str, Any]]:
        """Stored alarms of products after ``since_seq`` (newest ``limit``, oldest first)."""
        sql = f"SELECT {_ALARM_COLS} FROM alarms WHERE seq > ?"
        if unacked:
            sql += " AND acked_at IS NULL"
        sql += " ORDER BY id DESC LIMIT ?"
        rows = self.store.query(sql, (since_seq, int(limit)))
        return [_alarm(r) for r in reversed(rows)]

    def acknowledge(self, alarm_id: int, note: str = "", now: float | None = None
                    ) -> dict[str, Any]:
        """Acknowledge an alarm; return it. ``KeyError`` for an unknown id; acknowledging
        twice keeps the first acknowledgement."""
        t = time.time() if now is None else now
        self.store.execute("UPDATE alarms SET acked_at = ?, ack_note = ? WHERE id = ? AND "
                           "acked_at IS NULL", (t, note[:200], int(alarm_id)))
        rows = self.store.query(f"SELECT {_ALARM_COLS} FROM alarms WHERE id = ?",
                                (int(alarm_id),))
        if not rows:
            raise KeyError(f"no alarm with id {alarm_id}")
        return _alarm(rows[0])

    def limits(self) -> dict[str, Any]:
        """What the page draws: the charted quantities, their charts and chart settings."""
        c = self.config
        return {"quantities": list(c.quantities), "health": list(c.health), "glr": list(c.glr),
                "ewma": {"lam": c.ewma.lam, "L": c.ewma.L},
                "cusum": {"k": c.cusum.k, "h": c.cusum.h},
                "mismatch": {"k": c.mismatch.k, "h": c.mismatch.h},
                "warmup": c.warmup, "phase1": c.phase1,
                "means": {n: m for n, m in self.monitor.means.items()}}


_ALARM_COLS = ("id, seq, part_id, product_index, variable, chart, side, statistic, "
               "limit_value, raised_at, acked_at, ack_note")
_ALARM_KEYS = ("id", "seq", "part_id", "index", "variable", "chart", "side", "statistic",
               "limit", "raised_at", "acked_at", "ack_note")


def _alarm(row: tuple[Any, ...]) -> dict[str, Any]:
    """An alarm as a JSON-safe dict from its row (columns :data:`_ALARM_COLS`)."""
    return {k: _num(v) if isinstance(v, float) else v
            for k, v in zip(_ALARM_KEYS, row, strict=True)}


def _num(v: float) -> float | None:
    """JSON-safe number."""
    return float(v) if math.isfinite(v) else None


def _real(v: Any) -> float:
    """A stored statistic (None -> NaN)."""
    return math.nan if v is None else float(v)


__all__ = ["MonitorSource", "ServiceMonitor", "monitor_config", "values_of"]
