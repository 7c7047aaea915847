"""Closed-loop control with the line's real sensors: the camera's noisy, late final angle and
the strip gauge.

The plants, trackers and controllers of the control study (:mod:`formtwin.study.control`:
series-6 conditions, the physics model as the plant) with two changes:

* the camera: every controller that reads a product's final angle (the run-to-run EWMA,
  the feedforward's trim) reads it with the camera's Gaussian error of sd ``s`` in
  :data:`CAMERA_NOISES` (degrees), one product late; the plant's own angle, the one
  scored, stays exact. The errors are one standard normal draw per product and dataset
  (its own random stream), scaled by ``s``, so the noise levels share their draws;
* the posterior the feedforward chooses on: ``curve`` the stage-1 curve alone (the
  paper), ``gauge`` the curve and the strip gauge's thickness of the same product
  (the spec's noise, 0.5 um), fused into the product's step (known before its curve,
  :mod:`formtwin.tracker.ahead`) before the setting is chosen.

Per dataset, camera noise and set, three feedforwards:

* ``predictive`` (:class:`~formtwin.control.Predictive`): the feedforward on the posterior
  predictive of the measured final angle, the camera's values (moved to the nominal setting
  by the posterior's own gain) teaching a discrepancy of the posterior's predicted angle
  (:class:`~formtwin.tracker.angle_discrepancy.AngleDiscrepancy`: bias and slope by
  Kalman updates whose gain follows the camera's noise, hypotheses weighted by their
  evidence); nothing tuned on the datasets;
* ``fused`` (at the spec's camera noise only): the same with the camera's values also fused
  into the particles (:meth:`~formtwin.tracker.Tracker.fuse`, one tracker pass of its own:
  the posterior then depends on the settings chosen): the feedforward on the fused
  posterior;
* the earlier controller (:class:`~formtwin.control.Combined`, the weight learned on the
  line) with each ``(lam, rho)`` of :data:`GRID`, an EWMA trim of the raw camera values.

The run-to-run EWMA runs with each weight of :data:`~formtwin.study.control.R2R_LAMS`. As in
the control study, dataset ``k`` is scored with the weights best on the other datasets
(least mean ratio of the final angle's std to fixed ``u``'s), and the figure is the median
over the datasets of the feedforward's std over the EWMA's (within each dataset, after
``burn_in``). :func:`reference_limit` is what a feedforward linear in the posterior's
predicted angle could reach on the same lines with the best coefficients known.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.control import Predictive
from formtwin.measurement import ProcessModel
from formtwin.simulator import Simulator
from formtwin.spec.sensors import line_sensors, sensor_by_name
from formtwin.study.control import (
    R2R_LAMS,
    ControlStudySettings,
    default_target,
    metamodel_final,
    plant_run,
    r2r,
    r2r_gain,
    study_controllers,
)
from formtwin.study.control_ff import ADAPTIVE, track_and_choose
from formtwin.study.control_run import load_result, result_key, save_result
from formtwin.tracker.angle_discrepancy import AngleDiscrepancy
from formtwin.tracker.discrepancy import angle_residual_variance

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: the camera's noise sd tried, degrees (0: the plant's exact angle, as the control study)
CAMERA_NOISES = (0.0, 0.1, 0.2)
#: the posteriors the feedforward chooses on: name -> sensors fused besides the curve
SETS: dict[str, tuple[str, ...]] = {"curve": (), "gauge": ("gauge",)}
#: the feedforward's ``(lam, rho)`` tried (the weight learned on the line): the trim's EWMA
#: weight, the persistence of the last product's deviation (a noisy camera wants small ones)
GRID = tuple((lam, rho) for rho in (0.0, 0.7) for lam in (0.02, 0.05, 0.1))
#: the sensor the closed loop reads the final angle with (its noise the spec's for the
#: pass with the camera fused into the particles)
CAMERA = "camera"


@dataclass(frozen=True)
class SensorControlSettings:
    """Settings of the closed-loop study with sensors.

    Attributes
    ----------
    base : the control study's settings (products, datasets, burn-in, tracker, seed...).
    camera_noises : the camera's noise sds, degrees.
    sets : names of :data:`SETS` run.
    grid : the earlier feedforward's ``(lam, rho)`` tried (:data:`GRID`; each costs a
        feedforward choice per product and camera noise).
    """

    base: ControlStudySettings = field(default_factory=ControlStudySettings)
    camera_noises: tuple[float, ...] = CAMERA_NOISES
    sets: tuple[str, ...] = tuple(SETS)
    grid: tuple[tuple[float, float], ...] = GRID

    def __post_init__(self) -> None:
        bad = [s for s in self.sets if s not in SETS]
        if bad:
            raise ValueError(f"sets = {bad}: unknown, expected some of {', '.join(SETS)}")
        if not all(np.isfinite(s) and s >= 0 for s in self.camera_noises):
            raise ValueError(f"camera_noises = {self.camera_noises}: expected sds >= 0 deg")


def sensor_draws(seed: int, k: int, n: int) -> tuple[FloatArray, FloatArray]:
    """Standard normals (n,) of the camera and of the gauge of dataset ``k``: children 0 and
    1 of ``SeedSequence([seed, k])`` (the plant draws from the sequence itself)."""
    cam, gauge = np.random.SeedSequence([seed, k]).spawn(2)
    return (np.random.default_rng(cam).standard_normal(n),
            np.random.default_rng(gauge).standard_normal(n))


def sensor_dataset(metamodel: ProcessModel, physics: Simulator,
                   settings: SensorControlSettings, k: int, folder: Path, target: float,
                   gain: float) -> dict[str, Any]:
    """Dataset ``k``'s plant angles (n,) under fixed ``u`` (``angle_fixed``) and the oracle
    (``angle_oracle``); per camera noise ``c`` (index into ``camera_noises``) those of the
    EWMA for each weight, ``angle_r2r_<c>`` (len(R2R_LAMS), n), and per set those of the
    feedforward for each ``(lam, rho)`` of :data:`GRID`, ``angle_<set>_<c>``
    (len(GRID), n)."""
    base = settings.base
    spec = metamodel.spec
    run, curves, ok, plant = plant_run(spec, physics, base, k, folder)
    n = run.n
    act, ff, nominal = study_controllers(metamodel, base, target)
    z_cam, z_gauge = sensor_draws(base.seed, k, n)
    noises = np.asarray(settings.camera_noises, dtype=np.float64)

    def angles(us: FloatArray) -> FloatArray:
        return np.where(ok, [plant(i, us[i]) for i in range(n)], np.nan)

    out: dict[str, Any] = {"ok": ok, "angle_fixed": angles(np.full(n, nominal))}
    u_or, prev = np.full(n, nominal), nominal  # the oracle: the true inputs
    for i in range(n):
        def truth(uu: FloatArray, x: FloatArray = run.inputs[i: i + 1]) -> FloatArray:
            return metamodel_final(metamodel, x, uu)

        prev = u_or[i] = ff.choose(truth, u_prev=prev).u
    out["angle_oracle"] = angles(u_or)
    for c, sd in enumerate(noises):
        def camera(j: int, u: float, sd: float = float(sd)) -> float:
            return plant(j, u) + sd * float(z_cam[j])
        out[f"angle_r2r_{c}"] = np.array([angles(r2r(camera, ok, n, target, gain, lam, act,
                                                     nominal, base.r2r_delay))
                                          for lam in R2R_LAMS])
    grid = settings.grid
    controllers = [(lam, ADAPTIVE, rho) for _ in noises for lam, rho in grid]
    noise = np.vstack([np.repeat(noises[:, None] * z_cam[None, :], len(grid), axis=0),
                       noises[:, None] * z_cam[None, :]])
    sensors = line_sensors(spec)
    gauge, cam = sensor_by_name(sensors, "gauge"), sensor_by_name(sensors, CAMERA)
    thickness = run.x[:, spec.state.index[gauge.measures]] + gauge.noise * z_gauge
    var = angle_residual_variance(metamodel)
    model_var = 0.0 if var is None else float(var[1])

    def predictive(sd: float) -> Predictive:  # the discrepancy's prior: noise and model
        return Predictive(ff, AngleDiscrepancy(max(sd**2 + model_var, 1e-6)), nominal)

    out["nominal"] = np.full(n, nominal)
    for name in settings.sets:
        config = replace(base.tracker, seed=base.seed + k, sensors=SETS[name])
        readings = {"gauge": thickness} if "gauge" in SETS[name] else None
        p = track_and_choose(metamodel, config, curves, ok, plant, ff, controllers, nominal,
                             base.r2r_delay, noise=noise, readings=readings,
                             predictive=[predictive(float(sd)) for sd in noises])
        out[f"reference_{name}"] = p.nominal_mean
        for c in range(noises.size):
            rows = p.u[c * len(grid):(c + 1) * len(grid)]
            out[f"angle_{name}_{c}"] = np.array([angles(v) for v in rows])
            out[f"angle_{name}_predictive_{c}"] = angles(p.u[len(controllers) + c])
        # the camera fused into the particles too: one pass at the spec's camera noise
        config = replace(config, sensors=(*SETS[name], CAMERA))
        q = track_and_choose(metamodel, config, curves, ok, plant, ff, [], nominal,
                             base.r2r_delay, noise=cam.noise * z_cam[None, :],
                             readings=readings, predictive=[predictive(cam.noise)],
                             camera=CAMERA)
        out[f"angle_{name}_fused"] = angles(q.u[0])
        out[f"reference_{name}_fused"] = q.nominal_mean
    return out


def _run(args: tuple[Any, ...]) -> dict[str, Any]:
    """:func:`sensor_dataset` of one argument tuple (for a pool)."""
    log.info("control study with sensors: dataset %d", args[3])
    return sensor_dataset(*args)


def loo_ratios(ff_std: FloatArray, r2r_std: FloatArray, fixed_std: FloatArray
               ) -> tuple[FloatArray, list[int], list[int]]:
    """Per dataset ``k``: the feedforward's std over the EWMA's, each with the weights best
    on the other datasets (least mean ratio to fixed ``u``'s std); ``ff_std`` (K, m),
    ``r2r_std`` (K, r), ``fixed_std`` (K,). Returns the ratios (K,) and the indices chosen.

    >>> ff = np.array([[1.0, 2.0], [1.0, 2.0], [3.0, 1.0]])
    >>> ratio, a, b = loo_ratios(ff, np.full((3, 1), 2.0), np.ones(3))
    >>> ratio.tolist(), a  # datasets 0, 1 scored with column 1 (best on the others), 2 with 0
    ([1.0, 1.0, 1.5], [1, 1, 0])
    """
    scale = np.asarray(fixed_std, dtype=np.float64)[:, None]
    K = ff_std.shape[0]
    a = [int(np.argmin(np.mean(np.delete(ff_std / scale, k, 0), axis=0))) for k in range(K)]
    b = [int(np.argmin(np.mean(np.delete(r2r_std / scale, k, 0), axis=0))) for k in range(K)]
    ratio = np.array([ff_std[k, a[k]] / r2r_std[k, b[k]] for k in range(K)])
    return ratio, a, b


def reference_limit(results: list[dict[str, Any]], name: str, c: int, burn_in: int,
                    fixed: FloatArray, r2r_std: FloatArray) -> dict[str, Any]:
    """What a feedforward linear in the posterior's reference angle ``c_i`` (``reference_
    <name>``) can reach at best: per dataset ``sqrt(1 - r^2)`` times fixed ``u``'s std, ``r``
    the correlation of ``c_i`` with the plant's angle at the nominal setting after
    ``burn_in`` (the best level and slope known, no learning cost, the camera's
    persistence of the states unused), over the EWMA's std at camera noise ``c`` (its
    weight chosen on the other datasets); the median and the correlations."""
    corr = []
    for r in results:
        x, y = r[f"reference_{name}"][burn_in:], r["angle_fixed"][burn_in:]
        ok = np.isfinite(x) & np.isfinite(y)
        corr.append(float(np.corrcoef(x[ok], y[ok])[0, 1]))
    r2 = np.square(corr)
    limit = np.sqrt(1.0 - r2) * fixed
    ratio = loo_ratios(limit[:, None], r2r_std, fixed)[0]
    return {"ff_vs_ewma_median": round(float(np.median(ratio)), 4),
            "per_dataset": np.round(ratio, 3).tolist(), "corr": np.round(corr, 3).tolist()}


def run_sensor_control(metamodel: ProcessModel, physics: Simulator,
                       settings: SensorControlSettings, out: str | Path) -> dict[str, Any]:
    """Run (or reuse, ``sensors_<k>.npz`` in ``out``) every dataset and score it; returns
    per set and camera noise (``<set>`` -> ``"<sd>"``) the within-dataset ratios
    ``ff_vs_ewma`` (per dataset and their median), the stds of the feedforward, the EWMA,
    fixed ``u`` and the oracle (mean over datasets, degrees) and the weights chosen on
    all datasets."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = settings.base
    target = default_target(metamodel) if base.target is None else base.target
    gain = r2r_gain(metamodel, np.random.default_rng(base.seed))
    key = result_key(base, target, str(getattr(physics, "version", "")), metamodel) + repr(
        (settings.camera_noises, settings.sets, settings.grid, R2R_LAMS, "predictive", CAMERA))
    paths = [out / f"sensors_{k}.npz" for k in range(base.datasets)]
    res = [load_result(p, key) for p in paths]
    todo = [k for k, r in enumerate(res) if r is None]
    for k in todo:  # the plants first, one after the other (their physics uses the workers)
        plant_run(metamodel.spec, physics, base, k, out)
    args = [(metamodel, physics, settings, k, out, target, gain) for k in todo]
    workers = min(base.workers or os.cpu_count() or 1, max(len(todo), 1))
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(
                "forkserver")) as pool:
            done = list(pool.map(_run, args))
    else:
        done = [_run(a) for a in args]
    for k, r in zip(todo, done, strict=True):
        save_result(paths[k], key, r)
        res[k] = r
    results = [r for r in res if r is not None]
    b = base.burn_in

    def std(name: str) -> FloatArray:
        return np.array([np.nanstd(r[name][..., b:], axis=-1) for r in results])

    fixed, oracle = std("angle_fixed"), std("angle_oracle")
    cam_sd = sensor_by_name(line_sensors(metamodel.spec), CAMERA).noise
    summary: dict[str, Any] = {}

    def vs_ewma(ff: FloatArray, c: int) -> dict[str, Any]:
        """One controller's stds (K,) over the EWMA's at camera noise ``c``."""
        ratio = loo_ratios(ff[:, None], std(f"angle_r2r_{c}"), fixed)[0]
        return {"ff_vs_ewma": {"per_dataset": np.round(ratio, 3).tolist(),
                               "median": round(float(np.median(ratio)), 4)},
                "ff_std_deg": round(float(np.mean(ff)), 4)}

    for name in settings.sets:
        summary[name] = {}
        for c, sd in enumerate(settings.camera_noises):
            ff, ew = std(f"angle_{name}_{c}"), std(f"angle_r2r_{c}")
            ratio, a, e = loo_ratios(ff, ew, fixed)
            best = int(np.argmin(np.mean(ff / fixed[:, None], axis=0)))
            summary[name][f"{sd:g}"] = {
                "predictive": vs_ewma(std(f"angle_{name}_predictive_{c}"), c),
                "reference_limit": reference_limit(results, name, c, b, fixed,
                                                   std(f"angle_r2r_{c}")),
                "ff_vs_ewma": {"per_dataset": np.round(ratio, 3).tolist(),
                               "median": round(float(np.median(ratio)), 4)},
                "ff_vs_oracle_median": round(float(np.median(
                    [ff[k, a[k]] / oracle[k] for k in range(len(results))])), 4)
                if np.all(oracle > 1e-9 * fixed) else None,  # an oracle on target: no ratio
                "ff_std_deg": round(float(np.mean([ff[k, a[k]] for k in range(len(a))])), 4),
                "ewma_std_deg": round(float(np.mean([ew[k, e[k]] for k in range(len(e))])), 4),
                "ff_lam": settings.grid[best][0], "ff_rho": settings.grid[best][1],
                "ewma_lam": R2R_LAMS[int(np.argmin(np.mean(ew / fixed[:, None], axis=0)))]}
        cf = next((c for c, sd in enumerate(settings.camera_noises) if sd == cam_sd), None)
        if cf is not None:  # the camera fused into the particles too, at the spec's noise
            summary[name]["fused"] = {
                "camera_deg": cam_sd, **vs_ewma(std(f"angle_{name}_fused"), cf),
                "reference_limit": reference_limit(results, f"{name}_fused", cf, b, fixed,
                                                   std(f"angle_r2r_{cf}"))}
    summary["fixed_std_deg"] = round(float(np.mean(fixed)), 4)
    summary["oracle_std_deg"] = round(float(np.mean(oracle)), 4)
    summary["target_deg"] = target
    summary["settings"] = {
        "camera_noises_deg": list(settings.camera_noises), "sets": list(settings.sets),
        "grid_lam_rho": [list(g) for g in settings.grid], "r2r_lams": list(R2R_LAMS),
        **{k: v for k, v in dataclasses.asdict(base).items() if k != "tracker"},
        "tracker": base.tracker.to_dict()}
    return summary


__all__ = ["CAMERA", "CAMERA_NOISES", "GRID", "SETS", "SensorControlSettings", "loo_ratios",
           "reference_limit", "run_sensor_control", "sensor_dataset", "sensor_draws"]
