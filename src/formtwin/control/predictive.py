"""Feedforward on the posterior predictive of the measured final angle: the camera's late,
noisy values correct the posterior through a learned discrepancy, not through an EWMA of
raw values.

After product ``i``'s stage-1 curve (and the readings fused with it, e.g. a thickness
gauge's) the posterior gives ``c_i``, its mean final angle at a reference setting
``u_ref``, and ``m_i(u)``, its mean at any setting. A camera reads the final angle of
product ``j`` with Gaussian noise some products later. The camera's values are moved to
the reference setting by the posterior's own response to the setting (the model's gain is
reliable, what it does not know is the product)::

    A_j = y_j - (m_j(u_j) - c_j)

and a :class:`Corrector` learns the discrepancy between ``A_j`` and ``c_j``: its
predictive ``E[A_i | c_i, A_1..A_j]`` (for
:class:`~formtwin.tracker.angle_discrepancy.AngleDiscrepancy`: a dynamic linear
regression ``A = a_ref + b0 + b1 (c - a_ref) + e``, bias and slope learned by Kalman
updates, hypotheses of a static or drifting bias weighted by their evidence). The camera's
noise enters the corrector's gain: a noisy value moves the bias and slope little, many
values move them much; a slope ``b1`` below 1 discounts a posterior whose
product-to-product change does not show in the camera. The setting then minimises the
posterior expected squared error of the final angle predicted through the discrepancy::

    offset_i = E[A_i | c_i] - c_i
    u_i = argmin_u  sum_k w_k (a(x_k, u) + offset_i - T)^2

Compared with :class:`~formtwin.control.Combined` (an EWMA trim of the prediction errors
and an EWMA of ``c``, the trust in the posterior's change a clipped least-squares slope)
nothing is tuned on the line's data by hand: the weights of the camera's values follow
from their noise and the evidence.

>>> import numpy as np
>>> from formtwin.control.feedforward import Actuator, Feedforward
>>> class Bias:                       # a corrector that knows the model is 0.5 deg low
...     def predict(self, model_angle): return model_angle + 0.5, 0.01
...     def update(self, model_angle, value): return 0.0
>>> p = Predictive(Feedforward(90.0, Actuator(-100, 100)), Bias(), u_ref=0.0)
>>> s = p.choose(0, lambda u: 90.0 - 0.05 * np.asarray(u)[None, :])   # model: 90 at 0
>>> round(s.u, 6), round(s.angle_mean, 6)      # aims the model at 89.5: +10, 90 predicted
(10.0, 90.0)
>>> p.measured(0, 90.1)    # the camera's value, moved to u_ref: 90.1 - (89.5 - 90) = 90.6
90.6
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Protocol

from formtwin.control.feedforward import (
    AngleFunction,
    Feedforward,
    FloatArray,
    Suggestion,
    reference_angle,
)


class Corrector(Protocol):
    """What :class:`Predictive` needs of a learned discrepancy (degrees throughout)."""

    def predict(self, model_angle: float) -> tuple[float, float]:
        """Mean and variance of the measured angle for the model's ``model_angle``."""

    def update(self, model_angle: float, value: float) -> float:
        """Learn from one measured ``value`` of a product whose model angle was
        ``model_angle``; returns the value's log evidence."""


@dataclass
class Predictive:
    """Feedforward on the posterior predictive through a learned discrepancy (mutable: the
    corrector learns, the settings' predictions wait for their camera values).

    Attributes
    ----------
    feedforward : the feedforward controller (its target is the wanted angle).
    corrector : the learned discrepancy of the camera's values at ``u_ref``.
    u_ref : the reference setting of ``c_i``.
    pending : product -> ``(c_j, m_j(u_j))`` of the products whose camera value has not
        arrived.
    """

    feedforward: Feedforward
    corrector: Corrector
    u_ref: float = 0.0
    pending: dict[int, tuple[float, float]] = field(default_factory=dict)

    def reference(self, final_angle: AngleFunction, weights: FloatArray | None = None) -> float:
        """``c_i``: the posterior mean of the final angle at ``u_ref``, degrees (NaN if no
        particle gives a finite angle)."""
        return reference_angle(final_angle, self.u_ref, weights)

    def offset(self, reference: float) -> tuple[float, float]:
        """The discrepancy's shift of the posterior's angle, ``E[A | c] - c``, and the
        predictive variance, degrees and degrees^2 (0 and NaN for a non-finite ``c``)."""
        if not math.isfinite(reference):
            return 0.0, math.nan
        mean, var = self.corrector.predict(reference)
        return mean - reference, var

    def choose(self, product: int, final_angle: AngleFunction,
               weights: FloatArray | None = None, u_prev: float | None = None,
               reference: float | None = None) -> Suggestion:
        """Product ``product``'s setting: the feedforward against the target minus the
        discrepancy's shift (``reference`` is ``c_i``, None: computed here). The
        suggestion's predicted angle and interval include the shift; its ``angle_std``
        is the posterior predictive's (the corrector's) where finite."""
        c = self.reference(final_angle, weights) if reference is None else float(reference)
        b, var = self.offset(c)
        ff = replace(self.feedforward, target=self.feedforward.target - b)
        s = ff.choose(final_angle, weights, u_prev)
        if math.isfinite(c) and math.isfinite(s.angle_mean):
            self.pending[int(product)] = (c, s.angle_mean)
        std = math.sqrt(var) if math.isfinite(var) and var >= 0 else s.angle_std
        return replace(s, angle_mean=s.angle_mean + b, angle_std=std,
                       interval=(s.interval[0] + b, s.interval[1] + b))

    def measured(self, product: int, value: float) -> float:
        """Take the camera's ``value`` (degrees) of an earlier product; returns it moved to
        ``u_ref`` (``A_j``), NaN for a non-finite value or a product not chosen here.
        Products before ``product`` still waiting are dropped (values arrive in order)."""
        got = self.pending.pop(int(product), None)
        for stale in [k for k in self.pending if k < product]:
            del self.pending[stale]
        if got is None or not math.isfinite(value):
            return math.nan
        c, m = got
        a = float(value) - (m - c)
        self.corrector.update(c, a)
        return a


__all__ = ["Corrector", "Predictive"]
