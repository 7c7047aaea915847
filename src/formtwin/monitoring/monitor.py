"""Control charts on a stream of estimates: an EWMA chart per quantity, a CUSUM and a GLR
chart for a level change (:mod:`~formtwin.monitoring.glr`) on those configured, and a
model-mismatch chart on the filter's health; alarms: :class:`~formtwin.monitoring.charts.Alarm`.

Quantities: the posterior means of the state variables (``spec.state.names``) and the
predicted outputs (``spec.output_names``: the demonstrator's ``angle_stage1``,
``angle_stage2``), each standardised by its in-control
AR model (:class:`~formtwin.monitoring.incontrol.InControl`) into a residual ``z`` that is
N(0, 1) and independent in control. Health: the log-evidence increment ``loglik`` and the
ESS of each step, as normal scores against their simulated in-control distribution
(:class:`~formtwin.monitoring.incontrol.Reference`), each on a one-sided CUSUM that signals
a worse fit only.

Life of a monitor: the first ``warmup`` products are not charted (the filter is still
converging from its prior); the next ``phase1`` products estimate the in-control mean of
every quantity whose mean is not set (Phase I, Montgomery ch. 7.1: the angles' level
depends on the machine parameters, known only once the line runs); charting starts after
that. With ``health_per_line`` the health statistics' references are the line's own
Phase-I values, frozen at its end (the filter's health depends on the line: with the
deviation estimated its ESS does on ``theta_d``). A chart that signals restarts from zero.

The state is a JSON-safe dict (:meth:`Monitor.state`); ``Monitor(config, state)`` continues
exactly where the saved one stopped.
"""

from __future__ import annotations

import json
import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from formtwin.estimates import Estimate
from formtwin.monitoring.charts import Alarm, Cusum, CusumState, Ewma, EwmaState
from formtwin.monitoring.glr import Glr, GlrState
from formtwin.monitoring.incontrol import InControl, Reference

#: names of the demonstrator's predicted angles as monitored quantities (a spec's own are
#: ``spec.output_names``, carried by every estimate as ``output_names``)
ANGLES = ("angle_stage1", "angle_stage2")
#: health statistics of a step that the mismatch chart can watch, with their bad side:
#: the log-evidence increment, the ESS, and the absolute fit's log10 p-value
#: (:mod:`formtwin.tracker.fit`; NaN where an estimate has none)
HEALTH = {"loglik": "low", "ess": "low", "fit": "low"}


