"""The metamodel's own error: statistics of held-out residuals (physics minus metamodel).

k-fold cross-validation on the DOE (:func:`~formtwin.metamodel.validate.cross_validate`)
predicts every successful run with a metamodel that did not see it. The residuals
``r = physics - metamodel`` of the force curves ``(n, n_t)`` and of the two angles
``(n, 2)`` estimate the error the metamodel makes at a new input; their second moments
``K_res = E[r r^T]`` (bias included) are what the calibrated likelihood adds to the paper's
``fraction^2 K_MC`` (:mod:`formtwin.measurement`) and what the predicted angles' std adds
to the spread of the particles.

:class:`ResidualModel` is stored with the metamodel (arrays ``residuals.*`` of its
``.npz``), so the error model travels with the model it describes. Nothing here depends
on which columns the design has: a design with an extra control input works the same.

>>> import numpy as np
>>> r = ResidualModel.from_residuals(np.array([[1.0, 0.0], [-1.0, 2.0]]),
...                                  np.zeros((2, 2)), k=2)
>>> r.curve_cov.tolist(), r.curve_mean.tolist()
([[1.0, -1.0], [-1.0, 2.0]], [0.0, 1.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ResidualModel:
    """Second moments of held-out residuals (physics minus metamodel).

    Attributes
    ----------
    curve_cov : (n_t, n_t) ``E[r r^T]`` of the force-curve residuals, N^2 (bias included).
    curve_mean : (n_t,) mean curve residual, N (diagnostic).
    angle_cov : (n_outputs, n_outputs) ``E[r r^T]`` of the output (angle) residuals, deg^2.
    angle_mean : (n_outputs,) mean output (angle) residual, deg (diagnostic).
    k : number of folds of the cross-validation.
    n : number of runs behind the statistics.
    rows : which runs they are of (:func:`~formtwin.metamodel.validate.residual_model`'s
        rule, e.g. ``"interior, line 2 sigma"``; ``""`` for a file from before the rule
        was stored), so a loader can tell statistics made by another rule.
    """

    curve_cov: FloatArray
    curve_mean: FloatArray
    angle_cov: FloatArray
    angle_mean: FloatArray
    k: int
    n: int
    rows: str = ""

    def __post_init__(self) -> None:
        c, a = np.asarray(self.curve_cov, np.float64), np.asarray(self.angle_cov, np.float64)
        n_t = c.shape[0]
        if c.shape != (n_t, n_t) or np.shape(self.curve_mean) != (n_t,):
            raise ValueError(f"curve_cov {c.shape} and curve_mean {np.shape(self.curve_mean)} "
                             "do not match (n_t, n_t), (n_t,)")
        m = np.shape(self.angle_mean)[0] if np.ndim(self.angle_mean) == 1 else -1
        if a.shape != (m, m):
            raise ValueError(f"angle_cov {a.shape}, angle_mean {np.shape(self.angle_mean)}: "
                             "expected (n_outputs, n_outputs), (n_outputs,)")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
            raise ValueError("residual covariances must be finite")
        object.__setattr__(self, "curve_cov", c)
        object.__setattr__(self, "angle_cov", a)

    @classmethod
    def from_residuals(cls, curves: FloatArray, angles: FloatArray, k: int, rows: str = ""
                       ) -> ResidualModel:
        """Statistics of residual curves ``(n, n_t)`` N and outputs ``(n, n_outputs)`` (deg).

        Rows with a non-finite value are dropped (a failed run has no residual).
        """
        rc, ra = np.asarray(curves, np.float64), np.asarray(angles, np.float64)
        if rc.ndim != 2 or ra.ndim != 2 or ra.shape[0] != rc.shape[0]:
            raise ValueError(f"residuals of shape {rc.shape} and {ra.shape}, expected "
                             "(n, n_t) and (n, n_outputs)")
        good = np.all(np.isfinite(rc), axis=1) & np.all(np.isfinite(ra), axis=1)
        rc, ra = rc[good], ra[good]
        n = rc.shape[0]
        if n < 2:
            raise ValueError(f"{n} finite residual rows, expected at least 2")
        return cls(curve_cov=rc.T @ rc / n, curve_mean=rc.mean(axis=0),
                   angle_cov=ra.T @ ra / n, angle_mean=ra.mean(axis=0), k=int(k), n=n, rows=rows)

    @property
    def n_t(self) -> int:
        """Samples per curve."""
        return int(self.curve_cov.shape[0])

    def state(self) -> dict[str, np.ndarray]:
        """Arrays that rebuild the model (saved as ``residuals.*`` with the metamodel)."""
        return {"curve_cov": self.curve_cov, "curve_mean": np.asarray(self.curve_mean),
                "angle_cov": self.angle_cov, "angle_mean": np.asarray(self.angle_mean),
                "k": np.array(self.k), "n": np.array(self.n), "rows": np.array(self.rows)}

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray]) -> ResidualModel:
        """Inverse of :meth:`state`."""
        return cls(curve_cov=np.asarray(arrays["curve_cov"], np.float64),
                   curve_mean=np.asarray(arrays["curve_mean"], np.float64),
                   angle_cov=np.asarray(arrays["angle_cov"], np.float64),
                   angle_mean=np.asarray(arrays["angle_mean"], np.float64),
                   k=int(arrays["k"]), n=int(arrays["n"]),
                   rows=str(arrays["rows"]) if "rows" in arrays else "")
