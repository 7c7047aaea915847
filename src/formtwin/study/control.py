"""Closed-loop study of the final angle: no control, run-to-run EWMA, feedforward (open, with
feedback, with the angles in the filter), oracle.

The plant is the physics model under the realistic conditions of the paper's series 6:
state means mu drawn in ``[mu_min, mu_max]`` and unknown to the tracker (it assumes the
mid-range), states drifting by eq. 4-5, machine parameters drawn once per dataset, and the
measured stage-1 curve distorted by the deviation model (``g(FE)``, theta_d drawn), tracked
with the deviation estimated. Per dataset (``products`` products):

* ``fixed``: ``u`` at its nominal value (no control);
* ``ewma``: run-to-run EWMA on the measured final angles of earlier products
  (:class:`~formtwin.control.EwmaRunToRun`; gain from the metamodel, ``lam`` the best of
  :data:`R2R_LAMS` on the other datasets, measurements ``r2r_delay`` products late);
* ``feedforward``: feedforward plus feedback (:class:`~formtwin.control.Combined`): after
  each product's curve, :class:`~formtwin.control.Feedforward` over the tracker's
  particles (the metamodel's final angle at each candidate ``u``), aiming at the target
  minus a trim: an EWMA of its prediction error on the measured angles of earlier
  products, trusting a share of the posterior's product-to-product change learned on the
  line itself (``Combined(adaptive=True)``, starting at 0), with the persistence ``rho`` of
  the last product's deviation (the EWMA's weight and ``rho`` the best of :data:`FF_RHOS`
  on the other datasets): the service's default; ``feedforward_fixed`` the same with a
  fixed share (the best of :data:`FF_RHOS` x :data:`FF_WEIGHTS` on the other datasets);
  ``feedforward_full`` the whole change trusted and no persistence (weight 1, rho 0, its
  EWMA weight tuned likewise: the earlier sessions' controller); ``trim_only`` the
  feedforward's trim with weight 0 (the estimates' change unused: what the trim's
  time-series model alone gives); ``feedforward_open`` the feedforward without the trim;
* ``feedforward_angle``: ``feedforward`` with each measured final angle also entering the
  filter as a second measurement of its product's state
  (:func:`formtwin.tracker.fusion.update_angle`, likelihood sd the metamodel's held-out
  error of the final angle, offset the trim);
* ``oracle``: the same choice knowing the true state and machine parameters (the
  metamodel's angle at the true inputs): what a perfect estimate could give.

The physics model's final angle of every product is computed at three settings (the
actuator's limits and the nominal) and interpolated quadratically in ``u``
(:class:`PlantAngles`); ``interp_check`` products are also run at the chosen feedforward
setting to measure the interpolation error. Each controller respects the actuator's limits
and maximum step. The controllers' weights are chosen leave one dataset out: each dataset
is scored with the weights that did best on the others (every weight of the grids runs on
every dataset: one tracker pass each), so no dataset is scored with weights chosen on it;
the weights reported for the service are those best on all of them. "Best" is the least
mean over the datasets of the ratio of the final angle's std to that of fixed ``u`` on the
same dataset (each line counts alike; a mean of the stds lets the line of largest spread
choose). Scores: over the
products after ``burn_in``, pooled over datasets and within each.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.control import Actuator, EwmaRunToRun, Feedforward
from formtwin.dataset import DatasetError, DoeDataset, open_for_run
from formtwin.deviation import DeviationModel
from formtwin.doe import run_design
from formtwin.measurement import ProcessModel
from formtwin.production import ProductionRun, draw_production_run
from formtwin.simulator import Simulator
from formtwin.study.control_ff import ADAPTIVE, track_and_choose
from formtwin.tracker import TrackerConfig

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: the controllers compared
CONTROLLERS = ("fixed", "ewma", "feedforward", "oracle", "feedforward_open", "feedforward_fixed",
               "feedforward_full", "trim_only", "feedforward_angle")
#: EWMA weights tried for the run-to-run controller and the feedforward's trim
R2R_LAMS = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
#: shares of the posterior's product-to-product change tried for the feedforward
FF_WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
#: persistence of the last product's deviation from the level tried for the feedforward's
#: trim, each with the EWMA weights tried with it: without persistence a fast level (today's
#: EWMA), with it (the states' AR(1) coefficient of eq. 4, 0.7-0.8) a slow one (the grid
#: stays near the earlier 30 controllers: each costs a feedforward choice per product)
FF_RHOS = {0.0: (0.1, 0.3, 0.5, 0.7, 1.0), 0.7: (0.02, 0.05)}


@dataclass(frozen=True)
class ControlStudySettings:
    """Sizes and settings of the control study.

    Attributes
    ----------
    products, datasets : products per dataset, datasets (the benchmark's: 1000 x 5; each is scored
        with the weights chosen on the others, so at least 2).
    burn_in : first products of each dataset not scored (the filter's convergence).
    tracker : tracker settings (deviation estimated, mu mid-range: series 6).
    target : final angle wanted, degrees; ``None``: the metamodel's at the mid-range state,
        mid machine parameters and nominal setting, rounded to 0.1 deg.
    max_step : largest change of ``u`` per product as a share of its range.
    r2r_delay : products between a product and the use of its measured angle (1: the
        previous product's angle sets this one's ``u``).
    band : half-width of the tolerance band scored, degrees.
    interp_check : products per dataset also run at their feedforward setting.
    trim_lam : EWMA weight of the feedforward's trim (its prediction error on earlier
        products' measured angles, ``r2r_delay`` late); None: tuned (leave one dataset out).
    ff_weight : share of the posterior's product-to-product change the feedforward trusts;
        None: tuned with ``trim_lam`` and ``ff_rho`` (the best of :data:`FF_RHOS` x
        :data:`FF_WEIGHTS`).
    ff_rho : persistence of the last product's deviation in the trim
        (:class:`~formtwin.control.Combined`'s ``rho``); None: tuned with ``ff_weight``.
    angle_in_filter : also run the feedforward (learned weight) with the measured angles in
        the filter (``feedforward_angle``; needs ``r2r_delay`` 1).
    angle_sd : sd of that angle likelihood, degrees; None: the metamodel's held-out error
        of the final angle.
    seed : master seed.
    workers : physics worker processes, and datasets tracked at once.
    """

    products: int = 1000
    datasets: int = 6
    burn_in: int = 100
    tracker: TrackerConfig = field(default_factory=lambda: TrackerConfig(
        n_particles=500, estimate_deviation=True))
    target: float | None = None
    max_step: float = 0.25
    r2r_delay: int = 1
    band: float = 0.5
    interp_check: int = 20
    trim_lam: float | None = None
    ff_weight: float | None = None
    ff_rho: float | None = None
    angle_in_filter: bool = True
    angle_sd: float | None = None
    seed: int = 0
    workers: int | None = None

    def __post_init__(self) -> None:
        if self.datasets < 2:
            raise ValueError(f"datasets = {self.datasets}: the weights of each dataset are "
                             "chosen on the others, so at least 2 are needed")


class PlantAngles:
    """The plant's final angle of each product as a quadratic in ``u`` through its values
    at three settings.

    Parameters
    ----------
    u3 : (3,) the settings run (distinct).
    a3 : (n, 3) the final angles there, degrees (NaN where the run failed).
    """

    def __init__(self, u3: FloatArray, a3: FloatArray) -> None:
        self.u3 = np.asarray(u3, dtype=np.float64)
        self.a3 = np.asarray(a3, dtype=np.float64)

    def __call__(self, i: int, u: float) -> float:
        """Final angle of product ``i`` at setting ``u`` (Lagrange interpolation)."""
        (u0, u1, u2), (a0, a1, a2) = self.u3, self.a3[i]
        return float(a0 * (u - u1) * (u - u2) / ((u0 - u1) * (u0 - u2))
                     + a1 * (u - u0) * (u - u2) / ((u1 - u0) * (u1 - u2))
                     + a2 * (u - u0) * (u - u1) / ((u2 - u0) * (u2 - u1)))


def plant_path(folder: Path, k: int, version: str) -> Path:
    """The physics runs of dataset ``k``'s plant, one file per physics model version (a
    new version runs its own plant; the old one stays for reanalysis)."""
    return folder / f"plant_{k}_{version}.h5"


def plant_run(spec: Any, physics: Simulator, settings: ControlStudySettings, k: int,
              folder: Path
              ) -> tuple[ProductionRun, FloatArray, NDArray[np.bool_], PlantAngles]:
    """Dataset ``k``: its truth, the measured curves ``g(FE)`` (n, n_t) (NaN where the
    physics failed), the ok mask (n,) and the plant's angles."""
    rng = np.random.default_rng(np.random.SeedSequence([settings.seed, k]))
    run = draw_production_run(spec, settings.products, rng)  # mu, theta, theta_d drawn
    c = spec.controls
    u3 = np.array([c.lo[0], c.nominal[0], c.hi[0]])
    n = run.n
    X = np.vstack([spec.run_columns(run.inputs, float(u)) for u in u3])
    data: DoeDataset = run_design(physics, X, plant_path(folder, k, physics.version),
                                  executor="processes", workers=settings.workers,
                                  seed=settings.seed)
    ok: NDArray[np.bool_] = np.asarray(data.ok.reshape(3, n).all(axis=0), dtype=bool)
    a3 = data.angles[:, 1].reshape(3, n).T.copy()
    a3[~ok] = np.nan
    curves = data.curves[n: 2 * n].copy()  # the nominal runs (u acts after stage 1)
    g = DeviationModel.from_spec(spec)
    measured = g.apply(np.nan_to_num(curves), np.tile(run.theta_d, (n, 1)))
    measured[~ok] = np.nan
    return run, measured, ok, PlantAngles(u3, a3)


def metamodel_final(metamodel: ProcessModel, X: FloatArray, u: FloatArray) -> FloatArray:
    """Final angles (N, n_u) of the metamodel at inputs ``X`` (N, 10) and settings ``u``."""
    uu = np.asarray(u, dtype=np.float64).reshape(-1)
    rep = np.repeat(X, uu.size, axis=0)
    a = metamodel.predict_angles(rep, np.tile(uu, X.shape[0]))[:, 1]
    out: FloatArray = a.reshape(X.shape[0], uu.size)
    return out


def default_target(metamodel: ProcessModel) -> float:
    """The metamodel's final angle at the mid-range state and mid machine parameters at the
    nominal setting, rounded to 0.1 deg."""
    spec = metamodel.spec
    x = np.r_[spec.state.mu_mid, 0.5 * (spec.params.lo + spec.params.hi)][None, :]
    return round(float(metamodel_final(metamodel, x, spec.controls.nominal[:1])[0, 0]), 1)


def r2r_gain(metamodel: ProcessModel, rng: np.random.Generator, n: int = 200) -> float:
    """Mean slope d(final angle)/du of the metamodel over random inputs, deg per unit."""
    spec = metamodel.spec
    lo, hi = spec.inputs.lo, spec.inputs.hi
    X = lo + (hi - lo) * rng.random((n, lo.size))
    c = spec.controls
    a = metamodel_final(metamodel, X, np.array([c.lo[0], c.hi[0]]))
    return float(np.mean((a[:, 1] - a[:, 0]) / (c.hi[0] - c.lo[0])))


def study_controllers(metamodel: ProcessModel, settings: ControlStudySettings,
                      target: float) -> tuple[Actuator, Feedforward, float]:
    """The actuator, the feedforward and the nominal setting of the study."""
    c = metamodel.spec.controls
    act = Actuator(float(c.lo[0]), float(c.hi[0]),
                   settings.max_step * float(c.hi[0] - c.lo[0]))
    return act, Feedforward(target, act), float(c.nominal[0])


def controller_grid(settings: ControlStudySettings) -> list[tuple[float, float, float]]:
    """The combined feedforward's ``(lam, weight, rho)`` tried: :data:`FF_RHOS` x
    :data:`FF_WEIGHTS` (those the settings fix held), the earlier sessions' controller
    (weight 1, rho 0) with each of its ``lam`` values, and each ``(lam, rho)`` with the
    weight learned on the line (weight :data:`~formtwin.study.control_ff.ADAPTIVE`)."""
    weights = FF_WEIGHTS if settings.ff_weight is None else (settings.ff_weight,)
    rho_lams = dict(FF_RHOS) if settings.ff_rho is None else \
        {settings.ff_rho: FF_RHOS.get(settings.ff_rho, R2R_LAMS)}
    if settings.trim_lam is not None:
        rho_lams = {r: (settings.trim_lam,) for r in rho_lams}
    grid = {(lm, w, r) for r, lams in rho_lams.items() for lm in lams for w in weights}
    full_lams = FF_RHOS[0.0] if settings.trim_lam is None else (settings.trim_lam,)
    learned = {(lm, ADAPTIVE, r) for r, lams in rho_lams.items() for lm in lams}
    return sorted(grid | learned | {(lm, 1.0, 0.0) for lm in full_lams})


def choose_weights(ff_std: FloatArray, r2r_std: FloatArray, fixed_std: FloatArray,
                   grid: list[tuple[float, float, float]] | FloatArray) -> dict[str, float]:
    """The weights with the least mean within-dataset ratio over the datasets given (each
    controller's std over that of fixed ``u`` on the same dataset, ``fixed_std`` (K,)):
    ``ff_std`` (K, m) of the combined feedforward for each ``(lam, weight, rho)`` of
    ``grid`` (m, 3), ``r2r_std`` (K, len(:data:`R2R_LAMS`)) of the run-to-run EWMA; returns
    ``r2r_lam`` (EWMA), ``ff_lam`` and ``ff_rho`` (the feedforward: the weight learned on
    the line), ``fffixed_lam``, ``fffixed_weight`` and ``fffixed_rho`` (a fixed weight),
    ``full_lam`` (its trim's weight with the whole change trusted and rho 0).

    >>> g = [(0.1, -1.0, 0.7), (0.1, 0.0, 0.7), (0.1, 1.0, 0.0), (0.5, 1.0, 0.0)]
    >>> choose_weights(np.array([[0.1, 1.0, 2.0, 3.0], [0.1, 1.0, 0.5, 3.0]]),
    ...                np.ones((2, 8)), np.ones(2), g)  # doctest: +NORMALIZE_WHITESPACE
    {'r2r_lam': 0.02, 'ff_lam': 0.1, 'ff_rho': 0.7, 'fffixed_lam': 0.1,
     'fffixed_weight': 0.0, 'fffixed_rho': 0.7, 'full_lam': 0.1}

    A dataset of ten times the spread does not choose alone: weight 0 gives stds 1 and 10
    on two datasets, weight 0.5 gives 2 and 5; the mean std would choose 0.5, the mean
    ratio to fixed ``u`` (stds 1 and 10) chooses 0:

    >>> g = [(0.1, -1.0, 0.7), (0.1, 0.0, 0.7), (0.1, 0.5, 0.7), (0.1, 1.0, 0.0)]
    >>> choose_weights(np.array([[1.0, 1.0, 2.0, 9.0], [1.0, 10.0, 5.0, 90.0]]),
    ...                np.ones((2, 8)), np.array([1.0, 10.0]), g)["fffixed_weight"]
    0.0
    """
    g = np.asarray(grid, dtype=np.float64)
    scale = np.asarray(fixed_std, dtype=np.float64)[:, None]
    ff = np.mean(ff_std / scale, axis=0)
    full = np.flatnonzero((g[:, 1] == 1.0) & (g[:, 2] == 0.0))
    fixed, learned = np.flatnonzero(g[:, 1] != ADAPTIVE), np.flatnonzero(g[:, 1] == ADAPTIVE)
    if not learned.size:
        raise ValueError("choose_weights: no learned-weight controller in the grid")
    a = int(learned[np.argmin(ff[learned])])
    best = int(fixed[np.argmin(ff[fixed])])
    return {"r2r_lam": float(R2R_LAMS[int(np.argmin(np.mean(r2r_std / scale, axis=0)))]),
            "ff_lam": float(g[a, 0]), "ff_rho": float(g[a, 2]),
            "fffixed_lam": float(g[best, 0]), "fffixed_weight": float(g[best, 1]),
            "fffixed_rho": float(g[best, 2]),
            "full_lam": float(g[full[int(np.argmin(ff[full]))], 0])}


def run_dataset(metamodel: ProcessModel, physics: Simulator, settings: ControlStudySettings,
                k: int, folder: Path, target: float, gain: float) -> dict[str, Any]:
    """Every controller of every weight on dataset ``k`` (the choice among the weights is
    made across datasets afterwards, :func:`choose_weights`): the settings ``u_<name>`` (n,)
    and the plant's final angles ``angle_<name>`` (n,) of ``fixed``, ``oracle`` and
    ``feedforward_open``; ``u_grid``, ``angle_grid`` (m, n) and the predicted final angles
    ``pred_grid`` (m, n, 3) of the combined feedforward for each ``(lam, weight, rho)`` of
    ``grid`` (m, 3, :func:`controller_grid`); ``u_r2r``, ``angle_r2r`` (len(:data:`R2R_LAMS`),
    n) of the run-to-run EWMA; the posterior mean of the final angle at the nominal setting
    and of the run inputs, the true inputs and the metamodel's final angle there at the
    nominal setting."""
    spec = metamodel.spec
    run, curves, ok, plant = plant_run(spec, physics, settings, k, folder)
    n = run.n
    act, ff, nominal = study_controllers(metamodel, settings, target)
    grid = controller_grid(settings)
    # one tracker pass (series 6: deviation estimated, mu mid-range) for the open feedforward
    # and every combined one: the tracker does not depend on the settings chosen
    config = replace(settings.tracker, seed=settings.seed + k)
    p = track_and_choose(metamodel, config, curves, ok, plant, ff, [(0.0, 1.0, 0.0), *grid],
                         nominal, settings.r2r_delay)
    u = {"fixed": np.full(n, nominal), "feedforward_open": p.u[0], "oracle": np.full(n, nominal)}
    prev = nominal  # oracle: the true inputs, one particle
    for i in range(n):
        x = run.inputs[i: i + 1]

        def truth(uu: FloatArray, x: FloatArray = x) -> FloatArray:
            return metamodel_final(metamodel, x, uu)

        s = ff.choose(truth, u_prev=prev)
        prev = u["oracle"][i] = s.u

    def angles(us: FloatArray) -> FloatArray:
        return np.where(ok, [plant(i, us[i]) for i in range(n)], np.nan)

    out: dict[str, Any] = {"ok": ok, "target": target, "nominal_mean": p.nominal_mean,
                           "input_mean": p.input_mean, "inputs": run.inputs,
                           "truth_nominal": metamodel_final(metamodel, run.inputs,
                                                            np.array([nominal]))[:, 0],
                           "grid": np.array(grid), "u_grid": p.u[1:], "pred_grid": p.pred[1:],
                           "angle_grid": np.array([angles(v) for v in p.u[1:]])}
    out["u_r2r"] = np.array([r2r(plant, ok, n, target, gain, lm, act, nominal,
                                 settings.r2r_delay) for lm in R2R_LAMS])
    out["angle_r2r"] = np.array([angles(v) for v in out["u_r2r"]])
    for name, v in u.items():
        out[f"u_{name}"], out[f"angle_{name}"] = v, angles(v)
    return out


def finish_dataset(metamodel: ProcessModel, physics: Simulator,
                   settings: ControlStudySettings, k: int, folder: Path, target: float,
                   tuned: dict[str, float], u_ff: FloatArray) -> dict[str, Any]:
    """What needs dataset ``k``'s weights ``tuned``: the physics at ``interp_check`` of the
    feedforward's own settings ``u_ff`` (n,) (``interp_angle`` at products ``interp_idx``),
    and with ``angle_in_filter`` the feedforward with the measured angles in the filter
    (``u_feedforward_angle``, ``angle_feedforward_angle``, ``pred_angle``, ``angle_sd``)."""
    spec = metamodel.spec
    run, curves, ok, plant = plant_run(spec, physics, settings, k, folder)
    _, ff, nominal = study_controllers(metamodel, settings, target)
    out: dict[str, Any] = {}
    if settings.angle_in_filter:
        config = replace(settings.tracker, seed=settings.seed + k)
        best = (tuned["ff_lam"], ADAPTIVE, tuned["ff_rho"])
        q = track_and_choose(metamodel, config, curves, ok, plant, ff, [best], nominal,
                             settings.r2r_delay, angle_in_filter=True, sd=settings.angle_sd)
        out.update(u_feedforward_angle=q.u[0], pred_angle=q.pred[0], angle_sd=q.angle_sd,
                   angle_feedforward_angle=np.where(
                       ok, [plant(i, q.u[0][i]) for i in range(run.n)], np.nan))
    if settings.interp_check > 0:  # physics at the feedforward's own settings
        idx = np.flatnonzero(ok)[:: max(1, ok.sum() // settings.interp_check)]
        idx = idx[: settings.interp_check]
        X = spec.run_columns(run.inputs[idx], u_ff[idx])
        path = folder / f"check_{k}.h5"
        try:  # 20 runs: a file of other settings or another model version is replaced
            if path.exists():
                open_for_run(path, spec, X, physics.version).close()
        except DatasetError:
            path.unlink()
        chk = run_design(physics, X, path, executor="processes", workers=settings.workers,
                         seed=settings.seed)
        out.update(interp_idx=idx, interp_angle=chk.angles[:, 1])
    return out


def r2r(plant: Callable[[int, float], float], ok: NDArray[np.bool_], n: int, target: float,
        gain: float, lam: float, act: Actuator, nominal: float, delay: int) -> FloatArray:
    """Settings (n,) of the run-to-run EWMA controller on the measured angles ``plant(j,
    u)`` of product ``j`` made at ``u`` (a :class:`PlantAngles`, or one read by a noisy
    camera)."""
    ctl = EwmaRunToRun(target, gain, lam, act, u=nominal)
    u = np.full(n, nominal)
    for i in range(n):
        j = i - delay  # the newest product whose angle is known before product i
        if j >= 0 and ok[j]:
            ctl.update(plant(j, u[j]), u[j])
        u[i] = ctl.u
    return u


def scores(angles: FloatArray, target: float, band: float) -> dict[str, float]:
    """Mean error, std, RMSE and share within ``+-band`` of angles (finite ones)."""
    e = angles[np.isfinite(angles)] - target
    return {"mean_error_deg": round(float(e.mean()), 4), "std_deg": round(float(e.std()), 4),
            "rmse_deg": round(float(np.sqrt(np.mean(e * e))), 4),
            "within_band_share": round(float(np.mean(np.abs(e) <= band)), 4),
            "products": int(e.size)}


__all__ = ["CONTROLLERS", "FF_RHOS", "FF_WEIGHTS", "R2R_LAMS", "ControlStudySettings",
           "PlantAngles", "choose_weights", "controller_grid", "default_target", "finish_dataset",
           "metamodel_final", "plant_path", "plant_run", "r2r", "r2r_gain", "run_dataset",
           "scores"]
