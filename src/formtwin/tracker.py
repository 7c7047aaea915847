"""The online estimator: one particle-filter step per product, checkpoint and restore.

The filter's state is the augmented vector ``[x (7), theta (3), theta_d (8)]`` named by
``spec.augmented``. :class:`BendingSSM` is the state-space model the generic filter sees:

* initial law: ``x ~ N(mu, sigma^2)`` per variable (its stationary law under eq. 4-5,
  reflected into the design box), ``theta`` and ``theta_d`` uniform in their bounds;
* transition: ``x`` by the AR(1) evolution (eq. 4-5), ``theta`` and ``theta_d`` by the
  jitter of eq. 10 (``alpha`` times the range), all reflected into their bounds;
* likelihood (eq. 12): ``g^-1(z, theta_d)`` against the model curve ``z~(x, theta)`` under
  the :class:`~formtwin.measurement.MeasurementModel`.

With ``learn_mu=True`` (the paper's Discussion: the statistics as hyperparameters
estimated with the rest) the particles carry 7 more columns, their own mu: initially
``U(mu_min, mu_max)``, each particle's ``x`` evolves with its own mu, then mu takes a jitter
step of std ``mu_alpha (mu_max - mu_min)`` reflected into ``[mu_min, mu_max]``. The
estimate reports it in ``mu_mean``/``mu_std``; ``names``/``mean``/``std`` stay the 18
augmented variables.

With ``estimate_deviation=False`` (paper series 1, 2, 4, 5) ``theta_d`` is fixed at 0
(``g`` is the identity), never jittered, and reported with mean 0 and std 0 (an exact,
NaN-free statement of the filter's assumption).

Estimates (eq. 13-14) and the predicted angles (posterior predictive mean and std of the
angle model over the weighted particles) are taken *before* resampling.

Bad input: :meth:`Tracker.step` validates the curve first (1-D, numeric, length ``n_t``,
finite) and raises ``ValueError`` naming the problem; the tracker's state, RNG included, is
untouched. Weight collapse is handled by the filter (see :mod:`formtwin.filters.sir`): the
step keeps the predictive particles, and the estimate says ``collapsed=True``.

Checkpoints are ``.npz`` files (no pickle) holding particles, log-weights, the RNG state as
JSON, the config as JSON and the step count; a restored tracker continues bit for bit.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.deviation import DeviationModel
from formtwin.estimates import Estimate, Estimates
from formtwin.evolution import evolve, jitter, reflect, stationary
from formtwin.filters import SIR, Step, make_filter
from formtwin.filters.resampling import systematic
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

_CHECKPOINT_FORMAT = "formtwin.tracker/1"

#: where the likelihood compares curves: "model" (paper eq. 12: g^-1(z, theta_d) against
#: z~(x, theta)) or "measurement" (z against g(z~(x, theta), theta_d))
COMPARE = ("model", "measurement")

#: particles per block when evaluating the model: bounds peak memory at large N and keeps
#: the RBF distance blocks in cache (N = 1e4 on the 7024-point metamodel: 0.7 s per step
#: with 512, 1.9 s with 8192)
CHUNK = 512


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of a :class:`Tracker` (immutable; change with ``dataclasses.replace``).

    Attributes
    ----------
    n_particles : N (paper: 500).
    alpha : jitter of theta and theta_d as a fraction of their range (eq. 10).
    estimate_deviation : estimate theta_d (series 3, 6) or fix it at 0 (series 1, 2, 4, 5).
    mu, sigma, rho : (7,) assumed state statistics, internal units; ``None`` -> the spec's
        ``mu_mid`` (series 4, 6), ``sigma`` and ``rho``.
    resampling : resampling scheme name (or callable, not checkpointable).
    seed : seed of the tracker's ``numpy.random.default_rng``.
    filter : particle-filter name (:data:`formtwin.filters.FILTERS`).
    ess_threshold : resample when ESS < ess_threshold N (1.0: every step, Algorithm 1).
    compare : ``"model"`` (paper eq. 12) or ``"measurement"``, see :data:`COMPARE`.
    angle_particles : predict the angles from this many particles drawn from the weighted
        cloud by systematic resampling (cuts the cost of the angle models, adds Monte-Carlo
        error of order ``std / sqrt(angle_particles)``); ``None`` (default): all particles
        with their weights.
    learn_mu : estimate the statistics mu as per-particle hyperparameters (prior
        ``U(mu_min, mu_max)``); ``mu`` is then ignored. Default off (the paper's filter).
    mu_alpha : jitter of the learned mu per product, as a fraction of ``mu_max - mu_min``.
        0.02: with resampling every step the mu cloud collapses onto few ancestors and
        only the jitter keeps it diverse; on the analytic stand-in (5 datasets, N = 500,
        500 products) 0.005 left the mu posterior std at ~0.07 sigma with errors of
        1-2 sigma, 0.02 gave the smallest mu and state errors of 0.005/0.01/0.02
        (docs/improvements.md). The price: the filter forgets old products, mu is a
        local level over roughly the last 50-100 products rather than a constant.
    """

    n_particles: int = 500
    alpha: float = 0.01
    estimate_deviation: bool = True
    mu: tuple[float, ...] | None = None
    sigma: tuple[float, ...] | None = None
    rho: tuple[float, ...] | None = None
    resampling: Any = "systematic"
    seed: int = 0
    filter: str = "sir"
    ess_threshold: float = 1.0
    compare: str = "model"
    angle_particles: int | None = None
    learn_mu: bool = False
    mu_alpha: float = 0.02

    def __post_init__(self) -> None:
        if self.angle_particles is not None and self.angle_particles < 1:
            raise ValueError(f"angle_particles = {self.angle_particles}, expected >= 1 or None")
        if self.compare not in COMPARE:
            raise ValueError(f"compare = {self.compare!r}; known: {', '.join(COMPARE)}")
        for name in ("mu", "sigma", "rho"):
            v = getattr(self, name)
            if v is not None:  # store as a tuple of floats so the config stays hashable/JSON
                object.__setattr__(self, name, tuple(float(a) for a in np.ravel(v)))
        if self.n_particles < 1:
            raise ValueError(f"n_particles = {self.n_particles}, expected >= 1")
        if self.alpha < 0:
            raise ValueError(f"alpha = {self.alpha}, expected >= 0")
        if self.mu_alpha < 0:
            raise ValueError(f"mu_alpha = {self.mu_alpha}, expected >= 0")

    def to_json(self) -> str:
        if not isinstance(self.resampling, str):
            raise ValueError("a config with a callable resampling scheme cannot be saved")
        return json.dumps(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, text: str) -> TrackerConfig:
        return cls(**json.loads(text))


