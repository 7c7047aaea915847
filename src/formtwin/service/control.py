"""Feedforward control in the service: every accepted estimate carries the suggested press
setting for its product.

After the tracker has assimilated a product's stage-1 curve, :class:`ServiceController`
asks it for the setting ``u`` of the spec's one control that minimises the posterior
expected squared error of the final angle against the target
(:meth:`formtwin.tracker.Tracker.suggest`, :class:`formtwin.control.Feedforward`), within
the actuator's limits (the spec's bounds of the control) and a maximum step from the
previous suggestion. The estimate message gets::

    "control": {"target_deg": 90.0, "u": [0.012], "u_unit": "mm",
                "final_angle_deg": 89.98, "final_angle_std_deg": 0.11,
                "interval_deg": [89.8, 90.2], "coverage": 0.9, "limited": false}

The previous suggestion (for the maximum step) is the one stored with the last accepted
product, so a restarted service continues from it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from formtwin.control import Actuator, Feedforward
from formtwin.service.store import Store

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ControlSettings:
    """The service's feedforward settings.

    Attributes
    ----------
    target_deg : wanted final angle, degrees.
    max_step : largest change of ``u`` per product as a share of its range (0 < s <= 1).
    """

    target_deg: float
    max_step: float = 0.25

    def __post_init__(self) -> None:
        if not 0 < self.max_step <= 1:
            raise ValueError(f"control max_step = {self.max_step}, expected in (0, 1]")


class ServiceController:
    """Suggests each product's setting (see the module doc).

    Parameters
    ----------
    tracker : the service's tracker (needs ``suggest`` and ``spec`` with one control).
    settings : target and maximum step.
    store : the store, to continue from the last stored suggestion.
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
        self.controller = Feedforward(settings.target_deg,
                                      Actuator(lo, hi, settings.max_step * (hi - lo)))
        self.u_prev: float | None = None
        for row in store.products(since_seq=max(store.next_seq() - 50, 0), status="accepted"):
            ctl = (row.estimate or {}).get("control")
            if ctl and ctl.get("u"):
                self.u_prev = float(ctl["u"][0])
        self._saved: tuple[float | None] | None = None

    def observe(self, message: dict[str, Any]) -> dict[str, Any]:
        """The ``"control"`` entry for the product just stepped (:meth:`rollback` undoes
        the change of the previous suggestion)."""
        self._saved = (self.u_prev,)
        s = self.tracker.suggest(self.controller, self.u_prev)
        self.u_prev = s.u
        d = s.to_dict()
        return {"target_deg": self.settings.target_deg, "u": [d["u"]], "u_unit": self.unit,
                "final_angle_deg": d["angle_mean"], "final_angle_std_deg": d["angle_std"],
                "interval_deg": d["interval"], "coverage": self.controller.coverage,
                "limited": d["limited"]}

    def rollback(self) -> None:
        """Undo the last :meth:`observe` (its product was not committed)."""
        if self._saved is not None:
            (self.u_prev,) = self._saved
            self._saved = None


__all__ = ["ControlSettings", "ServiceController"]
