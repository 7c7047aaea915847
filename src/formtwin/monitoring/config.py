"""A monitor's configuration: what it watches and how (:class:`MonitorConfig`), the names
of the quantities it can watch (:data:`ANGLES`, :data:`HEALTH`) and their values in an
estimate (:func:`observe`)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from formtwin.estimates import Estimate
from formtwin.monitoring.charts import Cusum, Ewma
from formtwin.monitoring.glr import Glr
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


__all__ = ["ANGLES", "HEALTH", "MonitorConfig", "observe"]
