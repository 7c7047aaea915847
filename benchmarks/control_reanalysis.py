"""Reanalysis of a finished control study (``bench_control.py``'s cached datasets): how much
the posterior's predicted angles and, as a what-if, the angle after the first stage could
add to the run-to-run EWMA, without re-running any controller.

For each dataset, with the plant's final angle ``a_i`` at the nominal setting (no control)
and a second signal ``c_i`` known before product ``i``'s second stage (the posterior mean of
the final angle after its curve, or the measured stage-1 angle), the one-step prediction::

    a_hat_i = L + w (c_i - K)      L, K: EWMAs (weight lam) of a and c over earlier products

is scored by its error std over products 100-999 against ``w = 0`` (the EWMA alone):

* ``weight_grid``: ``w`` and ``lam`` the best in hindsight on each dataset (in-sample: an
  upper bound of what a fixed weight gives);
* ``adaptive``: ``w`` the running least-squares slope of ``a_i - L`` on ``c_i - K`` over the
  earlier products (clipped to [0, 1]; out of sample by construction), ``lam`` 0.7.

``ar`` (the posterior only): the prediction of :class:`formtwin.control.Combined` with
``rho``, the persistence of the last product's deviation from the level::

    a_hat_i = L + rho (a_j - L) + w ((c_i - K) - rho (c_j - K))      (j = i - 1)

with ``(rho, lam, w)`` chosen on the other datasets (least mean std: leave one dataset out,
as the study chooses its weights) and scored on each (``tuned``), the same with ``w = 0``
(``tuned_no_estimates``: what the time-series model alone gives), and the best in hindsight
per dataset (``best_in_sample``).

This is the nominal-setting proxy of the closed loop (the plant's angle is nearly linear in
``u``), not a closed-loop result. Run after ``bench_control.py``::

    python benchmarks/control_reanalysis.py
"""

from __future__ import annotations

import json
from itertools import product

import numpy as np

from formtwin._bench import CACHE
from formtwin.dataset import DoeDataset
from formtwin.defaults import physics_model
from formtwin.spec import load_spec
from formtwin.study.control import plant_path

LAMS = (0.5, 0.7, 1.0)
WEIGHTS = (0.0, 0.02, 0.05, 0.1, 0.25, 0.5, 0.75, 1.0)
#: the ``ar`` grid: (rho, lam, w)
AR_GRID = tuple(product((0.0, 0.5, 0.6, 0.7, 0.8), (0.01, 0.02, 0.05, 0.1, 0.3, 0.7, 1.0),
                        (0.0, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0)))


def predict(a: np.ndarray, c: np.ndarray, lam: float, w: float | None,
            burn_in: int = 100) -> np.ndarray:
    """Prediction errors of ``a`` (n,) from its EWMA and ``c`` (n,) after ``burn_in``;
    ``w`` None: the running least-squares slope."""
    level = ref = None
    sxy = sxx = 0.0
    err = []
    for i in np.flatnonzero(np.isfinite(a) & np.isfinite(c)):
        if level is None or ref is None:
            level, ref = a[i], c[i]
            continue
        x, y = c[i] - ref, a[i] - level
        wi = w if w is not None else (float(np.clip(sxy / sxx, 0, 1)) if sxx > 0 else 0.0)
        if i >= burn_in:
            err.append(y - wi * x)
        sxy, sxx = sxy + x * y, sxx + x * x
        level, ref = lam * a[i] + (1 - lam) * level, lam * c[i] + (1 - lam) * ref
    return np.asarray(err)


