"""A state variable's value known before its product's curve: fused in the proposal.

A strip gauge reads the thickness of a product before it is bent; its value can reach the
tracker before the product's force curve. Fused after the step (ancestor reweighting,
:meth:`~formtwin.tracker.SensorFusion.fuse`), a gauge much finer than the transition's
spread leaves few particles with weight (a 0.5 um gauge against a ~4 um transition keeps
about one in seven) and the rest of the state is estimated from those few. Known before the
step, the value enters the transition itself, the fully adapted proposal of that
component (Pitt & Shephard 1999): eq. 4-5 move the measured column ``j`` as ``x' = a + b
x + s v`` (:attr:`~formtwin.tracker.ssm.BendingSSM._drift`), and with the value ``y =
x'_j + e``, ``e ~ N(0, r^2)``,

* each parent is reweighted now by the value's predictive density
  ``N(y; a + b x_j, s^2 + r^2)`` (the log evidence increment is its weighted sum);
* the step draws ``x'_j`` from its conditional given the parent and ``y``, again an affine
  move: ``a' = (1 - K) a + K y``, ``b' = (1 - K) b``, ``s' = s sqrt(1 - K)``,
  ``K = s^2 / (s^2 + r^2)`` (:func:`conditioned`), with the same random numbers as the
  transition would use.

The product of the two is the transition times the value's likelihood, so the filter's
target is that of fusing the value after the step; only the variance is smaller. Like the
guided proposal (:mod:`formtwin.tracker.guide`) the draw is reflected into the design box
and the weight leaves the reflection's images out (the box is many ``s'`` wide). Only with
the transition of eq. 4-5 (not with a learned mu, nor a guided filter, whose proposals
differ) and after the first step (the parents must exist).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from formtwin.spec.sensors import Sensor
    from formtwin.tracker.fusion import SensorFusion

FloatArray = NDArray[np.float64]

#: the filters whose step draws from the model's transition (the value can enter it)
TRANSITION_FILTERS = ("sir", "regularised", "move")


def conditioned(drift: tuple[FloatArray, FloatArray, FloatArray],
                ahead: dict[int, tuple[float, float]]
                ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The transition ``x' = a + b x + s v`` per column (``drift``: ``a, b, s``) with the
    columns of ``ahead`` (column -> (value, noise variance r^2)) conditioned on their
    value; ``drift`` itself when ``ahead`` is empty."""
    if not ahead:
        return drift
    a, b, s = (v.copy() for v in drift)
    for j, (y, r2) in ahead.items():
        q = s[j] ** 2
        k = q / (q + r2)
        a[j], b[j], s[j] = (1.0 - k) * a[j] + k * y, (1.0 - k) * b[j], s[j] * math.sqrt(1.0 - k)
    return a, b, s


def refusal(tracker: SensorFusion, sensor: Sensor) -> str | None:
    """Why ``sensor``'s value of the next product cannot enter its step (None: it can)."""
    if sensor.kind != "state":
        return "a model output is known only once its product is stepped"
    if tracker.filter.x is None:
        return "no product stepped yet (the parents of its particles do not exist)"
    if tracker.config.learn_mu or tracker.config.filter not in TRANSITION_FILTERS:
        return (f"the value enters the transition of eq. 4-5, not the proposal of filter "
                f"{tracker.config.filter!r}" + (" with a learned mu" if
                                                tracker.config.learn_mu else ""))
    return None


def fuse_ahead(tracker: SensorFusion, sensor: Sensor, value: float) -> float:
    """Reweight the current particles by the predictive density of ``sensor``'s ``value``
    of the next product and keep the value for its step (:attr:`FusedLog.ahead
    <formtwin.tracker.fused_log.FusedLog.ahead>`); return the log evidence increment.
    The caller has checked the value and :func:`refusal`."""
    ssm = tracker.ssm
    j = tracker.spec.state.index[sensor.measures]
    a, b, s = (float(v[j]) for v in ssm._drift)
    x = tracker.filter.x
    assert x is not None
    pred = a + b * x[:, j]
    inc = tracker._reweight(pred, value, math.sqrt(s**2 + sensor.noise**2),
                            f"{sensor.name} of product {tracker.filter.t}")
    tracker.fused.ahead[sensor.name] = value
    return inc


def ahead_columns(tracker: SensorFusion) -> dict[int, tuple[float, float]]:
    """Column -> (value, noise variance) of the values kept for the next step."""
    if not tracker.fused.ahead:  # the usual step: nothing to look up
        return {}
    by_name = {s.name: s for s in tracker.sensors}
    return {tracker.spec.state.index[by_name[n].measures]: (v, by_name[n].noise ** 2)
            for n, v in tracker.fused.ahead.items()}


__all__ = ["TRANSITION_FILTERS", "ahead_columns", "conditioned", "fuse_ahead", "refusal"]
