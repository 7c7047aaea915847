"""SIR with a guided importance density: the model proposes ``x_i`` given the parent *and*
the observation (Doucet, Godsill & Andrieu 2000, the "optimal" proposal and its Gaussian
approximations).

The bootstrap filter (:class:`~formtwin.filters.SIR`) draws ``x_i`` from the transition and
lets the likelihood sort the draws out; when the observation pins ``x_i`` far more tightly
than the transition spreads it, most draws get negligible weight (ESS ~10 of 500 in the
study's series 3 and 6) and the cloud degenerates. Here the model draws from a density
``q(x_i | x_{i-1}, y_i)`` near the posterior and returns, with each draw, the log importance
ratio ``log p(x_i | x_{i-1}) - log q(x_i | x_{i-1}, y_i)``; the weight is the likelihood
times that ratio, so the posterior of the paths and the evidence are those of SIR, with a
smaller variance. The model must give ``sample_guided(x, y, rng) -> (x_new, log_ratio)``.
:attr:`GuidedSIR.log_ratio` keeps the last step's ratios (for hyperparameters learned from
the same particles, e.g. the tracker's share of the metamodel's error).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from formtwin.filters.resampling import Resampler
from formtwin.filters.sir import SIR, StateSpaceModel, Step

FloatArray = NDArray[np.float64]


class GuidedSIR(SIR):
    """:class:`SIR` with the model's guided proposal instead of its transition.

    Parameters as :class:`SIR`; the model needs ``sample_guided``.

    Examples
    --------
    >>> import numpy as np
    >>> class Walk:   # x_i = x_(i-1) + N(0, 1), y = x + N(0, 1): the optimal proposal
    ...     def sample_initial(self, n, rng): return rng.standard_normal((n, 1))
    ...     def sample_transition(self, x, rng): return x + rng.standard_normal(x.shape)
    ...     def loglik(self, x, y): return -0.5 * (y - x[:, 0]) ** 2 - 0.5 * np.log(2 * np.pi)
    ...     def sample_guided(self, x, y, rng):   # q = p(x | x_prev, y) = N((x + y)/2, 1/2)
    ...         m = 0.5 * (x[:, 0] + y); new = m + np.sqrt(0.5) * rng.standard_normal(len(x))
    ...         lp = -0.5 * (new - x[:, 0]) ** 2 - 0.5 * np.log(2 * np.pi)
    ...         lq = -(new - m) ** 2 - 0.5 * np.log(np.pi)
    ...         return new[:, None], lp - lq
    >>> f = GuidedSIR(Walk(), 1000, np.random.default_rng(0))
    >>> f.initialise(); f.x[:] = 0.0    # every parent at 0: all weights equal
    >>> s = f.step(2.0)
    >>> round(s.ess), round(float(s.mean()[0]), 1)
    (1000, 1.0)
    """

    name = "guided"
    #: keyword arguments of the model's ``sample_guided`` (none: its default proposal)
    proposal_kwargs: ClassVar[dict[str, Any]] = {}

    def __init__(self, model: StateSpaceModel, n_particles: int, rng: np.random.Generator,
                 resampling: str | Resampler = "systematic",
                 ess_threshold: float = 1.0) -> None:
        super().__init__(model, n_particles, rng, resampling, ess_threshold)
        if not hasattr(model, "sample_guided"):
            raise ValueError("the guided filter needs the model's sample_guided")
        #: (N,) log importance ratios of the last step's draws (zeros before any)
        self.log_ratio: FloatArray = np.zeros(self.n)

    def step(self, y: Any) -> Step:
        """Assimilate ``y``: guided draw, weight by likelihood x ratio, normalise, resample."""
        if self.x is None:
            self.initialise()
        m: Any = self.model
        xp, ratio = m.sample_guided(self.x, y, self.rng, **self.proposal_kwargs)
        xp = np.asarray(xp, dtype=np.float64)
        self.log_ratio = np.asarray(ratio, dtype=np.float64)
        ll = np.asarray(m.loglik(xp, y), dtype=np.float64) + self.log_ratio
        return self.update(xp, ll)


class GuidedLinSIR(GuidedSIR):
    """:class:`GuidedSIR` asking the model for its proposal without a pilot evaluation per
    particle (``sample_guided(x, y, rng, pilot=False)``: e.g. each parent's curve moved by
    a Jacobian), so a step costs about one model evaluation per particle, as :class:`SIR`."""

    name = "guided_lin"
    proposal_kwargs: ClassVar[dict[str, Any]] = {"pilot": False}
