"""Calibrated intervals (``TrackerConfig(intervals="calibrated")`` and ``"calibrated_fit"``):
floors learned offline on physics runs of the bundled metamodel
(:mod:`formtwin.study.calibrate`), added in quadrature to the reported std, constant or
gated by the curves' running fit distance (:class:`Floors`). The linearised filter's
terms (a persistent metamodel error's, an assumed mu's): :mod:`formtwin.tracker.sandwich`.
"""

from __future__ import annotations

import functools
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.tracker.discrepancy import residual_covariance

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: the interval calibration of the bundled metamodel (``intervals="calibrated"``), made by
#: ``python -m formtwin.study.calibrate`` on physics runs of its own (not the study's data)
CALIBRATION_PATH = Path(__file__).parents[1] / "data" / "interval_calibration.json"

#: relative tolerance on ``diag(K_res)`` for a calibration to belong to a metamodel
SIGNATURE_RTOL = 1e-6



def residual_signature(model: Any) -> FloatArray | None:
    """The diagonal (n_t,) of ``model``'s held-out residual covariance ``K_res``: identifies
    the metamodel fit a calibration was learned for (compared with a tolerance: the same fit
    made with another BLAS or thread count differs in the last bits), ``None`` without
    residual statistics."""
    k_res = residual_covariance(model)
    return None if k_res is None else np.ascontiguousarray(np.diag(k_res), dtype=np.float64)


def matches(signature: FloatArray, stored: Any) -> bool:
    """Whether a calibration's stored ``k_res_diag`` is that of the metamodel with
    ``signature`` (:func:`residual_signature`), to :data:`SIGNATURE_RTOL` of each entry or
    of the largest.

    >>> import numpy as np
    >>> d = np.array([1.0, 2.0, 3.0])
    >>> matches(d * (1 + 1e-12), list(d)), matches(d * 1.01, list(d)), matches(d, [1.0])
    (True, False, False)
    >>> matches(np.array([3.0, 1e-29]), [3.0, 0.0])   # rounding noise of a zero entry
    True
    """
    ref = np.asarray(stored if stored is not None else [], dtype=np.float64)
    if ref.shape != signature.shape or ref.size == 0:
        return False
    tol = SIGNATURE_RTOL * float(np.abs(ref).max())  # entries near 0 are rounding noise
    return bool(np.allclose(signature, ref, rtol=SIGNATURE_RTOL, atol=tol))


@functools.lru_cache(maxsize=4)
def _calibration(path: Path) -> dict[str, Any] | None:
    """The calibration file at ``path`` (``None``, logged once, if there is none)."""
    if not path.exists():
        log.warning("intervals='calibrated': no calibration file %s; reporting the cloud's "
                    "std", path)
        return None
    cal: dict[str, Any] = json.loads(path.read_text("utf-8"))
    return cal


@functools.lru_cache(maxsize=4)
def _warn_other_model(version: str, path: Path) -> None:
    """Log once that the calibration at ``path`` was learned for another metamodel."""
    log.warning("intervals='calibrated': no interval calibration for this metamodel (%s was "
                "learned for another fit of %s); reporting the cloud's std", path.name, version)


@functools.lru_cache(maxsize=4)
def _warn_other_layout(n_cal: int, n: int, path: Path) -> None:
    """Log once that the calibration at ``path`` has floors for ``n_cal`` estimated
    variables where the tracker has ``n`` (another deviation model: the spec's knots)."""
    log.warning("intervals='calibrated': %s has floors for %d estimated variables, this "
                "tracker estimates %d (another [deviation] knots than the calibration's); "
                "reporting the cloud's std", path.name, n_cal, n)


def _entry(model: Any, deviation: bool) -> dict[str, Any] | None:
    """The calibration's entry for a tracker on ``model`` with (``deviation``) or without
    theta_d, ``None`` for a model without ``K_res`` and (logged once) for another
    metamodel's calibration or another layout of the estimated variables."""
    signature = residual_signature(model)
    cal = None if signature is None else _calibration(CALIBRATION_PATH)
    if cal is None or signature is None:
        return None
    if not matches(signature, cal.get("k_res_diag")):
        _warn_other_model(str(cal.get("model_version")), CALIBRATION_PATH)
        return None
    entry: dict[str, Any] = dict(cal["deviation" if deviation else "no_deviation"])
    n, n_cal = len(model.spec.augmented), len(entry.get("floors", ()))
    if n_cal != n:
        _warn_other_layout(n_cal, n, CALIBRATION_PATH)
        return None
    entry["fit_gate"] = cal.get("fit_gate")
    return entry


def _floor_arrays(entry: dict[str, Any], prefix: str, n: int) -> tuple[FloatArray, FloatArray]:
    """The floors ``<prefix>floors`` (n,) and ``<prefix>angle_floors`` (2,) of ``entry``."""
    floors = np.array(entry[f"{prefix}floors"], dtype=np.float64)
    angles = np.array(entry[f"{prefix}angle_floors"], dtype=np.float64)
    if floors.shape != (n,) or angles.shape != (2,):
        raise ValueError(f"{CALIBRATION_PATH.name}: {prefix}floors of shape {floors.shape} "
                         f"and {angles.shape}, expected ({n},) and (2,)")
    return floors, angles


