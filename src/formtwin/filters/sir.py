"""The Sampling Importance Resampling filter (paper Algorithm 1), generic over the model.

The filter knows nothing of bending: it takes a :class:`StateSpaceModel` (math-named hooks
in the style of N. Chopin's ``particles``: initial law, transition, log-likelihood) and
steps once per observation. Weights are kept as log-weights and normalised with
log-sum-exp, so likelihoods far below ``1e-308`` cause no underflow.

One step (:meth:`SIR.step`)::

    x^k  ~ p(x_i | x_{i-1}^k)                     importance sampling (the transition)
    l^k  = log p(z_i | x^k)                      measurement
    log w^k = log w_{i-1}^k + l^k - logsumexp(.)  normalisation
    ESS = 1 / sum (w^k)^2
    resample (if ESS < ess_threshold N; the default 1.0 means every step, as Algorithm 1)

The returned :class:`Step` holds the weighted particles *before* resampling, which give
the lower-variance estimates of eq. 13-14.

Weight collapse
---------------
If no particle has a finite log-likelihood (all ``-inf`` or NaN: a curve the model cannot
explain at all, a model returning NaN), there is no posterior to normalise. The step then
keeps the *predicted* particles with their previous weights, i.e. it treats the observation
as uninformative (the posterior falls back to the predictive ``p(x_i | Z_{i-1})``), flags
``collapsed=True`` and reports ``loglik = -inf``. No NaN ever enters the weights. Single
particles with NaN or ``+inf`` log-likelihood get weight zero.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from formtwin.filters.resampling import Resampler, get_resampler

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)


class StateSpaceModel(Protocol):
    """A state-space model as the filters see it; states are ``(N, d)`` float arrays."""

    def sample_initial(self, n: int, rng: np.random.Generator) -> FloatArray:
        """``n`` draws ``(n, d)`` from the initial law p(x_0)."""
        ...

    def sample_transition(self, x: FloatArray, rng: np.random.Generator) -> FloatArray:
        """One draw per row ``(N, d)`` from p(x_i | x_{i-1} = x)."""
        ...

    def loglik(self, x: FloatArray, y: Any) -> FloatArray:
        """``log p(y | x)`` for every row of ``x``, shape ``(N,)``."""
        ...


@dataclass(frozen=True)
class Step:
    """The outcome of one filter step.

    Attributes
    ----------
    x : (N, d) particles after the transition, before resampling.
    w : (N,) their normalised weights (sum 1).
    ess : effective sample size ``1 / sum w^2`` in [1, N].
    loglik : log marginal-likelihood increment ``log p(y_i | y_{1:i-1})`` (``-inf`` if
        collapsed).
    collapsed : no particle explained the observation (see module doc).
    resampled : whether the particle set was resampled at the end of the step.
    """

    x: FloatArray
    w: FloatArray
    ess: float
    loglik: float
    collapsed: bool
    resampled: bool

    def mean(self) -> FloatArray:
        """Weighted mean (d,) (eq. 13)."""
        out: FloatArray = self.w @ self.x
        return out

    def std(self, mean: FloatArray | None = None) -> FloatArray:
        """Weighted standard deviation (d,) (eq. 14); ``mean`` (d,) :meth:`mean` when the
        caller has it (None: computed here)."""
        dev = self.x - (self.mean() if mean is None else mean)
        out: FloatArray = np.sqrt(np.maximum(self.w @ (dev * dev), 0.0))
        return out


def logsumexp(a: FloatArray, axis: int | None = None) -> Any:
    """``log sum exp(a)`` over ``axis`` (all entries: a float), stable as scipy's (rows of
    ``-inf`` give ``-inf``) without its per-call overhead (~0.1 ms, 3 calls per product).

    >>> import numpy as np
    >>> logsumexp(np.array([[0.0, -np.inf], [-np.inf, -np.inf]]), axis=1).tolist()
    [0.0, -inf]
    """
    if axis == 0 and np.ndim(a) == 2 and np.shape(a)[0] > 0:
        return _logsumexp_columns(np.asarray(a))
    top = np.max(a, axis=axis, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(np.exp(a - top), axis=axis, keepdims=True)) + top
    return float(out.reshape(())) if axis is None else np.squeeze(out, axis=axis)


def _logsumexp_columns(a: FloatArray) -> FloatArray:
    """:func:`logsumexp` over the rows of ``a`` (N, k), the same numbers: NumPy sums over
    the outer axis of a C array row after row, as ``cumsum`` along the rows of its
    transpose does (and max and exp do not depend on the layout); the transpose's long
    contiguous rows take half the time for a narrow ``a`` (the share's grid, k = 5)."""
    t = np.ascontiguousarray(a.T)
    top = np.max(t, axis=1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    total = np.cumsum(np.exp(t - top), axis=1)[:, -1:]
    with np.errstate(divide="ignore"):
        out: FloatArray = (np.log(total) + top)[:, 0]
    return out


def log_normalise(logw: FloatArray) -> tuple[FloatArray, float]:
    """Normalised log-weights and ``logsumexp(logw)``; ``logw`` must have a finite entry."""
    top = float(np.max(logw))
    lse = top + math.log(float(np.sum(np.exp(logw - top))))
    return logw - lse, lse


class SIR:
    """Sampling Importance Resampling (bootstrap) particle filter.

    Parameters
    ----------
    model : the state-space model.
    n_particles : N.
    rng : the random source (owned and advanced by the filter).
    resampling : a scheme name from :data:`~formtwin.filters.RESAMPLERS` or a callable.
    ess_threshold : resample when ``ESS < ess_threshold * N``; 1.0 (default) resamples
        every step as in Algorithm 1, 0.5 is the usual adaptive choice.

    Examples
    --------
    >>> import numpy as np
    >>> class RandomWalk:
    ...     def sample_initial(self, n, rng): return rng.standard_normal((n, 1))
    ...     def sample_transition(self, x, rng): return x + rng.standard_normal(x.shape)
    ...     def loglik(self, x, y): return -0.5 * (y - x[:, 0]) ** 2
    >>> f = SIR(RandomWalk(), 1000, np.random.default_rng(0))
    >>> s = f.step(1.0)
    >>> round(float(s.mean()[0]), 1), s.x.shape, f.t
    (0.7, (1000, 1), 1)
    """

    name = "sir"

    def __init__(self, model: StateSpaceModel, n_particles: int, rng: np.random.Generator,
                 resampling: str | Resampler = "systematic",
                 ess_threshold: float = 1.0) -> None:
        if n_particles < 1:
            raise ValueError(f"n_particles = {n_particles}, expected >= 1")
        self.model = model
        self.n = int(n_particles)
        self.rng = rng
        self.resample = get_resampler(resampling)
        self.ess_threshold = float(ess_threshold)
        self.t = 0
        self.x: FloatArray | None = None  # None until the first step draws p(x_0)
        #: after a step, the rows of its predicted particles the current ones copy
        #: (``x == step.x[ancestors]``); None when they were moved after resampling
        self.ancestors: NDArray[np.intp] | None = None
        self.logw: FloatArray = np.full(self.n, -math.log(self.n))

    def initialise(self) -> None:
        """Draw the initial particles from p(x_0) with equal weights."""
        self.x = np.asarray(self.model.sample_initial(self.n, self.rng), dtype=np.float64)
        self.logw = np.full(self.n, -math.log(self.n))

    def predict(self) -> FloatArray:
        """Propagate the particles one step (importance sampling); returns ``(N, d)``."""
        if self.x is None:
            self.initialise()
        assert self.x is not None
        return np.asarray(self.model.sample_transition(self.x, self.rng), dtype=np.float64)

    def step(self, y: Any) -> Step:
        """Assimilate observation ``y``: predict, weight, normalise, resample."""
        xp = self.predict()
        ll = np.asarray(self.model.loglik(xp, y), dtype=np.float64)
        return self.update(xp, ll)

    def update(self, xp: FloatArray, ll: FloatArray) -> Step:
        """Weight predicted particles ``xp`` (N, d) by log-likelihoods ``ll`` (N,), resample."""
        if ll.shape != (self.n,):
            raise ValueError(f"loglik returned shape {ll.shape}, expected ({self.n},)")
        bad = ~np.isfinite(ll) & ~np.isneginf(ll)
        if bad.any():
            log.warning("step %d: %d particles with NaN/+inf log-likelihood get weight 0",
                        self.t + 1, int(bad.sum()))
            ll = np.where(bad, -np.inf, ll)
        logw = self.logw + ll
        collapsed = not bool(np.isfinite(logw).any())
        if collapsed:
            log.warning("step %d: weight collapse (no particle explains the observation); "
                        "keeping the predictive particles", self.t + 1)
            logw_n, inc = self.logw, -math.inf
        else:
            logw_n, lse = log_normalise(logw)
            inc = lse  # self.logw is normalised, so this is log p(y_i | y_{1:i-1})
        w = np.exp(logw_n)
        w /= w.sum()
        ess = float(1.0 / np.sum(w * w))
        resampled = self.ess_threshold >= 1.0 or ess < self.ess_threshold * self.n
        if resampled:
            idx = self.resample(w, self.rng, self.n)
            self.x = xp[idx]
            self.ancestors = np.asarray(idx, dtype=np.intp)
            self.logw = np.full(self.n, -math.log(self.n))
        else:
            self.x = xp
            self.ancestors = np.arange(self.n)
            self.logw = logw_n
        self.t += 1
        return Step(x=xp, w=w, ess=ess, loglik=inc, collapsed=collapsed, resampled=resampled)
