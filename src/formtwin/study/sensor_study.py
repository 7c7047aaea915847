"""The study with sensors: a series' filter run with the line's sensors fused as they
arrive, and the camera-calibrated interval of the final angle.

One run (:func:`sensor_run`) takes a study :class:`~formtwin.study.series.Task` (series,
dataset, repetition, measurement model), reads the dataset's sensor pseudo-data
(:mod:`formtwin.study.sensor_data`) and, for every product ``i`` with a curve:

1. fuses the gauge's thickness of the product (delay 0: the strip is read before it is
   bent) into the product's step, where the filter allows it
   (:mod:`formtwin.tracker.ahead`; the first product's after its step), and steps the
   tracker with the curve;
2. fuses the camera's final angle of the previous product (delay 1), for the sensors of
   the run's set;
3. takes the posterior (:meth:`~formtwin.tracker.Tracker.posterior`: the particles'
   weighted mean and std, the predicted angles at the product's setting) and reports its
   std with the tracker's default intervals (:func:`reported_std`: what the step's
   estimate added to the cloud's std, the calibrated floors and the assumed mu's term,
   added in quadrature to the fused cloud's std, as every estimate of the report has it);
4. issues the 90 % interval of the product's *measured* final angle (predictive std with
   the camera's noise) from adaptive conformal inference on the camera's residuals
   (:class:`~formtwin.tracker.conformal.AdaptiveConformal`), scored when the camera's value
   arrives one product later. The camera is read in every set (its values calibrate the
   interval); the sets with ``camera`` fuse it into the particles and take the predicted
   final angle and its interval from the tracker (through the discrepancy it learns from the
   camera, ``TrackerConfig.camera_discrepancy``), the others run the same calibration
   beside it.

:func:`ewma_prediction` is the camera-only predictor the fused twin is compared with: a
run-to-run EWMA of the measured final angles, known one product late.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.spec.sensors import line_sensors, sensor_by_name
from formtwin.study.sensor_data import sensor_readings
from formtwin.study.series import SERIES, Task, prepare
from formtwin.tracker import FusionError
from formtwin.tracker.ahead import refusal
from formtwin.tracker.conformal import AdaptiveConformal

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: the sensor sets of the study: name -> sensors fused besides the curve
SENSOR_SETS: dict[str, tuple[str, ...]] = {"curve": (), "camera": ("camera",),
                                           "gauge": ("gauge",), "both": ("gauge", "camera")}


def sensor_run(task: Task, sensors: tuple[str, ...], gamma: float = 0.005,
               gauge_ahead: bool = True) -> dict[str, Any]:
    """Run ``task``'s tracker with ``sensors`` fused (see the module doc), the spec's sensor
    noise in the data and the likelihood, ACI step ``gamma``; ``gauge_ahead=False`` fuses
    the gauge after its product's step (the bootstrap's way, for comparison).

    Returns arrays over the dataset's ``n`` products (NaN where a curve is missing):
    ``mean, std`` (n, 18) (``std`` with the tracker's default intervals, ``cloud_std`` the
    particles' own), ``angles_mean, angles_std`` (n, 2), ``final_lo, final_hi`` (n,)
    the calibrated interval of the measured final angle, ``camera`` (n,) its measured value,
    ``ess`` (n,) after fusion, and ``rejected``: values the tracker refused.
    """
    series = SERIES[task.series - 1]
    config = dataclasses.replace(task.tracker, sensors=sensors)
    tracker, real, curves, u = prepare(dataclasses.replace(task, tracker=config))
    spec = tracker.spec
    read = sensor_readings(spec, real, series.data, task.seed, ("gauge", "camera"))
    cam_sd = sensor_by_name(line_sensors(spec), "camera").noise
    ok = real.ok[series.data]
    idx = np.flatnonzero(ok)
    n, na = real.n, len(spec.augmented)
    out: dict[str, Any] = {k: np.full((n, na), np.nan) for k in ("mean", "std", "cloud_std")}
    out.update({k: np.full((n, 2), np.nan) for k in ("angles_mean", "angles_std")})
    out.update({k: np.full(n, np.nan) for k in ("final_lo", "final_hi", "ess")})
    out["camera"] = np.where(ok, read["camera"], np.nan)
    aci = AdaptiveConformal(alpha_target=0.1, gamma=gamma)
    rejected = 0
    with single_blas_thread():
        gauge = sensor_by_name(line_sensors(spec), "gauge")
        for k, i in enumerate(idx):
            uk = None if u is None else u[k]
            # the gauge reads the strip before the product is bent: its value enters the
            # product's step where the filter allows (formtwin.tracker.ahead)
            ahead = gauge_ahead and "gauge" in sensors and refusal(tracker, gauge) is None
            values = [(k, "gauge", read["gauge"][i], uk)] if ahead else []
            rejected += _fuse_all(tracker, values, task)
            est = tracker.step(curves[k], uk)
            added = np.maximum(est.std**2 - tracker.posterior(uk).std ** 2, 0.0)
            values = [(k, "gauge", read["gauge"][i], uk)] \
                if "gauge" in sensors and not ahead else []
            if k >= 1:
                j = int(idx[k - 1])
                aci.update(k - 1, float(read["camera"][j]))
                if "camera" in sensors:
                    values.append((k - 1, "camera", read["camera"][j],
                                   None if u is None else u[k - 1]))
            rejected += _fuse_all(tracker, values, task)
            p = tracker.posterior(uk)
            out["mean"][i], out["cloud_std"][i] = p.mean, p.std
            out["std"][i] = reported_std(p.std, added)
            out["angles_mean"][i], out["angles_std"][i] = p.angles_mean, p.angles_std
            out["ess"][i] = p.ess
            if "camera" in sensors:  # the tracker's own: with the bias it learned
                final, (lo, hi) = tracker.issue_final(uk)
                out["angles_mean"][i, 1] = final
                out["final_lo"][i], out["final_hi"][i] = lo, hi
            else:
                sd = math.sqrt(float(p.angles_std[1]) ** 2 + cam_sd**2)
                out["final_lo"][i], out["final_hi"][i] = aci.interval(
                    k, float(p.angles_mean[1]), sd)
    out["rejected"] = rejected
    return out


def _fuse_all(tracker: Any, values: list[tuple[int, str, float, Any]], task: Task) -> int:
    """Fuse ``(product, sensor, value, setting)`` in order; return how many were refused."""
    refused = 0
    for product, name, value, setting in values:
        try:
            tracker.fuse(product, name, float(value), u=setting)
        except FusionError as exc:
            refused += 1
            log.warning("task %s: %s", task.out_path, exc)
    return refused


def reported_std(cloud: FloatArray, added: FloatArray) -> FloatArray:
    """The std with the tracker's default intervals after fusion: the fused ``cloud``'s std
    and the variance ``added`` in quadrature, ``added`` the step's estimate's std squared
    less the tracker's cloud's right after the step (its
    :meth:`~formtwin.tracker.Tracker.posterior`'s std: the resampled cloud the values are
    fused into): the calibrated floors and the assumed mu's term (and
    the resampling's noise), so that with nothing fused the reported std is the step's.

    >>> reported_std(np.array([0.3, 0.0]), np.array([0.16, 0.0])).tolist()
    [0.5, 0.0]
    """
    out: FloatArray = np.sqrt(np.square(cloud) + added)
    return out


def ewma_prediction(measured: FloatArray, lam: float) -> FloatArray:
    """Prediction (n,) of each product's final angle from the measured ones (n,) of the
    products before it (known one product late): an EWMA with weight ``lam`` on the
    newest, NaN until the first value; missing values (NaN) leave it as it was."""
    out = np.full(measured.size, np.nan)
    level = math.nan
    for i in range(measured.size):
        out[i] = level
        y = measured[i]
        if math.isfinite(y):
            level = y if math.isnan(level) else lam * y + (1.0 - lam) * level
    return out


__all__ = ["SENSOR_SETS", "ewma_prediction", "reported_std", "sensor_run"]
