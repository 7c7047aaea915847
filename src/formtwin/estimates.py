"""The tracker's output: one :class:`Estimate` per product, :class:`Estimates` stacked.

Every estimate carries its absolute goodness of fit (:class:`Fit`, computed by
:mod:`formtwin.tracker.fit` from the measurement model itself) and a one-word ``health``
(:data:`HEALTH`): an estimate that nothing supports never looks like one the data support.

Both are re-exported by :mod:`formtwin.tracker`. ``names``/``mean``/``std`` always hold the
18 augmented variables ``[x, theta, theta_d]``; a tracker that learns the statistics mu
(``TrackerConfig(learn_mu=True)``) adds the posterior mean and std of mu in the optional
``mu_mean``/``mu_std`` (``None`` otherwise), so consumers of the 18 names are unaffected.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import DEFAULT_OUTPUTS

FloatArray = NDArray[np.float64]


#: health of one estimate, best first: the curve is explained / explained with a warning
#: (fit in the tail, or few effective particles) / not explained (see formtwin.tracker.fit)
HEALTH = ("ok", "degraded", "no_fit")
#: output names of an estimate made without them: the demonstrator's two angles
DEFAULT_OUTPUT_NAMES = tuple(o.name for o in DEFAULT_OUTPUTS)


def _jsonable(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _jsonable_list(a: Any) -> list[float | None]:
    """Numbers (n,) as Python floats, non-finite ones ``None`` (one ``tolist``, not a
    NumPy scalar per entry)."""
    return [v if math.isfinite(v) else None
            for v in np.asarray(a, dtype=np.float64).reshape(-1).tolist()]


@dataclass(frozen=True)
class Fit:
    """Absolute goodness of fit of one curve (see :mod:`formtwin.tracker.fit`).

    Attributes
    ----------
    distance2 : posterior-weighted squared Mahalanobis distance of the curve from the
        particles' model curves under the likelihood's covariance (``inf`` if collapsed).
    dof : degrees of freedom of its reference distribution (``n_t``).
    quantile : posterior predictive quantile of the distance in its reference
        distribution (chi-square with ``dof`` for the Gaussian likelihood), in [0, 1].
    log10_p : ``log10(1 - quantile)`` computed without rounding (readable when the
        quantile rounds to 1).
    ess_share : ESS / N of the step, in (0, 1].
    health : one of :data:`HEALTH`.
    """

    distance2: float
    dof: int
    quantile: float
    log10_p: float
    ess_share: float
    health: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (non-finite numbers become ``None``), without ``health``."""
        return {"distance2": _jsonable(self.distance2), "dof": int(self.dof),
                "quantile": _jsonable(self.quantile), "log10_p": _jsonable(self.log10_p),
                "ess_share": _jsonable(self.ess_share)}


