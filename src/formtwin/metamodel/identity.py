"""What identifies a metamodel fit independently of the machine that made it.

A fit of the same DOE with the same settings gives, on another CPU, BLAS kernel or
thread count, numbers that differ in the last bits, and the tuned length scales and
least-squares centres amplify that to ~4e-4 of the largest entry of the held-out residual
covariance (measured between an AMD EPYC with OpenBLAS' Haswell kernels and an Intel
machine). What a fit *is* does not depend on that: :func:`fit_id` hashes the successful
runs of the DOE (their bytes as stored, the same everywhere), the settings of the
reduction and of the approximations, and the file format. An interval calibration is
learned for a fit id (:mod:`formtwin.tracker.intervals`); the residual covariance is kept
as a sanity check at :data:`SIGNATURE_RTOL`, loose enough for cross-machine rounding and
tight enough that a fit of other data or settings fails it (tests/test_same_twin.py shows
both).

>>> import numpy as np
>>> X = np.zeros((3, 2)); C = np.ones((3, 4)); A = np.ones((3, 2))
>>> data_digest(X, C, A) == data_digest(X.copy(), C.copy(), A.copy())
True
>>> data_digest(X, C, A) == data_digest(X, C + 1e-15, A)
False
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: relative tolerance, of the largest entry, of the residual covariance's diagonal for a
#: calibration's fit to be the tracker's: cross-machine refits differ by <= 4e-4
#: (tests/test_same_twin.py), fits of other data or settings by > 1e-2
SIGNATURE_RTOL = 1e-2


def data_digest(inputs: FloatArray, curves: FloatArray, angles: FloatArray) -> str:
    """SHA-256 (hex, 16 digits) of the runs a metamodel is fitted to: ``inputs`` (n, d),
    ``curves`` (n, n_t) and ``angles`` (n, k) as little-endian float64 bytes."""
    h = hashlib.sha256()
    for a in (inputs, curves, angles):
        arr = np.ascontiguousarray(a, dtype="<f8")
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()[:16]


def settings_of(part: Any) -> str:
    """The settings of a reduction or approximation template (its ``settings()`` if it has
    one, else its ``repr``)."""
    settings = getattr(part, "settings", None)
    return json.dumps(settings(), sort_keys=True) if callable(settings) else repr(part)


def fit_id(digest: str, file_format: str, parts: dict[str, Any]) -> str:
    """Identity (hex, 16 digits) of a fit: the data ``digest`` (:func:`data_digest`), the
    metamodel ``file_format`` and the settings of the named template ``parts``."""
    text = json.dumps({"data": digest, "format": file_format,
                       **{k: settings_of(v) for k, v in parts.items()}}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def signature_matches(signature: FloatArray, stored: Any, rtol: float = SIGNATURE_RTOL
                      ) -> bool:
    """Whether a calibration's stored diagonal of ``K_res`` is ``signature`` (n_t,) within
    ``rtol`` of its largest entry (entries near 0 are rounding noise).

    >>> d = np.array([1.0, 2.0, 3.0])
    >>> signature_matches(d * (1 + 4e-4), list(d)), signature_matches(d * 1.05, list(d))
    (True, False)
    >>> signature_matches(d, [1.0])   # another curve length
    False
    """
    ref = np.asarray(stored if stored is not None else [], dtype=np.float64)
    if ref.shape != signature.shape or ref.size == 0:
        return False
    return bool(np.all(np.abs(signature - ref) <= rtol * float(np.abs(ref).max())))
