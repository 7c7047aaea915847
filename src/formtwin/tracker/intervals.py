"""Misspecification-robust intervals (``TrackerConfig(intervals="sandwich")``): the part of
the estimate's error that a persistent metamodel error puts there and the particle cloud
does not show.

A metamodel error ``delta ~ N(0, K_res)`` (``K_res`` the k-fold held-out residual
covariance) that stays the same from product to product is not averaged away: on the
filter linearised about the cloud's mean (the curve's Jacobian ``J`` (n_t, m) in the m
columns that vary, the likelihood's covariance ``S``, the transition factors ``F`` (rho
for the state, 1 for the constant parameters) and the process noise ``Q`` (the AR(1)'s
``(1 - rho^2) sigma^2``, the jitter's ``(alpha range)^2``)), one Kalman step is

    P_pred = F P_prev F + Q,   P_lin = (P_pred^-1 + J^T S^-1 J)^-1,
    K = P_lin J^T S^-1,        A = P_lin P_pred^-1 F,

and the estimate's error from ``delta`` follows ``e_i = A e_(i-1) + K delta``: it is
``G_i delta`` with the sensitivity ``G_i = A G_(i-1) + K`` (m, n_t), ``G_0 = 0``. Its
covariance ``B = G K_res G^T`` is added to the cloud's covariance ``P`` in the reported
std (:func:`sandwich_step`); the angles add ``a' B a'^T`` with ``a'`` the angle
metamodel's gradient in ``[x, theta]`` at the cloud's mean. ``P_prev`` is the previous
product's cloud covariance; one step with ``F = 0`` is the one-product sandwich
``P J^T S^-1 K_res S^-1 J P``. For a linear-Gaussian model the recursion is exact: the
Kalman estimate's mean error under a fixed offset ``delta`` is ``G delta`` and its mean
squared error ``P + G delta delta^T G^T`` (tests/test_tracker_intervals.py).

``"gated"`` multiplies ``B`` by the posterior probability that the metamodel's error is in
the data (the adaptive likelihood's ``P(kappa > 0)``; 1 for the other likelihoods).
``J`` and the angle gradient are refreshed every :data:`EVERY` products (``m + 1`` curve
and ``n_in + 1`` angle evaluations); the particles, weights, means, ESS, evidence and
health do not change (the intervals are computed after the step and draw no random
numbers). What this does and does not explain on the physics data: docs/likelihood.md.
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

#: the curve's Jacobian and the angles' gradient are refreshed every this many products
#: (the cloud's mean drifts slowly; each refresh costs m + 1 + n_in + 1 model rows)
EVERY = 4

#: relative tolerance on ``diag(K_res)`` for a calibration to belong to a metamodel
SIGNATURE_RTOL = 1e-6

#: keys of the sandwich's state in :attr:`formtwin.tracker.TrackerState.model`
STATE_KEYS = ("sandwich_G", "sandwich_P", "sandwich_J", "sandwich_Ja")


def sandwich_step(G: FloatArray, P_prev: FloatArray, J: FloatArray, S_inv_J: FloatArray,
                  F: FloatArray, Q: FloatArray) -> FloatArray:
    """The next sensitivity ``G`` (m, n_t) of the estimate to a persistent curve error
    (module doc) from the previous ``G`` (m, n_t), the previous posterior covariance
    ``P_prev`` (m, m), the Jacobian ``J`` (n_t, m), ``S^-1 J`` (n_t, m), the transition
    factors ``F`` (m,) and the process-noise variances ``Q`` (m,).

    >>> import numpy as np   # scalar state, one sample: K = P_lin / s, A = P_lin / P_pred
    >>> G = sandwich_step(np.zeros((1, 1)), np.eye(1), np.eye(1), np.eye(1) / 2.0,
    ...                   np.ones(1), np.ones(1))
    >>> round(float(G[0, 0]), 6)   # P_pred = 2, P_lin = 1 / (1/2 + 1/2) = 1, K = 1/2
    0.5
    """
    P_pred = F[:, None] * P_prev * F[None, :] + np.diag(Q)
    pred_inv = np.linalg.inv(P_pred)
    P_lin = np.linalg.inv(pred_inv + J.T @ S_inv_J)
    P_lin = 0.5 * (P_lin + P_lin.T)
    out: FloatArray = (P_lin @ pred_inv * F[None, :]) @ G + P_lin @ S_inv_J.T
    return out


class Sandwich:
    """The robust intervals of one tracker: ``update`` after each step gives the variance
    to add to the reported std of the augmented state (18,) and of the angles (2,)."""

    def __init__(self, ssm: Any, gated: bool = False) -> None:
        """For the tracker's model ``ssm`` (:class:`~formtwin.tracker.BendingSSM`);
        ``gated``: ``B`` times the posterior probability of ``kappa > 0``."""
        self.ssm = ssm
        self.gated = gated
        nx, self.m = ssm.n_x, ssm.n_varying
        lo, hi = ssm._lo[:self.m], ssm._hi[:self.m]
        self.F = np.r_[ssm._rho, np.ones(self.m - nx)]
        self.Q = np.r_[(1.0 - ssm._rho**2) * ssm._sigma**2,
                       (ssm.config.alpha * (hi[nx:] - lo[nx:])) ** 2]
        k_res = residual_covariance(ssm.model)
        n_t = ssm.spec.n_t
        k_res = np.zeros((n_t, n_t)) if k_res is None else k_res
        lam, vec = np.linalg.eigh(0.5 * (k_res + k_res.T))
        self.k_half: FloatArray = vec * np.sqrt(np.maximum(lam, 0.0))  # K_res = R R^T
        self.G = np.zeros((self.m, n_t))
        self.P = self.P0 = np.diag(np.r_[ssm._sigma**2, (hi[nx:] - lo[nx:]) ** 2 / 12.0])
        self.J: FloatArray | None = None
        self.Ja: FloatArray | None = None

    def weight(self) -> float:
        """The factor on ``B``: 1, or (gated, adaptive likelihood) ``P(kappa > 0)``."""
        d = self.ssm.discrepancy
        if not self.gated or d is None or d.shared:
            return 1.0
        return float(np.exp(self.ssm.share_logpost) @ (d.shares > 0))

    def update(self, x: FloatArray, w: FloatArray, y: FloatArray, t: int,
               u: FloatArray | None) -> tuple[FloatArray, FloatArray]:
        """After product ``t`` (0-based) with particles ``x`` (N, d), weights ``w`` (N,)
        and curve ``y`` (n_t,): the variances (n_aug,) and (2,) to add to the cloud's
        for the state and the angles at setting ``u``."""
        ssm, m = self.ssm, self.m
        n_in, na = ssm.n_in, ssm.n_aug
        mean = w @ x
        dev = x[:, :m] - mean[:m]
        P = (dev * w[:, None]).T @ dev
        if self.J is None or t % EVERY == 0:
            self._refresh(mean, np.sqrt(np.maximum(np.diag(P), 0.0)), y, u)
        assert self.J is not None and self.Ja is not None
        S = np.asarray(ssm._lik_cov())
        if np.all(np.isfinite(self.J)) and np.all(np.isfinite(P)):
            self.G = sandwich_step(self.G, self.P, self.J, np.linalg.solve(S, self.J),
                                   self.F, self.Q)
            self.P = P
        H = self.G @ self.k_half  # B = H H^T
        c = self.weight()
        var = np.zeros(na)
        var[:m] = c * np.sum(H * H, axis=1)
        Ha = self.Ja @ H[:n_in]
        return var, c * np.sum(Ha * Ha, axis=1)

    def _refresh(self, mean: FloatArray, spread: FloatArray, y: FloatArray,
                 u: FloatArray | None) -> None:
        """The curve's Jacobian (n_t, m) and the angles' gradient (2, n_in) at ``mean``."""
        ssm, n_in = self.ssm, self.ssm.n_in
        self.J, step = ssm._cloud_jacobian(mean, spread[ssm.n_x:], y)
        base = np.repeat(mean[None, :n_in], n_in + 1, axis=0)
        base[1:] += np.diag(step[:n_in])
        a = ssm.model.predict_angles(base, u)
        self.Ja = (a[1:] - a[0]).T / step[:n_in]

    def snapshot(self) -> tuple[Any, ...]:
        """The recursion's arrays, for :meth:`restore` (they are replaced, never changed in
        place, so references suffice)."""
        return self.G, self.P, self.J, self.Ja

    def restore(self, snap: tuple[Any, ...]) -> None:
        """Back to a :meth:`snapshot`."""
        self.G, self.P, self.J, self.Ja = snap

    def state(self) -> dict[str, list[float]]:
        """The recursion's state as JSON numbers (for the tracker's checkpoint)."""
        if self.J is None or self.Ja is None:
            return {}
        return {k: [float(v) for v in a.ravel()]
                for k, a in zip(STATE_KEYS, (self.G, self.P, self.J, self.Ja), strict=True)}

    def set_state(self, d: dict[str, list[float]]) -> None:
        """Continue from :meth:`state` (an empty dict: the start)."""
        n_t, m, n_in = self.G.shape[1], self.m, self.ssm.n_in
        if not d:
            self.G, self.P, self.J, self.Ja = np.zeros((m, n_t)), self.P0, None, None
            return
        self.G = np.array(d["sandwich_G"], dtype=np.float64).reshape(m, n_t)
        self.P = np.array(d["sandwich_P"], dtype=np.float64).reshape(m, m)
        self.J = np.array(d["sandwich_J"], dtype=np.float64).reshape(n_t, m)
        self.Ja = np.array(d["sandwich_Ja"], dtype=np.float64).reshape(2, n_in)


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