@dataclass(frozen=True)
class BendingSSM:
    """The augmented state-space model ``[x, theta, theta_d]`` for the generic filters."""

    model: ProcessModel
    measurement: MeasurementModel
    config: TrackerConfig
    spec: ProcessSpec = field(init=False)
    deviation: DeviationModel = field(init=False)
    _mu: FloatArray = field(init=False, repr=False)
    _sigma: FloatArray = field(init=False, repr=False)
    _rho: FloatArray = field(init=False, repr=False)
    # bounds of the particle columns: (18,), or (25,) with [mu_min, mu_max] when learning mu
    _lo: FloatArray = field(init=False, repr=False)
    _hi: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        spec = self.model.spec
        object.__setattr__(self, "spec", spec)
        # the spec builds these arrays on every access (~20 us): keep them
        lo, hi = spec.augmented.lo, spec.augmented.hi
        if self.config.learn_mu:
            lo, hi = np.r_[lo, spec.state.mu_min], np.r_[hi, spec.state.mu_max]
        object.__setattr__(self, "_lo", lo)
        object.__setattr__(self, "_hi", hi)
        object.__setattr__(self, "deviation", DeviationModel.from_spec(spec))
        st, c = spec.state, self.config
        for name, v in (("mu", c.mu), ("sigma", c.sigma), ("rho", c.rho)):
            if v is not None and len(v) != len(st):
                raise ValueError(f"config.{name} has {len(v)} values, expected {len(st)} "
                                 f"({', '.join(st.names)})")
        object.__setattr__(self, "_mu", st.mu_mid if c.mu is None else np.array(c.mu))
        object.__setattr__(self, "_sigma", st.sigma if c.sigma is None else np.array(c.sigma))
        object.__setattr__(self, "_rho", st.rho if c.rho is None else np.array(c.rho))
        if self.measurement.n_t != spec.n_t:
            raise ValueError(f"measurement model has {self.measurement.n_t} samples, "
                             f"the spec's curves {spec.n_t}")

    @property
    def n_x(self) -> int:
        return len(self.spec.state)

    @property
    def n_in(self) -> int:
        return self.spec.n_inputs

    @property
    def n_aug(self) -> int:
        """Width of the augmented state ``[x, theta, theta_d]`` (18); the particles have
        ``n_x`` more columns (their mu) when learning mu."""
        return len(self.spec.augmented)

    def sample_initial(self, n: int, rng: np.random.Generator) -> FloatArray:
        lo, hi, nx = self._lo, self._hi, self.n_x
        out = lo + (hi - lo) * rng.random((n, lo.size))
        if self.config.learn_mu:  # x from the stationary law of each particle's own mu
            mu = out[:, self.n_aug:]
            out[:, :nx] = reflect(mu + self._sigma * rng.standard_normal((n, nx)),
                                  lo[:nx], hi[:nx])
        else:
            out[:, :nx] = stationary(n, self._mu, self._sigma, rng, lo[:nx], hi[:nx])
        if not self.config.estimate_deviation:
            out[:, self.n_in:self.n_aug] = 0.0
        return out

    def sample_transition(self, x: FloatArray, rng: np.random.Generator) -> FloatArray:
        lo, hi, nx, na = self._lo, self._hi, self.n_x, self.n_aug
        out = np.empty_like(x)
        mu = x[:, na:] if self.config.learn_mu else self._mu
        # eq. 4-5, then reflection of the few rows that left the box
        out[:, :nx] = _into_box(evolve(x[:, :nx], mu, self._sigma, self._rho, rng),
                                lo[:nx], hi[:nx])
        stop = na if self.config.estimate_deviation else self.n_in
        out[:, nx:stop] = jitter(x[:, nx:stop], lo[nx:stop], hi[nx:stop], rng,
                                 self.config.alpha)
        out[:, stop:na] = x[:, stop:na]
        if self.config.learn_mu:
            out[:, na:] = jitter(x[:, na:], lo[na:], hi[na:], rng, self.config.mu_alpha)
        return out

    def loglik(self, x: FloatArray, y: FloatArray) -> FloatArray:
        if x.shape[0] <= CHUNK:
            return self._loglik(x, y)
        # in blocks of particles: bounds the (N, n_t) temporaries of model and g^-1
        return np.concatenate([self._loglik(x[i: i + CHUNK], y)
                               for i in range(0, x.shape[0], CHUNK)])

    def constrain(self, x: FloatArray) -> FloatArray:
        """Reflect particles (N, 18) or (N, 25) into their bounds (used by kernel moves);
        ``theta_d`` stays 0 when it is not estimated."""
        out = reflect(x, self._lo, self._hi)
        if not self.config.estimate_deviation:
            out[:, self.n_in:self.n_aug] = 0.0
        return out

    def predict_angles(self, x: FloatArray) -> FloatArray:
        """Angles (N, 2) of particles ``x`` (N, 18) or (N, 25), in blocks of particles."""
        return np.concatenate([self.model.predict_angles(x[i: i + CHUNK, : self.n_in])
                               for i in range(0, x.shape[0], CHUNK)])

    def _loglik(self, x: FloatArray, y: FloatArray) -> FloatArray:
        curves = self.model.predict_curves(x[:, : self.n_in])
        if not self.config.estimate_deviation:
            return self.measurement.loglik(curves, y)
        td = x[:, self.n_in:self.n_aug]
        if self.config.compare == "measurement":
            return self.measurement.loglik(self.deviation.apply(curves, td), y)
        return self.measurement.loglik(curves, self.deviation.invert(y, td))


