"""SIR with a kernel move after resampling (regularised / kernel-shrinkage particle filter).

Resampling duplicates particles; with static parameters in the state (``theta``,
``theta_d``) the copies only separate again through the transition's jitter, and the
cloud can collapse onto a few values. After each resampling this filter moves every
particle with a Gaussian kernel that *shrinks* towards the weighted mean so that the first
two moments of the cloud are kept (Liu & West 2001; the regularised filter of Musso,
Oudjane & Le Gland 2001 without its variance inflation)::

    x' = a x + (1 - a) m + h s eps,    a = sqrt(1 - h^2),    eps ~ N(0, I)

with ``m`` and ``s`` the weighted mean and per-component std of the particles before
resampling, and ``h`` the bandwidth (default 0.1). If the model has a ``constrain(x)``
method (e.g. reflection into the bounds), it is applied after the move.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters.resampling import Resampler
from formtwin.filters.sir import SIR, StateSpaceModel, Step

FloatArray = NDArray[np.float64]


class RegularisedSIR(SIR):
    """:class:`SIR` plus a moment-preserving Gaussian kernel move after resampling.

    The parameters not listed here are those of :class:`SIR`.

    Parameters
    ----------
    bandwidth : h in (0, 1); the kernel std as a fraction of the particle std.
    """

    name = "regularised"

    def __init__(self, model: StateSpaceModel, n_particles: int, rng: np.random.Generator,
                 resampling: str | Resampler = "systematic", ess_threshold: float = 1.0,
                 bandwidth: float = 0.1) -> None:
        super().__init__(model, n_particles, rng, resampling, ess_threshold)
        if not 0.0 < bandwidth < 1.0:
            raise ValueError(f"bandwidth = {bandwidth}, expected 0 < h < 1")
        self.bandwidth = float(bandwidth)

    def update(self, xp: FloatArray, ll: FloatArray) -> Step:
        """Weight the predicted particles ``xp`` (N, d) by their log-likelihoods ``ll``
        (N,) as SIR does, then move the resampled particles by the regularisation kernel."""
        step = super().update(xp, ll)
        if step.resampled and not step.collapsed and self.x is not None:
            h = self.bandwidth
            a = math.sqrt(1.0 - h * h)
            m, s = step.mean(), step.std()
            moved = a * self.x + (1.0 - a) * m + (h * s) * self.rng.standard_normal(
                self.x.shape)
            constrain: Any = getattr(self.model, "constrain", None)
            self.x = np.asarray(constrain(moved), dtype=np.float64) if constrain else moved
            self.ancestors = None
        return step
