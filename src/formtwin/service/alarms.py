"""Monitoring in the service: control charts on every accepted estimate, alarm episodes
stored, published and acknowledged.

:class:`ServiceMonitor` runs a :class:`~formtwin.monitoring.Monitor` (EWMA and CUSUM charts
on the state posterior means and the predicted angles, GLR charts for a level change of a
state variable, the model-mismatch CUSUM on the filter's health: log-evidence increment
and ESS against their in-control distribution) and the charts' alarm episodes
(:class:`~formtwin.monitoring.episodes.Episodes`: raised by a chart's first signal, active
while it signals, cleared after it has been quiet for its clear-after products). The
service's model health (:mod:`formtwin.service.health`) is an alarm too, chart
``model_mismatch``: its episode is the model-health episode (every product in it is a
signal, cleared at the product that closes it). For every accepted product the processor
calls :meth:`ServiceMonitor.observe` *before* the commit: the chart statistics, their
limits, the product's signals and episode changes go into the estimate message
(``"monitoring"``), and :meth:`ServiceMonitor.write` puts them into the ``alarms`` table
(one row per signal, unique per product, variable and chart, with its episode's id) and the
``alarm_episodes`` table (one row per episode, where it is acknowledged), both in the
SQLite transaction of the product and the tracker checkpoint
(:meth:`~formtwin.service.store.Store.commit_product`): a kill at any instant leaves a
product with all its rows or none. The episode changes that are reported (raised, updated
at most once per clear-after products, cleared) are published and shown on the page.

Restart: the monitor's and the episodes' state are rebuilt by charting the stored estimates
again in commit order (the charts are deterministic). A store of the schema before the
episodes (``alarms`` only) gets the ``episode_id`` column and its episodes from that
rebuild, each linked to its signal rows and acknowledged if all of them were.

The chart configuration is fixed with the store (``meta`` key ``monitor_config``, JSON):
either calibrated at the store's first start on simulated in-control runs of the service's
own model, measurement model and tracker settings
(:func:`~formtwin.monitoring.calibrate.in_control_runs`: the tracker's statistics mu,
sigma, rho, and measurement noise as the likelihood assumes it; the state charts watch
for departures from the tracker's mu, the line's means ``--mu`` or by default the spec's
mid-range, so a line running elsewhere alarms: give it its means;
:func:`~formtwin.monitoring.calibrate.calibrate`), or a user's file
(:meth:`~formtwin.monitoring.MonitorConfig.to_json` format: in-control means, residual
sigmas, chart limits). So are the episodes' clear-after products (``meta`` key
``alarm_clear_after``, :func:`~formtwin.monitoring.episodes.clear_after`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.monitoring.bank import load_kernels
from formtwin.monitoring.calibrate import ChartDesign, calibrate, in_control_runs
from formtwin.monitoring.charts import Alarm
from formtwin.monitoring.episodes import Change, Episode, Episodes, clear_after
from formtwin.monitoring.monitor import ANGLES, Monitor, MonitorConfig
from formtwin.service import alarm_tables as tables
from formtwin.service import cache as _cache
from formtwin.service.store import Store
from formtwin.tracker import Tracker
from formtwin.tracker.state import fingerprint

log = logging.getLogger(__name__)

#: the model-health alarm's episode is the model-health episode: it clears with it
HEALTH_CLEAR_AFTER = {"model_mismatch": 1}


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
    cache : folder of calibrations kept by a digest of their inputs
        (:mod:`formtwin.service.cache`): a new store with the same model, measurement
        model, tracker settings and the above reuses one; ``None``: always calibrate.
    """

    file: str | None = None
    runs: int = 2
    products: int = 600
    design: ChartDesign = ChartDesign()
    seed: int = 0
    cache: str | None = None


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
        config = _calibrated(store, tracker, source)
    store.set_meta("monitor_config", config.to_json())
    return config


def _calibrated(store: Store, tracker: Tracker, source: MonitorSource) -> MonitorConfig:
    """The charts calibrated on simulated in-control runs, or the same calibration kept in
    ``source.cache`` by a digest of its inputs (made by one service at a time: a second
    one with the same inputs waits for it)."""
    path = None
    if source.cache is not None:
        inputs = {"model": store.get_meta("model_digest"),
                  "measurement": fingerprint(tracker.measurement),
                  "tracker": tracker.config.to_dict(), "runs": source.runs,
                  "products": source.products, "seed": source.seed,
                  "design": dataclasses.asdict(source.design)}
        path = _cache.entry(source.cache, "monitor-config", inputs, ".json")
    with _cache.computing(path):
        return _kept_or_calibrated(tracker, source, path)


def _kept_or_calibrated(tracker: Tracker, source: MonitorSource, path: Path | None
                        ) -> MonitorConfig:
    """The calibration kept at ``path``, else made (and kept there)."""
    if path is not None:
        try:
            config = MonitorConfig.from_json(path.read_text(encoding="utf-8"))
        except (OSError, ValueError, KeyError, TypeError):
            pass  # none yet (or unreadable): calibrate
        else:
            log.info("chart calibration from %s", path)
            return config
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
    if path is not None:
        _cache.write_atomic(path, config.to_json().encode())
    return config


