"""Sensor values besides the curve, fused when they arrive: late and in any order.

A line's sensors (:mod:`formtwin.spec.sensors`: a strip gauge reading a state variable, a
camera reading the final angle one product later) give scalar values of a product ``j``
that arrive after its curve, up to ``L`` products late (``TrackerConfig.sensor_lag``,
default: the largest delay of the sensors used). The particles keep the model inputs
``[x, theta]`` of their last ``L`` ancestors in extra columns (:class:`LagColumns`, the
generic pieces in :mod:`formtwin.filters.lagged`), and :meth:`SensorFusion.fuse`
multiplies the current weights by the likelihood of the value at each particle's
ancestor ``j`` (ancestor reweighting)::

    l_k = log N(s; h(x_j^k, theta_j^k, u_j) + offset, noise^2 + v_model)

with ``h`` the measured state variable (``v_model = 0``) or the model output (the
metamodel's angle at the product's setting ``u_j``; ``v_model`` its held-out error as the
predicted angles carry it, :meth:`~formtwin.tracker.BendingSSM.angle_error`). For the final
angle with ``config.camera_discrepancy``, ``h`` is the model's angle mapped by the
discrepancy learned from the camera (:mod:`formtwin.tracker.angle_discrepancy`: ``ref + b0
+ b1 (a - ref)``) and the variance is at least that discrepancy's residual variance ``V``
(see :meth:`SensorFusion.posterior`). The weights
stay with the particles; the next step multiplies its curve likelihood in and resamples.
Each (product, sensor) is fused once. Everything is in the particles, their weights and
the small :class:`FusedLog`, so it is part of the state bytes and checkpoints, and a
failed step or fusion leaves the tracker as it was.

:func:`update_angle` is the special case of an angle of the product just stepped with a
likelihood sd of the caller's choice (the control study's what-if), without the log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters.lagged import distinct_rows, lagged, shift
from formtwin.spec import ProcessSpec
from formtwin.spec.sensors import Sensor, final_output, line_sensors, output_column, value_refusal
from formtwin.tracker._fusion_kernels import normal_reweight, weighted_moments
from formtwin.tracker.ahead import fuse_ahead, refusal
from formtwin.tracker.angle_discrepancy import AngleDiscrepancy
from formtwin.tracker.config import TrackerConfig
from formtwin.tracker.final_angles import FinalAngles
from formtwin.tracker.fused_log import FusedLog
from formtwin.tracker.validate import validate_controls

if TYPE_CHECKING:
    from formtwin.filters import SIR
    from formtwin.tracker.ssm import BendingSSM

FloatArray = NDArray[np.float64]


#: log sqrt(2 pi), as ``scipy.stats.norm`` has it
_LOG_SQRT_2PI = np.log(np.sqrt(2 * np.pi))



class FusionError(ValueError):
    """A sensor value the tracker refuses (it is left untouched); the message names the
    sensor, the product and the reason."""


def used_sensors(spec: ProcessSpec, config: TrackerConfig) -> tuple[Sensor, ...]:
    """The sensors ``config.sensors`` of the spec's line (:func:`line_sensors`), in the
    config's order; ``ValueError`` naming an unknown one and the known ones. A tracker
    finds them once (:attr:`SensorFusion.sensors`)."""
    known = {s.name: s for s in line_sensors(spec)}
    for name in config.sensors:
        if name not in known:
            raise ValueError(f"sensors: {name!r} is not a sensor of spec {spec.name!r}; "
                             f"known: {', '.join(known) or 'none'}")
    return tuple(known[n] for n in config.sensors)


def lag_depth(spec: ProcessSpec, config: TrackerConfig) -> int:
    """``L``: ``config.sensor_lag``, or the largest delay of the sensors used (0: none);
    ``ValueError`` if ``sensor_lag`` is below a used sensor's delay."""
    delays = [s.delay for s in used_sensors(spec, config)]
    need = max(delays, default=0)
    if config.sensor_lag is None:
        return need
    if config.sensor_lag < need:
        raise ValueError(f"sensor_lag = {config.sensor_lag}, below the largest delay "
                         f"{need} of the sensors {', '.join(config.sensors)}")
    return int(config.sensor_lag)


