"""Measurement model: likelihood of a force curve given particles (paper eq. 6, 12).

Two likelihoods (``TrackerConfig.likelihood``):

* ``"paper"``: eq. 12 below, ``Sigma = fraction^2 K_MC + sigma_n^2 I``;
* ``"calibrated"`` (default): ``Sigma = fraction^2 K_MC + K_res + sigma_n^2 I``, where
  ``K_res`` is the second moment of the metamodel's k-fold held-out residuals (physics
  minus metamodel, :class:`formtwin.metamodel.ResidualModel`, stored with the metamodel):
  the filter is told how far the metamodel's curve may be from the true one. Both are
  built by :meth:`MeasurementModel.from_curves` (``extra_cov`` is ``K_res``) and stored in
  the same PPCA form; :meth:`MeasurementModel.covariance` gives the dense ``Sigma``.

The paper models the (deviation-corrected) measured curve as

    g^-1(z, theta_d) ~ N( z~(x, theta), fraction^2 K_MC ),    fraction = 1/2,   (eq. 12)

where ``K_MC`` is the covariance of ``10^4`` model curves with the state drawn per variable
from ``N(mu, sigma^2)`` (``rho = 0``) and the machine parameters uniform in their bounds.

Rank deficiency and the choice made here
----------------------------------------
Metamodel curves are combinations of a few POD modes, so ``K_MC`` has rank ``r <= n_modes``
(far below ``n_t = 101``) and ``N(., K_MC)`` has no density off that span. Curves from the
physics model, from the real press or passed through ``g^-1`` do leave the span. We add an
isotropic sensor noise to the paper's covariance and store it in probabilistic-PCA form
(Tipping & Bishop 1999)::

    Sigma = fraction^2 K_MC + sigma_n^2 I
          = U diag(lam + sigma_n^2) U^T + (tail + sigma_n^2) (I - U U^T)

* ``U`` (n_t, r), ``lam`` (r,): principal directions and variances of ``fraction^2 K_MC``
  with ``lam >= rel_tol * lam_max`` (numerically zero directions are dropped);
* ``tail``: the mean of the dropped eigenvalues (the PPCA estimate; ~0 for a metamodel);
* ``sigma_n^2 = max(sensor_noise^2, rel_floor * lam_max)``: the sensor-noise variance,
  floored relative to the largest variance, so that ``cond(Sigma) <= 1 + 1/rel_floor``
  whatever the data. With the defaults (``rel_floor = 1e-4``) ``sigma_n`` is 1 % of the
  largest principal std of ``w``; directions of ``K_MC`` weaker than that are not trusted
  more than the sensor, which keeps numerically tiny POD directions from making the
  likelihood spiky.

The stored ``lam`` and ``s2`` already include ``sigma_n^2``.
Then, for a difference ``d = obs - model`` (n_t,), with ``c = U^T d``::

    -2 log p = sum(c^2 / lam) + (|d|^2 - |c|^2) / s2 + sum(log lam) + (n_t - r) log s2
               + n_t log(2 pi)

which costs ``O(n_t r)`` per particle and needs no matrix inverse on the hot path. A
particle-independent part of the residual (metamodel curves all lie in the span) shifts all
log-weights equally and cancels in the normalisation.

Robust option: ``nu`` (degrees of freedom) replaces the Gaussian by a multivariate
Student-t with the same scale matrix, whose log-density falls only logarithmically with
the Mahalanobis distance, so one outlier curve cannot wipe out the particle cloud.

>>> import numpy as np
>>> from formtwin.defaults import analytic_model
>>> model = analytic_model(); spec = model.spec
>>> mm = MeasurementModel.from_monte_carlo(model, spec, n=2000,
...                                        rng=np.random.default_rng(0))
>>> curves = model.predict_curves(np.tile(spec.inputs.lo, (3, 1)))
>>> mm.loglik(curves, curves[0]).shape
(3,)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaln

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

_FORMAT = "formtwin.measurement/1"


@runtime_checkable
class ProcessModel(Protocol):
    """What the tracker needs of a process model (a metamodel or a fast stand-in).

    ``X`` holds model inputs, state then parameters (``spec.inputs``), internal units,
    optionally followed by the controls (``spec.run_inputs``); the stage-1 curve does not
    depend on the controls, the final angle does (``u`` None: the nominal setting).
    """

    @property
    def spec(self) -> ProcessSpec:
        """The process definition whose inputs the model takes."""
        ...

    def predict_curves(self, X: FloatArray) -> FloatArray:
        """Stage-1 force curves (N, n_t), N, for inputs ``X`` (N, 10) or (N, 11)."""
        ...

    def predict_angles(self, X: FloatArray, u: FloatArray | float | None = None) -> FloatArray:
        """Bend angles after stage 1 and 2 (N, 2), degrees, for inputs ``X`` (N, 10) at the
        controls ``u`` (scalar or (N,); None: nominal), or ``X`` (N, 11) with ``u`` None."""
        ...


def _check_cov(cov: FloatArray, n_t: int) -> FloatArray:
    """``cov`` as a symmetric (n_t, n_t) float array, or ``ValueError``."""
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (n_t, n_t):
        raise ValueError(f"extra_cov has shape {c.shape}, expected ({n_t}, {n_t})")
    if not np.all(np.isfinite(c)):
        raise ValueError("extra_cov has non-finite entries")
    scale = max(float(np.abs(c).max()), 1e-300)
    if float(np.abs(c - c.T).max()) > 1e-8 * scale:
        raise ValueError("extra_cov is not symmetric")
    return 0.5 * (c + c.T)


def monte_carlo_inputs(spec: ProcessSpec, n: int, rng: np.random.Generator,
                       mu: FloatArray | None = None) -> FloatArray:
    """Inputs (n, 10) for ``K_MC``: x ~ N(mu, sigma^2) per variable (rho = 0), reflected into
    the design box, theta ~ U(bounds). ``mu`` (7,) defaults to ``spec.state.mu_mid``."""
    from formtwin.evolution import stationary

    st, pa = spec.state, spec.params
    m = st.mu_mid if mu is None else np.asarray(mu, dtype=np.float64)
    if m.shape != (len(st),):
        raise ValueError(f"mu has shape {m.shape}, expected ({len(st)},)")
    x = stationary(n, m, st.sigma, rng, st.lo, st.hi)
    theta = pa.lo + (pa.hi - pa.lo) * rng.random((n, len(pa)))
    return np.hstack([x, theta])


@dataclass(frozen=True, eq=False)
class MeasurementModel:
    """Gaussian (or Student-t) likelihood of a curve with PPCA covariance (see module doc).

    Attributes
    ----------
    basis : (n_t, r) orthonormal principal directions of ``fraction^2 K_MC``.
    lam : (r,) variances along them, sensor noise included, N^2.
    s2 : variance off the span (tail + sensor noise), N^2.
    nu : Student-t degrees of freedom, or ``inf`` for the Gaussian of eq. 12.
    mean : (n_t,) mean Monte-Carlo curve, N (kept for diagnostics; not used by loglik).
    """

    basis: FloatArray
    lam: FloatArray
    s2: float
    nu: float = math.inf
    mean: FloatArray | None = None
    _white: FloatArray = field(init=False, repr=False)
    _lognorm: float = field(init=False, repr=False)
    _cov: dict[str, FloatArray] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        b, lam = np.asarray(self.basis, np.float64), np.asarray(self.lam, np.float64)
        if b.ndim != 2 or lam.shape != (b.shape[1],):
            raise ValueError(f"basis {b.shape} and lam {lam.shape} do not match")
        if not (np.all(lam > 0) and self.s2 > 0 and np.isfinite(self.s2)):
            raise ValueError("variances lam and s2 must be positive and finite")
        if not self.nu > 0:
            raise ValueError(f"nu = {self.nu}, expected > 0 (inf for Gaussian)")
        # whitened basis: c_w = d @ W gives c / sqrt(lam)
        object.__setattr__(self, "basis", b)
        object.__setattr__(self, "lam", lam)
        object.__setattr__(self, "_white", b / np.sqrt(lam))
        n_t, r = b.shape
        logdet = float(np.sum(np.log(lam)) + (n_t - r) * math.log(self.s2))
        object.__setattr__(self, "_lognorm", -0.5 * (logdet + n_t * math.log(2 * math.pi)))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_curves(cls, curves: FloatArray, fraction: float = 0.5, rel_tol: float = 1e-10,
                    rel_floor: float = 1e-4, sensor_noise: float = 0.0,
                    nu: float = math.inf,
                    extra_cov: FloatArray | None = None) -> MeasurementModel:
        """Build from a Monte-Carlo set of curves ``(n, n_t)`` (their covariance is K_MC).

        Parameters
        ----------
        fraction : the std of ``w`` as a fraction of the Monte-Carlo std (paper: 1/2).
        rel_tol : directions with variance below ``rel_tol * lam_max`` join the tail.
        rel_floor : ``sigma_n^2 >= rel_floor * lam_max`` (bounds the condition number).
        sensor_noise : std of the sensor, N: ``sigma_n >= sensor_noise``.
        nu : Student-t degrees of freedom; ``inf`` (default) is the paper's Gaussian.
        extra_cov : (n_t, n_t) symmetric positive semi-definite covariance added to
            ``fraction^2 K_MC`` before the decomposition, N^2: the metamodel's residual
            covariance ``K_res`` of the calibrated likelihood. ``None``: the paper's.
        """
        z = np.asarray(curves, dtype=np.float64)
        if z.ndim != 2 or z.shape[0] < 2:
            raise ValueError(f"curves have shape {z.shape}, expected (n >= 2, n_t)")
        if not np.all(np.isfinite(z)):
            bad = int(np.sum(~np.all(np.isfinite(z), axis=1)))
            log.warning("dropping %d Monte-Carlo curves with NaN/inf", bad)
            z = z[np.all(np.isfinite(z), axis=1)]
        if not 0 < fraction:
            raise ValueError(f"fraction = {fraction}, expected > 0")
        mean = z.mean(axis=0)
        n_t = z.shape[1]
        eig_all = np.zeros(n_t)
        if extra_cov is None:
            # eigenvalues of the sample covariance via SVD of the centred data
            _, sv, vt = np.linalg.svd(z - mean, full_matrices=False)
            eig = fraction**2 * sv**2 / (z.shape[0] - 1)
        else:
            extra = _check_cov(extra_cov, n_t)
            d = z - mean
            eig, vecs = np.linalg.eigh(fraction**2 * (d.T @ d) / (z.shape[0] - 1) + extra)
            eig, vt = np.maximum(eig[::-1], 0.0), vecs[:, ::-1].T
        eig_all[: eig.size] = eig
        lam_max = float(eig_all[0])
        if lam_max <= 0:
            raise ValueError("the Monte-Carlo curves do not vary: K_MC is zero")
        r = int(np.sum(eig_all >= rel_tol * lam_max))
        tail = float(eig_all[r:].mean()) if r < n_t else 0.0
        noise = max(sensor_noise**2, rel_floor * lam_max)
        log.info("measurement model: rank %d of %d, lam_max %.3g, tail %.3g, sigma_n %.3g",
                 r, n_t, lam_max, tail, math.sqrt(noise))
        return cls(basis=vt[:r].T.copy(), lam=eig_all[:r] + noise, s2=tail + noise, nu=nu,
                   mean=mean)

    @classmethod
    def from_monte_carlo(cls, model: ProcessModel, spec: ProcessSpec | None = None,
                         mu: FloatArray | None = None, n: int = 10_000,
                         fraction: float = 0.5, rng: np.random.Generator | None = None,
                         **kwargs: Any) -> MeasurementModel:
        """``K_MC`` from ``n`` model curves (paper "Simulation runs"), then :meth:`from_curves`.

        Parameters
        ----------
        model : the process model (metamodel) whose curves define ``K_MC``.
        spec : process spec; defaults to ``model.spec``.
        mu : (7,) assumed state means; default ``spec.state.mu_mid`` (series 4, 6).
        n : number of Monte-Carlo curves (paper: 10^4).
        fraction : std of ``w`` relative to the Monte-Carlo std (paper: 1/2).
        rng : random source; default ``numpy.random.default_rng(0)``.
        **kwargs : ``rel_tol``, ``rel_floor``, ``sensor_noise``, ``nu``, ``extra_cov`` of
            :meth:`from_curves`.
        """
        spec = model.spec if spec is None else spec
        rng = np.random.default_rng(0) if rng is None else rng
        X = monte_carlo_inputs(spec, n, rng, mu)
        return cls.from_curves(model.predict_curves(X), fraction=fraction, **kwargs)

    # ------------------------------------------------------------------ evaluation
    @property
    def n_t(self) -> int:
        """Samples per curve ``n_t``."""
        return int(self.basis.shape[0])

    @property
    def rank(self) -> int:
        """Number of principal directions ``r``."""
        return int(self.basis.shape[1])

    def covariance(self) -> FloatArray:
        """The likelihood's covariance ``Sigma`` (n_t, n_t), N^2 (the scale matrix for
        the Student-t): ``U diag(lam) U^T + s2 (I - U U^T)``; sensor noise and, for the
        calibrated likelihood, the residual covariance ``K_res`` included. Computed once
        and read-only."""
        if "sigma" not in self._cov:  # once: the goodness of fit asks every product
            u = self.basis
            self._cov["sigma"] = (u * (self.lam - self.s2)) @ u.T + self.s2 * np.eye(self.n_t)
            self._cov["sigma"].flags.writeable = False
        return self._cov["sigma"]

    def mahalanobis2(self, curves_model: FloatArray, curves_obs: FloatArray) -> FloatArray:
        """Squared Mahalanobis distance ``d^T Sigma^-1 d`` (N,) of ``obs - model``."""
        obs = np.asarray(curves_obs, dtype=np.float64)
        mod = np.asarray(curves_model, dtype=np.float64)
        for what, a in (("observed", obs), ("model", mod)):
            if a.shape[-1] != self.n_t or a.ndim > 2:
                raise ValueError(f"{what} curves have shape {a.shape}, expected "
                                 f"(N, {self.n_t}) or ({self.n_t},)")
        d = np.atleast_2d(obs - mod)
        cw = d @ self._white
        c = cw * np.sqrt(self.lam)
        resid2 = np.einsum("ij,ij->i", d, d) - np.einsum("ij,ij->i", c, c)
        out: FloatArray = np.einsum("ij,ij->i", cw, cw) + np.maximum(resid2, 0.0) / self.s2
        return out

    def loglik(self, curves_model: FloatArray, curves_obs: FloatArray) -> FloatArray:
        """Log-likelihood (N,) of observed curves given model curves.

        Parameters
        ----------
        curves_model : (N, n_t) model curves ``z~(x, theta)`` of the particles, N.
        curves_obs : (N, n_t) or (n_t,) observed curves (already through ``g^-1``), N.

        Returns
        -------
        (N,) log densities; NaN in a row gives ``-inf`` for that row.
        """
        m2 = self.mahalanobis2(curves_model, curves_obs)
        if math.isinf(self.nu):
            out: FloatArray = self._lognorm - 0.5 * m2
        else:
            nu, p = self.nu, self.n_t
            const = (float(gammaln(0.5 * (nu + p)) - gammaln(0.5 * nu))
                     - 0.5 * p * math.log(0.5 * nu))
            out = self._lognorm + const - 0.5 * (nu + p) * np.log1p(m2 / nu)
        return np.where(np.isnan(out), -np.inf, out)

    def loglik_scaled(self, curves_model: FloatArray, curves_obs: FloatArray,
                      scales: FloatArray) -> FloatArray:
        """Gaussian log-likelihoods (N, n_c) under ``c Sigma`` for each scale ``c`` (n_c,).

        ``log N(d; 0, c Sigma) = log N(d; 0, Sigma) - n_t/2 log c - (1/c - 1) m2 / 2``
        with ``m2`` the squared Mahalanobis distance under ``Sigma``.
        """
        if not math.isinf(self.nu):
            raise ValueError("a learned likelihood scale needs the Gaussian (nu = inf)")
        c = np.asarray(scales, dtype=np.float64)
        m2 = self.mahalanobis2(curves_model, curves_obs)[:, None]
        out: FloatArray = (self._lognorm - 0.5 * self.n_t * np.log(c)
                           - 0.5 * m2 / c)
        return np.where(np.isnan(out), -np.inf, out)

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write an ``.npz`` (no pickle) and return its path."""
        p = Path(path)
        mean = np.full(self.n_t, np.nan) if self.mean is None else self.mean
        np.savez(p, format=np.array(_FORMAT), basis=self.basis, lam=self.lam,
                 s2=np.array(self.s2), nu=np.array(self.nu), mean=mean)
        return p if p.suffix == ".npz" else p.with_name(p.name + ".npz")

    @classmethod
    def load(cls, path: str | Path) -> MeasurementModel:
        """Read a file written by :meth:`save`."""
        with np.load(Path(path), allow_pickle=False) as f:
            fmt = str(f["format"]) if "format" in f else ""
            if fmt != _FORMAT:
                raise ValueError(f"{path}: not a measurement-model file (format {fmt!r})")
            mean = f["mean"]
            return cls(basis=f["basis"], lam=f["lam"], s2=float(f["s2"]), nu=float(f["nu"]),
                       mean=None if np.all(np.isnan(mean)) else mean)
