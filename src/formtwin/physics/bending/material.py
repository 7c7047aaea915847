"""Sheet material: elastic constants, tabulated hardening and Cowper-Symonds rate dependence.

Hardening curve
    The demonstrator's stainless steel curve is not public. The table is the Swift law
    ``sigma0 = K (eps_0 + eps)^n`` with ``K = 1275 MPa``, ``n = 0.45``, typical literature
    values for annealed AISI 304 (1.4301), normalised by its value at ``eps = 0``
    (``eps_0 = (290 / K)^(1/n) = 0.0373``, i.e. a 290 MPa initial yield stress), so that
    ``sigma0(eps) = sigma_y h(eps)`` with ``h(0) = 1``. It is sampled at the strains of
    :data:`HARD_EPS` and interpolated linearly (linear extrapolation beyond 1.0).

Rate dependence (paper eq. 11)
    ``sigma = (1 + (epsdot / epsdot0)^q) sigma0(eps)`` with ``epsdot0 = 10**log_rate``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

SWIFT_K, SWIFT_N, SWIFT_SY = 1275.0, 0.45, 290.0
_EPS0 = (SWIFT_SY / SWIFT_K) ** (1.0 / SWIFT_N)

#: equivalent plastic strains of the hardening table
HARD_EPS = np.array([0.0, 0.002, 0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.2,
                     0.3, 0.4, 0.6, 1.0])
#: flow stress / initial yield stress at :data:`HARD_EPS`
HARD_RATIO = (1.0 + HARD_EPS / _EPS0) ** SWIFT_N
#: slope of :data:`HARD_RATIO` over each interval of :data:`HARD_EPS` (the same quotients
#: the hardening kernel took on every call)
HARD_SLOPE = np.diff(HARD_RATIO) / np.diff(HARD_EPS)


@dataclass(frozen=True)
class Material:
    """Elastic-plastic, rate-dependent sheet material (MPa, 1/s).

    ``hardening=False`` gives elastic-perfectly plastic behaviour (verification).
    ``E`` and ``nu`` are for stainless steel; the model uses ``E' = E / (1 - nu^2)``.
    """

    yield_stress: float = 300.0
    log_rate: float = 2.2
    rate_exponent: float = 0.8
    E: float = 193_000.0
    nu: float = 0.3
    hardening: bool = True
    rate: bool = True

    @property
    def plane_strain_modulus(self) -> float:
        """``E' = E / (1 - nu^2)`` (MPa)."""
        return self.E / (1.0 - self.nu**2)

    @property
    def array(self) -> FloatArray:
        """``[E', sigma_y, epsdot0, q, hardening]`` for the kernels (no rate: ``epsdot0 = inf``)."""
        e0 = 10.0**self.log_rate if self.rate else np.inf
        return np.array([self.plane_strain_modulus, self.yield_stress, e0, self.rate_exponent,
                         1.0 if self.hardening else 0.0])
