"""Speed and robustness of the two-stage bending model (formtwin.physics.bending).

One full two-stage run at the centre of Table 1, then 50 random Table-1 points (uniform in
the input box, seed 2024), one core. Figures: ``median_s_per_run`` (wall clock, random
points), ``converged_fraction``, ``compile_s`` (first run in a fresh process with an empty
Numba cache), ``cache_load_s`` (first run in a fresh process with the cache filled).
Targets (issue 3): median <= 0.2 s, converged fraction >= 0.99.

Run: ``python benchmarks/bench_physics.py [--points 50]``.
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=50)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        compile_s = first_run_seconds(tmp)
    cache_load_s = first_run_seconds(None)

    model = BendingModel()
    centre = model.centre()
    model.run(centre)
    centre_s = []
    for _ in range(5):
        t = time.perf_counter()
        r = model.run(centre)
        centre_s.append(time.perf_counter() - t)
    assert r.ok, r.reason

    rng = np.random.default_rng(2024)
    lo, hi = model.spec.inputs.lo, model.spec.inputs.hi
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
    figures = {
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
    write_result("physics", figures)


if __name__ == "__main__":
    main()
