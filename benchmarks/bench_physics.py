"""Speed, robustness and final-angle behaviour of the two-stage bending model.

One full two-stage run at the centre of Table 1, then 50 random points of the run-input box
(Table 1 plus the stage-2 setting u, uniform, seed 2024), one core. Figures:

* ``median_s_per_run`` (wall clock, random points), ``converged_fraction``, ``compile_s``
  (first run in a fresh process with an empty Numba cache), ``cache_load_s`` (first run in
  a fresh process with the cache filled); targets: median <= 0.2 s,
  converged fraction >= 0.99;
* ``final_angle_range_yield_deg``, ``final_angle_range_thickness_deg``: the final angle's
  change from the input's minimum to its maximum, the others at the centre (targets
  >= 1.5 and >= 0.5 deg);
* ``angle2_gain_deg_per_mm``: d final angle / d u at the centre (central difference over
  +-50 um);
* ``angle2_noise_ratio``: the std of the final angle over 20 runs at the centre with every
  input perturbed by 1e-6 of its range (numerical noise), over the std of the final angle in
  a production run (40 products of :func:`~formtwin.production.draw_production_run`, seed
  7, nominal u) (target <= 0.05); ``angle2_sweep_scatter_deg``: the largest std about a
  quadratic trend of the final angle in 9-point sweeps of yield stress and thickness
  (noise from the adaptive steps and contact events).

Run: ``python benchmarks/bench_physics.py [--points 50] [--beam KEY=VALUE,...]`` (a variant of
the beam model, e.g. ``--beam pinch_reach=0.5``, writes ``bench_physics_variant.json``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from formtwin._bench import write_result  # noqa: E402
from formtwin.physics.bending import VERSION, BendingModel  # noqa: E402
from formtwin.production import draw_production_run  # noqa: E402

_FIRST_RUN = (
    "import time; t = time.perf_counter();"
    "from formtwin.physics.bending import BendingModel;"
    "m = BendingModel(); r = m.run(m.centre());"
    "print(time.perf_counter() - t, r.ok)"
)


def first_run_seconds(cache_dir: str | None) -> float:
    """Seconds for import + first run in a fresh interpreter (optionally a fresh cache)."""
    env = dict(os.environ)
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = cache_dir
    out = subprocess.run([sys.executable, "-c", _FIRST_RUN], env=env, check=True,
                         capture_output=True, text=True).stdout.split()
    return float(out[0])


def final_angle_figures(model: BendingModel) -> dict[str, float]:
    """Ranges of the final angle with yield stress and thickness, its gain with u, and its
    numerical noise against its spread in a production run (see the module doc)."""
    box, centre = model.spec.run_inputs, model.centre()

    def angle2(x: np.ndarray) -> float:
        r = model.run(x)
        return float(r.angles[1]) if r.ok else float("nan")

    def moved(name: str, value: float) -> np.ndarray:
        x = centre.copy()
        x[box.index[name]] = value
        return x

    out: dict[str, float] = {}
    for name, key in (("yield_stress", "yield"), ("thickness", "thickness")):
        a, b = angle2(moved(name, box[name].lo)), angle2(moved(name, box[name].hi))
        out[f"final_angle_range_{key}_deg"] = round(abs(b - a), 4)
    du = 0.05
    out["angle2_gain_deg_per_mm"] = round(
        (angle2(moved("stage2_depth", du)) - angle2(moved("stage2_depth", -du))) / (2 * du), 3)
    rng = np.random.default_rng(11)
    noise = [angle2(centre + 1e-6 * (hi - lo) * rng.uniform(-1, 1, lo.size))
             for lo, hi in [(box.lo, box.hi)] for _ in range(20)]
    run = draw_production_run(model.spec, 40, np.random.default_rng(7))
    in_run = [angle2(x) for x in run.run_inputs]
    out["angle2_noise_std_deg"] = float(f"{np.nanstd(noise):.3g}")
    out["angle2_in_run_std_deg"] = round(float(np.nanstd(in_run)), 4)
    out["angle2_noise_ratio"] = float(f"{np.nanstd(noise) / np.nanstd(in_run):.3g}")
    # a coarser view of the noise: scatter about a quadratic trend in a 9-point sweep
    worst = 0.0
    for name in ("yield_stress", "thickness"):
        v = np.linspace(box[name].lo, box[name].hi, 9)
        a = np.array([angle2(moved(name, val)) for val in v])
        z = (v - v.mean()) / np.ptp(v)
        worst = max(worst, float(np.std(a - np.polyval(np.polyfit(z, a, 2), z))))
    out["angle2_sweep_scatter_deg"] = float(f"{worst:.3g}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=50)
    parser.add_argument("--beam", default="", help="beam-model variant: Discretisation "
                        "fields KEY=VALUE,... (writes bench_physics_variant.json)")
    args = parser.parse_args()
    from bench_physics_fe import beam_overrides

    overrides = beam_overrides(args.beam)
    with tempfile.TemporaryDirectory() as tmp:
        compile_s = first_run_seconds(tmp)
    cache_load_s = first_run_seconds(None)

    model = BendingModel(**overrides)
    centre = model.centre()
    model.run(centre)
    centre_s = []
    for _ in range(5):
        t = time.perf_counter()
        r = model.run(centre)
        centre_s.append(time.perf_counter() - t)
    assert r.ok, r.reason

    rng = np.random.default_rng(2024)
    box = model.spec.run_inputs
    lo, hi = box.lo, box.hi
    wall, cpu, ok, reasons = [], [], 0, []
    for _ in range(args.points):
        x = lo + (hi - lo) * rng.random(lo.size)
        t, c = time.perf_counter(), time.process_time()
        res = model.run(x)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        ok += res.ok
        if not res.ok:
            reasons.append(res.reason)
    angle = final_angle_figures(model)
    figures = {
        **angle,
        "median_s_per_run": round(float(np.median(wall)), 4),
        "converged_fraction": ok / args.points,
        "compile_s": round(compile_s, 2),
        "cache_load_s": round(cache_load_s, 2),
        "centre_s_per_run": round(float(np.median(centre_s)), 4),
        "cpu_median_s_per_run": round(float(np.median(cpu)), 4),
        "p90_s_per_run": round(float(np.percentile(wall, 90)), 4),
        "max_s_per_run": round(float(np.max(wall)), 4),
        "points": args.points,
        "model_version": VERSION,
        "n_elements": model.disc.n_elements,
        "n_layers": model.disc.n_layers,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "failures": "; ".join(sorted(set(reasons))) or "none",
    }
    if overrides:
        figures["beam_overrides"] = overrides
    write_result("physics_variant" if overrides else "physics", figures)


if __name__ == "__main__":
    main()
