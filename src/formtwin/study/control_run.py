"""Run the control study (:mod:`formtwin.study.control`) over its datasets, score it and draw
its figure: ``control_study.json`` and ``control_study.png`` in the output folder, the
per-dataset results in ``dataset_<k>.npz`` (reused when present with the same settings, the
same model and the same code)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from formtwin.figures import pyplot
from formtwin.measurement import ProcessModel
from formtwin.simulator import Simulator
from formtwin.study.control import (
    CONTROLLERS,
    ControlStudySettings,
    default_target,
    r2r_gain,
    run_dataset,
    scores,
)

log = logging.getLogger(__name__)

LABELS = {"fixed": "fixed u (no control)", "ewma": "run-to-run EWMA",
          "feedforward": "feedforward (formtwin, with trim)", "oracle": "oracle (true state)",
          "feedforward_open": "feedforward without trim"}
#: the four cases of the figure
SHOWN = ("fixed", "ewma", "feedforward", "oracle")


#: packages whose code does not change a control-study result
NOT_IN_RESULTS = ("service", "cli", "monitoring", "figures.py")


def _key(settings: ControlStudySettings, target: float, version: str,
         metamodel: ProcessModel) -> str:
    """Hash of what makes a dataset's result: settings (not the worker count), target,
    physics version, the metamodel (its curve and angles at the box's middle) and the source
    of the package outside :data:`NOT_IN_RESULTS` (tracker, controllers, plant, study)."""
    d = dataclasses.asdict(settings)
    d["tracker"] = settings.tracker.to_dict()
    d.pop("workers")
    h = hashlib.sha256(json.dumps([d, target, version], sort_keys=True,
                                  default=str).encode())
    spec = metamodel.spec
    mid = 0.5 * (spec.inputs.lo + spec.inputs.hi)[None, :]
    h.update(np.ascontiguousarray(metamodel.predict_curves(mid), dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(metamodel.predict_angles(mid), dtype="<f8").tobytes())
    pkg = Path(__file__).resolve().parents[1]
    for f in sorted(pkg.rglob("*.py")):
        if f.relative_to(pkg).parts[0] not in NOT_IN_RESULTS:
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def run_control_study(metamodel: ProcessModel, physics: Simulator,
                      settings: ControlStudySettings, out: str | Path) -> dict[str, Any]:
    """Run (or reuse) every dataset, write the figure and ``control_study.json``; return
    the summary (per controller: mean error, std, RMSE, share in the band; the ratios of
    the feedforward's std to the others')."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    target = default_target(metamodel) if settings.target is None else settings.target
    gain = r2r_gain(metamodel, np.random.default_rng(settings.seed))
    key = _key(settings, target, str(getattr(physics, "version", "")), metamodel)
    results: list[dict[str, Any]] = []
    lam: float | None = None
    for k in range(settings.datasets):
        path = out / f"dataset_{k}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as f:
                if str(f["key"]) == key:
                    res = {n: f[n] for n in f.files}
                    res["r2r_lam"] = float(res["r2r_lam"])
                    results.append(res)
                    lam = res["r2r_lam"] if lam is None else lam
                    continue
        log.info("control study: dataset %d of %d", k + 1, settings.datasets)
        res = run_dataset(metamodel, physics, settings, k, out, target, gain, lam)
        lam = res["r2r_lam"] if lam is None else lam
        arrays = {n: np.asarray(v) for n, v in res.items()}
        np.savez(path, key=np.array(key), **arrays)  # type: ignore[arg-type]
        results.append(res)
    b = settings.burn_in
    pooled = {c: np.concatenate([r[f"angle_{c}"][b:] for r in results]) for c in CONTROLLERS}
    summary: dict[str, Any] = {c: scores(pooled[c], target, settings.band)
                               for c in CONTROLLERS}
    sd = {c: summary[c]["std_deg"] for c in CONTROLLERS}
    def ratio(other: str) -> float | None:
        return round(sd["feedforward"] / sd[other], 4) if sd[other] > 0 else None

    summary.update({
        "angle2_std_ratio_ff_vs_fixed": ratio("fixed"),
        "angle2_std_ratio_ff_vs_oracle": ratio("oracle"),
        "angle2_std_ratio_ff_vs_ewma": ratio("ewma"),
        "target_deg": target, "r2r_gain_deg_per_unit": round(gain, 6),
        "r2r_lam": lam, "burn_in": b,
        "per_dataset_std_deg": {c: [round(float(np.nanstd(r[f"angle_{c}"][b:])), 4)
                                    for r in results] for c in CONTROLLERS},
    })
    pred = np.concatenate([r["pred"][b:] for r in results])
    ang = pooled["feedforward"]
    ok = np.all(np.isfinite(pred), axis=1) & np.isfinite(ang)
    summary["feedforward_interval_coverage"] = round(float(np.mean(
        (ang[ok] >= pred[ok, 1]) & (ang[ok] <= pred[ok, 2]))), 4)
    summary["feedforward_prediction_rmse_deg"] = round(float(np.sqrt(np.mean(
        (ang[ok] - pred[ok, 0]) ** 2))), 4)
    errs = [r["interp_error"] for r in results if "interp_error" in r]
    if errs:
        e = np.concatenate(errs)
        summary["plant_interpolation_max_abs_error_deg"] = round(float(np.nanmax(np.abs(e))), 4)
    summary["settings"] = {**{k: v for k, v in dataclasses.asdict(settings).items()
                              if k != "tracker"}, "tracker": settings.tracker.to_dict()}
    plot_control(results[0], target, settings.band, out / "control_study.png")
    (out / "control_study.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def plot_control(res: dict[str, Any], target: float, band: float, path: Path) -> Path:
    """The final angle over the products of one dataset for the four controllers."""
    plt = pyplot()
    fig, axes = plt.subplots(len(SHOWN), 1, figsize=(10, 9), sharex=True, sharey=True)
    for ax, c in zip(axes, SHOWN, strict=True):
        a = res[f"angle_{c}"]
        ax.plot(np.arange(a.size), a, ".", ms=2, color="#1f5fa8")
        ax.axhline(target, color="k", lw=0.8)
        ax.axhspan(target - band, target + band, color="#2a7a2a", alpha=0.12, lw=0)
        e = a[np.isfinite(a)] - target
        ax.set_title(f"{LABELS[c]}: std {e.std():.3f} deg, within +-{band} deg "
                     f"{np.mean(np.abs(e) <= band):.0%}", fontsize=9)
        ax.set_ylabel("final angle (deg)")
    axes[-1].set_xlabel("product")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["LABELS", "plot_control", "run_control_study"]