@dataclass(frozen=True)
class Estimate:
    """The estimate after one product (eq. 13-14), internal units.

    Attributes
    ----------
    index : 0-based number of the product in the tracker's stream.
    names : (18,) names of the augmented state (``spec.augmented.names``).
    mean, std : (18,) weighted posterior mean and std.
    angles_mean, angles_std : (n_outputs,) posterior predictive mean and std of the spec's
        scalar outputs (the demonstrator: its two bend angles, degrees).
    ess : effective sample size before resampling.
    collapsed : no particle explained the curve (estimate = predictive).
    loglik : log marginal-likelihood increment of the curve (``-inf`` if collapsed).
    mu_mean, mu_std : (7,) posterior mean and std of the statistics mu of the state
        variables (``spec.state.names`` order, internal units) when the tracker learns mu;
        ``None`` otherwise.
    fit : the absolute goodness of fit (``None`` only for estimates made without one).
    intervals : what ``std`` and ``angles_std`` are (``TrackerConfig.intervals``), or
        ``"uncalibrated"`` where a calibrated kind was asked for and the model has no
        interval calibration (the cloud's std: overconfident under model error).
    output_names : names of the outputs in ``angles_mean`` (``spec.output_names``).
    """

    index: int
    names: tuple[str, ...]
    mean: FloatArray
    std: FloatArray
    angles_mean: FloatArray
    angles_std: FloatArray
    ess: float
    collapsed: bool
    loglik: float
    mu_mean: FloatArray | None = None
    mu_std: FloatArray | None = None
    fit: Fit | None = None
    intervals: str = "cloud"
    output_names: tuple[str, ...] = DEFAULT_OUTPUT_NAMES

    def __getitem__(self, name: str) -> float:
        """Posterior mean of the variable ``name``."""
        return float(self.mean[self.names.index(name)])

    @property
    def health(self) -> str:
        """``fit.health``; ``"no_fit"`` for a collapsed step without a fit, else ``"ok"``."""
        if self.fit is not None:
            return self.fit.health
        return "no_fit" if self.collapsed else "ok"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (non-finite numbers become ``None``) with ``health`` and ``fit``;
        ``mu_mean``/``mu_std`` (lists of 7) only when mu is learned."""
        out: dict[str, Any] = {
            "index": int(self.index),
            "mean": dict(zip(self.names, _jsonable_list(self.mean), strict=True)),
            "std": dict(zip(self.names, _jsonable_list(self.std), strict=True)),
            "angles_mean": _jsonable_list(self.angles_mean),
            "angles_std": _jsonable_list(self.angles_std),
            "output_names": list(self.output_names),
            "ess": _jsonable(self.ess),
            "collapsed": bool(self.collapsed),
            "loglik": _jsonable(self.loglik),
            "health": self.health,
            "intervals": self.intervals,
        }
        if self.fit is not None:
            out["fit"] = self.fit.to_dict()
        if self.mu_mean is not None and self.mu_std is not None:
            out["mu_mean"] = _jsonable_list(self.mu_mean)
            out["mu_std"] = _jsonable_list(self.mu_std)
        return out


@dataclass(frozen=True)
class Estimates:
    """Stacked estimates of ``n`` products: arrays with a leading axis ``n``
    (``mu_mean``, ``mu_std``: (n, 7) when mu is learned, else ``None``; ``fit_distance2``,
    ``fit_quantile``, ``fit_log10_p``, ``ess_share`` NaN where an estimate has no fit;
    ``intervals`` that of the estimates, :class:`Estimate`)."""

    names: tuple[str, ...]
    index: NDArray[np.int64]
    mean: FloatArray
    std: FloatArray
    angles_mean: FloatArray
    angles_std: FloatArray
    ess: FloatArray
    collapsed: NDArray[np.bool_]
    loglik: FloatArray
    mu_mean: FloatArray | None = None
    mu_std: FloatArray | None = None
    health: NDArray[np.str_] | None = None
    fit_distance2: FloatArray | None = None
    fit_quantile: FloatArray | None = None
    fit_log10_p: FloatArray | None = None
    ess_share: FloatArray | None = None
    intervals: str = "cloud"
    output_names: tuple[str, ...] = DEFAULT_OUTPUT_NAMES

    def __len__(self) -> int:
        return int(self.index.size)

    def __getitem__(self, name: str) -> FloatArray:
        """Posterior means (n,) of the variable ``name``."""
        out: FloatArray = self.mean[:, self.names.index(name)]
        return out

    @classmethod
    def stack(cls, items: Sequence[Estimate], names: tuple[str, ...]) -> Estimates:
        """Stack single estimates (possibly none) into arrays."""
        d = len(names)
        n_out = len(items[0].angles_mean) if items else 2

        def arr(attr: str, width: int) -> FloatArray:
            if not items:
                return np.empty((0, width))
            return np.array([getattr(e, attr) for e in items], dtype=np.float64)

        learned = bool(items) and all(e.mu_mean is not None for e in items)

        def fit(attr: str) -> FloatArray:
            return np.array([math.nan if e.fit is None else getattr(e.fit, attr)
                             for e in items], dtype=np.float64)

        return cls(names=names, index=np.array([e.index for e in items], dtype=np.int64),
                   mean=arr("mean", d), std=arr("std", d), angles_mean=arr("angles_mean", n_out),
                   angles_std=arr("angles_std", n_out),
                   ess=np.array([e.ess for e in items], dtype=np.float64),
                   collapsed=np.array([e.collapsed for e in items], dtype=bool),
                   loglik=np.array([e.loglik for e in items], dtype=np.float64),
                   mu_mean=arr("mu_mean", 0) if learned else None,
                   mu_std=arr("mu_std", 0) if learned else None,
                   health=np.array([e.health for e in items], dtype=np.str_),
                   fit_distance2=fit("distance2"), fit_quantile=fit("quantile"),
                   fit_log10_p=fit("log10_p"), ess_share=fit("ess_share"),
                   intervals=items[0].intervals if items else "cloud",
                   output_names=items[0].output_names if items else DEFAULT_OUTPUT_NAMES)

    def columns(self) -> dict[str, NDArray[Any]]:
        """Flat table columns: index, mean_<name>, std_<name>, angles, ess, collapsed,
        loglik, health, fit_distance2, fit_quantile, fit_log10_p, ess_share (each (n,));
        plus mu_mean_<state name>, mu_std_<state name> when mu is learned."""
        cols: dict[str, NDArray[Any]] = {"index": self.index}
        for j, n in enumerate(self.names):
            cols[f"mean_{n}"] = self.mean[:, j]
        for j, n in enumerate(self.names):
            cols[f"std_{n}"] = self.std[:, j]
        for j in range(self.angles_mean.shape[1]):  # the spec's outputs, in their order
            cols[f"angle{j + 1}_mean"] = self.angles_mean[:, j]
            cols[f"angle{j + 1}_std"] = self.angles_std[:, j]
        cols.update(ess=self.ess, collapsed=self.collapsed, loglik=self.loglik)
        for key in ("health", "fit_distance2", "fit_quantile", "fit_log10_p", "ess_share"):
            v = getattr(self, key)
            if v is not None:
                cols[key] = v
        if self.mu_mean is not None and self.mu_std is not None:
            for j in range(self.mu_mean.shape[1]):  # the first 7 names are the state's
                cols[f"mu_mean_{self.names[j]}"] = self.mu_mean[:, j]
                cols[f"mu_std_{self.names[j]}"] = self.mu_std[:, j]
        return cols


__all__ = ["HEALTH", "Estimate", "Estimates", "Fit"]
