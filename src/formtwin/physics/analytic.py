"""A closed-form stand-in for the two-stage flap bending model.

.. warning::
   This is **not** the paper's finite-element model (MSC.Marc, ~10 min a run) nor
   formtwin's physics model (:mod:`formtwin.physics.bending`). It is a cheap, smooth,
   deterministic formula in which every one of the ten inputs acts with plausible
   physics, written so that the design of experiments, the dataset, the metamodel, the
   particle filter and the study can be built and tested in microseconds per run.

The punch follows a crank motion ``p(t) = P (1 - cos(w t))`` above its lowest point
(reached at ``t = 0``). It touches the flap at height ``p_c`` (shifted by the vertical
alignment); after contact the punch travel is ``u = p_c - p`` (a softplus, so the curve is
smooth). The stage-1 force is the sum of

* bending: ``F_p = C sigma_y (1 + (epsdot / 10^log_rate)^q) w t^2 / (4 L(beta))`` with the
  Cowper-Symonds rate factor of paper eq. 11, strain rate ``epsdot ~ t / (2 R) dbeta/dt``
  from the punch speed, and the lever arm ``L`` shrinking as the flap wraps (angle
  ``beta``) and shifted by the horizontal alignment;
* friction: tool-flap friction scales the bending force by ``(1 + mu_tf cot-like)``, and
  tool-tool friction adds a sliding force that follows the sign of the punch speed;
* elastic compliance: the force rises as ``F_p tanh(k_eff u / F_p)`` with ``k_eff`` the
  press stiffness in series with the flap's elastic stiffness, and unloads after ``t = 0``
  along the same stiffness;
* bottoming: when the punch end distance approaches the (bent, thickened) sheet, the
  sheet is coined between punch and die: a contact spring in series with the press gives
  a spike at ``t = 0`` that grows as ``punch_end_distance - thickness`` shrinks.

The angles after stage 1 and stage 2 are geometric angles (deeper punch, shorter lever ->
more bending) minus an elastic springback ``~ sigma_y R / (E t)``, reduced by coining;
the stage-2 depth setting ``u`` (the spec's control ``stage2_depth``, if any) adds
``_GAIN_U u`` to the final angle.

All inputs are internal units (mm, N, s, MPa); see :mod:`formtwin.spec`.

>>> from formtwin.spec import load_spec
>>> sim = AnalyticBending(load_spec())
>>> mid = 0.5 * (sim.spec.inputs.lo + sim.spec.inputs.hi)
>>> r = sim.run(mid)
>>> r.ok, r.curve.shape, bool(r.curve.max() > 50.0), r.angles.round(1).tolist()
(True, (101,), True, [43.5, 87.7])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from formtwin.simulator import RunResult
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

#: bumped whenever the formula changes, so datasets made with an older formula are detected
VERSION = "analytic-2"

# fixed geometry and material constants of the stand-in (mm, s, MPa)
_STROKE_HALF = 5.0          # P: half stroke, mm
_OMEGA = 2.0 * np.pi / 0.5  # crank angular speed, rad/s (120 strokes/min)
_CONTACT = 2.0              # p_c: punch height at first contact, mm
_WIDTH = 10.0               # flap width, mm
_LEVER = 1.0                # nominal lever arm, mm
_RADIUS = 1.0               # bend radius, mm
_E = 193e3                  # Young's modulus of stainless steel, MPa
_K_FLAP = 2000.0            # elastic stiffness of flap and tools, N/mm
_K_COIN = 3.0e4             # coining contact stiffness, N/mm
_SOFT = 0.02                # softplus width of the contact onset, mm
_SOFT_COIN = 0.004          # softplus width of the coining onset, mm
_THICKEN = 1.22             # bent sheet thickness / sheet thickness at the bend
_BETA_MAX = np.pi / 2.0     # bend angle reached at full travel, rad
_F_SLIDE = 40.0             # normal load of the tool-tool sliding contact, N
_V_SLIDE = 2.0              # speed scale of the friction sign change, mm/s
_GAIN_U = 20.0              # final angle per mm of stage-2 depth setting, deg/mm


def _softplus(z: FloatArray) -> FloatArray:
    return np.logaddexp(0.0, z)


def _coin_stiffness(c: dict[str, FloatArray]) -> FloatArray:
    """The coining contact in series with the press (n, 1), N/mm, of the columns ``c``."""
    out: FloatArray = 1.0 / (1.0 / _K_COIN + 1.0 / c["press_stiffness"])
    return out


def _angles(c: dict[str, FloatArray], k_coin: FloatArray) -> FloatArray:
    """Bend angles after stage 1 and stage 2 (n, 2), degrees, of the input columns ``c``
    (each (n, 1)): geometry minus springback (reduced by coining); ``k_coin`` (n, 1) N/mm
    is the coining contact in series with the press."""
    sy, q, th = c["yield_stress"], c["rate_exponent"], c["thickness"]
    eps0 = 10.0 ** c["log_rate"]
    mu_tt, mu_tf = c["friction_tool_tool"], c["friction_tool_flap"]
    d_end, h_al = c["punch_end_distance"], c["horizontal_alignment"]
    v_al = c["vertical_alignment"]
    coin0 = k_coin * _SOFT_COIN * _softplus(-(d_end + v_al - _THICKEN * th) / _SOFT_COIN)
    f_pl0 = 1.6 * sy * _WIDTH * th**2 / (4.0 * _LEVER)
    geo1 = 45.0 + 150.0 * (0.36 - d_end - v_al) - 300.0 * h_al + 40.0 * (th - 0.3)
    spring = 3.0 * sy * 3.0 * _RADIUS / (_E * th) * (1.0 + 0.5 * mu_tf)
    relief = 1.0 / (1.0 + coin0 / f_pl0)
    ang1 = geo1 * (1.0 - spring * relief) + 2.0 * (mu_tt - 0.3)
    rate2 = 1.0 + (3.0 / eps0) ** q
    ang2 = 90.0 + 0.25 * (ang1 - 44.0) - 250.0 * h_al \
        - 4.0 * (sy * rate2 / 300.0 - 1.0) - 1.5 * (q - 0.7) + _GAIN_U * c["stage2_depth"]
    return np.hstack([ang1, ang2])


@dataclass(frozen=True)
class AnalyticBending:
    """Closed-form stand-in for the flap-bending simulator (a :class:`Simulator`).

    Parameters
    ----------
    spec : ProcessSpec
        The process; its ``inputs`` must be the demonstrator's ten inputs (any order is
        fine, they are looked up by name) and its ``time`` grid (s) the curve grid.
    failure_clearance : float or None
        If set (mm), runs whose clearance ``punch_end_distance + vertical_alignment -
        thickness`` is below it fail with a reason, emulating FE runs that crash under
        severe coining (the paper kept 6953 of 7024 runs). ``None`` (default): never fails.

    Notes
    -----
    Deterministic; one run costs microseconds, :meth:`run_batch` is vectorised.
    """

    spec: ProcessSpec
    failure_clearance: float | None = None
    version: str = VERSION

    def _columns(self, X: FloatArray) -> dict[str, FloatArray]:
        idx = self.spec.run_inputs.index
        out = {name: X[:, idx[name]][:, None] for name in idx}
        out.setdefault("stage2_depth", np.zeros((X.shape[0], 1)))
        return out

    def run_batch(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Run a batch of input points.

        Parameters
        ----------
        X : ndarray, shape (n, 11) or (n, 10)
            Inputs (state x, parameters theta, controls u; without u: nominal u),
            internal units.

        Returns
        -------
        curves : ndarray, shape (n, n_t)
            Stage-1 punch force on ``spec.time``, N. Failed runs are NaN.
        angles : ndarray, shape (n, 2)
            Bend angle after stage 1 and stage 2, degrees. Failed runs are NaN.
        """
        c = self._columns(self.spec.run_columns(X))
        t = self.spec.time[None, :]
        sy, q = c["yield_stress"], c["rate_exponent"]
        eps0 = 10.0 ** c["log_rate"]
        th = c["thickness"]
        mu_tt, mu_tf = c["friction_tool_tool"], c["friction_tool_flap"]
        d_end, h_al = c["punch_end_distance"], c["horizontal_alignment"]
        v_al, k_press = c["vertical_alignment"], c["press_stiffness"]

        # punch kinematics (mm, mm/s); contact height shifted by vertical misalignment
        p = _STROKE_HALF * (1.0 - np.cos(_OMEGA * t))
        speed = _STROKE_HALF * _OMEGA * np.sin(_OMEGA * t)          # > 0 going up
        p_c = _CONTACT + 8.0 * v_al - 2.0 * (d_end - 0.36)
        u = _SOFT * _softplus((p_c - p) / _SOFT)                    # travel after contact
        u_tot = p_c                                                 # travel at t = 0
        # loading branch uses the travel reached so far (u is symmetric in t)
        frac = np.clip(u / u_tot, 0.0, 1.0)
        beta = _BETA_MAX * frac
        lever = (_LEVER + 6.0 * h_al) * (1.0 - 0.45 * np.sin(beta))
        # strain rate from the bending speed: t/(2R) * dbeta/dt, 1/s
        dbeta = _BETA_MAX * np.abs(speed) / u_tot * (u > 0.5 * _SOFT)
        epsdot = th / (2.0 * _RADIUS) * dbeta + 1e-3
        rate = 1.0 + (epsdot / eps0) ** q
        f_plastic = 1.6 * sy * rate * _WIDTH * th**2 / (4.0 * lever)
        f_plastic = f_plastic * (1.0 + 1.5 * mu_tf * np.sin(beta + 0.3))
        k_eff = 1.0 / (1.0 / k_press + 1.0 / _K_FLAP)
        f_bend = f_plastic * np.tanh(k_eff * u / np.maximum(f_plastic, 1e-9))
        # unloading after the bottom dead centre: elastic recovery along k_eff
        f0 = f_bend[:, [int(np.argmin(np.abs(self.spec.time)))]] if self.spec.time[0] <= 0 \
            <= self.spec.time[-1] else f_bend.max(axis=1, keepdims=True)
        after = self.spec.time > 0.0  # the unloading branch, computed where it applies
        unload = f0 * _softplus((f0 - k_eff * p[:, after]) / f0 * 6.0) / 6.0
        f_bend[:, after] = np.minimum(unload, f_bend[:, after])
        # tool-tool sliding friction follows the sign of the punch speed
        engaged = np.tanh(u / (4.0 * _SOFT))
        f_slide = mu_tt * _F_SLIDE * engaged * np.tanh(-speed / _V_SLIDE)
        # coining: bent sheet pressed between punch and die, spring in series with press
        gap = d_end + v_al + p - _THICKEN * th
        k_coin = _coin_stiffness(c)
        f_coin = k_coin * _SOFT_COIN * _softplus(-gap / _SOFT_COIN)
        curves = f_bend + f_slide + f_coin

        angles = _angles(c, k_coin)
        bad = self._failed(c)
        curves[bad] = np.nan
        angles[bad] = np.nan
        return curves, angles

    def run_angles(self, X: FloatArray) -> FloatArray:
        """The angles of :meth:`run_batch` alone (the same numbers, without the curves'
        cost): ``X`` (n, 11) or (n, 10), internal units; returns (n, 2), degrees, NaN for
        failed runs."""
        c = self._columns(self.spec.run_columns(X))
        angles = _angles(c, _coin_stiffness(c))
        angles[self._failed(c)] = np.nan
        return angles

    def _failed(self, c: dict[str, FloatArray]) -> NDArray[np.bool_]:
        """The runs (n,) of the input columns ``c`` whose clearance is below
        ``failure_clearance`` (none without it)."""
        clearance = (c["punch_end_distance"] + c["vertical_alignment"] - c["thickness"])[:, 0]
        if self.failure_clearance is None:
            return np.zeros(clearance.shape, dtype=bool)
        out: NDArray[np.bool_] = clearance < self.failure_clearance
        return out

    def failure_reason(self, x: FloatArray) -> str:
        """Why the run at ``x`` (shape ``(11,)`` or ``(10,)``) fails, or ``""`` if it does not."""
        if self.failure_clearance is None:
            return ""
        idx = self.spec.inputs.index
        clearance = x[idx["punch_end_distance"]] + x[idx["vertical_alignment"]] \
            - x[idx["thickness"]]
        if clearance < self.failure_clearance:
            return (f"coining too severe: clearance {clearance * 1e3:.1f} um below "
                    f"{self.failure_clearance * 1e3:.1f} um (emulated solver failure)")
        return ""

    def run(self, inputs: FloatArray) -> RunResult:
        """Run one input point ``(11,)`` = ``(x, theta, u)`` in internal units (the
        :class:`Simulator` protocol)."""
        x = np.asarray(inputs, dtype=np.float64).reshape(-1)
        reason = self.failure_reason(x)
        if reason:
            return RunResult.failure(self.spec.n_t, reason)
        curves, angles = self.run_batch(x[None, :])
        return RunResult(curves[0], angles[0])
