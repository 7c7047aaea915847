"""Feedforward plus feedback: the posterior's product-to-product correction and a run-to-run
EWMA of its own prediction error on the measured final angles.

Standard run-to-run practice combines a feedforward term (what is known of the product
before it is formed) with an EWMA feedback on the measured output (Moyne, del Castillo &
Hurwitz, *Run-to-run control in semiconductor manufacturing*, ch. 3). Here the feedforward
is :class:`~formtwin.control.Feedforward` over the posterior; the feedback estimates the
bias of its predictions (the metamodel's error, a posterior off under unknown statistics)::

    e_j  = a_j - m_j(u_j)              measured minus predicted angle of an earlier product
    b   <- lam e_j + (1 - lam) b
    u_i  = argmin_u  J(u) against the target T - b

so that ``m_i(u_i) + b = T``: the EWMA removes what persists in the prediction errors and the
feedforward adds what the posterior knows of product ``i`` itself. ``lam = 0`` is the open
feedforward; with a posterior that knows nothing of the product (``m_i`` constant) it is
the plain EWMA controller of :mod:`~formtwin.control.runtorun`.

>>> from formtwin.control.feedforward import Actuator, Feedforward
>>> import numpy as np
>>> c = Combined(Feedforward(90.0, Actuator(-100, 100)), lam=0.5)
>>> c.measured(angle=89.0, predicted=90.0)    # the model predicted 1 deg too high
-0.5
>>> s = c.choose(lambda u: 90.0 - 0.05 * np.asarray(u)[None, :])   # one particle
>>> round(s.u, 6), round(s.angle_mean, 6)      # aims the model at 90.5: -10 um, 90 deg
(-10.0, 90.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from formtwin.control.feedforward import AngleFunction, Feedforward, FloatArray, Suggestion


@dataclass
class Combined:
    """Feedforward with an EWMA trim of its prediction error (mutable: it keeps the trim).

    Attributes
    ----------
    feedforward : the feedforward controller (its target is the wanted angle).
    lam : EWMA weight of the newest prediction error, in [0, 1] (0: no feedback).
    bias : the current trim ``b``, degrees (the predictions' estimated bias).
    """

    feedforward: Feedforward
    lam: float
    bias: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.lam <= 1:
            raise ValueError(f"combined control lam = {self.lam}, expected 0 <= lam <= 1")

    def choose(self, final_angle: AngleFunction, weights: FloatArray | None = None,
               u_prev: float | None = None) -> Suggestion:
        """The feedforward's choice against the target minus the trim; the suggestion's
        predicted angle and interval include the trim (``m(u) + b``)."""
        ff = replace(self.feedforward, target=self.feedforward.target - self.bias)
        s = ff.choose(final_angle, weights, u_prev)
        b = self.bias
        return replace(s, angle_mean=s.angle_mean + b,
                       interval=(s.interval[0] + b, s.interval[1] + b))

    def measured(self, angle: float, predicted: float) -> float:
        """Take an earlier product's measured final ``angle`` and the model's prediction
        ``predicted`` of it at the setting it was made with (without the trim: the
        posterior mean ``m_j(u_j)``), degrees; return the new trim. Non-finite values are
        skipped."""
        if math.isfinite(angle) and math.isfinite(predicted):
            self.bias = self.lam * (angle - predicted) + (1 - self.lam) * self.bias
        return self.bias


__all__ = ["Combined"]
