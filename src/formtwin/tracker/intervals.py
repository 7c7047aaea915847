"""Calibrated intervals (``TrackerConfig(intervals="calibrated")`` and ``"calibrated_fit"``):
floors learned offline on physics runs of a metamodel (:mod:`formtwin.study.calibrate`,
``formtwin metamodel calibrate``), added in quadrature to the reported std, constant or
gated by the curves' running fit distance (:class:`Floors`). The linearised filter's
terms (a persistent metamodel error's, an assumed mu's): :mod:`formtwin.tracker.sandwich`.

A calibration belongs to one fit of a metamodel, named by its
:attr:`~formtwin.metamodel.Metamodel.fit_id` (the same on every machine,
:mod:`formtwin.metamodel.identity`). :func:`find_calibration` takes the one stored in the
metamodel's own file, else the package's calibration of the bundled default fit
(:data:`CALIBRATION_PATH`) when the fit ids agree, in both cases only if the diagonal of
the metamodel's ``K_res`` agrees with the calibration's within
:data:`~formtwin.metamodel.identity.SIGNATURE_RTOL`. Without one the tracker reports the
cloud's std and every estimate says ``intervals = "uncalibrated"``.

A calibration is learned for one likelihood setting, ``learn_residuals`` off or on (its
``settings.tracker.learn_residuals``; a calibration without settings counts as off): the
package keeps one per setting (:data:`CALIBRATION_PATH`,
:data:`LEARN_RESIDUALS_CALIBRATION_PATH`, :func:`calibration_path`), and a tracker is given
only the one of its own setting (the floors of the other would be wrong: the learned
residual moment widens the likelihood the fit gate is taken under).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.metamodel.identity import SIGNATURE_RTOL, signature_matches
from formtwin.tracker.discrepancy import residual_covariance

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: the interval calibration of the bundled metamodel (``intervals="calibrated"``), made by
#: ``python -m formtwin.study.calibrate`` on physics runs of its own (not the study's data)
CALIBRATION_PATH = Path(__file__).parents[1] / "data" / "interval_calibration.json"
#: the calibration of the bundled metamodel for trackers with ``learn_residuals``
#: (``python -m formtwin.study.calibrate --learn-residuals``)
LEARN_RESIDUALS_CALIBRATION_PATH = CALIBRATION_PATH.with_name(
    "interval_calibration_learn_residuals.json")


def calibration_path(learn_residuals: bool = False) -> Path:
    """The package's calibration file for trackers with ``learn_residuals`` off or on."""
    return LEARN_RESIDUALS_CALIBRATION_PATH if learn_residuals else CALIBRATION_PATH


def learned_for(cal: dict[str, Any]) -> bool:
    """The ``learn_residuals`` setting the calibration ``cal`` was learned for (its
    ``settings.tracker``; off when it does not say)."""
    return bool(cal.get("settings", {}).get("tracker", {}).get("learn_residuals", False))


def residual_signature(model: Any) -> FloatArray | None:
    """The diagonal (n_t,) of ``model``'s held-out residual covariance ``K_res``: the sanity
    check of a calibration's fit (compared within
    :data:`~formtwin.metamodel.identity.SIGNATURE_RTOL`: the same fit made on another
    machine differs in the last bits), ``None`` without residual statistics."""
    k_res = residual_covariance(model)
    return None if k_res is None else np.ascontiguousarray(np.diag(k_res), dtype=np.float64)


def residual_rule(model: Any) -> dict[str, Any]:
    """How ``model``'s held-out residual statistics were made (``k`` folds, ``rows``): part
    of what a calibration was learned for ({} without statistics)."""
    r = getattr(model, "residuals", None)
    return {} if r is None else {"k": int(r.k), "rows": str(r.rows)}


@functools.lru_cache(maxsize=4)
def _calibration(path: Path) -> dict[str, Any] | None:
    """The calibration file at ``path`` (``None``, logged once, if there is none)."""
    if not path.exists():
        log.warning("intervals='calibrated': no calibration file %s; reporting the cloud's "
                    "std", path)
        return None
    cal: dict[str, Any] = json.loads(path.read_text("utf-8"))
    return cal


