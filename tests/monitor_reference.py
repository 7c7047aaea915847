"""The monitor as it charted before its arrays (:mod:`formtwin.monitoring.bank`): one Python
object per chart state, each chart's scalar update in turn. Kept as the reference the
vectorised :class:`~formtwin.monitoring.Monitor` is held to, bit for bit
(``tests/test_monitoring_bank.py``)."""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from formtwin.monitoring.charts import Alarm, CusumState, EwmaState
from formtwin.monitoring.config import MonitorConfig
from formtwin.monitoring.glr import GlrState
from formtwin.monitoring.incontrol import Reference


class ScalarMonitor:
    """EWMA, CUSUM, GLR and mismatch charts over a stream of estimates.

    Parameters
    ----------
    config : what to watch.
    state : a state from :meth:`state` to continue from; ``None``: a fresh start.

    """

    def __init__(self, config: MonitorConfig, state: Mapping[str, Any] | None = None) -> None:
        self.config = config
        self.n = 0  # products seen
        #: the chart statistics and limits of the last charted product, by quantity and
        #: chart (``{"thickness": {"ewma": (Z, limit), "cusum": (C, h)}, "ess":
        #: {"mismatch": (C, h)}}``, sigma units); empty before charting starts
        self.last: dict[str, dict[str, tuple[float, float]]] = {}
        #: every AR model by name: the quantities' and the health scores'
        self.models = {**config.quantities, **config.health_models}
        self.means = {n: q.mean for n, q in self.models.items()}
        self.phase1_sums = {n: 0.0 for n, q in self.models.items() if q.mean is None}
        self.history: dict[str, list[float]] = {n: [] for n in self.models}
        self.ewma = {n: EwmaState() for n in config.quantities}
        self.cusum = {n: CusumState() for n in config.quantities
                      if config.cusum_on is None or n in config.cusum_on}
        self.health = {n: CusumState() for n in config.health}
        self.glr = {n: GlrState() for n in config.glr}
        #: products seen (:attr:`n`) at each health statistic's last mismatch alarm
        self.alarmed_at: dict[str, int] = {}
        w = config.widen
        #: each quantity's charts with its limits (the design's times its ``widen``)
        self.charts = {n: (replace(config.ewma, L=config.ewma.L * w.get(n, {}).get("ewma", 1.0)),
                           replace(config.cusum, h=config.cusum.h * w.get(n, {}).get("cusum", 1.0)),
                           None if config.shewhart is None
                           else config.shewhart * w.get(n, {}).get("shewhart", 1.0))
                       for n in config.quantities}
        self.glr_charts = {n: replace(g, h=g.h * w.get(n, {}).get("glr", 1.0))
                           for n, g in config.glr.items()}
        self.mismatch = {n: replace(config.mismatch,
                                    h=config.mismatch.h * w.get(n, {}).get("mismatch", 1.0))
                         for n in config.health}
        #: the health statistics' Phase-I values on this line (``health_per_line``)
        self.phase1_health: dict[str, list[float]] = {n: [] for n in config.health}
        #: the references in force: the config's pooled ones, or this line's after Phase I
        self.references: dict[str, Reference] = dict(config.health)
        if state is not None:
            self._load(state)

    @property
    def charting(self) -> bool:
        """Whether the charts are running (warm-up and Phase I over)."""
        return self.n >= self.config.warmup + self.config.phase1

    def update_values(self, values: Mapping[str, float], index: int | None = None
                      ) -> tuple[Alarm, ...]:
        """Chart one product given its monitored values by name (see :func:`observe`);
        ``index`` defaults to the number of products seen before."""
        c = self.config
        idx = self.n if index is None else int(index)
        missing = [n for n in (*c.quantities, *c.health) if n not in values]
        if missing:
            raise ValueError(f"values lack {missing}; expected {list(c.quantities)} and "
                             f"{list(c.health)}")
        self.n += 1
        if self.n <= c.warmup:
            return ()
        per_line = c.health_per_line and self.n <= c.warmup + c.phase1
        if per_line:  # this line's health references: its Phase-I values, raw
            for n, vals in self.phase1_health.items():
                v = float(values[n])
                if math.isfinite(v):
                    vals.append(v)
        else:  # health: normal scores
            values = {**values, **{n: ref.normal_score(float(values[n]))
                                   for n, ref in self.references.items()}}
        if self.n <= c.warmup + c.phase1:
            for n in self.phase1_sums:
                self.phase1_sums[n] += float(values[n])
            if self.n == c.warmup + c.phase1:
                for n, total in self.phase1_sums.items():
                    self.means[n] = total / c.phase1
                if c.health_per_line:
                    self._line_references()
            self._remember(values, skip=c.health if per_line else ())
            return ()
        alarms: list[Alarm] = []
        self.last = {}
        for n, q in c.quantities.items():
            y, hist, mean = float(values[n]), self.history[n], self.means[n]
            if len(hist) < q.order or mean is None or not math.isfinite(y):
                continue
            z = q.score(y, hist, mean)
            ewma, cusum, shewhart = self.charts[n]
            self.ewma[n], s = ewma.update(self.ewma[n], z)
            last = self.last.setdefault(n, {})
            last["ewma"] = (s.statistic, s.limit)
            if s.side:
                alarms.append(Alarm(n, "ewma", idx, s.statistic, s.limit, s.side))
            if n in self.glr:
                self.glr[n], s = self.glr_charts[n].update(self.glr[n], z)
                last["glr"] = (s.statistic, s.limit)
                if s.side:
                    alarms.append(Alarm(n, "glr", idx, s.statistic, s.limit, s.side))
            if n not in self.cusum:
                continue
            self.cusum[n], s = cusum.update(self.cusum[n], z)
            last["cusum"] = (s.statistic, s.limit)
            if s.side:
                alarms.append(Alarm(n, "cusum", idx, s.statistic, s.limit, s.side))
            if shewhart is not None:
                last["shewhart"] = (z, shewhart)
                if abs(z) > shewhart:
                    alarms.append(Alarm(n, "shewhart", idx, z, shewhart,
                                        "high" if z > 0 else "low"))
        for n in c.health:
            z, hm = float(values[n]), c.health_models.get(n)
            if hm is not None:
                hist, mean = self.history[n], self.means[n]
                if len(hist) < hm.order or mean is None:
                    continue
                z = hm.score(z, hist, mean)
            self.health[n], s = self.mismatch[n].update(self.health[n], z)
            self.last[n] = {"mismatch": (s.statistic, s.limit)}
            if s.side:
                alarms.append(Alarm(n, "mismatch", idx, s.statistic, s.limit, s.side))
                self.alarmed_at[n] = self.n
        self._remember(values)
        self._follow(values)
        return tuple(alarms)

    def _follow(self, values: Mapping[str, float]) -> None:
        """Move each health model's level towards this product's score (``health_level``),
        except within 1 / ``health_level`` products of its mismatch chart's last alarm."""
        lam = self.config.health_level
        if lam is None:
            return
        for n in self.config.health_models:
            if self.n - self.alarmed_at.get(n, -(10**9)) < round(1.0 / lam):
                continue  # out of control: the level is not re-estimated from it
            m, y = self.means[n], float(values[n])
            if m is not None and math.isfinite(y):
                self.means[n] = m + lam * min(max(y - m, -3.0), 3.0)

    def _line_references(self) -> None:
        """Freeze this line's health references from its Phase-I values (the pooled one
        where there are fewer than 20)."""
        self.references = {n: ref.of_line(self.phase1_health[n])
                           for n, ref in self.config.health.items()}

    def _remember(self, values: Mapping[str, float], skip: Collection[str] = ()) -> None:
        """Add each AR model's value to its history (those in ``skip`` not)."""
        for n, q in self.models.items():
            if n in skip:
                continue
            y = float(values[n])
            if q.order and math.isfinite(y):
                self.history[n] = [*self.history[n], y][-q.order:]

    # ------------------------------------------------------------------ persistence
    def state(self) -> dict[str, Any]:
        """JSON-safe state (products seen, Phase-I sums and means, AR history, charts, the
        health statistics' Phase-I values and last mismatch alarms)."""
        return {"n": self.n, "means": dict(self.means), "phase1_sums": dict(self.phase1_sums),
                "history": {n: list(h) for n, h in self.history.items()},
                "ewma": {n: [s.z, s.i] for n, s in self.ewma.items()},
                "cusum": {n: [s.hi, s.lo] for n, s in self.cusum.items()},
                "health": {n: [s.hi, s.lo] for n, s in self.health.items()},
                "glr": {n: [s.sums.tolist(), s.i] for n, s in self.glr.items()},
                "phase1_health": {n: list(v) for n, v in self.phase1_health.items()},
                "alarmed_at": dict(self.alarmed_at)}

    def _load(self, st: Mapping[str, Any]) -> None:
        names, health = set(self.models), set(self.config.health)
        if (set(st["history"]) != names or set(st["health"]) != health
                or set(st["cusum"]) != set(self.cusum)):
            raise ValueError(f"monitor state watches {sorted(st['history'])} and "
                             f"{sorted(st['health'])}, the config {sorted(names)} and "
                             f"{sorted(health)}")
        self.n = int(st["n"])
        self.means = {n: None if v is None else float(v) for n, v in st["means"].items()}
        self.phase1_sums = {n: float(v) for n, v in st["phase1_sums"].items()}
        self.history = {n: [float(v) for v in h] for n, h in st["history"].items()}
        self.ewma = {n: EwmaState(float(z), int(i)) for n, (z, i) in st["ewma"].items()}
        self.cusum = {n: CusumState(float(a), float(b)) for n, (a, b) in st["cusum"].items()}
        self.health = {n: CusumState(float(a), float(b)) for n, (a, b) in st["health"].items()}
        glr = st.get("glr", {})
        if set(glr) - set(self.glr):
            raise ValueError(f"monitor state has GLR charts {sorted(glr)}, the config "
                             f"{sorted(self.glr)}")
        self.glr.update({n: GlrState(np.asarray(v, dtype=np.float64), int(i))
                         for n, (v, i) in glr.items()})
        self.phase1_health.update({n: [float(v) for v in vals] for n, vals in
                                   st.get("phase1_health", {}).items() if n in health})
        self.alarmed_at = {n: int(v) for n, v in st.get("alarmed_at", {}).items() if n in health}
        if self.config.health_per_line and self.charting:
            self._line_references()