def values_of(message: dict[str, Any], config: MonitorConfig) -> dict[str, float]:
    """The monitored values of an estimate message (``None`` -> NaN, i.e. worst health)."""
    mean = message.get("mean") or {}
    names = message.get("output_names") or ANGLES
    angles = message.get("angles_mean") or [None] * len(names)
    raw: dict[str, Any] = {n: mean.get(n) for n in config.quantities if n not in names}
    raw.update({a: angles[k] for k, a in enumerate(names)})
    raw.update(loglik=message.get("loglik"), ess=message.get("ess"),
               fit=(message.get("fit") or {}).get("log10_p"))
    return {k: math.nan if v is None else float(v) for k, v in raw.items()}


class ServiceMonitor:
    """The charts of a running service, their ``alarms`` (signals) and ``alarm_episodes``.

    Parameters
    ----------
    store : the service's store (the tables are created in its file, an older ``alarms``
        table is migrated).
    config : the chart configuration (see :func:`monitor_config`).
    """

    def __init__(self, store: Store, config: MonitorConfig, cache: str | None = None
                 ) -> None:
        self.config = config
        self.store = store
        had_episodes = tables.ensure(store)
        self.monitor = Monitor(config)
        load_kernels(self.monitor)  # at the start, not at the first charted product
        stored = store.get_meta("alarm_clear_after")
        if stored is None:
            stored = self._clear_after(cache)
            store.set_meta("alarm_clear_after", stored)
        self.clear_after: dict[str, int] = json.loads(stored)
        self.episodes = Episodes(self.clear_after)
        self._saved: tuple[tuple[Any, ...], dict[str, Any]] | None = None
        seen: dict[tuple[str, str, int], Episode] = {}
        products: dict[int, tuple[str, float]] = {}
        for row in store.products(status="accepted"):  # rebuild the charts' state
            if row.estimate is None:
                continue
            index = int(row.estimate.get("index", row.seq - 1))
            alarms = self.monitor.update_values(values_of(row.estimate, config), index)
            changes = self.episodes.update(row.seq, _signals(row.estimate, alarms, index))
            if not had_episodes:  # an older store: its episodes from this rebuild
                products[row.seq] = (row.part_id, row.received_at)
                seen.update({(c.episode.variable, c.episode.chart, c.episode.first):
                             c.episode for c in changes})
        if seen:
            with store.transaction() as cur:
                tables.backfill(cur, list(seen.values()), products)
            log.info("alarm episodes rebuilt for %d earlier products: %d", len(products),
                     len(seen))

    def _clear_after(self, cache: str | None) -> str:
        """The episodes' clear-after products (JSON) of a new store: simulated from the
        charts (seconds), or kept in ``cache`` by a digest of the chart configuration."""
        path = None if cache is None else _cache.entry(
            cache, "clear-after", {"config": self.config.to_json()}, ".json")
        with _cache.computing(path):
            return self._kept_or_simulated(path)

    def _kept_or_simulated(self, path: Path | None) -> str:
        """The clear-after products kept at ``path``, else simulated (and kept there)."""
        if path is not None and path.is_file():
            try:
                text = path.read_text(encoding="utf-8")
                if all(isinstance(v, int) for v in json.loads(text).values()):
                    return text
            except (OSError, ValueError, AttributeError):
                pass
        text = json.dumps({**clear_after(self.monitor), **HEALTH_CLEAR_AFTER})
        if path is not None:
            _cache.write_atomic(path, text.encode())
        return text

    # ------------------------------------------------------------------ processor hooks
    def observe(self, message: dict[str, Any]) -> dict[str, Any]:
        """Chart one accepted estimate message (its ``seq`` set); return its
        ``"monitoring"`` entry: ``phase`` (warmup, phase1, charting), ``charts`` (quantity
        -> chart -> [statistic, limit], sigma units), ``alarms`` (the product's signals)
        and ``episodes`` (the changes it made). :meth:`rollback` undoes it."""
        self._saved = (self.monitor.save(), self.episodes.state())
        index = int(message.get("index", self.monitor.n))
        alarms = self.monitor.update_values(values_of(message, self.config), index)
        signals = _signals(message, alarms, index)
        changes = self.episodes.update(int(message["seq"]), signals)
        c = self.config
        n = self.monitor.n  # this product's phase: its charts ran only when charting
        phase = ("warmup" if n <= c.warmup else "phase1" if n <= c.warmup + c.phase1
                 else "charting")
        fin = math.isfinite  # tables.num: NaN, inf -> None
        charts = {n: {k: [a if fin(a) else None, b if fin(b) else None]
                      for k, (a, b) in d.items()} for n, d in self.monitor.last.items()}
        out = [{**a.to_dict(), "statistic": tables.num(a.statistic),
                "limit": tables.num(a.limit)}
               for a in alarms]
        if (message.get("model_health") or {}).get("event") == "opened":
            a = signals[-1]  # the service's model-health episode opens: a signal row
            out.append({**a.to_dict(), "limit": tables.num(a.limit)})
        return {"phase": phase, "charts": charts, "alarms": out,
                "episodes": [_change(ch) for ch in changes]}

    def rollback(self) -> None:
        """Undo the last :meth:`observe` (its product was not committed)."""
        if self._saved is not None:
            self.monitor.restore(self._saved[0])
            self.episodes = Episodes(self.clear_after, self._saved[1])
            self._saved = None

    def write(self, cur: sqlite3.Cursor, seq: int, part_id: str, entry: dict[str, Any],
              now: float) -> list[dict[str, Any]]:
        """Write the episodes and signals of product ``seq`` with ``cur`` (inside the
        product's transaction); return the reported episode changes (the alarms-topic
        messages: the episode with ``event`` raised, updated or cleared)."""
        ids, out = {}, []
        for ch in entry.get("episodes") or []:
            key = (str(ch["variable"]), str(ch["chart"]))
            ids[key] = tables.put(cur, ch, part_id, now)
            if ch["event"] != "signal":
                out.append({"event": ch["event"], **tables.episode_by_id(cur, ids[key])})
        for a in entry.get("alarms") or []:
            tables.insert_signal(cur, seq, part_id, a, now,
                                 ids.get((str(a["variable"]), str(a["chart"]))))
        return out

    def committed(self) -> None:
        """The product of the last :meth:`observe` is in: forget its undo."""
        self._saved = None

    # ------------------------------------------------------------------ the tables
    def alarms(self, unacked: bool = False, active: bool = False, limit: int = 1000
               ) -> list[dict[str, Any]]:
        """Stored alarm episodes (newest ``limit``, oldest first): ``state`` active,
        cleared or closed (cleared and acknowledged)."""
        sql = f"SELECT {tables.EPISODE_COLS} FROM alarm_episodes WHERE 1"
        if unacked:
            sql += " AND acked_at IS NULL"
        if active:
            sql += " AND cleared_seq IS NULL"
        rows = self.store.query(sql + " ORDER BY id DESC LIMIT ?", (int(limit),))
        return [tables.episode(r) for r in reversed(rows)]

    def signals(self, since_seq: int = 0, limit: int = 1000) -> list[dict[str, Any]]:
        """Stored signals of products after ``since_seq`` (newest ``limit``, oldest
        first), each with its ``episode_id``."""
        rows = self.store.query(f"SELECT {tables.SIGNAL_COLS} FROM alarms WHERE seq > ? "
                                "ORDER BY id DESC LIMIT ?", (since_seq, int(limit)))
        return [tables.row_dict(tables.SIGNAL_KEYS, r) for r in reversed(rows)]

    def acknowledge(self, episode_id: int, note: str = "", now: float | None = None
                    ) -> dict[str, Any]:
        """Acknowledge an alarm episode; return it. ``KeyError`` for an unknown id;
        acknowledging twice keeps the first acknowledgement."""
        t = time.time() if now is None else now
        self.store.execute("UPDATE alarm_episodes SET acked_at = ?, ack_note = ? WHERE "
                           "id = ? AND acked_at IS NULL", (t, note[:200], int(episode_id)))
        rows = self.store.query(f"SELECT {tables.EPISODE_COLS} FROM alarm_episodes WHERE id = ?",
                                (int(episode_id),))
        if not rows:
            raise KeyError(f"no alarm with id {episode_id}")
        return tables.episode(rows[0])

    def limits(self) -> dict[str, Any]:
        """What the page draws: the charted quantities, their charts and chart settings,
        and the episodes' clear-after products."""
        c = self.config
        return {"quantities": list(c.quantities), "health": list(c.health), "glr": list(c.glr),
                "ewma": {"lam": c.ewma.lam, "L": c.ewma.L},
                "cusum": {"k": c.cusum.k, "h": c.cusum.h},
                "mismatch": {"k": c.mismatch.k, "h": c.mismatch.h},
                "warmup": c.warmup, "phase1": c.phase1,
                "means": {n: m for n, m in self.monitor.means.items()},
                "clear_after": dict(self.clear_after)}


def _signals(message: dict[str, Any], alarms: tuple[Alarm, ...], index: int
             ) -> list[Alarm]:
    """A product's signals for its episodes: the charts' alarms, and the model-health
    alarm while the service's model-health episode is open."""
    health = message.get("model_health") or {}
    if health.get("state") != "model_mismatch":
        return list(alarms)
    k = float((health.get("rule") or {}).get("k", math.nan))
    return [*alarms, Alarm("model_health", "model_mismatch", index,
                           float(health.get("failing", 0)), k, "high")]


def _change(ch: Change) -> dict[str, Any]:
    """An episode change as it goes into the estimate message."""
    d = ch.episode.to_dict()
    return {"event": ch.kind, **{k: d[k] for k in (
        "variable", "chart", "side", "first", "last", "signals", "ratio", "statistic",
        "limit", "cleared")}}


__all__ = ["HEALTH_CLEAR_AFTER", "MonitorSource", "ServiceMonitor", "monitor_config",
           "values_of"]