@dataclass(frozen=True)
class Calibration:
    """The interval calibration a tracker on a model uses (:func:`find_calibration`).

    Attributes
    ----------
    data : the calibration (JSON-safe dict), ``None`` when there is none for the model.
    source : where it came from ("metamodel file" or the package's file name); "".
    fit_id : the model's fit identity ("" for a model without one).
    reason : why there is none ("" when there is one).
    """

    data: dict[str, Any] | None
    source: str
    fit_id: str
    reason: str

    def describe(self) -> str:
        """One line for logs and reports."""
        if self.data is None:
            return f"uncalibrated: {self.reason}"
        return f"calibrated for fit {self.fit_id} ({self.source})"


def find_calibration(model: Any, learn_residuals: bool = False) -> Calibration:
    """The interval calibration of ``model`` for trackers with ``learn_residuals`` off or
    on: its file's own, else the package's for the bundled fit
    (:func:`calibration_path`), if the fit ids and the setting (:func:`learned_for`) agree
    and ``diag(K_res)`` agrees within :data:`~formtwin.metamodel.identity.SIGNATURE_RTOL`
    of its largest entry."""
    path = calibration_path(learn_residuals)
    fid = str(getattr(model, "fit_id", ""))
    signature = residual_signature(model)
    if signature is None:
        return Calibration(None, "", fid, "the model has no held-out residual statistics "
                           "(K_res): fit it with cross-validation folds")
    candidates = [(c, s) for c, s in ((getattr(model, "calibration", None), "metamodel file"),
                                      (_calibration(path), path.name))
                  if c is not None and fid and c.get("fit_id") == fid
                  and learned_for(c) == learn_residuals]
    for cal, source in candidates:
        if cal.get("residuals", residual_rule(model)) != residual_rule(model):
            return Calibration(None, source, fid, f"the calibration of fit {fid} ({source}) "
                               f"was learned with the residual statistics "
                               f"{cal.get('residuals')}, the model has "
                               f"{residual_rule(model)}; run `formtwin metamodel calibrate`")
        if signature_matches(signature, cal.get("k_res_diag")):
            return Calibration(cal, source, fid, "")
        ref = np.asarray(cal.get("k_res_diag"), dtype=np.float64)
        off = float(np.abs(signature - ref).max() / np.abs(ref).max()) \
            if ref.shape == signature.shape else float("inf")
        return Calibration(None, source, fid, f"the calibration of fit {fid} ({source}) has a "
                           f"residual covariance {off:.2g} of its largest entry away from this "
                           f"model's (tolerance {SIGNATURE_RTOL:g}): the fit was made by other "
                           "code; run `formtwin metamodel calibrate`")
    which = fid or "(none: a file of an older formtwin; refit it)"
    setting = " with learn_residuals" if learn_residuals else ""
    return Calibration(None, "", fid, f"no interval calibration for fit {which}{setting}: "
                       "run `formtwin metamodel calibrate`")


@functools.lru_cache(maxsize=8)
def _warn(text: str) -> None:
    """Log ``text`` once."""
    log.warning("%s", text)


def _entry(model: Any, deviation: bool, learn_residuals: bool = False
           ) -> tuple[dict[str, Any] | None, Calibration]:
    """The calibration's entry for a tracker on ``model`` with (``deviation``) or without
    theta_d and ``learn_residuals`` off or on (``None``, logged once, where there is none
    or it has floors for another layout of the estimated variables), and the calibration
    found."""
    cal = find_calibration(model, learn_residuals)
    if cal.data is None:
        if residual_signature(model) is not None:
            _warn(f"intervals='calibrated': {cal.describe()}; reporting the cloud's std")
        return None, cal
    entry: dict[str, Any] = dict(cal.data["deviation" if deviation else "no_deviation"])
    n, n_cal = len(model.spec.augmented), len(entry.get("floors", ()))
    if n_cal != n:
        reason = (f"the calibration has floors for {n_cal} estimated variables, this tracker "
                  f"estimates {n} (another [deviation] than the calibration's)")
        _warn(f"intervals='calibrated': {reason}; reporting the cloud's std")
        return None, dataclasses.replace(cal, data=None, reason=reason)
    entry["fit_gate"] = cal.data.get("fit_gate")
    return entry, cal


