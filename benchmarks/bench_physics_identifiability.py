"""What limits the series-1 final-angle nRMSE: a linear-Gaussian analysis.

Series 1 of the study is metamodel data tracked with the metamodel (mu known), so its error
is identifiability, not model error. For each of the study's realisations (``--seed``,
``--realisations``: the same mu and theta as the study draws) this script takes the bundled
metamodel's Jacobian of the stage-1 curve, the stage-1 angle and the final angle with
respect to the seven state variables (central differences of half a sigma, theta at the
realisation's value, nominal u) and computes:

- the final angle's in-run standard deviation (``sqrt(sum (dA/dx_i sigma_i)^2)``, deg) and
  each state variable's share of its variance;
- the steady-state Kalman filter of the AR(1) state (``x_k - mu = rho (x_{k-1} - mu) + w``,
  the filter's own model) observing the curve with the filter's likelihood covariance
  (``K_MC/4 + sigma_n^2`` as the paper, ``"paper"``; plus the metamodel's held-out residual
  covariance ``K_res``, ``"calibrated"``): each variable's posterior std over its sigma and the
  final angle's nRMSE (posterior std of the final angle over its in-run std, the study's
  normalisation);
- the same with the stage-1 angle measured too (its held-out metamodel error as noise),
  with one curve and no memory (stationary prior), with the variables the curve identifies
  (posterior/prior < 0.5) known exactly and the others at their AR(1) prediction, with
  thickness and/or yield stress known, a 0.5 um thickness gauge, and with the final angle's
  sensitivity to the punch end distance scaled by 2, 4, 8, to yield stress by 2, 4, to
  thickness (and yield stress) by 0.5, 0.25 (what the physics would need).

``--study DIR`` (a study output folder: ``data/realisation_K.nc``, ``runs/``) adds the
study's own series-1 figures for comparison: the final angle's nRMSE and each variable's
mean posterior std over sigma (last 500 products, repetitions averaged).

Run: ``python benchmarks/bench_physics_identifiability.py [--study DIR]`` (~1 min CPU,
the bundled metamodel from the cache); writes
``benchmarks/results/bench_physics_identifiability.json``.
"""

from __future__ import annotations

import argparse
import glob
import os
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from formtwin._bench import bundled_metamodel, write_result  # noqa: E402
from formtwin.tracker import TrackerConfig, build_measurement  # noqa: E402
from formtwin.tracker.discrepancy import (  # noqa: E402
    angle_residual_variance,
    residual_covariance,
)

FloatArray = np.ndarray


def steady_kalman(H: FloatArray, R: FloatArray, rho: FloatArray, sigma: FloatArray,
                  n_iter: int = 500) -> FloatArray:
    """Filtered covariance (d, d) of the AR(1) state with stationary std ``sigma`` and
    autocorrelation ``rho`` (d,), observed as ``y = H x + v``, ``v ~ N(0, R)``, at steady
    state (Riccati recursion from the stationary covariance)."""
    F = np.diag(rho)
    Q = np.diag((sigma * np.sqrt(1.0 - rho**2)) ** 2)
    P = np.diag(sigma**2)
    eye = np.eye(sigma.size)
    for _ in range(n_iter):
        Pp = F @ P @ F.T + Q
        K = np.linalg.solve(H @ Pp @ H.T + R, H @ Pp).T
        P = (eye - K @ H) @ Pp
        P = 0.5 * (P + P.T)
    return P


def jacobian(mm: Any, x0: FloatArray, sigma: FloatArray) -> FloatArray:
    """d(curve (n_t), angle 1, final angle)/d(state) (n_t + 2, 7) at ``x0`` (10,), nominal u."""
    n_t = mm.spec.n_t
    J = np.zeros((n_t + 2, sigma.size))
    for i, s in enumerate(sigma):
        X = np.tile(x0, (2, 1))
        X[0, i] += 0.5 * s
        X[1, i] -= 0.5 * s
        c, a = mm.predict_curves(X), mm.predict_angles(X, 0.0)
        J[:n_t, i] = (c[0] - c[1]) / s
        J[n_t:, i] = (a[0] - a[1]) / s
    return J


def augmented(H: FloatArray, R: FloatArray, rows: FloatArray, var: FloatArray
              ) -> tuple[FloatArray, FloatArray]:
    """``H, R`` with extra independent observations ``rows (m, d)`` of variances ``var (m,)``."""
    n, m = R.shape[0], rows.shape[0]
    R2 = np.zeros((n + m, n + m))
    R2[:n, :n] = R
    R2[n:, n:] = np.diag(var)
    return np.vstack([H, rows]), R2


