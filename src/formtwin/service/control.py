"""Feedforward control in the service: every accepted estimate carries the suggested press
setting for its product.

After the tracker has assimilated a product's stage-1 curve, :class:`ServiceController`
asks :class:`formtwin.control.Combined` (feedforward plus feedback, the closed-loop study's
controller: by default the weight of the posterior's change learned on the line, with the
study's ``lam`` and ``rho``, :data:`formtwin.control.TUNED_LAM`,
:data:`~formtwin.control.TUNED_RHO`; :meth:`ControlSettings.fixed_weight` the study's best
fixed weight, :data:`~formtwin.control.TUNED_FIXED_WEIGHT`) for the setting
``u`` of the spec's one control that minimises the posterior expected squared error of the
final angle over the particles against the target minus a trim, minus the untrusted share
``1 - weight`` of the posterior's product-to-product change and minus what persists (``rho``)
of the last product's deviation, within the actuator's limits (the spec's bounds of
the control) and a maximum step from the previous suggestion. The trim is an EWMA (weight
``lam``) of the model's prediction error on measured final angles: a stroke message's
optional ``angles_deg`` (the product's measured angles, final angle second; validated like
the curve) against the tracker's predicted final angle at the stroke's ``u``; the level is
the EWMA (same ``lam``) of the posterior mean of the final angle at the nominal setting over
the measured products. A stroke without measured angles leaves both as they are (``lam = 0``
or no measured angles: the open feedforward). The estimate message gets::

    "control": {"target_deg": 90.0, "u": [0.012], "u_unit": "mm",
                "final_angle_deg": 89.98, "final_angle_std_deg": 0.11,
                "interval_deg": [89.8, 90.2], "coverage": 0.9, "limited": false,
                "trim_deg": -0.05, "level_deg": 90.02, "last_error_deg": 0.01,
                "last_reference_deg": 90.03, "lam": 0.02, "weight": 0.41, "rho": 0.7,
                "adaptive": true, "weight_sxy": 0.012, "weight_sxx": 0.029}

``final_angle_deg`` and the interval are the predicted final angle at ``u``, with the shift
used for the suggestion; ``trim_deg``, ``level_deg``, ``last_error_deg`` and
``last_reference_deg`` are the controller's state after this product's measured angle (used
for the next product; null before the first measured angle); with the learned weight
(``adaptive``) so are ``weight`` and its least-squares sums ``weight_sxy``, ``weight_sxx``.
The suggestion is made before the product's own measured angle is used. The previous
suggestion (for the maximum step) and the controller's state are those stored with the last
accepted product, so a restarted service continues from them bit for bit. The closed-loop
study (``docs/explanation/control.md``) measured this controller against the open feedforward, the
run-to-run EWMA and an oracle.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from formtwin.control import (
    TUNED_FIXED_LAM,
    TUNED_FIXED_RHO,
    TUNED_FIXED_WEIGHT,
    TUNED_LAM,
    TUNED_RHO,
    Actuator,
    Combined,
    Feedforward,
)
from formtwin.service.store import Store

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ControlSettings:
    """The service's feedforward settings (default: the weight learned on the line, the
    control study's controller; :meth:`fixed_weight`: its best fixed weight).

    Attributes
    ----------
    target_deg : wanted final angle, degrees.
    max_step : largest change of ``u`` per product as a share of its range (0 < s <= 1).
    lam : EWMA weight of the trim (the newest measured prediction error) and of the level,
        in [0, 1]; default: the closed-loop study's tuning.
    weight : share of the posterior's product-to-product change trusted, in [0, 1] (1: all
        of it); with ``adaptive`` the start of the learned weight (default 0, as in the
        study).
    rho : persistence of the last product's deviation from the level, in [0, 1); default:
        the closed-loop study's tuning.
    adaptive : learn the weight on the line (``Combined(adaptive=True)``, starting at
        ``weight``; the control study's feedforward, docs/explanation/control.md).
    """

    target_deg: float
    max_step: float = 0.25
    lam: float = TUNED_LAM
    weight: float = 0.0
    rho: float = TUNED_RHO
    adaptive: bool = True

    def __post_init__(self) -> None:
        if not 0 < self.max_step <= 1:
            raise ValueError(f"control max_step = {self.max_step}, expected in (0, 1]")
        if not 0 <= self.lam <= 1:
            raise ValueError(f"control lam = {self.lam}, expected in [0, 1]")
        if not 0 <= self.weight <= 1:
            raise ValueError(f"control weight = {self.weight}, expected in [0, 1]")
        if not 0 <= self.rho < 1:
            raise ValueError(f"control rho = {self.rho}, expected in [0, 1)")

    @classmethod
    def fixed_weight(cls, target_deg: float, max_step: float = 0.25,
                     lam: float = TUNED_FIXED_LAM, weight: float = TUNED_FIXED_WEIGHT,
                     rho: float = TUNED_FIXED_RHO) -> ControlSettings:
        """The settings with a fixed weight (default: the control study's best fixed
        weight and its ``lam`` and ``rho``)."""
        return cls(target_deg, max_step, lam, weight, rho, adaptive=False)


class ServiceController:
    """Suggests each product's setting (see the module doc).

    Parameters
    ----------
    tracker : the service's tracker (needs ``final_angle``, ``weights`` and ``spec`` with
        one control).
    settings : target, maximum step, the trim's and the level's weight, the feedforward's.
    store : the store, to continue from the last stored suggestion, trim and level.
    """

    def __init__(self, tracker: Any, settings: ControlSettings, store: Store) -> None:
        spec = tracker.spec
        if len(spec.controls) != 1:
            raise ValueError(f"feedforward control needs one control in the spec, it has "
                             f"{len(spec.controls)} ({', '.join(spec.controls.names)})")
        c = spec.controls
        lo, hi = float(c.lo[0]), float(c.hi[0])
        self.tracker = tracker
        self.settings = settings
        self.unit = str(c.variables[0].internal_unit)
        self.controller = Combined(Feedforward(settings.target_deg,
                                               Actuator(lo, hi, settings.max_step * (hi - lo))),
                                   settings.lam, settings.weight, float(c.nominal[0]),
                                   rho=settings.rho, adaptive=settings.adaptive)
        self.u_prev: float | None = None
        for row in store.products(since_seq=max(store.next_seq() - 50, 0), status="accepted"):
            ctl = (row.estimate or {}).get("control")
            if ctl and ctl.get("u"):
                self.u_prev = float(ctl["u"][0])
                self.controller.bias = float(ctl.get("trim_deg") or 0.0)
                for name, key in _STATE:
                    v = ctl.get(key)
                    setattr(self.controller, name, None if v is None else float(v))
                if settings.adaptive and ctl.get("adaptive"):  # the learned weight's state
                    for name, key in _LEARNED:
                        setattr(self.controller, name, float(ctl[key]))
        self._saved: tuple[Any, ...] | None = None

    def observe(self, message: dict[str, Any]) -> dict[str, Any]:
        """The ``"control"`` entry for the product just stepped (:meth:`rollback` undoes
        the change of the controller's state)."""
        ctl = self.controller
        self._saved = (self.u_prev, ctl.bias, *(getattr(ctl, n) for n, _ in _STATE + _LEARNED))
        w = self.tracker.weights()
        # c_i: the posterior mean at the nominal setting
        ref = ctl.reference(self.tracker.final_angle, w) if ctl.uses_reference else None
        s = self.tracker.suggest(ctl, self.u_prev, ref)
        self.u_prev = s.u
        d = s.to_dict()
        measured = message.get("measured_angles_deg")
        predicted = (message.get("angles_mean") or [None, None])[1]
        if measured is not None and predicted is not None:  # the model's error at the u used
            ctl.measured(float(measured[1]), float(predicted), ref)
        return {"target_deg": self.settings.target_deg, "u": [d["u"]], "u_unit": self.unit,
                "final_angle_deg": d["angle_mean"], "final_angle_std_deg": d["angle_std"],
                "interval_deg": d["interval"], "coverage": ctl.feedforward.coverage,
                "limited": d["limited"], "trim_deg": _num(ctl.bias),
                **{key: _num(getattr(ctl, name)) for name, key in _STATE},
                "lam": ctl.lam, "weight": ctl.weight, "rho": ctl.rho,
                **({"adaptive": True, "weight_sxy": ctl.sxy, "weight_sxx": ctl.sxx}
                   if ctl.adaptive else {})}

    def rollback(self) -> None:
        """Undo the last :meth:`observe` (its product was not committed)."""
        if self._saved is not None:
            self.u_prev, self.controller.bias, *state = self._saved
            for (name, _), v in zip(_STATE + _LEARNED, state, strict=True):
                setattr(self.controller, name, v)
            self._saved = None


#: the controller's state besides the trim: (attribute of Combined, key in the message)
_STATE = (("level", "level_deg"), ("last_error", "last_error_deg"),
          ("last_reference", "last_reference_deg"))
#: the learned weight's state (``adaptive``): (attribute of Combined, key in the message)
_LEARNED = (("weight", "weight"), ("sxy", "weight_sxy"), ("sxx", "weight_sxx"))


def _num(v: float | None) -> float | None:
    """``v``, or None when missing or not finite (JSON)."""
    return v if v is not None and math.isfinite(v) else None


__all__ = ["ControlSettings", "ServiceController"]
