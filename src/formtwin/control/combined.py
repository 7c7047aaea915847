"""Feedforward plus feedback: the posterior's product-to-product correction and a run-to-run
EWMA of its own prediction error on the measured final angles.

Standard run-to-run practice combines a feedforward term (what is known of the product
before it is formed) with an EWMA feedback on the measured output (Moyne, del Castillo &
Hurwitz, *Run-to-run control in semiconductor manufacturing*, ch. 3). Here the feedforward
is :class:`~formtwin.control.Feedforward` over the posterior; the feedback estimates the
bias of its predictions (the metamodel's error, a posterior off under unknown statistics)::

    e_j  = a_j - m_j(u_j)              measured minus predicted angle of an earlier product
    b   <- lam e_j + (1 - lam) b       (b = e_j at the first measured product)
    u_i  = argmin_u  J(u) against the target T - b

so that ``m_i(u_i) + b = T``: the EWMA removes what persists in the prediction errors and the
feedforward adds what the posterior knows of product ``i`` itself. ``lam = 0`` is the open
feedforward (``b`` stays 0); with a posterior that knows nothing of the product (``m_i``
constant) it is the plain EWMA controller of :mod:`~formtwin.control.runtorun`.

The feedforward's ``weight`` ``w`` in [0, 1] says how much of the posterior's
product-to-product change to trust. With ``c_i`` the posterior mean of the final angle at a
reference setting ``u_ref`` and ``k`` its EWMA over the measured products (same ``lam``)::

    k   <- lam c_j + (1 - lam) k
    u_i  = argmin_u  J(u) against  T - b + (1 - w) (c_i - k)

so the predicted angle at ``u_ref`` is ``(b + k) + w (c_i - k)``: the EWMA of the measured
angles (moved to ``u_ref`` by the model's gain) plus ``w`` times the posterior's deviation
from its own running level. ``w = 1`` is the combination above; ``w = 0`` the plain EWMA
(with the model's gain); in between a shrunk feedforward, the regression weight of the
plant's change on the estimate's when the estimates are noisy.

``rho`` in [0, 1) adds what the last measured product says of the next one when the
process's deviations from its level persist from product to product (the states' AR(1),
eq. 4): with ``A_j = e_j + c_j`` the last product's angle moved to ``u_ref`` and ``L = b + k``
its level, the predicted angle at ``u_ref`` is::

    L + rho (A_j - L) + w ((c_i - k) - rho (c_j - k))

(an AR(1) around a slowly moving level, ``lam`` small; the posterior's change counted beyond
what its own persistence predicts). ``rho = 0`` is the controller above.

With ``adaptive`` the weight is learned on the line itself: after each measured product,
``w`` is the least-squares slope (clipped to [0, 1]) of what the trim left of the measured
products' angles, ``(A_j - L) - rho (A_{j-1} - L)``, on the posterior's change it would
have counted, ``(c_j - k) - rho (c_{j-1} - k)`` (each with the level before product ``j``):
near 1 on a line whose posterior follows its angle, near 0 on one whose does not.

>>> from formtwin.control.feedforward import Actuator, Feedforward
>>> import numpy as np
>>> c = Combined(Feedforward(90.0, Actuator(-100, 100)), lam=0.5)
>>> c.measured(angle=89.0, predicted=90.0)    # the model predicted 1 deg too high
-1.0
>>> c.measured(angle=90.0, predicted=90.0)    # right this time: the EWMA halves the trim
-0.5
>>> s = c.choose(lambda u: 90.0 - 0.05 * np.asarray(u)[None, :])   # one particle
>>> round(s.u, 6), round(s.angle_mean, 6)      # aims the model at 90.5: -10 um, 90 deg
(-10.0, 90.0)
>>> h = Combined(Feedforward(90.0, Actuator(-100, 100)), lam=1.0, weight=0.5)
>>> h.measured(angle=89.0, predicted=89.0, reference=89.0)   # on target at u_ref = 0
0.0
>>> s = h.choose(lambda u: 90.0 - 0.05 * np.asarray(u)[None, :])   # the model: +1 deg
>>> round(s.u, 6), round(s.angle_mean, 6)      # half of the change trusted: 89.5 deg at 0
(-10.0, 90.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from formtwin.control.feedforward import (
    AngleFunction,
    Feedforward,
    FloatArray,
    Suggestion,
    reference_angle,
)

#: ``lam`` and ``rho`` of the closed-loop study's feedforward, the weight learned on the line
#: (``adaptive``, starting at 0), chosen on all its datasets (least mean within-dataset std
#: ratio; the last ``benchmarks/results/bench_control.json``'s ``ff_lam`` and ``ff_rho``,
#: docs/explanation/control.md): the service's defaults
TUNED_LAM = 0.02
TUNED_RHO = 0.7
#: ``lam``, ``weight`` and ``rho`` of the study's best fixed weight (``fffixed_lam``,
#: ``fffixed_weight``, ``fffixed_rho``): the service's ``--control-fixed-weight``
TUNED_FIXED_LAM = 0.02
TUNED_FIXED_WEIGHT = 0.5
TUNED_FIXED_RHO = 0.7


@dataclass
class Combined:
    """Feedforward with an EWMA trim of its prediction error (mutable: it keeps the trim).

    Attributes
    ----------
    feedforward : the feedforward controller (its target is the wanted angle).
    lam : EWMA weight of the newest prediction error, in [0, 1] (0: no feedback).
    weight : share of the posterior's product-to-product change trusted, in [0, 1]
        (1: all of it; 0: none, the plain EWMA).
    u_ref : the reference setting of ``c_i`` (only used when ``weight < 1``).
    bias : the current trim ``b``, degrees (the predictions' estimated bias).
    level : ``k``, the EWMA of the posterior's final angle at ``u_ref`` over the measured
        products, degrees (None before the first).
    rho : persistence of the deviation from the level from one product to the next, in
        [0, 1) (0: none).
    last_error : ``e_j`` of the last measured product, degrees (None before the first).
    last_reference : its ``c_j``, degrees (None before the first given).
    adaptive : learn ``weight`` from the measured products (its value until then: the
        initial weight).
    sxy, sxx : the sums of the weight's least-squares slope (``adaptive``).
    """

    feedforward: Feedforward
    lam: float
    weight: float = 1.0
    u_ref: float = 0.0
    bias: float = 0.0
    level: float | None = None
    rho: float = 0.0
    last_error: float | None = None
    last_reference: float | None = None
    adaptive: bool = False
    sxy: float = 0.0
    sxx: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.lam <= 1:
            raise ValueError(f"combined control lam = {self.lam}, expected 0 <= lam <= 1")
        if not 0 <= self.weight <= 1:
            raise ValueError(f"combined control weight = {self.weight}, expected in [0, 1]")
        if not 0 <= self.rho < 1:
            raise ValueError(f"combined control rho = {self.rho}, expected 0 <= rho < 1")

    @property
    def uses_reference(self) -> bool:
        """Whether ``c_i`` counts: a weight below 1 discounts the posterior's change, a
        learned weight needs it for its slope."""
        return self.weight < 1 or self.adaptive

    def reference(self, final_angle: AngleFunction, weights: FloatArray | None = None) -> float:
        """``c_i``: the posterior mean of the final angle at ``u_ref``, degrees."""
        return reference_angle(final_angle, self.u_ref, weights)

    def offset(self, reference: float | None) -> float:
        """The shift of the feedforward's aim, degrees: ``b - (1 - w) (c_i - k)`` plus, for
        ``rho > 0``, ``rho ((e_j - b) + (1 - w) (c_j - k))``."""
        out = self.bias
        if self.rho > 0 and self.last_error is not None:
            out += self.rho * (self.last_error - self.bias)
        if self.weight == 1 or self.level is None or reference is None or \
                not math.isfinite(reference):
            return out
        out -= (1 - self.weight) * (reference - self.level)
        if self.rho > 0 and self.last_reference is not None:
            out += self.rho * (1 - self.weight) * (self.last_reference - self.level)
        return out

    def choose(self, final_angle: AngleFunction, weights: FloatArray | None = None,
               u_prev: float | None = None, reference: float | None = None) -> Suggestion:
        """The feedforward's choice against the target minus the trim (and, for
        ``weight < 1``, plus the untrusted share of the posterior's change: ``reference``
        is ``c_i``, None: computed here); the suggestion's predicted angle and interval
        include that shift."""
        if self.weight < 1 and reference is None and self.level is not None:
            reference = self.reference(final_angle, weights)
        b = self.offset(reference)
        ff = replace(self.feedforward, target=self.feedforward.target - b)
        s = ff.choose(final_angle, weights, u_prev)
        return replace(s, angle_mean=s.angle_mean + b,
                       interval=(s.interval[0] + b, s.interval[1] + b))

    def measured(self, angle: float, predicted: float, reference: float | None = None
                 ) -> float:
        """Take an earlier product's measured final ``angle`` and the model's prediction
        ``predicted`` of it at the setting it was made with (without the trim: the
        posterior mean ``m_j(u_j)``), degrees, and (for ``weight < 1`` or ``rho > 0``)
        ``reference``, its ``c_j``; return the new trim. Non-finite values are skipped."""
        if math.isfinite(angle) and math.isfinite(predicted):
            e = angle - predicted
            if self.adaptive and reference is not None and math.isfinite(reference):
                self._learn_weight(e, reference)
            first = self.last_error is None and self.lam > 0
            self.bias = e if first else self.lam * e + (1 - self.lam) * self.bias
            self.last_error = e
            if reference is not None and math.isfinite(reference):
                self.level = reference if self.level is None else \
                    self.lam * reference + (1 - self.lam) * self.level
                self.last_reference = reference
        return self.bias

    def _learn_weight(self, e: float, c: float) -> None:
        """Add product ``j`` (error ``e``, reference ``c``) to the weight's slope, with the
        state before it is taken in; set ``weight`` to the clipped slope."""
        if self.level is None or self.last_error is None or self.last_reference is None:
            return
        L = self.bias + self.level
        x = (c - self.level) - self.rho * (self.last_reference - self.level)
        y = (e + c - L) - self.rho * (self.last_error + self.last_reference - L)
        self.sxy += x * y
        self.sxx += x * x
        if self.sxx > 0:
            self.weight = min(max(self.sxy / self.sxx, 0.0), 1.0)


__all__ = ["TUNED_FIXED_LAM", "TUNED_FIXED_RHO", "TUNED_FIXED_WEIGHT", "TUNED_LAM", "TUNED_RHO",
           "Combined"]
