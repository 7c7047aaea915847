"""Checks of what a tracker is given per product: the force curve and the press setting.
Each raises ``ValueError`` naming what is wrong (the tracker is then left untouched)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]


def validate_controls(u: Any, spec: ProcessSpec) -> FloatArray | None:
    """The press setting ``u`` of a product as (n_controls,) internal units, or None.

    ``None`` stays None (the nominal setting). Raises ``ValueError`` naming the control
    for a wrong count, a non-number or a value outside its bounds (the metamodel would
    extrapolate).
    """
    if u is None:
        return None
    box = spec.controls
    try:
        arr = np.asarray(u, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"u = {u!r}: expected a number per control "
                         f"({', '.join(box.names) or 'none'})") from None
    if arr.size != len(box):
        raise ValueError(f"u has {arr.size} values, expected {len(box)} "
                         f"({', '.join(box.names) or 'no controls in this spec'})")
    for v, val in zip(box, arr, strict=True):
        if not (np.isfinite(val) and v.lo - 1e-12 <= val <= v.hi + 1e-12):
            raise ValueError(f"u: {v.name} = {val / v.scale:g} {v.unit}, expected a value in "
                             f"[{v.lo / v.scale:g}, {v.hi / v.scale:g}] {v.unit}")
    return arr


def validate_curve(curve: Any, n_t: int) -> FloatArray:
    """``curve`` as a float array (n_t,), or ``ValueError`` naming what is wrong."""
    if isinstance(curve, (str, bytes)):
        raise ValueError(f"curve is a {type(curve).__name__}, expected {n_t} numbers")
    try:
        arr = np.asarray(curve)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"curve cannot be read as an array: {exc}") from exc
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"curve has dtype {arr.dtype}, expected real numbers")
    if arr.ndim != 1:
        raise ValueError(f"curve has shape {arr.shape}, expected ({n_t},)")
    if arr.size != n_t:
        raise ValueError(f"curve has {arr.size} samples, expected {n_t}")
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ValueError(f"curve has {int(bad.sum())} non-finite values (NaN/inf), first "
                         f"at sample {int(np.argmax(bad))}")
    return arr
