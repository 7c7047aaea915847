"""Proper orthogonal decomposition (POD) of force curves (paper, section "Metamodel").

The curves of a DOE, centred on their mean, are decomposed by a thin SVD; the leading
right singular vectors are the modes. A curve ``f`` (n_t,) is represented by its mode
coefficients ``a = (f - mean) @ modes.T`` and rebuilt as ``mean + a @ modes``. The modes
are orthonormal, so the L2 error of a curve equals the L2 error of its coefficients.

>>> rng = np.random.default_rng(0)
>>> curves = rng.normal(size=(50, 3)) @ rng.normal(size=(3, 20)) + 5.0
>>> pod = POD(energy=0.999999).fit(curves)
>>> pod.n_modes
3
>>> bool(np.allclose(pod.inverse_transform(pod.transform(curves)), curves))
True
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)


class POD:
    """POD of centred snapshots with a fixed mode count or an energy criterion.

    Parameters
    ----------
    n_modes : int or None
        Number of modes to keep (paper: 40). Clipped to the rank the data allows,
        ``min(n_runs - 1, n_t)``. Ignored when ``energy`` is given.
    energy : float or None
        Keep the fewest modes whose share of the total variance (sum of squared singular
        values of the centred curves) reaches ``energy``, in (0, 1].

    Attributes
    ----------
    mean : ndarray, shape (n_t,)
        Mean curve, N (set by :meth:`fit`, like the attributes below).
    modes : ndarray, shape (n_modes, n_t)
        Orthonormal modes (rows).
    singular_values : ndarray, shape (min(n, n_t),)
        All singular values of the centred curves, N.
    """

    kind = "POD"

    def __init__(self, n_modes: int | None = 40, energy: float | None = None) -> None:
        if energy is not None and not 0.0 < energy <= 1.0:
            raise ValueError(f"POD energy = {energy!r}, expected a fraction in (0, 1]")
        if energy is None and (n_modes is None or n_modes < 1):
            raise ValueError(f"POD n_modes = {n_modes!r}, expected a positive integer "
                             "(or give energy)")
        self.n_modes_requested = n_modes
        self.energy = energy
        self.mean = np.zeros(0)
        self.modes = np.zeros((0, 0))
        self.singular_values = np.zeros(0)

    def __repr__(self) -> str:
        if self.energy is not None:
            return f"POD(energy={self.energy})"
        return f"POD(n_modes={self.n_modes_requested})"

    def settings(self) -> dict[str, Any]:
        """The constructor's settings (:func:`~formtwin.metamodel.identity.fit_id`)."""
        return {"kind": self.kind, "n_modes": self.n_modes_requested, "energy": self.energy}

    @property
    def n_modes(self) -> int:
        """Number of modes kept (0 before :meth:`fit`)."""
        return int(self.modes.shape[0])

    @property
    def captured_energy(self) -> float:
        """Share of the centred curves' variance that the kept modes capture."""
        s2 = self.singular_values**2
        return float(s2[: self.n_modes].sum() / s2.sum()) if s2.sum() > 0 else 1.0

    def fit(self, curves: FloatArray) -> POD:
        """Compute mean and modes of ``curves`` (n, n_t), N; returns ``self``."""
        curves = np.asarray(curves, dtype=np.float64)
        if curves.ndim != 2 or curves.shape[0] < 2:
            raise ValueError(f"POD.fit: curves of shape {curves.shape}, expected (n >= 2, n_t)")
        if not np.all(np.isfinite(curves)):
            raise ValueError("POD.fit: curves contain NaN or inf (exclude failed runs first)")
        self.mean = curves.mean(axis=0)
        _, s, vt = np.linalg.svd(curves - self.mean, full_matrices=False)
        self.singular_values = s
        rank = int(np.sum(s > s[0] * 1e-12)) if s[0] > 0 else 1
        if self.energy is not None:
            share = np.cumsum(s**2) / np.sum(s**2) if s[0] > 0 else np.ones_like(s)
            r = int(np.searchsorted(share, self.energy * (1.0 - 1e-12)) + 1)
        else:
            assert self.n_modes_requested is not None
            r = self.n_modes_requested
            if r > rank:
                log.warning("POD: %d modes requested, the curves have rank %d; keeping %d",
                            r, rank, rank)
        r = max(1, min(r, rank))
        self.modes = vt[:r].copy()
        log.info("POD: %d modes capture %.8f of the variance", r, self.captured_energy)
        return self

    def transform(self, curves: FloatArray) -> FloatArray:
        """Mode coefficients (n, n_modes) of ``curves`` (n, n_t)."""
        return (np.asarray(curves, dtype=np.float64) - self.mean) @ self.modes.T

    def inverse_transform(self, coeffs: FloatArray) -> FloatArray:
        """Curves (n, n_t), N, from mode coefficients (n, n_modes)."""
        out: FloatArray = np.asarray(coeffs) @ self.modes + self.mean
        return out

    def state(self) -> dict[str, np.ndarray]:
        """Arrays that define the fitted POD (for the metamodel file)."""
        return {"mean": self.mean, "modes": self.modes, "singular_values": self.singular_values,
                "n_modes_requested": np.array(self.n_modes_requested or 0),
                "energy": np.array(np.nan if self.energy is None else self.energy)}

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray]) -> POD:
        """Rebuild a fitted POD from :meth:`state`."""
        energy = float(arrays["energy"])
        pod = cls(n_modes=int(arrays["n_modes_requested"]) or None,
                  energy=None if np.isnan(energy) else energy)
        pod.mean = np.asarray(arrays["mean"], dtype=np.float64)
        pod.modes = np.asarray(arrays["modes"], dtype=np.float64)
        pod.singular_values = np.asarray(arrays["singular_values"], dtype=np.float64)
        return pod
