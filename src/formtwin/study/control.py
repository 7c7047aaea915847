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
  :data:`R2R_LAMS` on the tuning datasets, measurements ``r2r_delay`` products late);
* ``feedforward``: feedforward plus feedback (:class:`~formtwin.control.Combined`): after
  each product's curve, :class:`~formtwin.control.Feedforward` over the tracker's
  particles (the metamodel's final angle at each candidate ``u``), aiming at the target
  minus a trim: an EWMA of its prediction error on the measured angles of earlier
  products, trusting a share ``weight`` of the posterior's product-to-product change, with
  the persistence ``rho`` of the last product's deviation (the EWMA's weight, the share and
  ``rho`` the best of :data:`FF_RHOS` x :data:`FF_WEIGHTS` on the tuning datasets, each
  ``rho`` with its ``lam`` values); ``feedforward_full`` the same with the whole change
  trusted and no persistence (weight 1, rho 0, its EWMA weight tuned likewise: the earlier
  sessions' controller); ``trim_only`` the tuned one with weight 0 (the estimates' change unused:
  what the trim's time-series model alone gives); ``feedforward_open`` the feedforward
  without the trim;
* ``feedforward_angle``: ``feedforward`` with each measured final angle also entering the
  filter as a second measurement of its product's state
  (:func:`formtwin.tracker.angle.update_angle`, likelihood sd the metamodel's held-out
  error of the final angle, offset the trim);
* ``oracle``: the same choice knowing the true state and machine parameters (the
  metamodel's angle at the true inputs): what a perfect estimate could give.

The physics model's final angle of every product is computed at three settings (the
actuator's limits and the nominal) and interpolated quadratically in ``u``
(:class:`PlantAngles`); ``interp_check`` products are also run at the chosen feedforward
setting to measure the interpolation error. Each controller respects the actuator's limits
and maximum step. The controllers' weights are tuned on ``tune_datasets`` datasets of their
own (seeds apart from the scored ones) and scored on the ``datasets`` others. Scores: over
the products after ``burn_in``, pooled over datasets and within each.
"""

from __future__ import annotations

import logging
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
from formtwin.study.control_ff import track_and_choose
from formtwin.tracker import TrackerConfig

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: the controllers compared
CONTROLLERS = ("fixed", "ewma", "feedforward", "oracle", "feedforward_open", "feedforward_full",
               "trim_only", "feedforward_angle")
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
    products, datasets : products per dataset, datasets (issue: 1000 x 5).
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
        products' measured angles, ``r2r_delay`` late); None: tuned (see ``tune_datasets``).
    ff_weight : share of the posterior's product-to-product change the feedforward trusts;
        None: tuned with ``trim_lam`` and ``ff_rho`` (the best of :data:`FF_RHOS` x
        :data:`FF_WEIGHTS`).
    ff_rho : persistence of the last product's deviation in the trim
        (:class:`~formtwin.control.Combined`'s ``rho``); None: tuned with ``ff_weight``.
    tune_datasets : datasets (indices ``datasets`` onwards: seeds apart from the scored
        ones) on which the EWMA weights and ``ff_weight`` are tuned, not scored; 0: tuned on
        the first scored dataset.
    angle_in_filter : also run the combined feedforward with the measured angles in the
        filter (``feedforward_angle``; needs ``r2r_delay`` 1).
    angle_sd : sd of that angle likelihood, degrees; None: the metamodel's held-out error
        of the final angle.
    seed : master seed.
    workers : physics worker processes.
    """

    products: int = 1000
    datasets: int = 5
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
    tune_datasets: int = 1
    angle_in_filter: bool = True
    angle_sd: float | None = None
    seed: int = 0
    workers: int | None = None


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


def _setup(metamodel: ProcessModel, settings: ControlStudySettings, target: float
           ) -> tuple[Actuator, Feedforward, float]:
    """The actuator, the feedforward and the nominal setting of the study."""
    c = metamodel.spec.controls
    act = Actuator(float(c.lo[0]), float(c.hi[0]),
                   settings.max_step * float(c.hi[0] - c.lo[0]))
    return act, Feedforward(target, act), float(c.nominal[0])


def _std(plant: PlantAngles, ok: NDArray[np.bool_], u: FloatArray, burn_in: int) -> float:
    """Std of the plant's final angle at settings ``u`` (n,) over the scored products."""
    return float(np.nanstd([plant(i, u[i]) for i in range(burn_in, u.size) if ok[i]]))


def tune_dataset(metamodel: ProcessModel, physics: Simulator, settings: ControlStudySettings,
                 k: int, folder: Path, target: float, gain: float) -> dict[str, Any]:
    """The weights' grids on dataset ``k`` (a tuning dataset): the std of the final angle
    (after ``burn_in``) of the combined feedforward for every ``(lam, weight)`` of
    ``ff_grid`` (``ff_std``) and of the run-to-run EWMA for every ``r2r_lams``
    (``r2r_std``)."""
    run, curves, ok, plant = plant_run(metamodel.spec, physics, settings, k, folder)
    act, ff, nominal = _setup(metamodel, settings, target)
    weights = FF_WEIGHTS if settings.ff_weight is None else (settings.ff_weight,)
    rho_lams = dict(FF_RHOS) if settings.ff_rho is None else \
        {settings.ff_rho: FF_RHOS.get(settings.ff_rho, R2R_LAMS)}
    if settings.trim_lam is not None:
        rho_lams = {r: (settings.trim_lam,) for r in rho_lams}
    grid_set = {(lm, w, r) for r, lams in rho_lams.items() for lm in lams for w in weights}
    # the earlier sessions' controller (weight 1, rho 0) is scored too, its lam tuned as well
    full_lams = FF_RHOS[0.0] if settings.trim_lam is None else (settings.trim_lam,)
    grid = sorted(grid_set | {(lm, 1.0, 0.0) for lm in full_lams})
    config = replace(settings.tracker, seed=settings.seed + k)
    p = track_and_choose(metamodel, config, curves, ok, plant, ff, grid, nominal,
                         settings.r2r_delay)
    b = settings.burn_in
    r2r_std = [_std(plant, ok, r2r(plant, ok, run.n, target, gain, lm, act, nominal,
                                   settings.r2r_delay), b) for lm in R2R_LAMS]
    return {"ff_grid": np.array(grid), "ff_std": np.array([_std(plant, ok, p.u[c], b)
                                                          for c in range(len(grid))]),
            "r2r_lams": np.array(R2R_LAMS), "r2r_std": np.array(r2r_std),
            "angle_nominal": np.where(ok, [plant(i, nominal) for i in range(run.n)], np.nan),
            "nominal_mean": p.nominal_mean}


def choose_weights(tunes: list[dict[str, Any]]) -> dict[str, float]:
    """The weights with the least mean std over the tuning datasets: ``r2r_lam`` (EWMA),
    ``ff_lam``, ``ff_weight`` and ``ff_rho`` (combined feedforward), ``full_lam`` (its
    trim's weight with the whole change trusted and rho 0)."""
    ff = np.mean([t["ff_std"] for t in tunes], axis=0)
    grid = tunes[0]["ff_grid"]
    full = np.flatnonzero((grid[:, 1] == 1.0) & (grid[:, 2] == 0.0))
    r2r_std = np.mean([t["r2r_std"] for t in tunes], axis=0)
    best = int(np.argmin(ff))
    return {"r2r_lam": float(tunes[0]["r2r_lams"][int(np.argmin(r2r_std))]),
            "ff_lam": float(grid[best, 0]), "ff_weight": float(grid[best, 1]),
            "ff_rho": float(grid[best, 2]),
            "full_lam": float(grid[full[int(np.argmin(ff[full]))], 0])}


def run_dataset(metamodel: ProcessModel, physics: Simulator, settings: ControlStudySettings,
                k: int, folder: Path, target: float, gain: float, tuned: dict[str, float]
                ) -> dict[str, Any]:
    """All controllers on dataset ``k`` with the weights ``tuned``
    (:func:`choose_weights`): per controller the settings ``u`` (n,) and the plant's final
    angles (n,); the feedforward's predicted means and intervals, the posterior mean of the
    final angle at the nominal setting and of the run inputs, the true inputs and the
    metamodel's final angle there at the nominal setting."""
    spec = metamodel.spec
    run, curves, ok, plant = plant_run(spec, physics, settings, k, folder)
    n = run.n
    act, ff, nominal = _setup(metamodel, settings, target)
    names = [c for c in CONTROLLERS if c != "feedforward_angle" or settings.angle_in_filter]
    u = {name: np.full(n, nominal) for name in names}
    # feedforward from the tracker (series 6: deviation estimated, mu mid-range): open, the
    # combined one with the tuned weights, and with the whole change trusted
    config = replace(settings.tracker, seed=settings.seed + k)
    best = (tuned["ff_lam"], tuned["ff_weight"], tuned["ff_rho"])
    p = track_and_choose(metamodel, config, curves, ok, plant, ff,
                         [(0.0, 1.0, 0.0), best, (tuned["full_lam"], 1.0, 0.0),
                          (tuned["ff_lam"], 0.0, tuned["ff_rho"])], nominal,
                         settings.r2r_delay)
    u["feedforward_open"], u["feedforward"], u["feedforward_full"], u["trim_only"] = p.u
    out: dict[str, Any] = {"ok": ok, "target": target, "pred": p.pred[1],
                           "nominal_mean": p.nominal_mean, **tuned,
                           "input_mean": p.input_mean, "inputs": run.inputs,
                           "truth_nominal": metamodel_final(metamodel, run.inputs,
                                                            np.array([nominal]))[:, 0]}
    if settings.angle_in_filter:
        q = track_and_choose(metamodel, config, curves, ok, plant, ff, [best], nominal,
                             settings.r2r_delay, angle_in_filter=True, sd=settings.angle_sd)
        u["feedforward_angle"] = q.u[0]
        out.update(pred_angle=q.pred[0], angle_sd=q.angle_sd)
    # oracle: the true inputs, one particle
    prev = nominal
    for i in range(n):
        x = run.inputs[i: i + 1]

        def truth(uu: FloatArray, x: FloatArray = x) -> FloatArray:
            return metamodel_final(metamodel, x, uu)

        s = ff.choose(truth, u_prev=prev)
        prev = u["oracle"][i] = s.u
    u["ewma"] = r2r(plant, ok, n, target, gain, tuned["r2r_lam"], act, nominal,
                    settings.r2r_delay)
    for name in names:
        out[f"u_{name}"] = u[name]
        out[f"angle_{name}"] = np.where(ok, [plant(i, u[name][i]) for i in range(n)], np.nan)
    if settings.interp_check > 0:  # physics at the feedforward's own settings
        idx = np.flatnonzero(ok)[:: max(1, ok.sum() // settings.interp_check)]
        idx = idx[: settings.interp_check]
        X = spec.run_columns(run.inputs[idx], u["feedforward"][idx])
        path = folder / f"check_{k}.h5"
        try:  # 20 runs: a file of other settings or another model version is replaced
            if path.exists():
                open_for_run(path, spec, X, physics.version).close()
        except DatasetError:
            path.unlink()
        chk = run_design(physics, X, path, executor="processes", workers=settings.workers,
                         seed=settings.seed)
        out["interp_error"] = chk.angles[:, 1] - out["angle_feedforward"][idx]
    return out


def r2r(plant: PlantAngles, ok: NDArray[np.bool_], n: int, target: float, gain: float,
        lam: float, act: Actuator, nominal: float, delay: int) -> FloatArray:
    """Settings (n,) of the run-to-run EWMA controller on the plant's measured angles."""
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
           "PlantAngles", "choose_weights", "default_target", "metamodel_final", "plant_path",
           "plant_run", "r2r", "r2r_gain", "run_dataset", "scores", "tune_dataset"]
