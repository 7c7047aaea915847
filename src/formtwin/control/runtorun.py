"""Run-to-run EWMA control of the final angle: today's practice on a line.

The line measures each product's final angle after it has left the press; the controller
knows the process only through a linear model with gain ``b`` (degrees per unit of ``u``)
and an offset ``d`` that drifts::

    a_i = b u_i + d_i + noise

and after each measured product updates an EWMA estimate of the offset and sets the next
setting to cancel it (Sachs, Hu & Ingolfsson 1995; Moyne, del Castillo & Hurwitz,
*Run-to-run control in semiconductor manufacturing*, ch. 1)::

    d_hat <- lam (a_i - b u_i) + (1 - lam) d_hat
    u_next = clip((T - d_hat) / b)          (actuator limits and maximum step)

A measurement arrives ``delay`` products late (the camera sits after stage 2, the press
has already formed the next products): the caller feeds each measurement when it arrives.

>>> from formtwin.control.feedforward import Actuator
>>> r2r = EwmaRunToRun(target=90.0, gain=-0.05, lam=1.0, actuator=Actuator(-100, 100))
>>> r2r.update(angle=88.0, u=0.0)   # offset 88 deg: u = (90 - 88) / -0.05
-40.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from formtwin.control.feedforward import Actuator


@dataclass
class EwmaRunToRun:
    """EWMA run-to-run controller (mutable: it keeps ``d_hat`` and the last setting).

    Attributes
    ----------
    target : wanted final angle, degrees.
    gain : ``b``, degrees per unit of ``u`` (its sign matters; nonzero).
    lam : EWMA weight of the newest measurement, in (0, 1].
    actuator : limits and maximum step of ``u``.
    u : the current setting (starts at ``u0``).
    d_hat : the offset estimate (``None`` until the first measurement).
    """

    target: float
    gain: float
    lam: float
    actuator: Actuator
    u: float = 0.0
    d_hat: float | None = field(default=None)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gain) and self.gain != 0):
            raise ValueError(f"run-to-run gain = {self.gain}, expected a nonzero number")
        if not 0 < self.lam <= 1:
            raise ValueError(f"run-to-run lam = {self.lam}, expected 0 < lam <= 1")
        self.u = self.actuator.clip(self.u)

    def update(self, angle: float, u: float) -> float:
        """Take the measured final ``angle`` of a product made with setting ``u``; return
        the setting for the next product (non-finite measurements are skipped)."""
        if math.isfinite(angle):
            d = angle - self.gain * u
            self.d_hat = d if self.d_hat is None else self.lam * d + (1 - self.lam) * self.d_hat
            self.u = self.actuator.clip((self.target - self.d_hat) / self.gain, self.u)
        return self.u


__all__ = ["EwmaRunToRun"]
