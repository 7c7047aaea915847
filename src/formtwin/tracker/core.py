"""The online estimator: one particle-filter step per product (Algorithm 1 of the paper).

Estimates (eq. 13-14) and the predicted angles (posterior predictive mean and std of the
angle model over the weighted particles; with the calibrated likelihood the std adds the
metamodel's held-out angle error) are taken *before* resampling. With
``estimate_deviation=False`` ``theta_d`` is reported with mean 0 and std 0 (an exact,
NaN-free statement of the filter's assumption); with ``learn_mu=True`` the estimate adds
``mu_mean``/``mu_std`` while ``names``/``mean``/``std`` stay the 18 augmented variables.
The reported ``std`` and ``angles_std`` are the particles' plus what ``config.intervals``
adds (:mod:`formtwin.tracker.intervals`: fit-gated floors calibrated offline by default); nothing
else depends on them.

Bad input (a curve not 1-D, numeric, of length ``n_t`` and finite) raises ``ValueError``
naming the problem and leaves the tracker, RNG included, as it was; on weight collapse the
step keeps the predictive particles and says ``collapsed=True`` (:mod:`formtwin.filters.sir`).
The state goes to bytes or a checkpoint file and back, bit for bit (:mod:`formtwin.tracker.state`).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import retain_heap, single_blas_thread
from formtwin.control import Combined, Feedforward, Suggestion
from formtwin.estimates import Estimate, Estimates
from formtwin.filters import SIR, Step, make_filter
from formtwin.filters.resampling import systematic
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.spec.sensors import final_output, output_column
from formtwin.tracker import state as _state
from formtwin.tracker._kernels import angle_moments, cloud_moments, select_heaviest
from formtwin.tracker.ahead import ahead_columns
from formtwin.tracker.config import SCALES, TrackerConfig
from formtwin.tracker.final_angles import FinalAngles
from formtwin.tracker.fit import FitRule, assess
from formtwin.tracker.fusion import FusedLog, SensorFusion, used_sensors
from formtwin.tracker.intervals import Floors
from formtwin.tracker.sandwich import STATE_KEYS, Sandwich
from formtwin.tracker.ssm import BendingSSM
from formtwin.tracker.validate import validate_controls, validate_curve

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)


#: weight the predicted angles may leave out: the lightest particles whose weights sum to at
#: most this are not evaluated. The angles' weighted mean moves by at most ~2 times this
#: times the particles' angle spread ``D`` (max |a_k - mean|), their variance by at most
#: this times ``D^2 + var``. On the bench_filter run (physics metamodel, N = 500, ESS
#: 6-27) the angles' mean stayed within 1.2e-3 of its reported std and the std within
#: 5e-4 relative of evaluating every particle (the float32 angle model's own rounding
#: moves them by 4.7e-4 of the std when the batch changes); it evaluates ~134 of 500
#: particles (median; 257 with 1e-9)
ANGLE_MASS = 1e-4


def heaviest(w: FloatArray, mass: float) -> NDArray[np.intp]:
    """Indices (ascending) of the particles with weights ``w`` (N,) (summing to 1) left
    after dropping the lightest ones whose weights sum to at most ``mass``.

    >>> heaviest(np.array([0.5, 1e-12, 0.3, 0.2 - 1e-12]), 1e-9).tolist()
    [0, 2, 3]
    """
    # only weights <= mass can be dropped, and they come first in the stable ascending
    # order of all weights: sorting them alone gives the same prefix and the same sums
    # (in one Numba pass: the stable sort and the sums in order, the same selection)
    out: NDArray[np.intp] = select_heaviest(np.ascontiguousarray(w, dtype=np.float64),
                                            float(mass))
    return out


class Tracker(SensorFusion):
    """Online state, parameter and deviation estimation for a stream of products.

    Parameters
    ----------
    model : the process model (metamodel) giving curves and angles.
    measurement : the measurement model (likelihood).
    config : settings; default :class:`TrackerConfig()`.
    fit_rule : thresholds of the estimates' health (:mod:`formtwin.tracker.fit`); see
        :func:`formtwin.tracker.build_tracker` for building a tracker from a config alone.

    Examples
    --------
    >>> import numpy as np
    >>> from formtwin.defaults import analytic_model
    >>> model = analytic_model(); spec = model.spec
    >>> mm = MeasurementModel.from_monte_carlo(model, n=2000)
    >>> tr = Tracker(model, mm, TrackerConfig(n_particles=200, estimate_deviation=False))
    >>> curve = model.predict_curves(np.tile(0.5 * (spec.inputs.lo + spec.inputs.hi), (1, 1)))[0]
    >>> e = tr.step(curve)
    >>> e.index, e.mean.shape, tr.n_steps
    (0, (18,), 1)
    >>> Tracker.from_state_bytes(tr.state_bytes(), model, mm).state_bytes() == tr.state_bytes()
    True
    """

    def __init__(self, model: ProcessModel, measurement: MeasurementModel,
                 config: TrackerConfig | None = None, fit_rule: FitRule | None = None
                 ) -> None:
        retain_heap()  # the step's ~MB temporaries: no page faults per product
        self.config = TrackerConfig() if config is None else config
        self.fit_rule = FitRule() if fit_rule is None else fit_rule
        self.model = model
        self.measurement = measurement
        self.ssm = BendingSSM(model, measurement, self.config)
        self.spec = model.spec
        self.names: tuple[str, ...] = self.spec.augmented.names
        self.rng = np.random.default_rng(self.config.seed)
        self.filter: SIR = make_filter(self.config.filter, self.ssm, self.config.n_particles,
                                       self.rng, self.config.resampling,
                                       self.config.ess_threshold)
        c = self.config
        metamodel = c.intervals in ("sandwich", "gated")
        assumed = c.intervals != "cloud" and not (c.mu_known or c.learn_mu)
        self.sandwich = Sandwich(self.ssm, c.intervals == "gated", metamodel, assumed) \
            if metamodel or assumed else None
        self.floors = Floors(model, c.estimate_deviation, c.intervals == "calibrated_fit",
                             learn_residuals=c.learn_residuals) \
            if c.intervals in ("calibrated", "calibrated_fit") else None
        #: what the estimates' std are (:attr:`Estimate.intervals`)
        self.intervals = "uncalibrated" if self.floors is not None \
            and self.floors.calibration.data is None else c.intervals
        self.fused = FusedLog(self.config.sensors)  # sensor values (fuse)
        self.sensors = used_sensors(self.spec, self.config)
        #: with a camera: the particles' final angles and their ancestors', from the step
        self.finals = FinalAngles(self.ssm.lag_depth, len(self.spec.controls)) \
            if any(s.measures == final_output(self.spec) for s in self.sensors) else None
        self._config_dict: dict[str, Any] | None = None
        self._fingerprint: str | None = None

    @property
    def scale(self) -> float | None:
        """Posterior mean of the learned factor on the likelihood covariance
        (``learn_scale``), else ``None``."""
        if not self.config.learn_scale:
            return None
        return float(np.exp(self.ssm.scale_logpost) @ np.array(SCALES))

    @property
    def error_share(self) -> float | None:
        """Posterior mean of the share ``kappa`` of ``K_res`` added to the likelihood's
        covariance (adaptive and discrepancy likelihoods), else ``None``."""
        d = self.ssm.discrepancy
        return None if d is None else float(np.exp(self.ssm.share_logpost) @ d.shares)

    @property
    def n_steps(self) -> int:
        """Number of products assimilated so far."""
        return self.filter.t

    @property
    def particles(self) -> FloatArray | None:
        """Current (resampled) particles (N, 18) (N, 32 with the learned mu's ``m, P`` last), or
        ``None`` before the first step."""
        return self.filter.x

    def step(self, curve: Any, u: Any = None) -> Estimate:
        """Assimilate the force curve (n_t,) N of the next product; return its estimate.

        ``u`` is the product's press setting (the spec's controls, internal units: a
        number, or a sequence of one per control; None: the nominal setting). It does not
        act on the stage-1 curve; the predicted angles are those at ``u``.

        Raises ``ValueError`` for a malformed curve or setting. If anything fails during
        the step (the checks, or the model raising), the tracker is left exactly as before:
        particles, weights, step count and RNG state.
        """
        y = validate_curve(curve, self.spec.n_t)
        uu = validate_controls(u, self.spec)
        f = self.filter
        saved = (f.x, f.logw, f.t, self.rng.bit_generator.state)
        scale = self.ssm.scale_logpost if self.config.learn_scale else None
        share, learned = self.ssm.share_logpost, self.ssm.learned_snapshot()
        sw = None if self.sandwich is None else self.sandwich.snapshot()
        fl = None if self.floors is None else self.floors.state()
        fa = None if self.finals is None else self.finals.snapshot()
        try:
            logw_prev = f.logw
            self.ssm.ahead.update(ahead_columns(self))  # values known before this curve
            s = f.step(y)
            if scale is not None:
                self.ssm.update_scale(logw_prev)
            ratio = getattr(f, "log_ratio", None)  # guided filter: p(x | parent) / q(x)
            self.ssm.update_share(logw_prev if ratio is None else logw_prev + ratio)
            self.ssm.update_residuals(s)
            c = 1.0 if scale is None else float(np.exp(scale) @ np.array(SCALES))
            est = self._estimate(s, np.exp(saved[1]), c, uu, y, saved[0])
            self.fused.ahead.clear()
            return est
        except BaseException:
            f.x, f.logw, f.t = saved[0], saved[1], saved[2]
            if self.sandwich is not None and sw is not None:
                self.sandwich.restore(sw)
            if self.floors is not None and fl is not None:
                self.floors.set_state(fl)
            if self.finals is not None and fa is not None:
                self.finals.restore(fa)
            self.rng.bit_generator.state = saved[3]
            if scale is not None:
                self.ssm.set_scale_logpost(scale)
            self.ssm.set_share_logpost(share)
            self.ssm.learned_restore(learned)
            raise
        finally:
            self.ssm.ahead.clear()

    def final_angle(self, u: Any) -> FloatArray:
        """Final angle (N, n_u), degrees, of the current particles (:attr:`particles`,
        equally weighted after the last step) at each setting ``u`` (n_u,) of the control."""
        if self.filter.x is None:
            raise RuntimeError("final_angle: no particles yet (call step first)")
        return self.ssm.final_angle(self.filter.x, np.asarray(u, dtype=np.float64))

    def weights(self) -> FloatArray | None:
        """Relative weights (N,) of the current particles (largest 1), ``None`` when they
        are equal (as after resampling)."""
        logw = np.asarray(self.filter.logw, dtype=np.float64)
        if self.filter.x is None or logw.shape != (self.filter.x.shape[0],) or np.ptp(logw) == 0:
            return None
        out: FloatArray = np.exp(logw - logw.max())
        return out

    def suggest(self, controller: Feedforward | Combined, u_prev: float | None = None,
                reference: float | None = None) -> Suggestion:
        """The press setting for the product just assimilated: ``controller``'s choice over
        the current particles and weights (:mod:`formtwin.control.feedforward`: least
        posterior expected squared error of the final angle, within the actuator's limits
        and maximum step after ``u_prev``), with the predicted final angle there;
        ``reference`` the :class:`~formtwin.control.Combined` controller's ``c_i`` (None:
        computed by it where needed)."""
        if self.filter.x is None:
            raise RuntimeError("suggest: no particles yet (call step first)")
        if isinstance(controller, Combined):
            return controller.choose(self.final_angle, self.weights(), u_prev, reference)
        return controller.choose(self.final_angle, self.weights(), u_prev)

    def _estimate(self, s: Step, v: FloatArray, scale: float = 1.0,
                  u: FloatArray | None = None, y: FloatArray | None = None,
                  parents: FloatArray | None = None) -> Estimate:
        """The estimate of step ``s``; ``v`` (N,) the predictive weights of its particles,
        ``scale`` the predictive mean of the likelihood's covariance factor, ``u`` the
        product's press setting (None: nominal) for the predicted angles, ``y`` its curve
        (for the sandwich intervals), ``parents`` the filter's particles before the step
        (for :attr:`finals`)."""
        m, rows = self.config.angle_particles, None
        if m is None or m >= s.x.shape[0]:
            keep = rows = heaviest(s.w, ANGLE_MASS)
            xa, wa = (s.x, s.w) if keep.size == s.x.shape[0] else (s.x[keep], s.w[keep])
        else:
            xa, wa = s.x[systematic(s.w, self.rng, m)], np.full(m, 1.0 / m)
        angles = self.ssm.predict_angles(xa, u)
        if self.finals is not None:  # kept for the final angle's interval and the camera
            self._keep_finals(s, angles, rows, u, parents)
        # the angles' weighted mean and std, rows with NaN or inf left out (Numba)
        am, astd = angle_moments(np.ascontiguousarray(angles, dtype=np.float64), wa,
                                 self.ssm.angle_error())
        mean, na = s.mean(), len(self.names)
        # the std (eq. 14) and, for the intervals, the cloud's covariance in one pass (the
        # mean computed once)
        sw = self.sandwich if y is not None else None
        var_x, P = cloud_moments(s.x, s.w, mean, 0 if sw is None else sw.m)
        std = np.sqrt(np.maximum(var_x, 0.0))
        if self.sandwich is not None and y is not None:
            var, avar = self.sandwich.update(s.x, s.w, y, self.filter.t - 1, u, mean, P)
            std = np.sqrt(std[:na] ** 2 + var)
            astd = np.sqrt(astd**2 + avar)
        mu = self.ssm.mu_moments(s.x, s.w) if self.config.learn_mu else None
        r, cov = self.ssm.fit_residuals()  # whitened by the step where it can
        fit = assess(r, v, s.ess, self.measurement, s.collapsed, self.fit_rule, scale, cov)
        if self.floors is not None:  # calibrated offline: floors in quadrature
            std, astd = self.floors.apply(std[:na], astd, fit.distance2)
        return Estimate(index=self.filter.t - 1, names=self.names, mean=mean[:na],
                        std=std[:na], angles_mean=am, angles_std=astd, ess=s.ess,
                        collapsed=s.collapsed, loglik=s.loglik,
                        mu_mean=mu[0] if mu else None, mu_std=mu[1] if mu else None,
                        fit=fit, intervals=self.intervals,
                        output_names=self.ssm.spec.output_names)

    def _keep_finals(self, s: Step, angles: FloatArray, rows: NDArray[np.intp] | None,
                     u: FloatArray | None, parents: FloatArray | None) -> None:
        """:attr:`finals` after step ``s``: ``angles`` (m, 2) at ``u`` of its particles
        ``rows`` (None: of a resampled subset, not kept); ``parents`` the filter's rows
        before the step."""
        assert self.finals is not None
        n = s.x.shape[0]
        own = np.full(n, np.nan)
        if rows is not None:
            own[rows] = angles[:, output_column(self.spec, final_output(self.spec))]
        start, width = self.ssm.lag_start, self.ssm.n_in
        same = parents is not None and parents.shape[0] == n and self.ssm.lag_depth > 0 \
            and np.array_equal(s.x[:, start:start + width], parents[:, :width])
        self.finals.stepped(own, u, bool(same), self.filter.ancestors)

    def run(self, curves: Iterable[Any], progress: bool = False,
            u: Any = None) -> Estimates:
        """Assimilate curves (n, n_t) one product at a time; return stacked estimates.

        ``u`` (n,) or (n, n_controls): each product's press setting (None: nominal).

        ``progress`` shows a tqdm bar (only on a terminal). BLAS is limited to one thread
        for the run (:func:`formtwin._threads.single_blas_thread`); callers of :meth:`step`
        in a loop should do the same around their loop.
        """
        items: list[Estimate] = []
        it: Iterable[Any] = curves
        if progress:
            from tqdm import tqdm
            it = tqdm(curves, desc="tracking", unit="product", disable=not sys.stderr.isatty())
        with single_blas_thread():  # once per run: entering it costs ~0.25 ms
            for i, c in enumerate(it):
                items.append(self.step(c, None if u is None else u[i]))
        return Estimates.stack(items, self.names)

    # ------------------------------------------------------------------ state
    def state(self) -> _state.TrackerState:
        """The full state (a copy-free view: do not modify its arrays)."""
        if self._config_dict is None:
            self._config_dict = self.config.to_dict()
        if self._fingerprint is None:
            self._fingerprint = _state.fingerprint(self.measurement)
        f = self.filter
        x = np.empty((0, self.ssm.n_aug)) if f.x is None else f.x
        model: dict[str, Any] = {"scale_logpost": [float(v) for v in self.ssm.scale_logpost]} \
            if self.config.learn_scale else {}
        if self.ssm.share_logpost.size > 1:
            model["share_logpost"] = [float(v) for v in self.ssm.share_logpost]
        for part in (self.sandwich, self.floors, self.ssm.learned, self.fused, self.finals):
            model.update({} if part is None else part.state())
        return _state.TrackerState(particles=x, logw=np.asarray(f.logw, dtype=np.float64),
                                   t=f.t, rng=dict(self.rng.bit_generator.state),
                                   config=self._config_dict, names=self.names,
                                   measurement=self._fingerprint, model=model)

    def set_state(self, s: _state.TrackerState, where: str = "state") -> None:
        """Continue from ``s`` (made by a tracker with the same config and names)."""
        if TrackerConfig.from_dict(s.config) != self.config:
            raise ValueError(f"{where}: saved with config {s.config}, this tracker has "
                             f"{self.config.to_dict()}")
        if s.names != self.names:
            raise ValueError(f"{where}: state names {s.names} differ from the model's "
                             f"{self.names}")
        if s.measurement != (self._fingerprint or _state.fingerprint(self.measurement)):
            log.warning("%s: restoring with a different measurement model than saved", where)
        self.rng.bit_generator.state = s.rng
        if self.config.learn_scale and "scale_logpost" in s.model:
            self.ssm.set_scale_logpost(np.array(s.model["scale_logpost"], dtype=np.float64))
        if "share_logpost" in s.model:
            self.ssm.set_share_logpost(np.array(s.model["share_logpost"], dtype=np.float64))
        if self.sandwich is not None:
            self.sandwich.set_state({k: s.model[k] for k in STATE_KEYS if k in s.model})
        if self.floors is not None:
            self.floors.set_state(s.model)
        self.ssm.set_learned_state(s.model)
        self.fused.set_state(s.model)
        if self.finals is not None:
            self.finals.set_state(s.model)
        self.filter.x = s.particles if s.t > 0 and s.particles.size else None
        self.filter.logw = s.logw
        self.filter.t = s.t

    def state_bytes(self) -> bytes:
        """The full state as bytes (:func:`formtwin.tracker.state.encode`)."""
        return _state.encode(self.state())

    def load_state_bytes(self, data: bytes) -> None:
        """Continue from bytes made by :meth:`state_bytes` of a tracker like this one."""
        self.set_state(_state.decode(data))

    @classmethod
    def from_state(cls, s: _state.TrackerState, model: ProcessModel,
                   measurement: MeasurementModel, where: str = "state") -> Tracker:
        """A tracker continuing exactly where the one that saved ``s`` stopped."""
        tr = cls(model, measurement, TrackerConfig.from_dict(s.config))
        tr.set_state(s, where)
        return tr

    @classmethod
    def from_state_bytes(cls, data: bytes, model: ProcessModel,
                         measurement: MeasurementModel) -> Tracker:
        """A tracker continuing from bytes made by :meth:`state_bytes`."""
        return cls.from_state(_state.decode(data), model, measurement)

    def checkpoint(self, path: str | Path) -> Path:
        """Save the full state to ``path`` (.npz, atomic replace); return the path."""
        return _state.save_npz(self.state(), path)

    @classmethod
    def restore(cls, path: str | Path, model: ProcessModel,
                measurement: MeasurementModel) -> Tracker:
        """A tracker continuing exactly where the one that wrote ``path`` stopped."""
        return cls.from_state(_state.load_npz(path), model, measurement, where=str(path))
