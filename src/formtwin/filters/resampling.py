"""Resampling schemes, chosen by name from a registry (or passed as a callable).

A scheme maps normalised weights ``w`` (N,) and a ``numpy.random.Generator`` to ``m``
ancestor indices (m,) (``m = N`` by default) such that each index ``k`` is drawn
``m w_k`` times in expectation. All four standard schemes are unbiased; they differ in
variance (multinomial > residual, stratified > systematic, Douc & Cappe 2005) and cost
(all ``O(N log N)`` or better here, no Python loop).

>>> import numpy as np
>>> w = np.array([0.5, 0.25, 0.25, 0.0])
>>> get_resampler("systematic")(w, np.random.default_rng(1)).tolist()
[0, 0, 1, 2]
>>> sorted(RESAMPLERS)
['multinomial', 'residual', 'stratified', 'systematic']
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: ``scheme(weights (N,), rng, m) -> indices (m,)``
Resampler: TypeAlias = Callable[[FloatArray, np.random.Generator, int], IntArray]

RESAMPLERS: dict[str, Resampler] = {}


def register_resampler(name: str) -> Callable[[Resampler], Resampler]:
    """Decorator adding a scheme to :data:`RESAMPLERS` under ``name``."""

    def deco(fn: Resampler) -> Resampler:
        RESAMPLERS[name] = fn
        return fn

    return deco


def get_resampler(scheme: str | Resampler) -> Resampler:
    """The scheme called ``scheme`` (or ``scheme`` itself if callable).

    Raises
    ------
    ValueError
        For an unknown name; the message lists the known ones.
    """
    if callable(scheme):
        return scheme
    try:
        return RESAMPLERS[scheme]
    except (KeyError, TypeError):
        raise ValueError(f"unknown resampling scheme {scheme!r}; known: "
                         f"{', '.join(sorted(RESAMPLERS))} (or pass a callable)") from None


def _inverse_cdf(w: FloatArray, u: FloatArray) -> IntArray:
    """Indices ``k`` with ``cdf[k-1] <= u < cdf[k]`` for sorted or unsorted ``u`` in [0, 1)."""
    cdf = np.cumsum(w)
    cdf /= cdf[-1]
    idx: IntArray = np.minimum(np.searchsorted(cdf, u, side="right"), w.size - 1)
    return idx


@register_resampler("multinomial")
def multinomial(w: FloatArray, rng: np.random.Generator, m: int = 0) -> IntArray:
    """``m`` i.i.d. draws from the categorical distribution ``w``."""
    m = m or w.size
    return _inverse_cdf(w, np.sort(rng.random(m)))


@register_resampler("stratified")
def stratified(w: FloatArray, rng: np.random.Generator, m: int = 0) -> IntArray:
    """One uniform draw in each of ``m`` equal strata of [0, 1)."""
    m = m or w.size
    return _inverse_cdf(w, (np.arange(m) + rng.random(m)) / m)


@register_resampler("systematic")
def systematic(w: FloatArray, rng: np.random.Generator, m: int = 0) -> IntArray:
    """``m`` evenly spaced points with a single uniform offset (the default)."""
    m = m or w.size
    return _inverse_cdf(w, (np.arange(m) + rng.random()) / m)


@register_resampler("residual")
def residual(w: FloatArray, rng: np.random.Generator, m: int = 0) -> IntArray:
    """``floor(m w_k)`` copies of each ``k``, the remainder multinomial on the residuals."""
    m = m or w.size
    counts = np.floor(m * w).astype(np.intp)
    det = np.repeat(np.arange(w.size), counts)
    rest = m - det.size
    if rest == 0:
        return det
    r = m * w - counts
    return np.concatenate([det, multinomial(r / r.sum(), rng, rest)])