def _into_box(v: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """:func:`~formtwin.evolution.reflect` applied to the rows (N, d) that left the box
    (most rows stay inside, and ``reflect`` costs a float modulo per entry)."""
    rows = np.any((v < lo) | (v > hi), axis=1)
    if rows.any():
        v[rows] = reflect(v[rows], lo, hi)
    return v


def validate_curve(curve: Any, n_t: int) -> FloatArray:
    """``curve`` as a float array (n_t,), or ``ValueError`` naming what is wrong."""
    if isinstance(curve, (str, bytes)):
        raise ValueError(f"curve is a {type(curve).__name__}, expected {n_t} numbers")
    try:
        arr = np.asarray(curve)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"curve cannot be read as an array: {exc}") from exc
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"curve has dtype {arr.dtype}, expected real numbers")
    if arr.ndim != 1:
        raise ValueError(f"curve has shape {arr.shape}, expected ({n_t},)")
    if arr.size != n_t:
        raise ValueError(f"curve has {arr.size} samples, expected {n_t}")
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ValueError(f"curve has {int(bad.sum())} non-finite values (NaN/inf), first "
                         f"at sample {int(np.argmax(bad))}")
    return arr


class Tracker:
    """Online state, parameter and deviation estimation for a stream of products.

    Parameters
    ----------
    model : the process model (metamodel) giving curves and angles.
    measurement : the measurement model (likelihood).
    config : settings; default :class:`TrackerConfig()`.

    Examples
    --------
    >>> import numpy as np
    >>> from formtwin.spec import load_spec
    >>> from formtwin.measurement import AnalyticModel, MeasurementModel
    >>> spec = load_spec(); model = AnalyticModel(spec)
    >>> mm = MeasurementModel.from_monte_carlo(model, n=2000)
    >>> tr = Tracker(model, mm, TrackerConfig(n_particles=200, estimate_deviation=False))
    >>> curve = model.predict_curves(np.tile(0.5 * (spec.inputs.lo + spec.inputs.hi), (1, 1)))[0]
    >>> e = tr.step(curve)
    >>> e.index, e.mean.shape, tr.n_steps
    (0, (18,), 1)
    """

    def __init__(self, model: ProcessModel, measurement: MeasurementModel,
                 config: TrackerConfig | None = None) -> None:
        self.config = TrackerConfig() if config is None else config
        self.model = model
        self.measurement = measurement
        self.ssm = BendingSSM(model, measurement, self.config)
        self.spec = model.spec
        self.names: tuple[str, ...] = self.spec.augmented.names
        self.rng = np.random.default_rng(self.config.seed)
        self.filter: SIR = make_filter(self.config.filter, self.ssm, self.config.n_particles,
                                       self.rng, self.config.resampling,
                                       self.config.ess_threshold)

    @property
    def n_steps(self) -> int:
        """Number of products assimilated so far."""
        return self.filter.t

    @property
    def particles(self) -> FloatArray | None:
        """Current (resampled) particles (N, 18) (N, 25 with the learned mu last), or
        ``None`` before the first step."""
        return self.filter.x

    def step(self, curve: Any) -> Estimate:
        """Assimilate the force curve (n_t,) N of the next product; return its estimate.

        Raises ``ValueError`` for a malformed curve. If anything fails during the step
        (the curve check, or the model raising), the tracker is left exactly as before:
        particles, weights, step count and RNG state.
        """
        y = validate_curve(curve, self.spec.n_t)
        f = self.filter
        saved = (f.x, f.logw, f.t, self.rng.bit_generator.state)
        try:
            s = f.step(y)
            return self._estimate(s)
        except BaseException:
            f.x, f.logw, f.t = saved[0], saved[1], saved[2]
            self.rng.bit_generator.state = saved[3]
            raise

    def _estimate(self, s: Step) -> Estimate:
        m = self.config.angle_particles
        if m is None or m >= s.x.shape[0]:
            xa, wa = s.x, s.w
        else:
            xa, wa = s.x[systematic(s.w, self.rng, m)], np.full(m, 1.0 / m)
        angles = self.ssm.predict_angles(xa)
        ok = np.all(np.isfinite(angles), axis=1)
        w = np.where(ok, wa, 0.0)
        if w.sum() > 0:
            w = w / w.sum()
            a = np.where(ok[:, None], angles, 0.0)
            am = w @ a
            astd = np.sqrt(np.maximum(w @ (a - am) ** 2, 0.0))
        else:
            am = astd = np.full(2, np.nan)
        mean, std, na = s.mean(), s.std(), len(self.names)
        learned = self.config.learn_mu
        return Estimate(index=self.filter.t - 1, names=self.names, mean=mean[:na],
                        std=std[:na], angles_mean=am, angles_std=astd, ess=s.ess,
                        collapsed=s.collapsed, loglik=s.loglik,
                        mu_mean=mean[na:] if learned else None,
                        mu_std=std[na:] if learned else None)

    def run(self, curves: Iterable[Any], progress: bool = False) -> Estimates:
        """Assimilate curves (n, n_t) one product at a time; return stacked estimates.

        ``progress`` shows a tqdm bar (only on a terminal). BLAS is limited to one thread
        for the run (:func:`formtwin._threads.single_blas_thread`); callers of :meth:`step`
        in a loop should do the same around their loop.
        """
        items: list[Estimate] = []
        it: Iterable[Any] = curves
        if progress:
            import sys

            from tqdm import tqdm
            it = tqdm(curves, desc="tracking", unit="product", disable=not sys.stderr.isatty())
        with single_blas_thread():  # once per run: entering it costs ~0.25 ms
            for c in it:
                items.append(self.step(c))
        return Estimates.stack(items, self.names)

    # ------------------------------------------------------------------ persistence
    def checkpoint(self, path: str | Path) -> Path:
        """Save the full state to ``path`` (.npz, atomic replace); return the path."""
        p = Path(path)
        f = self.filter
        x = np.empty((0, self.ssm.n_aug)) if f.x is None else f.x
        tmp = p.with_name(p.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, format=np.array(_CHECKPOINT_FORMAT), particles=x, logw=f.logw,
                     t=np.array(f.t), rng=np.array(json.dumps(self.rng.bit_generator.state)),
                     config=np.array(self.config.to_json()), names=np.array(self.names),
                     measurement=np.array(_fingerprint(self.measurement)))
        os.replace(tmp, p)
        return p

    @classmethod
    def restore(cls, path: str | Path, model: ProcessModel,
                measurement: MeasurementModel) -> Tracker:
        """A tracker continuing exactly where the one that wrote ``path`` stopped."""
        with np.load(Path(path), allow_pickle=False) as z:
            fmt = str(z["format"]) if "format" in z else ""
            if fmt != _CHECKPOINT_FORMAT:
                raise ValueError(f"{path}: not a tracker checkpoint (format {fmt!r})")
            config = TrackerConfig.from_json(str(z["config"]))
            names = tuple(str(n) for n in z["names"])
            particles, logw, t = z["particles"], z["logw"], int(z["t"])
            rng_state = json.loads(str(z["rng"]))
            mfp = str(z["measurement"])
        tr = cls(model, measurement, config)
        if names != tr.names:
            raise ValueError(f"{path}: state names {names} differ from the model's {tr.names}")
        if mfp != _fingerprint(measurement):
            log.warning("%s: restoring with a different measurement model than saved", path)
        tr.rng.bit_generator.state = rng_state
        tr.filter.x = particles if t > 0 and particles.size else None
        tr.filter.logw = logw
        tr.filter.t = t
        return tr


def _fingerprint(m: MeasurementModel) -> str:
    """A short hash of the measurement model's numbers (detects a swapped model)."""
    import hashlib

    h = hashlib.sha256()
    for a in (m.basis, m.lam, np.array([m.s2, m.nu])):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


__all__ = ["BendingSSM", "Estimate", "Estimates", "Tracker", "TrackerConfig",
           "validate_curve"]