class LagColumns:
    """Mixin of :class:`~formtwin.tracker.BendingSSM`: ``L`` blocks of ``[x, theta]``
    (``n_in`` columns each) of the particles' ancestors, columns ``[lag_start, lag_start +
    L n_in)``."""

    spec: ProcessSpec
    config: TrackerConfig
    #: the first lag column and ``L`` (0: no lag columns)
    lag_start: int = 0
    lag_depth: int = 0

    def add_lag_columns(self, lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Place the lag blocks after the columns bounded by ``lo, hi`` (d,); return the
        bounds extended by unbounded columns."""
        depth = lag_depth(self.spec, self.config)
        object.__setattr__(self, "lag_start", lo.size)
        object.__setattr__(self, "lag_depth", depth)
        k = depth * self.spec.n_inputs
        return np.r_[lo, np.full(k, -np.inf)], np.r_[hi, np.full(k, np.inf)]

    def shift_lags(self, parent: FloatArray, out: FloatArray) -> None:
        """At a transition from ``parent`` (N, d) to ``out`` (N, d): fill ``out``'s lag
        blocks (:func:`formtwin.filters.lagged.shift`)."""
        shift(parent, out, self.spec.n_inputs, self.lag_start, self.lag_depth)

    def lagged_inputs(self, x: FloatArray, lag: int) -> FloatArray:
        """``[x, theta]`` (N, n_in) of the particles ``x``'s ancestors ``lag`` products back
        (0: their own)."""
        if not 0 <= lag <= self.lag_depth:
            raise ValueError(f"lag = {lag}, expected 0..{self.lag_depth}")
        return lagged(x, self.spec.n_inputs, self.lag_start, lag)


class SensorFusion:
    """Mixin of :class:`~formtwin.tracker.Tracker`: :meth:`fuse` and :meth:`posterior`."""

    filter: SIR
    ssm: BendingSSM
    spec: ProcessSpec
    config: TrackerConfig
    fused: FusedLog
    finals: FinalAngles | None
    #: the spec's sensors this tracker fuses (:func:`used_sensors`), in the config's order
    sensors: tuple[Sensor, ...]

    def _column(self, output: str) -> int:
        """:func:`output_column` of the spec's ``output``, found once per tracker."""
        found: dict[str, int] = self.__dict__.setdefault("_output_columns", {})
        if output not in found:
            found[output] = output_column(self.spec, output)
        return found[output]

    def fuse(self, product: int, sensor: str, value: float, u: Any = None,
             offset: float = 0.0) -> float:
        """Fuse sensor ``sensor``'s ``value`` (internal units: mm for thickness, degrees
        for an angle) of product ``product`` (0-based, as :attr:`Estimate.index`): the
        current product or one of the last ``L`` before it, in any order, each (product,
        sensor) once; or, for a sensor of a state variable, the next product (its value
        known before its curve enters that product's step: :mod:`formtwin.tracker.ahead`).
        ``u`` is the product's press setting (None: nominal) for a model
        output, ``offset`` a known bias of the model output (degrees). Returns the log
        evidence increment ``log p(value | everything fused so far)``.

        Raises :class:`FusionError` (a ``ValueError``) for a sensor this tracker does not
        fuse, a non-finite value or offset, a product not yet stepped (but the next one's
        state variable where :func:`~formtwin.tracker.ahead.refusal` allows it) or older
        than ``L``, a second value of the same (product, sensor), a bad setting, or a
        value no particle explains; the tracker is then untouched.
        """
        used = {s.name: s for s in self.sensors}
        if sensor not in used:
            raise FusionError(f"fuse: sensor {sensor!r} is not fused by this tracker "
                              f"(config.sensors: {', '.join(used) or 'none'})")
        s = used[sensor]
        bad = value_refusal(self.spec, s, value, offset)
        if bad is not None:
            raise FusionError(f"fuse: {sensor} {bad}")
        newest, depth = self.filter.t - 1, self.ssm.lag_depth
        if isinstance(product, bool) or not isinstance(product, int | np.integer):
            raise FusionError(f"fuse: product = {product!r}, expected a whole number")
        if self.filter.x is not None and product == newest + 1:  # before its curve
            why = refusal(self, s)
            if why is not None:
                raise FusionError(f"fuse: {sensor} of product {product}, not yet seen "
                                  f"(the newest is {newest}): {why}")
        elif self.filter.x is None or product > newest:
            raise FusionError(f"fuse: {sensor} of product {product}, not yet seen (the "
                              f"newest is {newest})")
        if product < newest - depth or product < 0:
            raise FusionError(f"fuse: {sensor} of product {product} is older than the "
                              f"tracker keeps (L = {depth}: products {max(newest - depth, 0)}"
                              f"..{newest})")
        if (int(product), sensor) in self.fused.done:
            raise FusionError(f"fuse: {sensor} of product {product} was fused already")
        try:
            uu = validate_controls(u, self.spec)
        except ValueError as exc:
            raise FusionError(f"fuse: {exc}") from None
        if product == newest + 1:
            inc = fuse_ahead(self, s, float(value) - float(offset))
            self.fused.done.add((int(product), sensor))
            return inc
        x = self.ssm.lagged_inputs(self.filter.x, newest - int(product))
        camera = s.measures == final_output(self.spec)  # the output it calibrates
        if s.kind == "state":
            pred, var = x[:, self.spec.state.index[s.measures]], 0.0
        else:
            col = self._column(s.measures)
            if camera and self.finals is not None:
                pred = self.finals.column(newest - int(product), uu, x,
                                          lambda r: self.ssm.predict_angles(r, uu)[:, col])
            else:
                pred = distinct_angles(self.ssm, x, uu)[:, col]
            var = float(self.ssm.angle_error()[col])
        sd = math.sqrt(s.noise**2 + max(var, 0.0))
        if not sd > 0:
            raise FusionError(f"fuse: {sensor} has noise 0 and the model no error: the "
                              "likelihood is degenerate (give the sensor a noise)")
        learn = camera and self.config.camera_discrepancy
        if learn:  # the model's angle as the camera sees it: the learned discrepancy
            d = self.fused.learned(sd**2)
            if math.isfinite(d.ref):
                ref, b0, b1, v = d.mapping()
                pred = ref + b0 + b1 * (pred - ref)
                sd = max(sd, math.sqrt(v))
        inc = self._reweight(pred + float(offset), float(value), sd,
                             f"{sensor} of product {product}")
        self.fused.done = {d for d in self.fused.done if d[0] >= newest - depth}
        self.fused.done.add((int(product), sensor))
        if camera:  # how good was the prediction issued for it
            self.fused.conformal.update(int(product), float(value))
            if learn:
                self.fused.learned(sd**2).update_product(int(product), float(value))
        return inc

    def _reweight(self, pred: FloatArray, value: float, sd: float, what: str) -> float:
        """Multiply the current weights by ``N(value; pred, sd^2)`` (pred (N,)); return the
        log evidence increment; :class:`FusionError` (weights untouched) if no particle
        gives a finite likelihood. ``norm.logpdf``'s and :func:`~formtwin.filters.lagged.
        reweight`'s operations in one pass (:func:`~formtwin.tracker._fusion_kernels.
        normal_reweight`): the same numbers."""
        new, top, finite = normal_reweight(self.filter.logw, np.asarray(pred, np.float64),
                                           float(value), float(sd), _LOG_SQRT_2PI,
                                           np.log(np.float64(sd)))
        if not finite:
            raise FusionError(f"fuse: {what} = {value:g}: no particle gives the measurement "
                              "a finite likelihood")
        lse = top + math.log(float(np.sum(np.exp(new - top))))  # log_normalise's
        self.filter.logw = new - lse
        return float(lse)

    def posterior(self, u: Any = None) -> Posterior:
        """The current particles' weighted summary (after :meth:`fuse`, with what was
        fused): mean and std of ``[x, theta, theta_d]`` and of the angles at ``u``; the
        angles' std adds the metamodel's error as :meth:`Tracker.step`'s estimates do
        (the reported std here is the cloud's: no interval floors). With a fused camera,
        the final angle's prediction and interval :meth:`issue_final` would issue now
        (nothing is recorded: a report only)."""
        if self.filter.x is None:
            raise RuntimeError("posterior: no particles yet (call step first)")
        na = self.ssm.n_aug
        x = self.filter.x
        w = self._weights()
        mean = w @ x[:, :na]
        std = np.sqrt(np.maximum(w @ (x[:, :na] - mean) ** 2, 0.0))
        a = distinct_angles(self.ssm, x[:, :self.ssm.n_in], validate_controls(u, self.spec))
        am = w @ a
        astd = np.sqrt(np.maximum(w @ (a - am) ** 2, 0.0) + self.ssm.angle_error())
        final, lo, hi = math.nan, math.nan, math.nan
        if self.finals is not None:
            col = self._column(final_output(self.spec))
            final, (lo, hi) = self._final_interval(float(am[col]), float(astd[col]), False)
        return Posterior(mean, std, am, astd, float(1.0 / np.sum(w * w)), (lo, hi), final)

    def issue_final(self, u: Any = None) -> tuple[float, tuple[float, float]]:
        """Issue the current product's predicted measured final angle (degrees) and its
        90 % interval ``(lo, hi)``, calibrated by adaptive conformal inference on the
        camera values fused so far (:mod:`formtwin.tracker.conformal`; the interval issued
        last for a product is the one its camera value scores), centred on the measured
        angle predicted from the model's by the discrepancy learned from the camera
        (``config.camera_discrepancy``; its predictive std is the interval's scale), else
        on the model's angle with the camera's noise added to its std. The model's angle
        issued here is the one the product's camera value will teach the discrepancy with.
        The particles' final angles at ``u`` are those the step evaluated
        (:class:`~formtwin.tracker.final_angles.FinalAngles`). NaN without a camera."""
        if self.filter.x is None:
            raise RuntimeError("issue_final: no particles yet (call step first)")
        if self.finals is None:
            return math.nan, (math.nan, math.nan)
        uu, col = validate_controls(u, self.spec), self._column(final_output(self.spec))
        a = self.finals.column(0, uu, self.filter.x[:, :self.ssm.n_in],
                               lambda r: self.ssm.predict_angles(r, uu)[:, col])
        self.finals.fill_own(a)
        am, cloud = weighted_moments(self.filter.logw, a)  # one pass (Numba)
        model_var = float(self.ssm.angle_error()[col])
        var = max(cloud, 0.0) + model_var
        return self._final_interval(am, math.sqrt(var), True, model_var)

    def _weights(self) -> FloatArray:
        w = np.exp(self.filter.logw - np.max(self.filter.logw))
        out: FloatArray = w / w.sum()
        return out

    def _final_interval(self, final: float, std: float, record: bool,
                        model_var: float | None = None) -> tuple[float, tuple[float, float]]:
        """The measured final angle's prediction and interval from the model's ``final``
        and its ``std`` (degrees); ``record``: remember them for the product's camera
        value (:meth:`issue_final`), else a report. ``model_var``: the metamodel's final
        angle error variance (degrees^2) when the caller has it."""
        camera = next(s for s in self.sensors if s.measures == final_output(self.spec))
        t = self.filter.t - 1
        sd = math.sqrt(std**2 + camera.noise**2)
        if self.config.camera_discrepancy:
            if model_var is None:
                model_var = float(self.ssm.angle_error()[self._column(final_output(self.spec))])
            noise = camera.noise**2 + model_var
            if record:
                final, var = self.fused.learned(noise).issue(t, final)
            elif math.isfinite(final):
                d = self.fused.discrepancy or AngleDiscrepancy(noise)
                final, var = d.predict(final)
            else:
                final, var = math.nan, math.nan
            sd = math.sqrt(var) if var > 0 else sd
        if not record:
            ok = math.isfinite(final) and math.isfinite(sd) and sd > 0
            q = self.fused.conformal.multiplier() if ok else math.nan
            return final, (final - q * sd, final + q * sd)
        lo, hi = self.fused.conformal.interval(t, final, sd)
        self.fused.forget(t - self.ssm.lag_depth)
        return final, (lo, hi)


def distinct_angles(ssm: BendingSSM, x: FloatArray, u: FloatArray | None) -> FloatArray:
    """The angles (N, 2) of the model inputs ``x`` (N, n_in) at ``u``, the model evaluated
    once per distinct row (after resampling most rows are copies)."""
    rows, inverse = distinct_rows(x)
    out: FloatArray = ssm.predict_angles(rows, u)[inverse]
    return out


@dataclass(frozen=True)
class Posterior:
    """Weighted summary of the current particles (:meth:`SensorFusion.posterior`).

    Attributes
    ----------
    mean, std : (18,) of ``[x, theta, theta_d]``, internal units.
    angles_mean, angles_std : (2,) degrees.
    ess : effective sample size of the current weights.
    final_interval : ``(lo, hi)`` degrees, the camera-calibrated 90 % interval of the
        measured final angle (NaN without a camera among the fused sensors).
    final_mean : degrees, the predicted (measured) final angle, through the discrepancy
        learned from the camera (NaN without a camera).
    """

    mean: FloatArray
    std: FloatArray
    angles_mean: FloatArray
    angles_std: FloatArray
    ess: float
    final_interval: tuple[float, float] = (math.nan, math.nan)
    final_mean: float = math.nan


def angle_sd(tracker: Any, noise_sd: float = 0.0, stage: int = 1) -> float:
    """The default ``sd`` of :func:`update_angle`, degrees: the metamodel's held-out error of
    the angle after ``stage`` (0: the first bending stage, 1: the final angle) and the angle
    sensor's noise ``noise_sd`` added in quadrature."""
    var = float(np.asarray(tracker.ssm.angle_error_var)[stage])
    return math.sqrt(max(var, 0.0) + noise_sd ** 2)


def update_angle(tracker: Any, angle: float, u: float, sd: float | None = None,
                 offset: float = 0.0, stage: int = 1) -> float:
    """Reweight the tracker's particles by the measured ``angle`` (degrees) of the product
    last stepped, made at setting ``u`` (the spec's one control, internal units): the
    lag-0 case of :meth:`SensorFusion.fuse` with the likelihood ``N(angle; a_mm(x, u) +
    offset, sd^2)``, ``sd`` the caller's (None: :func:`angle_sd`), ``stage`` 0 the angle
    after the first bending stage instead; not entered in the tracker's :class:`FusedLog`.
    Returns the log evidence increment.

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
    a = tracker.final_angle(np.array([float(u)]))[:, 0] if stage == 1 else \
        tracker.ssm.predict_angles(tracker.filter.x, float(u))[:, 0]
    try:
        return float(tracker._reweight(a + float(offset), float(angle), s, "angle"))
    except FusionError:
        return -math.inf


__all__ = ["FusedLog", "FusionError", "LagColumns", "Posterior", "SensorFusion", "angle_sd",
           "lag_depth", "update_angle", "used_sensors"]
