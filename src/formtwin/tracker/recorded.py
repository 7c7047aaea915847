"""A recorded production run with its sensor values, tracked as the line delivered them.

Offline, the curves and every sensor's value of each product are known at once; this
fuses each value when the line would have known it, so that each product's estimate is the
one the live service would have issued:

* a state variable's value without delay (a strip gauge, upstream of the press) before its
  product's step, in the step where the filter allows it (:mod:`formtwin.tracker.ahead`),
  else right after it;
* a value with delay ``d`` (the camera's final angle, ``d >= 1``) after the step of product
  ``k + d``; the values still due after the last product are fused at the end (they reach
  the tracker's state, not the estimates).

A value the tracker refuses (:class:`~formtwin.tracker.fusion.FusionError`: e.g. no
particle explains it) is left out and listed in :attr:`Recorded.refused`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.estimates import Estimate, Estimates
from formtwin.tracker.ahead import refusal
from formtwin.tracker.fusion import FusionError

if TYPE_CHECKING:
    from formtwin.tracker.core import Tracker

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Recorded:
    """What :func:`track_recorded` gives.

    Attributes
    ----------
    estimates : each product's estimate at its step, with the values known by then.
    final : (n, 3) with a camera of the final angle: the measured final angle predicted at
        each product's step (degrees) and its calibrated 90 % interval (lo, hi)
        (:meth:`~formtwin.tracker.Tracker.issue_final`); ``None`` without one.
    fused : values fused, by sensor name.
    refused : ``"product k, sensor: reason"`` of each value the tracker refused.
    """

    estimates: Estimates
    final: FloatArray | None
    fused: dict[str, int]
    refused: list[str]


def track_recorded(tracker: Tracker, curves: FloatArray,
                   values: Mapping[str, FloatArray], u: FloatArray | None = None,
                   progress: bool = False) -> Recorded:
    """Track ``curves`` (n, n_t) N with the sensor ``values`` (name -> (n,) in the measured
    quantity's internal unit, NaN: none) of the sensors ``tracker`` fuses, each when the
    line knew it (module doc); ``u`` (n, n_controls) each product's press setting (None:
    nominal). ``ValueError`` for values of a sensor the tracker does not fuse or of
    another length than the curves."""
    n = curves.shape[0]
    sensors = {s.name: s for s in tracker.sensors}
    unknown = sorted(set(values) - set(sensors))
    if unknown:
        raise ValueError(f"values of {', '.join(unknown)}: not among the sensors the tracker "
                         f"fuses ({', '.join(sensors) or 'none'}; --sensors)")
    for name, v in values.items():
        if np.shape(v) != (n,):
            raise ValueError(f"values of {name}: shape {np.shape(v)}, expected ({n},): one per "
                             "curve")
    first = [s for s in tracker.sensors if s.kind == "state" and s.delay == 0 and s.name in values]
    late = [s for s in tracker.sensors if s not in first and s.name in values]
    fused = dict.fromkeys(values, 0)
    refused: list[str] = []

    def fuse(k: int, name: str) -> None:
        v = float(values[name][k])
        if not math.isfinite(v):
            return
        try:
            tracker.fuse(k, name, v, u=None if u is None else u[k])
            fused[name] += 1
        except FusionError as exc:
            refused.append(f"product {k}, {name}: {exc}")

    items: list[Estimate] = []
    final = np.full((n, 3), np.nan) if tracker.finals is not None else None
    steps: Any = range(n)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc="tracking", unit="product")
    with single_blas_thread():
        for k in steps:
            after = [s.name for s in first if refusal(tracker, s) is not None]
            for s in first:
                if s.name not in after:
                    fuse(k, s.name)  # enters this product's step
            items.append(tracker.step(curves[k], None if u is None else u[k]))
            for name in after:
                fuse(k, name)
            for s in late:
                if k - s.delay >= 0:
                    fuse(k - s.delay, s.name)
            if final is not None:
                issued, (lo, hi) = tracker.issue_final(None if u is None else u[k])
                final[k] = issued, lo, hi
        for s in late:  # due after the last product
            for j in range(max(n - s.delay, 0), n):
                fuse(j, s.name)
    return Recorded(Estimates.stack(items, tracker.names), final, fused, refused)


__all__ = ["Recorded", "track_recorded"]
