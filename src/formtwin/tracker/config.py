"""The tracker's settings: one :class:`TrackerConfig`, nested by the study, the service and
the command line (TOML section ``[tracker]``, flags generated from its fields by
:mod:`formtwin._config`)."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: where the likelihood compares curves: "model" (paper eq. 12: g^-1(z, theta_d) against
#: z~(x, theta)) or "measurement" (z against g(z~(x, theta), theta_d))
COMPARE = ("model", "measurement")

#: likelihoods (:mod:`formtwin.measurement`, :mod:`formtwin.tracker.discrepancy`):
#: "calibrated" adds the metamodel's k-fold residual covariance K_res to fraction^2 K_MC;
#: "paper" is eq. 12 alone; "adaptive" adds kappa K_res with the share kappa weighted by
#: the running evidence (Bayesian model averaging over :data:`SHARES`: kappa = 0 is the
#: paper's, 1 the calibrated); "discrepancy" also learns a part of the metamodel's error
#: shared by the products, prior N(0, (1 - kappa) K_res)
LIKELIHOODS = ("calibrated", "paper", "adaptive", "discrepancy")

#: the reported intervals (:mod:`formtwin.tracker.intervals`): "cloud" the particles'
#: weighted std (eq. 14); the others add the assumed mu's term unless ``mu_known``
#: (:mod:`formtwin.tracker.sandwich`), "cloud_mu" that alone; "calibrated"
#: adds in quadrature floors learned offline on physics runs
#: of the bundled metamodel; "calibrated_fit" scales their squares by the curves' running fit
#: distance in excess of its value on the metamodel's own curves (learned in the same
#: calibration); "sandwich" adds the covariance ``B`` of the error a persistent
#: metamodel error ``N(0, K_res)`` puts in the estimate; "gated" adds ``P(kappa > 0) B``
INTERVALS = ("cloud", "cloud_mu", "calibrated", "calibrated_fit", "sandwich", "gated")

#: priors of a learned mu (``learn_mu``): "uniform" is ``U(mu_min, mu_max)``, the law the
#: paper's statistics are drawn from (posterior: a truncated Normal), "normal" the Normal
#: with its mean and variance (posterior: a Normal, may leave the range)
MU_PRIORS = ("uniform", "normal")

#: the grid of the share ``kappa`` of ``K_res`` learned by the adaptive and discrepancy
#: likelihoods when ``error_share`` is None (0: the paper's likelihood, 1: the calibrated)
SHARES = (0.0, 0.25, 0.5, 0.75, 1.0)

#: the grid of factors on the likelihood covariance learned with ``learn_scale``
SCALES = tuple(float(2.0**k) for k in np.arange(-3.0, 3.5, 0.5))


def _help(text: str, *flags: str) -> dict[str, Any]:
    """Field metadata: help text and extra command-line flags."""
    return {"help": text, "flags": flags}


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of a :class:`~formtwin.tracker.Tracker` (immutable; change with
    ``dataclasses.replace``).

    Attributes
    ----------
    n_particles : N (paper: 500).
    alpha : jitter of theta and theta_d as a fraction of their range (eq. 10).
    estimate_deviation : estimate theta_d (series 3, 6) or fix it at 0 (series 1, 2, 4, 5).
    mu, sigma, rho : (7,) assumed state statistics, internal units; ``None`` -> the spec's
        ``mu_mid`` (series 4, 6), ``sigma`` and ``rho``. ``mu`` is also the mean of the
        Monte-Carlo states behind ``K_MC`` (paper, "Simulation runs").
    mu_known : ``mu`` is the line's true state mean (the study's series 1-3 and 5). False
        (default: a live line does not know it): the reported std add the error of
        assuming it, the line's mu drawn from ``U(mu_min, mu_max)`` (the linearised
        filter's ``G_mu``, :mod:`formtwin.tracker.sandwich`), for every ``intervals`` but
        ``"cloud"``; none with ``learn_mu``. The command line sets it when ``--mu`` is
        given (the line's means; ``--no-mu-known`` for a guess). Particles, means, ESS and
        evidence do not change.
    resampling : resampling scheme name (or callable, not checkpointable).
    seed : seed of the tracker's ``numpy.random.default_rng`` (and of the Monte-Carlo
        curves for ``K_MC`` when :func:`~formtwin.tracker.build_tracker` makes them).
    filter : particle-filter name (:data:`formtwin.filters.FILTERS`).
    ess_threshold : resample when ESS < ess_threshold N (1.0: every step, Algorithm 1).
    compare : ``"measurement"`` (default: the measured curve ``z`` against the deviated model
        curve ``g(z~, theta_d)``, a proper density of ``z``) or ``"model"`` (paper eq. 12:
        ``g^-1(z, theta_d)`` against ``z~``), see :data:`COMPARE` and
        docs/explanation/likelihood.md.
    angle_particles : predict the angles from this many particles drawn from the weighted
        cloud by systematic resampling (cuts the cost of the angle models, adds Monte-Carlo
        error of order ``std / sqrt(angle_particles)``; with an ESS of 20-100 of 500, 100
        hold the cloud's distinct particles and save ~15 % of a step at N = 500); ``None``
        (default, or a value >= N): all particles with their weights (but the lightest,
        whose weights sum to at most ``1e-4``: :data:`formtwin.tracker.core.ANGLE_MASS`).
    learn_mu : learn the statistics mu by conjugate Normal updates of per-particle
        sufficient statistics (prior with the mean and variance of ``U(mu_min, mu_max)``,
        see :mod:`formtwin.tracker.ssm`); ``mu`` is then ignored. Default off (the paper's
        filter).
    mu_prior : the prior of a learned mu, see :data:`MU_PRIORS`: ``"uniform"`` (default)
        ``U(mu_min, mu_max)``, the posterior given a state path a Normal truncated to the
        range (mu is drawn from it for each step); ``"normal"`` the Normal with the mean and
        variance of that uniform, integrated out of the step.
    n_mc : Monte-Carlo curves for the measurement model's ``K_MC`` (paper: 10^4).
    nu : Student-t degrees of freedom of the likelihood; ``inf`` is the paper's Gaussian,
        a finite value the heavy-tailed robust option.
    likelihood : str
        ``"adaptive"`` (default): covariance ``fraction^2 K_MC + kappa K_res +
        sigma_n^2 I`` with ``K_res`` the metamodel's held-out residual covariance and
        ``kappa`` averaged over :data:`SHARES` by the running evidence (``error_share``
        fixes it), and the predicted angles' variance adds the metamodel's angle error
        times the posterior probability of ``kappa > 0``; ``"calibrated"``: ``kappa = 1``;
        ``"discrepancy"``: also a shared part of the error learned; ``"paper"``: eq. 12,
        ``fraction^2 K_MC + sigma_n^2 I``. See :data:`LIKELIHOODS` and
        :mod:`formtwin.tracker.discrepancy`.
    fraction : std of the measurement uncertainty as a fraction of the Monte-Carlo std
        (paper: 1/2, i.e. ``K_MC / 4``).
    sensor_noise : std of the force sensor, N (a floor of 1 % of the largest principal std
        applies anyway, see :mod:`formtwin.measurement`).
    error_share : the share ``kappa`` of ``K_res`` that the adaptive and discrepancy
        likelihoods add to the paper's covariance, independent from product to product
        (for the discrepancy likelihood the rest, ``(1 - kappa) K_res``, is the prior of
        the shared discrepancy); ``None`` (default): learned over :data:`SHARES` by the
        evidence.
    intervals : the reported std of the estimates and angles, see :data:`INTERVALS`:
        ``"calibrated"`` adds to the particles' weighted std, in quadrature, floors learned
        offline on physics runs of the bundled metamodel (not the study's data:
        :mod:`formtwin.study.calibrate`; none for another metamodel);
        ``"calibrated_fit"`` (default) scales their squares by the running fit distance in
        excess of its mean on the metamodel's own curves (learned in the same calibration:
        :class:`~formtwin.tracker.intervals.Floors`), so they shrink where the metamodel
        explains the curves;
        ``"cloud"`` the particles' weighted std alone (eq. 14; no assumed-mu term);
        ``"cloud_mu"`` that plus the assumed mu's term (see ``mu_known``; the
        calibration's runs); ``"sandwich"`` adds the part of
        the error that a persistent metamodel error puts in the estimate
        (:mod:`formtwin.tracker.sandwich`); ``"gated"`` that times ``P(kappa > 0)``. The
        particles, weights, means, ESS and evidence are the same for all six.
    discrepancy_memory : with ``likelihood="discrepancy"``, the memory (products) of its
        statistics: ``1 - 1/memory`` is the forgetting factor; ``inf``: none.
    learn_scale : learn a factor ``c`` on the likelihood's covariance online: a posterior
        over :data:`SCALES`, updated by each product's innovation likelihood under each
        ``c`` (see :meth:`~formtwin.tracker.BendingSSM.update_scale`); the particles are
        weighted by the posterior mixture. Gaussian likelihood only. Off: on the physics
        data it drives ``c`` to the smallest value and hurts (docs/explanation/likelihood.md).
    learn_residuals : with the adaptive likelihood, learn the second moment ``M`` of the
        line's own residuals online and use ``Sigma + M`` as the likelihood's base
        covariance (:mod:`formtwin.tracker.learned`, docs/explanation/likelihood.md).
    sensors : names of the spec's ``[[sensor]]`` entries this run fuses besides the curve
        (:meth:`~formtwin.tracker.Tracker.fuse`); empty (default): the curve alone.
    sensor_lag : how many products back a value may arrive, ``L`` (the particles keep
        their last ``L`` states); ``None`` (default): the largest delay of ``sensors``.
    camera_discrepancy : with a fused camera (a sensor of the final angle), learn the model's
        final-angle discrepancy from the camera's values (:mod:`formtwin.tracker.
        angle_discrepancy`: bias and slope, weighed by their evidence against the model as
        it is), used in the camera's likelihood and the predicted final angle; False: the
        model's angle as it is.
    """

    n_particles: int = field(default=500, metadata=_help("particles N", "--particles"))
    alpha: float = field(default=0.01, metadata=_help("parameter jitter (eq. 10)"))
    estimate_deviation: bool = field(default=True, metadata=_help(
        "estimate the deviation parameters theta_d (else g = identity)", "--deviation"))
    mu: tuple[float, ...] | None = field(default=None, metadata=_help(
        "assumed state means, one comma-separated value per state variable of the spec, "
        "internal units (default: mid-range)"))
    sigma: tuple[float, ...] | None = field(default=None, metadata=_help(
        "state std, one value per state variable (default: the spec's)"))
    rho: tuple[float, ...] | None = field(default=None, metadata=_help(
        "state autocorrelation, one value per state variable (default: the spec's)"))
    mu_known: bool = field(default=False, metadata=_help(
        "mu is the line's true state mean (else the intervals add the error of assuming "
        "it, the line's mu anywhere in the spec's range)"))
    resampling: Any = field(default="systematic", metadata=_help(
        "resampling scheme (systematic, multinomial, stratified, residual)"))
    seed: int = field(default=0, metadata=_help("tracker seed"))
    filter: str = field(default="sir", metadata=_help("particle filter (formtwin.filters)"))
    ess_threshold: float = field(default=1.0, metadata=_help(
        "resample when ESS < this fraction of N (1: every step)"))
    compare: str = field(default="measurement", metadata=_help(
        "compare curves in model space (eq. 12) or measurement space"))
    angle_particles: int | None = field(default=None, metadata=_help(
        "predict angles from this many resampled particles (>= N: all)"))
    learn_mu: bool = field(default=False, metadata=_help(
        "learn the statistics mu as hyperparameters"))
    mu_prior: str = field(default="uniform", metadata=_help(
        "prior of a learned mu: uniform (U(mu_min, mu_max), truncated posterior) or normal"))
    n_mc: int = field(default=10_000, metadata=_help("Monte-Carlo curves for K_MC"))
    nu: float = field(default=math.inf, metadata=_help(
        "Student-t degrees of freedom of the likelihood (inf: Gaussian)", "--robust-nu"))
    likelihood: str = field(default="adaptive", metadata=_help(
        "likelihood: adaptive (K_MC fraction + a share of the metamodel's residual "
        "covariance weighted by the evidence), calibrated (the whole K_res), discrepancy "
        "(part of K_res learned as a shared error) or paper"))
    fraction: float = field(default=0.5, metadata=_help(
        "measurement std as a fraction of the Monte-Carlo std (paper: 0.5)"))
    sensor_noise: float = field(default=0.0, metadata=_help(
        "force sensor std, N (track and serve: default the spec's [curve] noise_sd)"))
    learn_scale: bool = field(default=False, metadata=_help(
        "learn a factor on the likelihood covariance online"))
    error_share: float | None = field(default=None, metadata=_help(
        "share of K_res in the adaptive/discrepancy likelihood (default: learned)"))
    discrepancy_memory: float = field(default=math.inf, metadata=_help(
        "memory of the learned discrepancy, products (inf: no forgetting)"))
    learn_residuals: bool = field(default=False, metadata=_help(
        "learn the line's residual moment online (adaptive likelihood)"))
    sensors: tuple[str, ...] = field(default=(), metadata=_help(
        "sensors fused besides the curve, comma-separated names of the spec's [[sensor]] "
        "entries (e.g. gauge,camera)"))
    sensor_lag: int | None = field(default=None, metadata=_help(
        "products back a sensor value may arrive (default: the largest delay)"))
    camera_discrepancy: bool = field(default=True, metadata=_help(
        "learn the final angle's discrepancy (bias, slope) from a fused camera"))
    intervals: str = field(default="calibrated_fit", metadata=_help(
        "reported std: cloud (the particles'), cloud_mu (+ the assumed mu's term, which "
        "all but cloud add), calibrated (+ floors learned offline on "
        "physics runs), calibrated_fit (those scaled by the excess fit distance), "
        "sandwich (+ the persistent metamodel error's part) or gated (that "
        "times P(kappa > 0))"))

    def __post_init__(self) -> None:
        if self.angle_particles is not None and self.angle_particles < 1:
            raise ValueError(f"angle_particles = {self.angle_particles}, expected >= 1 or None")
        if self.compare not in COMPARE:
            raise ValueError(f"compare = {self.compare!r}; known: {', '.join(COMPARE)}")
        if self.likelihood not in LIKELIHOODS:
            raise ValueError(f"likelihood = {self.likelihood!r}; known: "
                             f"{', '.join(LIKELIHOODS)}")
        if self.intervals not in INTERVALS:
            raise ValueError(f"intervals = {self.intervals!r}; known: {', '.join(INTERVALS)}")
        if self.mu_prior not in MU_PRIORS:
            raise ValueError(f"mu_prior = {self.mu_prior!r}; known: {', '.join(MU_PRIORS)}")
        if not self.fraction > 0:
            raise ValueError(f"fraction = {self.fraction}, expected > 0")
        if not self.sensor_noise >= 0:
            raise ValueError(f"sensor_noise = {self.sensor_noise}, expected >= 0")
        for name in ("mu", "sigma", "rho"):
            v = getattr(self, name)
            if v is not None:  # store as a tuple of floats so the config stays hashable/JSON
                object.__setattr__(self, name, tuple(float(a) for a in np.ravel(v)))
        for name in ("n_particles", "n_mc"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} = {getattr(self, name)}, expected >= 1")
        if self.alpha < 0:
            raise ValueError(f"alpha = {self.alpha}, expected >= 0")
        if not self.nu > 0:
            raise ValueError(f"nu = {self.nu}, expected > 0 (inf for Gaussian)")
        if self.learn_scale and not math.isinf(self.nu):
            raise ValueError("learn_scale needs the Gaussian likelihood (nu = inf)")
        if self.likelihood in ("adaptive", "discrepancy") and self.learn_scale:
            raise ValueError(f"the {self.likelihood} likelihood learns its own scale "
                             "(error_share): learn_scale is for calibrated or paper")
        if self.likelihood == "discrepancy" and self.filter == "move":
            raise ValueError("the move filter needs a likelihood without learned statistics: "
                             "not discrepancy")
        if self.filter in ("guided", "guided_lin") and (
                self.learn_mu or self.likelihood == "discrepancy"):
            raise ValueError("the guided filter needs a fixed mu and a likelihood without "
                             "learned statistics: not learn_mu, not discrepancy")
        if self.likelihood == "discrepancy" and not math.isinf(self.nu):
            raise ValueError("the discrepancy likelihood is Gaussian (nu = inf)")
        if self.error_share is not None and not 0.0 <= self.error_share <= 1.0:
            raise ValueError(f"error_share = {self.error_share}, expected in [0, 1]")
        if self.learn_residuals and self.likelihood != "adaptive":
            raise ValueError(f"learn_residuals needs the adaptive likelihood, not "
                             f"{self.likelihood!r}")
        names = self.sensors.split(",") if isinstance(self.sensors, str) else self.sensors
        object.__setattr__(self, "sensors", tuple(str(v).strip() for v in names
                                                  if str(v).strip()))
        if len(set(self.sensors)) != len(self.sensors):
            raise ValueError(f"sensors = {self.sensors}: a name given twice")
        if self.sensor_lag is not None and not (isinstance(self.sensor_lag, int)
                                                and self.sensor_lag >= 0):
            raise ValueError(f"sensor_lag = {self.sensor_lag!r}, expected a whole number "
                             ">= 0 or None")
        if not isinstance(self.camera_discrepancy, bool):
            raise ValueError(f"camera_discrepancy = {self.camera_discrepancy!r}, expected "
                             "true or false")
        if not self.discrepancy_memory >= 1:
            raise ValueError(f"discrepancy_memory = {self.discrepancy_memory}, expected >= 1 "
                             "(inf: no forgetting)")

    def to_dict(self) -> dict[str, Any]:
        """The settings as JSON-ready values (``nu = inf`` as ``None``)."""
        if not isinstance(self.resampling, str):
            raise ValueError("a config with a callable resampling scheme cannot be saved")
        d = dataclasses.asdict(self)
        for key in ("nu", "discrepancy_memory"):  # JSON has no infinity
            d[key] = None if math.isinf(d[key]) else d[key]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrackerConfig:
        """Inverse of :meth:`to_dict` (missing keys take their defaults; an older version's
        ``sensor_trim``, the weight of an EWMA of the camera's residuals, becomes
        ``camera_discrepancy = sensor_trim > 0``)."""
        d = dict(d)
        if "sensor_trim" in d:
            d.setdefault("camera_discrepancy", float(d.pop("sensor_trim")) > 0)
        for key in ("nu", "discrepancy_memory"):
            if key in d:
                d[key] = math.inf if d[key] is None else float(d[key])
        clean: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                 for k, v in d.items()}
        return cls(**clean)

    def to_json(self) -> str:
        """:meth:`to_dict` as JSON text."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> TrackerConfig:
        """Inverse of :meth:`to_json`."""
        return cls.from_dict(json.loads(text))