def _floor_arrays(entry: dict[str, Any], prefix: str, n: int, n_out: int = 2
                  ) -> tuple[FloatArray, FloatArray]:
    """The floors ``<prefix>floors`` (n,) and ``<prefix>angle_floors`` (2,) of ``entry``."""
    floors = np.array(entry[f"{prefix}floors"], dtype=np.float64)
    angles = np.array(entry[f"{prefix}angle_floors"], dtype=np.float64)
    if floors.shape != (n,) or angles.shape != (n_out,):
        raise ValueError(f"interval calibration: {prefix}floors of shape {floors.shape} "
                         f"and {angles.shape}, expected ({n},) and ({n_out},)")
    return floors, angles


def calibration_floors(model: Any, deviation: bool, learn_residuals: bool = False
                       ) -> tuple[FloatArray, FloatArray]:
    """The floors ``b`` (18,) internal units and (2,) degrees that the calibrated intervals
    add in quadrature to the cloud's std (``sqrt(std^2 + b^2)``) for a tracker on ``model``
    estimating theta_d (``deviation``) or not; zeros for a model without an error model
    (no ``K_res``, as the analytic stand-in) and, logged once, when the bundled calibration
    was learned for another metamodel (``learn_residuals``: the tracker's setting)."""
    n = len(model.spec.augmented)
    entry, _ = _entry(model, deviation, learn_residuals)
    return ((np.zeros(n), np.zeros(model.spec.n_outputs)) if entry is None
            else _floor_arrays(entry, "", n, model.spec.n_outputs))


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

    def __init__(self, model: Any, deviation: bool, gated: bool,
                 learn_residuals: bool = False) -> None:
        """Floors of the bundled calibration for a tracker on ``model`` with
        (``deviation``) or without theta_d; ``gated``: the fit gate; ``learn_residuals``:
        the tracker's setting (the calibration learned for it)."""
        n, n_out = len(model.spec.augmented), model.spec.n_outputs
        entry, self.calibration = _entry(model, deviation, learn_residuals)
        self.gated = gated
        self.ewma: tuple[float, float] = (0.0, 0.0)
        self.d0, self.a, self.s_max = 0.0, 1.0, 0.0
        if entry is None:
            self.b, self.b_angles = np.zeros(n), np.zeros(n_out)
        elif not gated:
            self.b, self.b_angles = _floor_arrays(entry, "", n, n_out)
        elif entry.get("fit_gate") is None or "fit_floors" not in entry:
            log.info("intervals='calibrated_fit': the calibration (%s) has no fit gate (%s); "
                     "the constant floors apply", self.calibration.source,
                     entry.get("fit_gate_unusable", "none learned"))
            self.gated = False
            self.b, self.b_angles = _floor_arrays(entry, "", n, n_out)
        else:
            self.b, self.b_angles = _floor_arrays(entry, "fit_", n, n_out)
            gate = entry["fit_gate"]
            self.d0, self.a = float(gate["d0"]), float(gate["ewma"])
            self.s_max = float(entry["fit_s_max"])

    def apply(self, std: FloatArray, astd: FloatArray, distance2: float
              ) -> tuple[FloatArray, FloatArray]:
        """The reported std (18,) and angle std (2,) from the cloud's ``std`` and
        ``astd`` after a product whose curve had the fit distance ``distance2``."""
        s = 1.0
        if self.gated:  # fit_ewma and gate_scale of one distance, in scalars
            sum_, w = self.ewma
            if math.isfinite(distance2):
                a = self.a
                sum_, w = (1.0 - a) * sum_ + a * distance2, (1.0 - a) * w + a
                self.ewma = (sum_, w)
            excess = sum_ / w - self.d0 if w > 0 else math.nan
            s = 0.0 if math.isnan(excess) else min(max(excess, 0.0), self.s_max)
        return np.sqrt(std**2 + s * self.b**2), np.sqrt(astd**2 + s * self.b_angles**2)

    def state(self) -> dict[str, list[float]]:
        """The gate's running mean (for the tracker's checkpoint; empty when not gated)."""
        return {"fit_ewma": list(self.ewma)} if self.gated else {}

    def set_state(self, d: dict[str, list[float]]) -> None:
        """Continue from :meth:`state` (no entry: the start)."""
        v = d.get("fit_ewma", [0.0, 0.0])
        self.ewma = (float(v[0]), float(v[1]))