def calibration_floors(model: Any, deviation: bool) -> tuple[FloatArray, FloatArray]:
    """The floors ``b`` (18,) internal units and (2,) degrees that the calibrated intervals
    add in quadrature to the cloud's std (``sqrt(std^2 + b^2)``) for a tracker on ``model``
    estimating theta_d (``deviation``) or not; zeros for a model without an error model
    (no ``K_res``, as the analytic stand-in) and, logged once, when the bundled calibration
    was learned for another metamodel."""
    n = len(model.spec.augmented)
    entry = _entry(model, deviation)
    return (np.zeros(n), np.zeros(2)) if entry is None else _floor_arrays(entry, "", n)


def fit_ewma(d2: FloatArray, a: float, start: tuple[float, float] = (0.0, 0.0)
             ) -> tuple[FloatArray, tuple[float, float]]:
    """The running mean ``E`` (n,) of the fit distances ``d2`` (n,) with weight ``a`` on
    the newest (exponentially weighted, divided by the weights' sum so the start is not
    pulled to 0; non-finite distances, as a collapsed step's, leave it unchanged; NaN
    before the first finite one), and the end state ``(sum, weight)`` to continue from
    (``start``).

    >>> E, end = fit_ewma(np.array([4.0, np.inf, 2.0]), 0.5)
    >>> np.round(E, 4).tolist(), end   # 4, 4, (0.5 * 0.5 * 4 + 0.5 * 2) / (0.25 + 0.5)
    ([4.0, 4.0, 2.6667], (2.0, 0.75))
    """
    s, w = start
    out = np.full(d2.shape, np.nan)
    for t, v in enumerate(np.asarray(d2, dtype=np.float64)):
        if np.isfinite(v):
            s, w = (1.0 - a) * s + a * v, (1.0 - a) * w + a
        if w > 0:
            out[t] = s / w
    return out, (float(s), float(w))


def gate_scale(E: Any, d0: float, s_max: float) -> Any:
    """The fit gate's factor on the squared floors: the running fit distance ``E`` in
    excess of its mean ``d0`` on the metamodel's own curves, ``clip(E - d0, 0, s_max)``
    (``s_max`` the largest seen in the calibration: no extrapolation; NaN ``E``: 0)."""
    return np.clip(np.nan_to_num(np.asarray(E, dtype=np.float64) - d0, nan=0.0), 0.0, s_max)


class Floors:
    """The calibrated floors of one tracker, constant (``intervals="calibrated"``) or
    gated by the fit (``"calibrated_fit"``).

    The gate: a metamodel error shows in the curve's fit distance (:mod:`.fit`): on the
    metamodel's own curves its running mean ``E`` (:func:`fit_ewma`, with the weight
    the calibration stored) is ``d0`` on average, on physics curves larger. The
    estimate's bias from a metamodel error ``delta`` grows like ``|delta|``, the excess
    distance like ``|delta|^2``, so the squared floor is ``s b_fit^2`` with
    ``s = clip(E - d0, 0, s_max)`` (:func:`gate_scale`), ``b_fit`` learned so that the
    90 % intervals hold 90 % on the calibration's physics runs
    (:func:`formtwin.study.calibrate.learn_floors` with ``scale``).
    """

    def __init__(self, model: Any, deviation: bool, gated: bool) -> None:
        """Floors of the bundled calibration for a tracker on ``model`` with
        (``deviation``) or without theta_d; ``gated``: the fit gate."""
        n = len(model.spec.augmented)
        entry = _entry(model, deviation)
        self.gated = gated
        self.ewma: tuple[float, float] = (0.0, 0.0)
        self.d0, self.a, self.s_max = 0.0, 1.0, 0.0
        if entry is None:
            self.b, self.b_angles = np.zeros(n), np.zeros(2)
        elif not gated:
            self.b, self.b_angles = _floor_arrays(entry, "", n)
        elif entry.get("fit_gate") is None or "fit_floors" not in entry:
            log.warning("intervals='calibrated_fit': %s has no fit gate; reporting the "
                        "cloud's std", CALIBRATION_PATH.name)
            self.b, self.b_angles = np.zeros(n), np.zeros(2)
        else:
            self.b, self.b_angles = _floor_arrays(entry, "fit_", n)
            gate = entry["fit_gate"]
            self.d0, self.a = float(gate["d0"]), float(gate["ewma"])
            self.s_max = float(entry["fit_s_max"])

    def apply(self, std: FloatArray, astd: FloatArray, distance2: float
              ) -> tuple[FloatArray, FloatArray]:
        """The reported std (18,) and angle std (2,) from the cloud's ``std`` and
        ``astd`` after a product whose curve had the fit distance ``distance2``."""
        s = 1.0
        if self.gated:
            E, self.ewma = fit_ewma(np.array([distance2]), self.a, self.ewma)
            s = float(gate_scale(E[0], self.d0, self.s_max))
        return np.sqrt(std**2 + s * self.b**2), np.sqrt(astd**2 + s * self.b_angles**2)

    def state(self) -> dict[str, list[float]]:
        """The gate's running mean (for the tracker's checkpoint; empty when not gated)."""
        return {"fit_ewma": list(self.ewma)} if self.gated else {}

    def set_state(self, d: dict[str, list[float]]) -> None:
        """Continue from :meth:`state` (no entry: the start)."""
        v = d.get("fit_ewma", [0.0, 0.0])
        self.ewma = (float(v[0]), float(v[1]))
