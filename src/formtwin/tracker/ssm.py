"""The augmented state-space model ``[x, theta, theta_d]`` that the generic filters see.

:class:`BendingSSM` is the model, apart from the algorithm (as in ``particles``):

* initial law: ``x ~ N(mu, sigma^2)`` per variable (its stationary law under eq. 4-5,
  reflected into the design box), ``theta`` and ``theta_d`` uniform in their bounds;
* transition: ``x`` by the AR(1) evolution (eq. 4-5), ``theta`` and ``theta_d`` by the
  jitter of eq. 10 (``alpha`` times the range), all reflected into their bounds;
* likelihood (eq. 12): ``g^-1(z, theta_d)`` against the model curve ``z~(x, theta)`` under
  the :class:`~formtwin.measurement.MeasurementModel`;
* :meth:`BendingSSM.simulate`: a production run as the model assumes it (constant theta and
  theta_d, curves ``g(z~(x, theta), theta_d)``).

With ``learn_mu=True`` (the paper's Discussion: the statistics as hyperparameters
estimated with the rest) mu is learned by conjugate updates (Storvik 2002; particle
learning, Carvalho et al. 2010): given a particle's state path, eq. 4 is linear-Gaussian in
mu, so a Normal prior ``mu ~ N(m0, P0)`` (``m0 = (mu_min + mu_max)/2``,
``P0 = (mu_max - mu_min)^2 / 12``: the mean and variance of the paper's ``U(mu_min,
mu_max)``) stays Normal. Each particle carries its sufficient statistics ``(m, P)`` in 14
more columns (``[x, theta, theta_d, m, P]``, (N, 32)); ``x`` is drawn from the predictive
with mu integrated out (:func:`~formtwin.evolution.mu_predictive`), then ``(m, P)`` take
the exact update of that step (:func:`~formtwin.evolution.mu_update`). No jitter: nothing
is forgotten, and the posterior of mu is the mixture of the particles' Normals.

With ``learn_scale=True`` the likelihood is a mixture over factors ``c`` on its covariance
(:data:`~formtwin.tracker.config.SCALES`) weighted by their posterior, which
:meth:`BendingSSM.update_scale` moves after each product by the evidence under each ``c``.

With ``likelihood="discrepancy"`` the metamodel's error is a discrepancy shared by the
products, integrated out per particle by conjugate updates
(:mod:`formtwin.tracker.discrepancy`); its statistics are the last ``n_t + 1`` columns.

With ``estimate_deviation=False`` (paper series 1, 2, 4, 5) ``theta_d`` is fixed at 0
(``g`` is the identity) and never jittered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from formtwin.deviation import DeviationModel
from formtwin.evolution import (
    evolve,
    into_box,
    jitter,
    mu_predictive,
    mu_update,
    reflect,
    stationary,
    truncated_moments,
    truncated_normal,
)
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.production import ProductionRun, draw_production_run
from formtwin.spec import ProcessSpec
from formtwin.tracker._kernels import drift
from formtwin.tracker.ahead import conditioned
from formtwin.tracker.config import SCALES, TrackerConfig
from formtwin.tracker.discrepancy import Discrepancy, angle_residual_variance
from formtwin.tracker.fusion import LagColumns
from formtwin.tracker.guide import GuidedProposal
from formtwin.tracker.learned import LearnedResiduals, ResidualMoment, make_discrepancy
from formtwin.tracker.moves import MoveHooks

FloatArray = NDArray[np.float64]

#: particles per block when evaluating the model: bounds peak memory at large N and keeps the
#: RBF blocks in cache (N = 1e4, 7024-point metamodel: 0.7 s a step with 512, 1.9 s with 8192)
CHUNK = 512


@dataclass(frozen=True)
class BendingSSM(MoveHooks, GuidedProposal, LearnedResiduals, LagColumns):
    """The augmented state-space model ``[x, theta, theta_d]`` for the generic filters.

    Parameters
    ----------
    model : the process model (metamodel) giving curves and angles.
    measurement : the likelihood of a curve.
    config : the tracker settings (statistics, jitter, deviation on/off, learned mu).
    """

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
    _sizes: tuple[int, int, int] = field(init=False, repr=False)
    # the transition x -> a + b x + s v, v ~ N(0, 1), of the columns that vary (not
    # learning mu): eq. 4-5 for x (a = (1 - rho) mu, b = rho, s = sqrt(1 - rho^2) sigma),
    # the jitter of eq. 10 for theta (and theta_d) (a = 0, b = 1, s = alpha (hi - lo))
    _drift: tuple[FloatArray, FloatArray, FloatArray] = field(init=False, repr=False)
    #: state values known before this step's curve, column -> (value, noise variance): the
    #: transition of their columns conditioned on them (:mod:`formtwin.tracker.ahead`)
    ahead: dict[int, tuple[float, float]] = field(init=False, repr=False, default_factory=dict)
    #: (2,) deg^2 added to the predicted angles' variance: the metamodel's held-out angle
    #: error (calibrated likelihood), zeros for the paper's
    angle_error_var: FloatArray = field(init=False, repr=False)
    # residuals (N, n_t) of the last loglik call (see last_residuals)
    _last: dict[str, FloatArray] = field(init=False, repr=False, default_factory=dict)
    # log-posterior of the likelihood scale (learn_scale)
    _scale: dict[str, FloatArray] = field(init=False, repr=False, default_factory=dict)
    #: the learned discrepancy (``likelihood="discrepancy"``), else None
    discrepancy: Discrepancy | None = field(init=False, repr=False, default=None)
    #: the line's residual moment (``learn_residuals``), else None
    learned: ResidualMoment | None = field(init=False, repr=False, default=None)
    _n_bounded: int = field(init=False, repr=False, default=0)  # [0, this): finite bounds
    # the discrepancy's statistics are the columns [_disc, d)
    _disc: int = field(init=False, repr=False, default=0)
    # filter "guided_lin": each particle's model curve at its last product, columns [_curve, +n_t)
    _curve: int = field(init=False, repr=False, default=0)

    def __post_init__(self) -> None:
        spec = self.model.spec
        object.__setattr__(self, "spec", spec)
        # (n_x, n_in, n_aug): the spec builds its groups on every access
        object.__setattr__(self, "_sizes", (len(spec.state), spec.n_inputs,
                                            len(spec.augmented)))
        # the spec builds these arrays on every access (~20 us): keep them
        lo, hi = spec.augmented.lo, spec.augmented.hi
        object.__setattr__(self, "_n_bounded", lo.size)  # [x, theta, theta_d]
        if self.config.learn_mu:  # m and P of mu: no bounds (m may leave the range)
            lo = np.r_[lo, np.full(2 * len(spec.state), -np.inf)]
            hi = np.r_[hi, np.full(2 * len(spec.state), np.inf)]
        lo, hi = self.add_lag_columns(lo, hi)  # late sensor values: [lag_start, _disc)
        object.__setattr__(self, "_disc", lo.size)
        if self.config.likelihood in ("adaptive", "discrepancy"):
            disc = make_discrepancy(self.model, self.measurement.covariance(), self.config)
            object.__setattr__(self, "discrepancy", disc)
            if self.config.learn_residuals:
                object.__setattr__(self, "learned", ResidualMoment(spec.n_t))
            if disc.shared:  # the statistics of the shared part: unbounded columns
                lo = np.r_[lo, np.full(disc.width, -np.inf)]
                hi = np.r_[hi, np.full(disc.width, np.inf)]
        if self.config.filter == "guided_lin":  # the parents' curves: unbounded columns
            object.__setattr__(self, "_curve", lo.size)
            lo = np.r_[lo, np.full(spec.n_t, -np.inf)]
            hi = np.r_[hi, np.full(spec.n_t, np.inf)]
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
        # the transition a + b x + s v per column (the field _drift)
        width = (hi - lo)[self.n_x:self.n_aug if c.estimate_deviation else self.n_in]
        rho = self._rho
        object.__setattr__(self, "_drift", (
            np.r_[(1.0 - rho) * self._mu, np.zeros(width.size)], np.r_[rho, np.ones(width.size)],
            np.r_[np.sqrt(1.0 - rho**2) * self._sigma, c.alpha * width]))
        var = angle_residual_variance(self.model) if c.likelihood != "paper" else None
        object.__setattr__(self, "angle_error_var",
                           np.zeros(spec.n_outputs) if var is None else var)
        if self.measurement.n_t != spec.n_t:
            raise ValueError(f"measurement model has {self.measurement.n_t} samples, "
                             f"the spec's curves {spec.n_t}")

    @property
    def mu_prior(self) -> tuple[FloatArray, FloatArray]:
        """Mean and variance (7,) of the Normal prior of a learned mu (``mu_prior =
        "normal"``): those of ``U(mu_min, mu_max)``."""
        st = self.model.spec.state
        return 0.5 * (st.mu_min + st.mu_max), (st.mu_max - st.mu_min) ** 2 / 12.0

    @property
    def mu_range(self) -> tuple[FloatArray, FloatArray] | None:
        """``(mu_min, mu_max)`` (7,) that truncate a learned mu (``mu_prior =
        "uniform"``), else ``None``."""
        if self.config.mu_prior != "uniform":
            return None
        st = self.model.spec.state
        return st.mu_min, st.mu_max

    def mu_moments(self, x: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std (7,) of a learned mu from particles ``x`` (N, 32) with
        weights ``w`` (N,): the moments of the mixture of the particles' posteriors
        (``N(m, P)``, truncated to ``[mu_min, mu_max]`` with the uniform prior)."""
        na, nx = self.n_aug, self.n_x
        m, P = x[:, na:na + nx], x[:, na + nx:na + 2 * nx]
        if self.mu_range is not None:
            m, P = truncated_moments(m, P, *self.mu_range)
        mean = w @ m
        var = w @ P + w @ (m - mean) ** 2
        return mean, np.sqrt(np.maximum(var, 0.0))

    @property
    def n_x(self) -> int:
        """Number of state variables (7)."""
        return self._sizes[0]

    @property
    def n_in(self) -> int:
        """Number of model inputs ``[x, theta]`` (10)."""
        return self._sizes[1]

    @property
    def n_aug(self) -> int:
        """Width of the augmented state ``[x, theta, theta_d]`` (18); the particles have
        ``2 n_x`` more columns (the statistics ``m, P`` of their mu) when learning mu."""
        return self._sizes[2]

    def sample_initial(self, n: int, rng: np.random.Generator) -> FloatArray:
        """``n`` particles (n, 18) or (n, 32) from the initial law."""
        lo, hi, nx, na = self._lo, self._hi, self.n_x, self.n_aug
        out = np.empty((n, lo.size))
        out[:, nx:na] = lo[nx:na] + (hi[nx:na] - lo[nx:na]) * rng.random((n, na - nx))
        if self.config.learn_mu and self.mu_range is not None:
            # mu ~ U(mu_min, mu_max), x_0 ~ N(mu, sigma^2); flat-prior statistics of x_0
            st = self.spec.state
            mu = st.mu_min + (st.mu_max - st.mu_min) * rng.random((n, nx))
            x0 = reflect(mu + self._sigma * rng.standard_normal((n, nx)), lo[:nx], hi[:nx])
            out[:, :nx] = x0
            out[:, na:na + nx] = x0
            out[:, na + nx:na + 2 * nx] = self._sigma**2
        elif self.config.learn_mu:  # x_0 ~ N(m0, P0 + sigma^2), then the update by x_0
            m0, P0 = self.mu_prior
            x0 = reflect(m0 + np.sqrt(P0 + self._sigma**2) * rng.standard_normal((n, nx)),
                         lo[:nx], hi[:nx])
            out[:, :nx] = x0
            P = np.broadcast_to(1.0 / (1.0 / P0 + 1.0 / self._sigma**2), (n, nx))
            out[:, na:na + nx] = P * (m0 / P0 + x0 / self._sigma**2)
            out[:, na + nx:na + 2 * nx] = P
        else:
            out[:, :nx] = stationary(n, self._mu, self._sigma, rng, lo[:nx], hi[:nx])
        if not self.config.estimate_deviation:
            out[:, self.n_in:self.n_aug] = 0.0
        if self.discrepancy is not None and self.discrepancy.shared:
            out[:, self._disc:] = 0.0  # its statistics: nothing seen yet
        if self._curve:
            out[:, self._curve:] = np.nan  # no curve evaluated yet
        out[:, self.lag_start:self._disc] = np.nan  # no ancestors yet
        return out

    def sample_transition(self, x: FloatArray, rng: np.random.Generator) -> FloatArray:
        """Particles (N, d) of the next product given those of this one (N, d)."""
        lo, hi, nx, na = self._lo, self._hi, self.n_x, self.n_aug
        stop = na if self.config.estimate_deviation else self.n_in
        out = np.empty_like(x)
        if self.config.learn_mu:  # a draw of the predictive with mu integrated out
            m, P = x[:, na:na + nx], x[:, na + nx:na + 2 * nx]
            rng_mu = self.mu_range
            if rng_mu is not None:  # mu from its truncated posterior, then eq. 4-5
                mu = truncated_normal(m, P, *rng_mu, rng)
                new = evolve(x[:, :nx], mu, self._sigma, self._rho, rng)
            else:  # the Normal predictive
                mean, var = mu_predictive(m, P, x[:, :nx], self._sigma, self._rho)
                new = mean + np.sqrt(var) * rng.standard_normal(mean.shape)
            out[:, :nx] = into_box(new, lo[:nx], hi[:nx])
            out[:, na:na + nx], out[:, na + nx:na + 2 * nx] = mu_update(
                m, P, x[:, :nx], out[:, :nx], self._sigma, self._rho)
            out[:, nx:stop] = jitter(x[:, nx:stop], lo[nx:stop], hi[nx:stop], rng,
                                     self.config.alpha)
        else:  # eq. 4-5 and the jitter of eq. 10 in one pass: x -> a + b x + s v (Numba;
            a, b, s = conditioned(self._drift, self.ahead)  # with the values ahead)
            left = drift(x, a, b, s, rng.standard_normal((x.shape[0], stop)), lo, hi, out)
            if left.any():  # the rows that left the box: reflected
                out[left, :stop] = reflect(out[left, :stop], lo[:stop], hi[:stop])
        out[:, stop:na] = x[:, stop:na]
        out[:, self._disc:] = x[:, self._disc:]
        self.shift_lags(x, out)
        return out

    def loglik(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Log-likelihood (N,) of the measured curve ``y`` (n_t,) N for particles ``x``.

        Also keeps the residuals ``obs - model`` (:meth:`last_residuals`).
        """
        # in blocks of particles: bounds the (N, n_t) temporaries of model and g^-1
        parts = [self._loglik(x[i: i + CHUNK], y) for i in range(0, x.shape[0], CHUNK)]
        if len(parts) == 1:
            self._last["r"], ll = parts[0][1], parts[0][0]
        else:
            self._last["r"] = np.concatenate([p[1] for p in parts])
            ll = np.concatenate([p[0] for p in parts])
        if self._curve:  # the particles' model curves, for the next guided proposal
            x[:, self._curve:] = y - self._last["r"] if self.config.compare == "measurement" \
                else np.nan
        disc = self.discrepancy
        if disc is not None:  # residuals net of each particle's shared discrepancy,
            stats = x[:, self._disc:] if disc.shared else None  # then this product
            w = np.exp(self.share_logpost)  # joins the statistics
            self._last["var"] = disc.predictive_var(stats, w)
            c = parts[0][2] if len(parts) == 1 else np.concatenate([p[2] for p in parts])
            assert c is not None
            self._last["c"] = c
            if stats is not None:
                b = disc.bias_whitened(stats, w)
                self._last["r"] = self._last["r"] - b @ disc.inverse.T
                self._last["c"] = c - b
                disc.update(stats, c)
            self._last["grid"] = ll  # (N, n_k): the mixture over the share's posterior
            ll = self.mix_share(ll)
        if not self.config.learn_scale:
            return ll
        self._last["scaled"] = ll  # (N, n_scales): the mixture over the scale posterior
        return self.mix_scale(ll)

    def residuals(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Residuals ``obs - model`` (N, n_t) N of curve ``y`` for particles ``x``, as the
        likelihood compares them (does not touch :meth:`last_residuals`)."""
        return self._compare(x, y)[2]

    def last_residuals(self) -> FloatArray:
        """Residuals (N, n_t) N of the curve of the last :meth:`loglik` call: ``obs - model``
        as the likelihood compares them (the goodness of fit, :mod:`formtwin.tracker.fit`);
        with the discrepancy likelihood, net of each particle's predicted discrepancy."""
        if "r" not in self._last:
            raise RuntimeError("no likelihood evaluated yet")
        return self._last["r"]

    def constrain(self, x: FloatArray) -> FloatArray:
        """Reflect particles (N, 18) or (N, 32) into their bounds (used by kernel moves);
        ``theta_d`` stays 0 when it is not estimated; the discrepancy's statistics are
        left as they are."""
        nb = self._n_bounded
        out = x.copy()
        out[:, :nb] = reflect(x[:, :nb], self._lo[:nb], self._hi[:nb])
        if not self.config.estimate_deviation:
            out[:, self.n_in:self.n_aug] = 0.0
        return out

    def predict_angles(self, x: FloatArray, u: float | FloatArray | None = None) -> FloatArray:
        """Angles (N, 2) of particles ``x`` (N, 18) or (N, 32) at the press settings ``u``
        (a scalar or (n_controls,) for all particles; None: nominal), in blocks."""
        return np.concatenate([self.model.predict_angles(x[i: i + CHUNK, : self.n_in], u)
                               for i in range(0, x.shape[0], CHUNK)])

    def final_angle(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """Final angle (N, n_u), degrees, of particles ``x`` (N, 18) or (N, 32) at each of
        the settings ``u`` (n_u,) of the one control (e.g. for choosing ``u``)."""
        uu = np.asarray(u, dtype=np.float64).reshape(-1)
        final = getattr(self.model, "final_angle", None)
        xin = x[:, : self.n_in]
        if final is not None:
            return np.concatenate([final(xin[i: i + CHUNK], uu)
                                   for i in range(0, x.shape[0], CHUNK)])
        rep = np.repeat(xin, uu.size, axis=0)
        a = self.model.predict_angles(rep, np.tile(uu, x.shape[0]))[:, -1]
        out: FloatArray = a.reshape(x.shape[0], uu.size)
        return out

    def simulate(self, n: int, rng: np.random.Generator) -> tuple[ProductionRun, FloatArray]:
        """A production run of ``n`` products as this model assumes it, and its curves.

        mu is the config's (drawn uniform in ``[mu_min, mu_max]`` when learning mu), theta
        and theta_d are drawn once and held constant (theta_d = 0 when the deviation is not
        estimated), the states follow eq. 4-5 with the config's sigma and rho; the curves
        (n, n_t) N are ``g(z~(x, theta), theta_d)``, without measurement noise.
        """
        run = draw_production_run(self.spec, n, rng,
                                  mu=None if self.config.learn_mu else self._mu,
                                  deviation=self.config.estimate_deviation,
                                  sigma=self._sigma, rho=self._rho)
        curves = self.model.predict_curves(run.inputs)
        if self.config.estimate_deviation:
            curves = self.deviation.apply(curves, np.tile(run.theta_d, (n, 1)))
        return run, curves

    def _loglik(self, x: FloatArray, y: FloatArray
                ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """Log-likelihoods (N,) of ``y`` for ``x``, the residuals (N, n_t) and, with the
        discrepancy likelihood, their whitened coordinates (N, n_t)."""
        curves, obs, r = self._compare(x, y)
        if self.discrepancy is not None:
            c = self.discrepancy.whiten(r)
            stats = x[:, self._disc:] if self.discrepancy.shared else None
            return self.discrepancy.loglik(r, stats, c), r, c
        ll = self.measurement.loglik_scaled(curves, obs, np.array(SCALES)) \
            if self.config.learn_scale else self.measurement.loglik(curves, obs)
        return ll, r, None

    def _compare(self, x: FloatArray, y: FloatArray
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """What the likelihood compares for particles ``x`` (N, d) and curve ``y`` (n_t,):
        the model side (N, n_t), the observed side ((n_t,) or (N, n_t)) and the residuals
        ``obs - model`` (N, n_t), N."""
        curves = self.model.predict_curves(x[:, : self.n_in])
        obs: FloatArray = y
        if self.config.estimate_deviation:
            td = x[:, self.n_in:self.n_aug]
            if self.config.compare == "measurement":
                curves = self.deviation.apply(curves, td)
            else:
                obs = self.deviation.invert(y, td)
        return curves, obs, np.atleast_2d(obs - curves)

