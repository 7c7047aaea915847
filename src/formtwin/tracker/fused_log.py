"""Which sensor values the tracker fused, and the final angle's calibration by the camera.

:class:`FusedLog` is the small part of the tracker's state that
:class:`~formtwin.tracker.SensorFusion` keeps besides the particles and their weights: the
(product, sensor) pairs fused over the last ``L + 1`` products (each is fused once), the
adaptive conformal calibration of the final angle's interval
(:mod:`formtwin.tracker.conformal`) and the model's final-angle discrepancy learned from the
camera (:mod:`formtwin.tracker.angle_discrepancy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from formtwin.tracker.angle_discrepancy import AngleDiscrepancy
from formtwin.tracker.conformal import AdaptiveConformal


@dataclass
class FusedLog:
    """Which (product, sensor) values were fused, over the last ``L + 1`` products, and the
    final angle's interval calibration by the fused camera values (:attr:`conformal`).

    ``sensors`` are the config's sensor names (the state stores their positions)."""

    sensors: tuple[str, ...]
    done: set[tuple[int, str]] = field(default_factory=set)
    conformal: AdaptiveConformal = field(default_factory=AdaptiveConformal)
    #: the model's final-angle discrepancy learned from the camera (None: not yet made)
    discrepancy: AngleDiscrepancy | None = None
    #: sensor -> value of the next product, known before its curve: for its step
    #: (:mod:`formtwin.tracker.ahead`)
    ahead: dict[str, float] = field(default_factory=dict)

    def state(self) -> dict[str, list[float]]:
        """The log as JSON numbers: ``fused`` ``[product, sensor position, ...]``, the
        calibration's ``aci_alpha``, ``aci_scores`` and ``aci_pending`` ``[product, mean,
        scale, q, ...]``, ``final_discrepancy`` ``[noise_var, *AngleDiscrepancy.state()]``,
        ``ahead`` ``[sensor position, value, ...]`` (keys only where there is something)."""
        out: dict[str, list[float]] = {}
        if self.done:
            pairs = sorted((p, self.sensors.index(s)) for p, s in self.done)
            out["fused"] = [float(v) for pair in pairs for v in pair]
        if self.ahead:
            out["ahead"] = [float(v) for name, value in sorted(self.ahead.items())
                            for v in (self.sensors.index(name), value)]
        d = self.discrepancy
        if d is not None and math.isfinite(d.ref):
            out["final_discrepancy"] = [d.noise_var, *d.state()]
        c = self.conformal
        if c.scores or c.pending:
            out["aci_alpha"], out["aci_scores"] = [c.alpha], list(c.scores)
            out["aci_pending"] = [float(v) for p, t in sorted(c.pending.items())
                                  for v in (p, *t)]
        return out

    def set_state(self, model: dict[str, list[float]]) -> None:
        """Inverse of :meth:`state`."""
        flat = [int(v) for v in model.get("fused", [])]
        self.done = {(flat[i], self.sensors[flat[i + 1]]) for i in range(0, len(flat), 2)}
        ahead = model.get("ahead", [])
        self.ahead = {self.sensors[int(ahead[i])]: float(ahead[i + 1])
                      for i in range(0, len(ahead), 2)}
        pend = model.get("aci_pending", [])
        c = AdaptiveConformal(alpha=float(model.get("aci_alpha", [math.nan])[0]),
                              scores=[float(v) for v in model.get("aci_scores", [])])
        c.pending = {int(pend[i]): (float(pend[i + 1]), float(pend[i + 2]), float(pend[i + 3]))
                     for i in range(0, len(pend), 4)}
        self.conformal = c
        disc = model.get("final_discrepancy")
        self.discrepancy = None
        if disc:
            self.discrepancy = AngleDiscrepancy(float(disc[0]))
            self.discrepancy.set_state(list(disc[1:]))

    def forget(self, oldest: int) -> None:
        """Drop the predictions issued for products before ``oldest`` (their camera
        values can no longer be fused)."""
        for pending in (self.conformal.pending, {} if self.discrepancy is None
                        else self.discrepancy.pending):
            for p in [p for p in pending if p < oldest]:
                del pending[p]

    def learned(self, noise_var: float) -> AngleDiscrepancy:
        """The final angle's discrepancy, made with the prior variance ``noise_var``
        (degrees^2) at first use."""
        if self.discrepancy is None:
            self.discrepancy = AngleDiscrepancy(noise_var)
        return self.discrepancy


__all__ = ["FusedLog"]