def realisation(mm: Any, k: int, seed: int, n_mc: int) -> dict[str, Any]:
    """All figures of realisation ``k`` (mu, theta drawn as the study draws them)."""
    spec = mm.spec
    st = spec.state
    sigma, rho = np.asarray(st.sigma, float), np.asarray(st.rho, float)
    d = sigma.size
    rng = np.random.default_rng(np.random.SeedSequence([seed, k]))
    mu = rng.uniform(st.mu_min, st.mu_max)
    theta = rng.uniform(spec.params.lo, spec.params.hi)
    J = jacobian(mm, np.r_[mu, theta], sigma)
    n_t = spec.n_t
    Hc, h1, a = J[:n_t], J[n_t], J[n_t + 1]
    var_a = float(np.sum((a * sigma) ** 2))
    config = TrackerConfig(mu=tuple(float(v) for v in mu), likelihood="paper", n_mc=n_mc)
    R_paper = build_measurement(mm, config, np.random.default_rng([seed, 7919, 1])).covariance()
    k_res = residual_covariance(mm)
    a_var = angle_residual_variance(mm)
    eye = np.eye(d)

    def nrmse(H: FloatArray, R: FloatArray, grad: FloatArray = a) -> float:
        P = steady_kalman(H, R, rho, sigma)
        return float(np.sqrt(grad @ P @ grad / np.sum((grad * sigma) ** 2)))

    P = steady_kalman(Hc, R_paper, rho, sigma)
    ratio = np.sqrt(np.diag(P)) / sigma
    single = np.linalg.inv(np.diag(sigma**-2) + Hc.T @ np.linalg.solve(R_paper, Hc))
    ident = ratio < 0.5
    out: dict[str, Any] = {
        "mu": mu.tolist(), "theta": theta.tolist(),
        "final_angle_sd_deg": float(np.sqrt(var_a)),
        "variance_share": ((a * sigma) ** 2 / var_a).tolist(),
        "posterior_ratio_paper": ratio.tolist(),
        "posterior_ratio_calibrated": (np.sqrt(np.diag(steady_kalman(
            Hc, R_paper + (0 if k_res is None else k_res), rho, sigma))) / sigma).tolist(),
        "nrmse_kf_paper": float(np.sqrt(a @ P @ a / var_a)),
        "nrmse_kf_calibrated": nrmse(Hc, R_paper + (0 if k_res is None else k_res)),
        "nrmse_one_curve_no_memory": float(np.sqrt(a @ single @ a / var_a)),
        "nrmse_kf_with_angle1": nrmse(*augmented(Hc, R_paper, h1[None], np.array(
            [0.0 if a_var is None else a_var[0]]) + 1e-12)),
        "identified": [n for n, b in zip(st.names, ident, strict=True) if b],
        "nrmse_identified_known": float(np.sqrt(np.sum(
            (a * sigma) ** 2 * (1 - rho**2) * ~ident) / var_a)),
    }
    ix = {n: i for i, n in enumerate(st.names)}
    for tag, names in (("thickness", ["thickness"]), ("yield", ["yield_stress"]),
                       ("yield_thickness", ["yield_stress", "thickness"])):
        idx = [ix[n] for n in names]
        out[f"nrmse_{tag}_known"] = nrmse(*augmented(Hc, R_paper, eye[idx],
                                                     (1e-3 * sigma[idx]) ** 2))
    out["nrmse_thickness_gauge_0p5um"] = nrmse(*augmented(
        Hc, R_paper, eye[[ix["thickness"]]], np.array([0.5e-3**2])))
    for tag, names, gains in (("punch_end_distance", ["punch_end_distance"], (2, 4, 8)),
                              ("thickness", ["thickness"], (0.25,)),
                              ("yield", ["yield_stress"], (2, 4)),
                              ("yield_thickness", ["yield_stress", "thickness"], (0.5, 0.25))):
        for f in gains:
            grad = a.copy()
            grad[[ix[n] for n in names]] *= f
            out[f"nrmse_{tag}_gain_x{f}"] = nrmse(Hc, R_paper, grad)
    return out


def study_figures(folder: Path, k: int, sigma: FloatArray) -> dict[str, Any]:
    """Series-1 figures of realisation ``k`` of a study output (last 500 products)."""
    import xarray as xr

    with xr.open_dataset(folder / "data" / f"realisation_{k}.nc") as ds:
        truth = ds.angles.sel(source="MM").values[-500:, 1]
        mu = ds.mu.values
    runs = sorted(glob.glob(str(folder / "runs" / f"series1_real{k}_rep?.npz")))
    est = np.array([np.load(r)["angles_mean"][-500:, 1] for r in runs])
    post = np.mean([np.load(r)["std"][-500:, :sigma.size].mean(axis=0) for r in runs], axis=0)
    return {"study_mu": mu.tolist(),
            "study_nrmse_final_angle": float(np.sqrt(np.mean((est - truth) ** 2)) / truth.std()),
            "study_posterior_ratio": (post / sigma).tolist(), "study_runs": len(runs)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0, help="study seed (default 0)")
    parser.add_argument("--realisations", type=int, default=5, help="default 5")
    parser.add_argument("--n-mc", type=int, default=10_000, help="curves behind K_MC")
    parser.add_argument("--study", type=Path, help="a study output folder to compare with")
    args = parser.parse_args()
    mm, _, model = bundled_metamodel()
    names = list(mm.spec.state.names)
    per = [realisation(mm, k, args.seed, args.n_mc) for k in range(args.realisations)]
    if args.study:
        for k, r in enumerate(per):
            r.update(study_figures(args.study, k, np.asarray(mm.spec.state.sigma, float)))

    def mean(key: str) -> Any:
        vals = np.array([r[key] for r in per], dtype=float)
        return np.round(vals.mean(axis=0), 4).tolist()

    figures: dict[str, Any] = {"inputs": names, "realisations": args.realisations,
                               "seed": args.seed}
    for key in per[0]:
        if key not in ("mu", "theta", "identified", "study_mu", "study_runs"):
            figures[key + "_mean"] = mean(key)
    figures["per_realisation"] = per
    cfg = TrackerConfig(likelihood="paper", n_mc=args.n_mc)
    figures["likelihood"] = {"fraction": cfg.fraction, "n_mc": cfg.n_mc,
                             "sensor_noise": cfg.sensor_noise}
    write_result("physics_identifiability", figures, model=model)


if __name__ == "__main__":
    main()