def ar_errors(a: np.ndarray, c: np.ndarray, rho: float, lam: float, w: float,
              burn_in: int = 100) -> np.ndarray:
    """Prediction errors of ``a`` (n,) by ``L + rho (a_j - L) + w ((c_i - K) - rho (c_j - K))``
    after ``burn_in`` (L, K: EWMAs of weight ``lam`` started at the first product)."""
    level = ref = last_a = last_c = None
    err = []
    for i in np.flatnonzero(np.isfinite(a) & np.isfinite(c)):
        if level is None or ref is None or last_a is None or last_c is None:
            level, ref, last_a, last_c = a[i], c[i], a[i], c[i]
            continue
        pred = level + rho * (last_a - level) + w * ((c[i] - ref) - rho * (last_c - ref))
        if i >= burn_in:
            err.append(a[i] - pred)
        level, ref = lam * a[i] + (1 - lam) * level, lam * c[i] + (1 - lam) * ref
        last_a, last_c = a[i], c[i]
    return np.asarray(err)


def ar_analysis(data: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, object]:
    """``ar`` std ratios to the best plain EWMA of each dataset of ``data`` (name -> (a, c)),
    each with the grid's choice on the other datasets (leave one out)."""
    sd = {k: np.array([np.std(ar_errors(a, c, *g)) for g in AR_GRID]) for k, (a, c) in
          data.items()}
    ewma = {k: min(float(np.std(ar_errors(a, c, 0.0, lm, 0.0))) for lm in LAMS)
            for k, (a, c) in data.items()}
    no_c = np.flatnonzero([g[2] == 0.0 for g in AR_GRID])
    out: dict[str, dict[str, object]] = {"tuned": {}, "tuned_no_estimates": {}}
    for k in sd if len(sd) > 1 else ():
        others = np.mean([v for n, v in sd.items() if n != k], axis=0)
        best, best0 = int(np.argmin(others)), int(no_c[np.argmin(others[no_c])])
        out["tuned"][k] = {"rho_lam_w": AR_GRID[best],
                           "ratio": round(float(sd[k][best]) / ewma[k], 3)}
        out["tuned_no_estimates"][k] = {"rho_lam": AR_GRID[best0][:2],
                                        "ratio": round(float(sd[k][best0]) / ewma[k], 3)}
    out["best_in_sample"] = {k: {"rho_lam_w": AR_GRID[int(np.argmin(v))],
                                 "ratio": round(float(v.min()) / ewma[k], 3)}
                             for k, v in sd.items()}
    return dict(out)


def analyse(a: np.ndarray, c: np.ndarray) -> dict[str, object]:
    """Std ratios to the EWMA alone: in-sample best fixed weight, adaptive weight."""
    sd = {(lm, w): float(np.std(predict(a, c, lm, w))) for lm, w in product(LAMS, WEIGHTS)}
    ewma = min(sd[(lm, 0.0)] for lm in LAMS)
    best = min(sd, key=lambda k: sd[k])
    return {"ewma_std_deg": round(ewma, 4),
            "weight_grid": {"lam": best[0], "w": best[1], "ratio": round(sd[best] / ewma, 3)},
            "adaptive_ratio": round(float(np.std(predict(a, c, 0.7, None))) / ewma, 3)}


def main() -> None:
    """Print the reanalysis of every cached dataset as JSON."""
    folder = CACHE / "control"
    version = physics_model("bending", load_spec()).version
    out: dict[str, object] = {"physics_version": version}
    posterior: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for k in range(6):
        plant = DoeDataset.load(plant_path(folder, k, version))
        n = plant.n // 3
        ok = plant.ok.reshape(3, n).all(axis=0)
        final = np.where(ok, plant.angles[:, 1].reshape(3, n)[1], np.nan)
        stage1 = np.where(ok, plant.angles[:, 0].reshape(3, n)[1], np.nan)
        res: dict[str, object] = {"stage1_angle": analyse(final, stage1)}
        if (folder / f"dataset_{k}.npz").exists():
            with np.load(folder / f"dataset_{k}.npz") as f:
                if "nominal_mean" in f.files:
                    posterior[f"dataset_{k}"] = (f["angle_fixed"], f["nominal_mean"])
                    res["posterior"] = analyse(f["angle_fixed"], f["nominal_mean"])
        out[f"dataset_{k}"] = res
    out["ar"] = ar_analysis(posterior)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
