"""One production run's hidden truth: statistics mu, machine parameters theta, deviation
theta_d and the state sequence x of its products (paper, "Simulation runs").

Every place that needs a simulated run (the study's pseudo-data, the service's synthetic
streams, :meth:`formtwin.tracker.BendingSSM.simulate`, benchmarks, examples and tests)
draws it with :func:`draw_production_run`.

>>> import numpy as np
>>> from formtwin.spec import load_spec
>>> run = draw_production_run(load_spec(), 5, np.random.default_rng(0))
>>> run.x.shape, run.inputs.shape, run.truth.shape, run.run_inputs.shape
((5, 7), (5, 10), (5, 18), (5, 11))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from formtwin.evolution import simulate
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ProductionRun:
    """The truth of ``n`` products of one run, internal units.

    Attributes
    ----------
    mu : (7,) state means of the run.
    theta : (3,) machine parameters, constant over the run.
    theta_d : (8,) deviation parameters, constant over the run (zeros: no deviation).
    x : (n, 7) state of each product, AR(1) about ``mu`` (eq. 4-5), in the design box.
    u : (n, n_controls) press setting of each product (known to the tracker).
    """

    mu: FloatArray
    theta: FloatArray
    theta_d: FloatArray
    x: FloatArray
    u: FloatArray

    @property
    def n(self) -> int:
        """Number of products."""
        return int(self.x.shape[0])

    @property
    def inputs(self) -> FloatArray:
        """Model inputs ``[x, theta]`` (n, 10)."""
        return np.hstack([self.x, np.tile(self.theta, (self.n, 1))])

    @property
    def run_inputs(self) -> FloatArray:
        """Model-run inputs ``[x, theta, u]`` (n, 11)."""
        return np.hstack([self.inputs, self.u])

    @property
    def truth(self) -> FloatArray:
        """The augmented state ``[x, theta, theta_d]`` (n, 18) of every product."""
        return np.hstack([self.inputs, np.tile(self.theta_d, (self.n, 1))])


def draw_production_run(spec: ProcessSpec, n: int, rng: np.random.Generator,
                        mu: FloatArray | None = None, deviation: bool = True,
                        sigma: FloatArray | None = None, rho: FloatArray | None = None,
                        u: FloatArray | float | None = None) -> ProductionRun:
    """Draw the truth of a run of ``n`` products.

    Parameters
    ----------
    spec : the process definition (bounds and statistics).
    n : number of products (>= 1).
    rng : random source; draws, in order, mu (unless given), theta, theta_d (when
        ``deviation``), then the states.
    mu : (7,) state means; default uniform in ``[mu_min, mu_max]`` per variable.
    deviation : draw theta_d uniform in its bounds; else theta_d = 0 (``g`` = identity).
    sigma, rho : (7,) state std and autocorrelation; default the spec's.
    u : press settings: a scalar, (n,) or (n, n_controls); default the nominal setting
        (never drawn: the random draws do not depend on it).
    """
    if n < 1:
        raise ValueError(f"n = {n}, expected >= 1")
    s, p, d = spec.state, spec.params, spec.deviation.group
    if mu is None:
        m = rng.uniform(s.mu_min, s.mu_max)
    else:
        m = np.asarray(mu, dtype=np.float64)
        if m.shape != (len(s),):
            raise ValueError(f"mu has shape {m.shape}, expected ({len(s)},)")
    theta = rng.uniform(p.lo, p.hi)
    theta_d = rng.uniform(d.lo, d.hi) if deviation else np.zeros(len(d))
    sg = s.sigma if sigma is None else np.asarray(sigma, dtype=np.float64)
    r = s.rho if rho is None else np.asarray(rho, dtype=np.float64)
    x = simulate(n, m, sg, r, rng, s.lo, s.hi)
    settings = spec.run_columns(np.zeros((n, len(s) + len(p))), u)[:, len(s) + len(p):]
    return ProductionRun(mu=m, theta=theta, theta_d=theta_d, x=x, u=settings)
