"""Fixed-lag memory of the particles' paths, for measurements that arrive late.

A measurement ``s`` of the state ``x_j`` of an earlier step ``j = t - l`` (``0 <= l <= L``)
is fused into the filter at step ``t`` by *ancestor reweighting*: each particle carries,
in ``L`` blocks of extra columns, the first ``width`` columns of its ancestors at the last
``L`` steps (its path ``x_{t-1}^k, ..., x_{t-L}^k``), copied with the particle at every
transition and resampling, so that the particle system stands for ``p(x_{t-L:t} | Z_t)``
and

    w_t^k  <-  w_t^k p(s | x_j^k)

gives ``p(x_{t-L:t} | Z_t, s)``, whose marginal at ``t`` is the filtering law with the late
value in it. No index bookkeeping and no loop over particles: resampling copies the rows.
The usual path degeneracy of particle smoothers applies: with resampling at every step
the lag-``l`` columns hold fewer distinct values as ``l`` grows, so keep ``L`` small (the
delays of a line's sensors: a few products).

:func:`shift` fills the blocks at a transition, :func:`lagged` reads one,
:func:`reweight` multiplies a likelihood in; :class:`FixedLag` wraps any
:class:`~formtwin.filters.StateSpaceModel` with the blocks (a model with its own column
layout calls :func:`shift` itself).

>>> import numpy as np
>>> parent = np.array([[1.0, 2.0, 10.0, 20.0]])   # width 2, one lag block at column 2
>>> out = np.zeros_like(parent); out[:, :2] = [[3.0, 4.0]]
>>> shift(parent, out, width=2, start=2, depth=1); out.tolist()
[[3.0, 4.0, 1.0, 2.0]]
>>> lagged(out, 2, 2, 1).tolist(), lagged(out, 2, 2, 0).tolist()
([[1.0, 2.0]], [[3.0, 4.0]])
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters.sir import StateSpaceModel, log_normalise

FloatArray = NDArray[np.float64]


def shift(parent: FloatArray, out: FloatArray, width: int, start: int, depth: int) -> None:
    """Fill the ``depth`` lag blocks of ``out`` (N, d), columns ``[start, start + depth
    width)``, from the particles' parents ``parent`` (N, d): block 1 is the parents'
    first ``width`` columns, block ``l`` the parents' block ``l - 1``."""
    if depth <= 0:
        return
    out[:, start:start + width] = parent[:, :width]
    out[:, start + width:start + depth * width] = parent[:, start:start + (depth - 1) * width]


def lagged(x: FloatArray, width: int, start: int, lag: int) -> FloatArray:
    """The first ``width`` columns (N, width) of the particles' ancestors ``lag`` steps
    back (0: the particles' own), from the lag blocks starting at column ``start``."""
    if lag == 0:
        return x[:, :width]
    return x[:, start + (lag - 1) * width:start + lag * width]


def distinct_rows(x: FloatArray) -> tuple[FloatArray, NDArray[np.intp]]:
    """The distinct rows of ``x`` (N, d) and, for each row of ``x``, its row among them
    (``rows[inverse] == x``): a model evaluated once per distinct row serves all copies
    that resampling made. Rows are compared by their bytes (one sort of N keys; ~10 times
    ``np.unique(x, axis=0)``'s speed at N = 500).

    >>> rows, inv = distinct_rows(np.array([[1.0, 2.0], [3.0, 4.0], [1.0, 2.0]]))
    >>> rows[inv].tolist()
    [[1.0, 2.0], [3.0, 4.0], [1.0, 2.0]]
    >>> len(rows)
    2
    """
    c = np.ascontiguousarray(x)
    keys = c.view(np.dtype((np.void, c.dtype.itemsize * c.shape[1]))).reshape(-1)
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return c[first], inverse.reshape(-1)


def reweight(logw: FloatArray, ll: FloatArray) -> tuple[FloatArray, float]:
    """Normalised log-weights (N,) ``logw + ll`` and the log evidence increment
    ``log sum exp(logw + ll)`` (``logw`` normalised: ``log p(s | Z)``). Non-finite ``ll``
    entries count as zero likelihood; ``ValueError`` if no particle is left (the caller's
    weights are not touched)."""
    ll = np.where(np.isnan(ll) | np.isposinf(ll), -np.inf, ll)
    new = np.asarray(logw, dtype=np.float64) + ll
    if not np.isfinite(new).any():
        raise ValueError("no particle gives the measurement a finite likelihood")
    return log_normalise(new)


class FixedLag:
    """``model`` with ``depth`` lag blocks of its first ``width`` columns appended.

    Parameters
    ----------
    model : a state-space model with ``d`` columns.
    d : its number of columns.
    width : how many of its leading columns each lag block keeps.
    depth : ``L``, the number of lag blocks.

    Examples
    --------
    >>> import numpy as np
    >>> class Walk:
    ...     def sample_initial(self, n, rng): return rng.standard_normal((n, 1))
    ...     def sample_transition(self, x, rng): return x + rng.standard_normal(x.shape)
    ...     def loglik(self, x, y): return -0.5 * (y - x[:, 0]) ** 2
    >>> m = FixedLag(Walk(), d=1, width=1, depth=2)
    >>> x0 = m.sample_initial(3, np.random.default_rng(0))
    >>> x1 = m.sample_transition(x0, np.random.default_rng(1))
    >>> bool(np.all(x1[:, 1] == x0[:, 0])), bool(np.isnan(x1[:, 2]).all())
    (True, True)
    """

    def __init__(self, model: StateSpaceModel, d: int, width: int, depth: int) -> None:
        if not 0 < width <= d or depth < 0:
            raise ValueError(f"FixedLag: width = {width}, depth = {depth}; expected "
                             f"0 < width <= d = {d} and depth >= 0")
        self.model, self.d, self.width, self.depth = model, d, width, depth

    def sample_initial(self, n: int, rng: np.random.Generator) -> FloatArray:
        """The model's initial particles (n, d) and ``depth`` blocks of NaN (no past)."""
        x = np.asarray(self.model.sample_initial(n, rng), dtype=np.float64)
        return np.hstack([x, np.full((n, self.depth * self.width), math.nan)])

    def sample_transition(self, x: FloatArray, rng: np.random.Generator) -> FloatArray:
        """The model's transition of the first ``d`` columns; the lag blocks shifted."""
        out = np.empty_like(x)
        out[:, :self.d] = self.model.sample_transition(x[:, :self.d], rng)
        shift(x, out, self.width, self.d, self.depth)
        return out

    def loglik(self, x: FloatArray, y: Any) -> FloatArray:
        """The model's log-likelihood of ``y`` on the first ``d`` columns."""
        return np.asarray(self.model.loglik(x[:, :self.d], y), dtype=np.float64)


__all__ = ["FixedLag", "distinct_rows", "lagged", "reweight", "shift"]
