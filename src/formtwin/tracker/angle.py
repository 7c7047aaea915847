"""The measured final angle as a second measurement of a product's state.

A product's final angle is measured after its second stage, before the next product's
curve is assimilated; the particles then still stand for that product's posterior
``p(x_i | Z_i)``. :func:`update_angle` multiplies their weights by the likelihood of the
measured angle ``a`` made at setting ``u``::

    l_k = log N(a; a_mm(x_k, u) + offset, sd^2)          sd^2 = model_var + noise_var

with ``a_mm`` the metamodel's final angle, ``offset`` a known bias of the metamodel (e.g. the
controller's running estimate of it) and ``model_var`` the metamodel's own error variance
at a given state (default: its held-out variance of the final angle, the tracker's
``ssm.angle_error_var[1]``). The weights stay with the particles (no resampling): the next
filter step multiplies its curve likelihood in and resamples, and
:meth:`~formtwin.tracker.Tracker.suggest` reads them.

>>> import numpy as np
>>> from formtwin.defaults import analytic_model
>>> from formtwin.tracker import TrackerConfig, build_tracker
>>> model = analytic_model(); spec = model.spec
>>> tr = build_tracker(model, TrackerConfig(n_particles=300, estimate_deviation=False))
>>> _ = tr.step(model.predict_curves((0.5 * (spec.inputs.lo + spec.inputs.hi))[None])[0])
>>> a = tr.final_angle(np.zeros(1))[:, 0]
>>> inc = update_angle(tr, float(a.mean()) + 3 * float(a.std()), 0.0, sd=0.1 * float(a.std()))
>>> bool(tr.final_angle(np.zeros(1))[:, 0] @ np.exp(tr.filter.logw) > a.mean())
True
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.stats import norm

from formtwin.filters import log_normalise
from formtwin.tracker.core import Tracker

FloatArray = NDArray[np.float64]


def angle_sd(tracker: Tracker, noise_sd: float = 0.0, stage: int = 1) -> float:
    """The default ``sd`` of :func:`update_angle`, degrees: the metamodel's held-out error of
    the angle after ``stage`` (0: the first bending stage, 1: the final angle) and the angle
    sensor's noise ``noise_sd`` added in quadrature."""
    var = float(np.asarray(tracker.ssm.angle_error_var)[stage])
    return math.sqrt(max(var, 0.0) + noise_sd ** 2)


def update_angle(tracker: Tracker, angle: float, u: float, sd: float | None = None,
                 offset: float = 0.0, stage: int = 1) -> float:
    """Reweight the tracker's particles by the measured final ``angle`` (degrees) of the
    product last stepped, made at setting ``u`` (the spec's one control, internal units);
    return the log evidence increment ``log p(angle | Z)``.

    ``sd`` (degrees, > 0): the spread of the measured angle around the metamodel's at a
    given state (None: :func:`angle_sd`); ``offset``: the metamodel's known bias, degrees;
    ``stage`` 0: ``angle`` is the angle after the first bending stage instead (``u`` does
    not act on it).
    Raises ``ValueError`` for a non-finite angle, setting or offset, or a bad ``sd``, and
    ``RuntimeError`` before the first step; the tracker is then untouched. If no particle
    gives a finite likelihood, the weights are left as they were and ``-inf`` is returned.
    """
    if tracker.filter.x is None:
        raise RuntimeError("update_angle: no particles yet (step a curve first)")
    for name, v in (("angle", angle), ("u", u), ("offset", offset)):
        if not math.isfinite(float(v)):
            raise ValueError(f"update_angle: {name} = {v}, expected a finite number")
    if stage not in (0, 1):
        raise ValueError(f"update_angle: stage = {stage}, expected 0 or 1")
    s = angle_sd(tracker, stage=stage) if sd is None else float(sd)
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"update_angle: sd = {sd}, expected a positive number of degrees "
                         "(the metamodel has no held-out angle error: give sd)")
    if stage == 1:
        a = tracker.final_angle(np.array([float(u)]))[:, 0] + float(offset)
    else:
        a = tracker.ssm.predict_angles(tracker.filter.x, float(u))[:, 0] + float(offset)
    ll = norm.logpdf(float(angle), loc=a, scale=s)
    logw = np.asarray(tracker.filter.logw, dtype=np.float64) + np.where(np.isfinite(ll), ll,
                                                                         -np.inf)
    if not np.isfinite(logw).any():
        return -math.inf
    tracker.filter.logw, lse = log_normalise(logw)
    return lse


__all__ = ["angle_sd", "update_angle"]
