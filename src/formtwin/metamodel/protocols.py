"""The seams of the metamodel: what it needs of a dataset, a reduction and an approximation."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class Dataset(Protocol):
    """What :meth:`Metamodel.fit` needs of a DOE dataset (:class:`formtwin.dataset.DoeDataset`)."""

    @property
    def spec(self) -> ProcessSpec:
        """The process definition of the runs."""
        ...

    @property
    def spec_text(self) -> str:
        """The spec as TOML text (stored with the metamodel)."""
        ...

    @property
    def inputs(self) -> FloatArray:
        """(n, 11) run inputs ``(x, theta, u)``, internal units."""
        ...

    @property
    def curves(self) -> FloatArray:
        """(n, n_t) stage-1 force curves, N."""
        ...

    @property
    def angles(self) -> FloatArray:
        """(n, 2) bend angles after stage 1 and 2, degrees."""
        ...

    @property
    def ok(self) -> BoolArray:
        """(n,) which runs succeeded."""
        ...

    @property
    def model_version(self) -> str:
        """Version of the process model that made the runs."""
        ...


@runtime_checkable
class Reduction(Protocol):
    """Reduces curves (n, n_t) to coefficients (n, r) and back (e.g. :class:`POD`)."""

    kind: str

    @property
    def n_modes(self) -> int:
        """Number of modes kept."""
        ...

    def fit(self, curves: FloatArray) -> Reduction:
        """Fit the reduction to ``curves`` (n, m); return it."""
        ...

    def transform(self, curves: FloatArray) -> FloatArray:
        """Coefficients (n, n_modes) of ``curves`` (n, m)."""
        ...

    def inverse_transform(self, coeffs: FloatArray) -> FloatArray:
        """Curves (n, m) of coefficients ``coeffs`` (n, n_modes)."""
        ...

    def state(self) -> dict[str, np.ndarray]:
        """Arrays that rebuild the fitted reduction (saved with the metamodel)."""
        ...


@runtime_checkable
class Approximation(Protocol):
    """Maps unit-box inputs (n, d) to outputs (n, k) (e.g. :class:`RBF`)."""

    kind: str

    def fit(self, U: FloatArray, Y: FloatArray) -> Approximation:
        """Fit to inputs ``U`` (n, d) and targets ``Y`` (n, k); return it."""
        ...

    def predict(self, U: FloatArray) -> FloatArray:
        """Predictions (N, k) at inputs ``U`` (N, d)."""
        ...

    def state(self) -> dict[str, np.ndarray]:
        """Arrays that rebuild the fitted approximation (saved with the metamodel)."""
        ...
