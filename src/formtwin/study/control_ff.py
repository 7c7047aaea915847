"""The control study's controllers that use the tracker: one pass of a tracker over a
dataset's measured curves, with one or more feedforward controllers choosing their settings
after each product's curve (:func:`track_and_choose`).

Every controller is :class:`~formtwin.control.Combined`: the feedforward over the posterior
aimed at the target minus an EWMA (weight ``lam``) of its own prediction error on the
measured final angles of earlier products (``lam = 0``: the open feedforward), trusting a
share ``weight`` of the posterior's product-to-product change (1: all of it), with the
persistence ``rho`` of the last product's deviation. The tracker
does not depend on the settings chosen, so several controllers can share one pass; with
``angle_in_filter`` the one controller's measured angles also enter the filter as a second
measurement of the state (:func:`formtwin.tracker.fusion.update_angle`), so that pass serves
that controller alone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.control import Combined, Feedforward, Predictive
from formtwin.measurement import ProcessModel
from formtwin.tracker import FusionError, TrackerConfig, build_tracker
from formtwin.tracker.ahead import refusal
from formtwin.tracker.fusion import angle_sd, update_angle

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: the ``weight`` of a controller tuple that stands for a weight learned on the line
#: (:class:`~formtwin.control.Combined` with ``adaptive``, starting at 0)
ADAPTIVE = -1.0


@dataclass(frozen=True)
class Pass:
    """What one tracker pass gave (``m`` controllers, ``n`` products).

    Attributes
    ----------
    u : (m, n) the settings chosen (the previous one where a product's physics failed).
    pred : (m, n, 3) the predicted final angle at ``u`` (mean with the trim, 90 % interval).
    nominal_mean : (n,) the posterior mean of the metamodel's final angle at the nominal
        setting (NaN where not tracked): what the estimates say of each product before any
        setting is chosen.
    angle_sd : the ``sd`` of the angle likelihood, degrees (NaN without angles in the filter).
    input_mean : (n, n_in) the posterior means of the run inputs (state, machine
        parameters) after each product's curve and the readings fused with it (NaN where
        not tracked).
    """

    u: FloatArray
    pred: FloatArray
    nominal_mean: FloatArray
    angle_sd: float
    input_mean: FloatArray


def track_and_choose(metamodel: ProcessModel, config: TrackerConfig, curves: FloatArray,
                     ok: NDArray[np.bool_], plant: Callable[[int, float], float],
                     ff: Feedforward, controllers: Sequence[tuple[float, float, float]],
                     nominal: float, delay: int = 1, angle_in_filter: bool = False,
                     sd: float | None = None, noise: FloatArray | None = None,
                     readings: Mapping[str, FloatArray] | None = None,
                     predictive: Sequence[Predictive] = (), camera: str | None = None
                     ) -> Pass:
    """Run a tracker (``config``) over the measured ``curves`` (n, n_t) of the products with
    ``ok``; after each curve every controller ``Combined(ff, lam, weight, rho=rho)`` (one
    per ``(lam, weight, rho)`` of ``controllers``, ``weight`` :data:`ADAPTIVE`: learned;
    reference setting ``nominal``) chooses its
    product's setting (start ``nominal``); ``plant(i, u)`` is product ``i``'s measured
    final angle at ``u``, known ``delay`` products later. With ``angle_in_filter`` (one
    controller, ``delay`` 1: the angle arrives before the next curve) the measured angle also
    reweights the particles (likelihood sd ``sd``, None: the metamodel's held-out error;
    offset: the controller's trim before this angle).

    ``noise`` (m, n), degrees, is added to what controller ``c`` measures of product ``j``
    (a camera's error: the plant's angle stays exact, the controller reads
    ``plant(j, u) + noise[c, j]``; None: exact). ``readings`` are values (n,) of sensors of
    ``config.sensors`` that read a product before it is formed (delay 0, internal units),
    fused by :meth:`~formtwin.tracker.Tracker.fuse` into the product's step where the
    filter allows (:mod:`formtwin.tracker.ahead`; else right after its curve), so that its
    setting is chosen on the fused posterior (NaN: no value).

    ``predictive`` are further controllers (:class:`~formtwin.control.Predictive`: the
    feedforward on the posterior predictive through a discrepancy learned from the measured
    angles), after the ``controllers`` in the rows of the result and of ``noise``. With
    ``camera`` (a sensor of ``config.sensors`` reading the final angle; one controller in
    all) the measured angle of product ``j`` is also fused into the particles
    (:meth:`~formtwin.tracker.Tracker.fuse` at its setting, before the next curve; the
    tracker's own interval issued at each chosen setting, so that its discrepancy learns):
    the settings are then chosen on the camera-fused posterior.
    """
    if angle_in_filter and (len(controllers) != 1 or delay != 1):
        raise ValueError("angles in the filter: one controller and delay 1 (got "
                         f"{len(controllers)} controllers, delay {delay})")
    if camera is not None and len(controllers) + len(predictive) != 1:
        raise ValueError("camera in the filter: one controller (got "
                         f"{len(controllers) + len(predictive)})")
    tracker = build_tracker(metamodel, config)
    ctl = [Combined(ff, lam, max(weight, 0.0), nominal, rho=rho, adaptive=weight == ADAPTIVE)
           for lam, weight, rho in controllers]
    m0, n = len(ctl), curves.shape[0]
    m = m0 + len(predictive)
    err = np.zeros((m, n)) if noise is None else np.asarray(noise, dtype=np.float64)
    if err.shape != (m, n):
        raise ValueError(f"noise: shape {err.shape}, expected ({m}, {n}) (controllers, "
                         "products)")
    stepped = -1  # the tracker's index of the newest product stepped
    index = np.full(n, -1)  # each product's index in the tracker
    u = np.full((m, n), nominal)
    pred = np.full((m, n, 3), np.nan)
    model_pred = np.full((m, n), np.nan)  # m_j(u_j): the prediction without the trim
    nominal_mean = np.full(n, np.nan)
    n_in = metamodel.spec.inputs.lo.size
    input_mean = np.full((n, n_in), np.nan)
    prev = [nominal] * m
    s_angle = angle_sd(tracker) if sd is None else float(sd)
    by_name = {s.name: s for s in tracker.sensors}
    with single_blas_thread():
        for i in range(n):
            j = i - delay  # the newest product whose angle is known now
            if j >= 0 and ok[j]:
                # each controller's measured angle of product j (its setting, its noise)
                y = [plant(j, u[c, j]) + err[c, j] for c in range(m)]
                if angle_in_filter:  # the particles are still product j's posterior
                    update_angle(tracker, y[0], u[0, j], s_angle, ctl[0].bias)
                for c, ctrl in enumerate(ctl):
                    ctrl.measured(y[c], model_pred[c, j], nominal_mean[j])
                for q, pc in enumerate(predictive, start=m0):
                    pc.measured(j, y[q])
                if camera is not None and index[j] >= 0:
                    try:
                        tracker.fuse(int(index[j]), camera, y[0], u=float(u[0, j]))
                    except FusionError as exc:  # refused: the particles as they were
                        log.warning("product %d: %s", j, exc)
            if ok[i]:
                # a reading of the strip known before the bend enters the product's step
                early = {n: float(v[i]) for n, v in (readings or {}).items()
                         if np.isfinite(v[i]) and refusal(tracker, by_name[n]) is None}
                for name, value in early.items():
                    tracker.fuse(stepped + 1, name, value)
                input_mean[i] = tracker.step(curves[i]).mean[:n_in]
                stepped += 1
                index[i] = stepped
                for name, values in (readings or {}).items():
                    if name not in early and np.isfinite(values[i]):
                        tracker.fuse(stepped, name, float(values[i]))
                w = tracker.weights()
                x = tracker.filter.x
                if w is not None and x is not None:  # the fused posterior's means
                    input_mean[i] = w @ x[:, :n_in] / w.sum()
                nominal_mean[i] = (ctl[0] if ctl else predictive[0]).reference(
                    tracker.final_angle, w)
                for c, ctrl in enumerate(ctl):
                    shift = ctrl.offset(nominal_mean[i])
                    s = ctrl.choose(tracker.final_angle, w, prev[c], nominal_mean[i])
                    prev[c] = s.u
                    pred[c, i] = (s.angle_mean, *s.interval)
                    model_pred[c, i] = s.angle_mean - shift
                for q, pc in enumerate(predictive, start=m0):
                    s = pc.choose(i, tracker.final_angle, w, prev[q], nominal_mean[i])
                    prev[q] = s.u
                    pred[q, i] = (s.angle_mean, *s.interval)
                if camera is not None:  # the interval its camera value will score
                    tracker.issue_final(np.array([prev[0]]))
            u[:, i] = prev
    return Pass(u, pred, nominal_mean, s_angle if angle_in_filter else float("nan"),
                input_mean)


__all__ = ["ADAPTIVE", "Pass", "track_and_choose"]
