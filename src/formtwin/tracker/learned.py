"""The line's own residual moment, learned online (``TrackerConfig.learn_residuals``).

The adaptive likelihood adds a share of ``K_res``, the metamodel's held-out error over the
DOE's line region, to the paper's covariance. A production line sees the metamodel's error
at its own inputs only, and there it has its own shape: on the study's physics lines the
second moment of ``physics - metamodel`` at the true inputs has directions with 12-18 times
``K_res``'s variance (``benchmarks/bench_model_error_bounds.py``,
``docs/notes/likelihood-bounds.md``).
With this option the tracker learns that moment from its own products: after each product
the posterior mean of the residual,

    r_i = sum_k w_k (z_i - model_k),   w_k the filter's posterior weights,

(measurement space, the residuals the likelihood compared) joins the mean
``M = (1/n) sum_i r_i r_i^T`` (N^2), folded in every :data:`EVERY` products, when the
likelihood's base covariance becomes ``Sigma + M`` (``kappa K_res`` on top, learned as
before). On metamodel data ``M`` stays small (the filter explains the curves), on physics
data it takes the line's error. ``M`` and ``n`` are part of the tracker's state
(checkpoints, state bytes).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters import Step
from formtwin.tracker.config import SHARES, TrackerConfig
from formtwin.tracker.discrepancy import Discrepancy, residual_covariance

FloatArray = NDArray[np.float64]

#: products between two refreshes of the likelihood's covariance (one joint
#: diagonalisation, ~2 ms for 101 samples, each time)
EVERY = 50


def make_discrepancy(model: Any, noise_cov: FloatArray, config: TrackerConfig) -> Discrepancy:
    """The adaptive or discrepancy likelihood of ``config`` on the base covariance
    ``noise_cov`` (n_t, n_t) N^2 (the paper's ``Sigma``, plus ``M`` when learned), with
    the model's ``K_res`` (zeros if it has none) and the grid or given share of it."""
    k_res = residual_covariance(model)
    share = config.error_share
    return Discrepancy.from_covariances(
        noise_cov, np.zeros_like(noise_cov) if k_res is None else k_res,
        np.array(SHARES) if share is None else share, config.discrepancy_memory,
        config.likelihood == "discrepancy", config.nu)


class ResidualMoment:
    """Mean ``M`` (n_t, n_t) N^2 of the outer products of the products' posterior mean
    residuals, folded in every :data:`EVERY` products: ``total`` and ``n`` are those
    folded (what the likelihood uses), ``recent`` the residuals (n_t,) since."""

    def __init__(self, n_t: int) -> None:
        self.total = np.zeros((n_t, n_t))
        self.n = 0
        self.recent: list[FloatArray] = []

    @property
    def moment(self) -> FloatArray:
        """``M`` as of the last fold (zeros before the first)."""
        out: FloatArray = self.total / max(self.n, 1)
        return out

    def add(self, residuals: FloatArray, w: FloatArray) -> bool:
        """Add the posterior mean of this product's ``residuals`` (N, n_t) N under the
        filter's normalised weights ``w`` (N,) (rows with NaN, which have no likelihood and
        weight 0, do not count; none left: the product is skipped). Returns whether ``M``
        was folded (the likelihood is due a refresh)."""
        good = np.all(np.isfinite(residuals), axis=1)
        if not good.any():
            return False
        self.recent.append(w[good] @ residuals[good])
        if len(self.recent) < EVERY:
            return False
        r = np.array(self.recent)
        self.total = self.total + r.T @ r
        self.n += len(r)
        self.recent = []
        return True

    def state(self) -> dict[str, Any]:
        """``M``'s sum (n_t, n_t), count and the residuals since (k, n_t) (the tracker
        state's ``model`` entries; the sum is not a copy: it is replaced, never changed)."""
        return {"residual_total": self.total, "residual_n": [float(self.n)],
                "residual_recent": np.array(self.recent).reshape(-1, self.total.shape[0])}

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore from :meth:`state` (arrays, or flat lists of numbers as in version 1's
        states; keys absent: nothing learned yet)."""
        n_t = self.total.shape[0]
        total = np.asarray(d.get("residual_total", np.zeros(n_t * n_t)), dtype=np.float64)
        recent = np.asarray(d.get("residual_recent", []), dtype=np.float64)
        if total.size != n_t * n_t or recent.size % n_t:
            raise ValueError(f"residual_total has {total.size} values, residual_recent "
                             f"{recent.size}: expected {n_t}^2 and a multiple of {n_t}")
        self.total = total.reshape(n_t, n_t).copy()
        self.n = int(d.get("residual_n", [0.0])[0])
        self.recent = list(recent.reshape(-1, n_t))


class LearnedResiduals:
    """Mixin of :class:`~formtwin.tracker.ssm.BendingSSM`: the residual moment's update
    after a product and the likelihood's refresh (``learned`` is None when off)."""

    learned: ResidualMoment | None
    discrepancy: Discrepancy | None
    model: Any
    measurement: Any
    config: TrackerConfig
    _last: dict[str, FloatArray]

    def update_residuals(self, step: Step) -> None:
        """After a filter ``step`` (its particles before resampling are those of the last
        likelihood): add the product's posterior mean residual to ``M``, and every
        :data:`EVERY` products make ``Sigma + M`` the likelihood's base covariance; a
        collapsed step, which no particle explained, is skipped."""
        if self.learned is not None and not step.collapsed and \
                self.learned.add(self._last["r"], step.w):
            self.refresh_likelihood()

    def set_learned_state(self, d: dict[str, Any]) -> None:
        """Restore ``M`` from a tracker state's ``model`` entries (:meth:`ResidualMoment.state`)
        and refresh the likelihood."""
        if self.learned is not None:
            self.learned.set_state(d)
            self.refresh_likelihood()

    def refresh_likelihood(self) -> None:
        """The likelihood on the base covariance ``Sigma + M`` (after a restore too)."""
        if self.learned is not None:
            cov = self.measurement.covariance() + self.learned.moment
            object.__setattr__(self, "discrepancy",
                               make_discrepancy(self.model, cov, self.config))

    def learned_snapshot(self) -> tuple[Any, ...] | None:
        """What :meth:`update_residuals` changes, to undo a failed step (None when off;
        ``add`` replaces ``total`` and ``recent``, never modifies them)."""
        m = self.learned
        return None if m is None else (m.total, m.n, list(m.recent), self.discrepancy)

    def learned_restore(self, snap: tuple[Any, ...] | None) -> None:
        """Undo to a :meth:`learned_snapshot`."""
        if self.learned is not None and snap is not None:
            self.learned.total, self.learned.n, self.learned.recent = snap[:3]
            object.__setattr__(self, "discrepancy", snap[3])