@dataclass(frozen=True)
class MonitorConfig:
    """What to watch and how (immutable; JSON with :meth:`to_json`).

    Attributes
    ----------
    quantities : name -> in-control model, for state variables and angles.
    health : name (a key of :data:`HEALTH`) -> in-control reference (maps the statistic to
        a normal score, large = worse fit).
    health_models : name -> in-control AR model of that normal score (its level, often
        set in Phase I: it depends on the machine parameters); the mismatch chart then
        watches the model's residual. Missing: the score itself.
    ewma, cusum : the charts (design: :class:`~formtwin.monitoring.calibrate.ChartDesign`):
        the EWMA on every quantity, the CUSUM on those of ``cusum_on``.
    cusum_on : the quantities with a CUSUM chart; ``None``: all. (The angles' level comes
        from Phase I, whose error a CUSUM tuned for small shifts would take for a shift.)
    shewhart : limit on ``|z|`` of a single product for the quantities with a CUSUM (the
        combined Shewhart-CUSUM, Lucas 1982; Montgomery ch. 9.1.7): the jump of the
        residual when a state mean steps is seen at once; ``None``: no such limit.
    mismatch : the one-sided CUSUM on every health score.
    glr : quantity -> GLR chart for a level change (:mod:`~formtwin.monitoring.glr`; its
        signature follows from the quantity's AR model); empty: none.
    warmup : products not charted at the start.
    phase1 : products after the warm-up that estimate the means left ``None``.
    health_per_line : the health references are the line's own Phase-I values (frozen at
        its end; ``health``'s pooled samples give the orientation, and stand in if Phase I
        has fewer than 20 finite values); the health models' means must be set (their
        scores exist only after Phase I).
    health_level : the health models' levels follow the line: once charting, each product
        moves a level by this share of its score's deviation from it (clipped to +-3), an
        EWMA whose time constant (1 / share products) is long against a mismatch's
        detection and short against the filter's health transient (docs/explanation/monitoring.md);
        not re-estimated from out-of-control data: a level pauses from its mismatch
        chart's alarm until that chart has been quiet for one time constant, so a
        mismatch that persists stays signalled; ``None``: the levels stay at the
        calibration lines' (or Phase I's).
    """

    quantities: Mapping[str, InControl]
    health: Mapping[str, Reference] = field(default_factory=dict)
    health_models: Mapping[str, InControl] = field(default_factory=dict)
    ewma: Ewma = Ewma()
    cusum: Cusum = Cusum()
    mismatch: Cusum = Cusum(sides="high")
    warmup: int = 50
    phase1: int = 100
    cusum_on: tuple[str, ...] | None = None
    shewhart: float | None = None
    widen: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    glr: Mapping[str, Glr] = field(default_factory=dict)
    health_per_line: bool = False
    health_level: float | None = None

    def __post_init__(self) -> None:
        bad_w = {f"{n}/{c}": f for n, d in self.widen.items() for c, f in d.items()
                 if not (math.isfinite(f) and f >= 1.0)}
        if bad_w:
            raise ValueError(f"limit factors {bad_w}: expected numbers >= 1")
        if self.shewhart is not None and not self.shewhart > 0:
            raise ValueError(f"shewhart limit = {self.shewhart}, expected > 0 or None")
        if self.cusum_on is not None:
            object.__setattr__(self, "cusum_on", tuple(self.cusum_on))
            unknown = [n for n in self.cusum_on if n not in self.quantities]
            if unknown:
                raise ValueError(f"cusum_on names {unknown}, not charted quantities")
        unknown_glr = [n for n in self.glr if n not in self.quantities]
        if unknown_glr:
            raise ValueError(f"GLR charts for {unknown_glr}, not charted quantities")
        bad = [n for n in self.health if n not in HEALTH]
        if bad:
            raise ValueError(f"health statistics {bad} unknown; known: {', '.join(HEALTH)}")
        if self.warmup < 0 or self.phase1 < 0:
            raise ValueError(f"warmup = {self.warmup}, phase1 = {self.phase1}: expected >= 0")
        extra = [n for n in self.health_models if n not in self.health]
        if extra:
            raise ValueError(f"health models for {extra} without a health reference")
        needs_phase1 = [n for n, q in (*self.quantities.items(), *self.health_models.items())
                        if q.mean is None]
        if needs_phase1 and self.phase1 < 2:
            raise ValueError(f"quantities {needs_phase1} have no in-control mean and "
                             f"phase1 = {self.phase1}: expected phase1 >= 2")
        if self.mismatch.sides != "high":
            raise ValueError("the mismatch chart is one-sided: expected Cusum(sides='high')")
        if self.health_per_line and any(q.mean is None for q in self.health_models.values()):
            raise ValueError("health_per_line: the health models need their means (the "
                             "scores exist only after Phase I)")
        if self.health_level is not None and not 0.0 < self.health_level < 1.0:
            raise ValueError(f"health_level = {self.health_level}: expected in (0, 1)")

    def to_json(self) -> str:
        return json.dumps({
            "quantities": {n: q.to_dict() for n, q in self.quantities.items()},
            "health": {n: {"sample": list(r.sample), "bad": r.bad}
                       for n, r in self.health.items()},
            "health_models": {n: q.to_dict() for n, q in self.health_models.items()},
            "ewma": {"lam": self.ewma.lam, "L": self.ewma.L},
            "cusum": {"k": self.cusum.k, "h": self.cusum.h},
            "mismatch": {"k": self.mismatch.k, "h": self.mismatch.h},
            "warmup": self.warmup, "phase1": self.phase1, "cusum_on": self.cusum_on,
            "shewhart": self.shewhart,
            "widen": {n: dict(d) for n, d in self.widen.items()},
            "glr": {n: {"signature": list(g.signature), "h": g.h, "window": g.window,
                        "clip": g.clip} for n, g in self.glr.items()},
            "health_per_line": self.health_per_line, "health_level": self.health_level})

    @classmethod
    def from_json(cls, text: str) -> MonitorConfig:
        d = json.loads(text)
        return cls(quantities={n: InControl.from_dict(q) for n, q in d["quantities"].items()},
                   health={n: Reference(tuple(r["sample"]), r["bad"])
                           for n, r in d["health"].items()},
                   health_models={n: InControl.from_dict(q)
                                  for n, q in d.get("health_models", {}).items()},
                   ewma=Ewma(**d["ewma"]), cusum=Cusum(**d["cusum"]),
                   mismatch=Cusum(**d["mismatch"], sides="high"),
                   warmup=int(d["warmup"]), phase1=int(d["phase1"]),
                   cusum_on=None if d.get("cusum_on") is None else tuple(d["cusum_on"]),
                   shewhart=None if d.get("shewhart") is None else float(d["shewhart"]),
                   widen={n: {c: float(f) for c, f in w.items()}
                          for n, w in d.get("widen", {}).items()},
                   glr={n: Glr(tuple(g["signature"]), float(g["h"]), int(g["window"]),
                               None if g.get("clip") is None else float(g["clip"]))
                        for n, g in d.get("glr", {}).items()},
                   health_per_line=bool(d.get("health_per_line", False)),
                   health_level=d.get("health_level"))


def observe(estimate: Estimate) -> dict[str, float]:
    """The monitored values of one estimate: state posterior means, predicted angles and
    the health statistics, by name."""
    out = {n: float(v) for n, v in zip(estimate.names, estimate.mean, strict=True)}
    out.update({n: float(v) for n, v in zip(estimate.output_names, estimate.angles_mean,
                                            strict=True)})
    out.update(loglik=float(estimate.loglik), ess=float(estimate.ess),
               fit=math.nan if estimate.fit is None else float(estimate.fit.log10_p))
    return out


class Monitor:
    """EWMA, CUSUM, GLR and mismatch charts over a stream of estimates.

    Parameters
    ----------
    config : what to watch.
    state : a state from :meth:`state` to continue from; ``None``: a fresh start.

    Examples
    --------
    >>> ic = {"thickness": InControl(mean=0.3, sigma=0.001)}
    >>> mon = Monitor(MonitorConfig(ic, warmup=0, phase1=0, cusum=Cusum(k=0.5, h=4.0)))
    >>> [a.chart for v in (0.3, 0.3, 0.305) for a in mon.update_values({"thickness": v})]
    ['ewma', 'cusum']
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

    def update(self, estimate: Estimate) -> tuple[Alarm, ...]:
        """Chart one estimate; the alarms it raises (usually none)."""
        return self.update_values(observe(estimate), estimate.index)

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


__all__ = ["ANGLES", "HEALTH", "Alarm", "Monitor", "MonitorConfig", "observe"]
