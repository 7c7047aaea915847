"""Benchmark of the tracker (SIR particle filter) against the ``particles`` library.

Run ``python benchmarks/bench_filter.py [--model physics|analytic|METAMODEL_FILE]`` (default
``physics``: the metamodel of the bundled physics DOE, what a fresh clone gets). One core, BLAS
single-threaded. Figures (``benchmarks/results/bench_filter.json``):

* ``step_ms_n500``: median wall time per product at N = 500, everything included (curve
  validation, transition, model curves, ``g^-1``, likelihood, normalisation, resampling,
  estimates and predicted angles), deviation estimated (the heaviest series, 3 and 6),
  over a 1000-product run; ``step_ms_n500_nodev`` the same without ``theta_d``;
* ``run_1000_s``: wall time of that 1000-product run;
* ``breakdown_n500_*_ms``: the parts of a step as the tracker's configuration does them,
  timed separately at all 500 particles: the transition, the metamodel's curves and
  angles, the deviation model in the direction the likelihood compares (``g`` with the
  default ``compare="measurement"``, ``g^-1`` with the paper's ``compare="model"``:
  ``deviation_apply`` or ``deviation_invert``, only the one the step calls), the
  likelihood given the residuals (with the adaptive likelihood the whitening and the
  density on the share's grid) and the resampling;
* ``model_ms_n500``: the model's own evaluation for the 500 particles (metamodel curves
  and angles plus the deviation model, the breakdown's ``predict_curves``,
  ``predict_angles`` and ``deviation_*``) and ``step_over_model``: ``step_cpu_ms_n500``
  over it (what the filter and the tracker's own terms add to the model);
* ``state_bytes_ms`` / ``state_bytes_ms_learn_residuals``: encode plus decode of the
  tracker's state bytes (median of 50) at N = 500, default settings and with
  ``learn_residuals`` (the learned (n_t, n_t) moment folded in); ``state_kb*`` their size;
* ``profile_top``: the 12 functions of largest own time in a cProfile of 250 steps, in
  % of the profile's total (``total_ms_per_step``, cProfile's overhead included; shares
  hold under other load, milliseconds do not), ``profile_top_before`` the same recorded
  on the version before the tracker's own terms were made cheaper (``--profile-before``);
* ``step_ms_n{1e3,1e4,1e5}``, ``peak_mb_n{...}``: time per step and tracemalloc peak;
* ``speedup_vs_particles``: ``particles_step_ms_n500 / step_ms_n500`` as each is
  installed (particles on numpy < 2); ``speedup_vs_particles_same_numpy``: the two
  filters interleaved product by product in one process on numpy < 2;
* ``particles_step_ms_n500``: the same model (same transition, likelihood and angle
  prediction code, same data, same estimates per step) through ``particles.SMC`` with its
  ``Bootstrap`` Feynman-Kac model and systematic resampling every step. ``particles`` 0.4
  pins ``numpy < 2``, so it runs in its own virtual environment
  ``benchmarks/.venv-particles`` (built on first use with ``pip install particles``) by the
  child script ``benchmarks/_particles_child.py``; data and measurement model are
  exchanged as ``.npz`` files in a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np

from formtwin._bench import bundled_metamodel, write_result
from formtwin._threads import single_blas_thread
from formtwin.defaults import AnalyticModel
from formtwin.deviation import DeviationModel
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.production import draw_production_run
from formtwin.spec import load_spec
from formtwin.tracker import Tracker, TrackerConfig

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
VENV = HERE / ".venv-particles"
#: exchange files with the particles child (a temporary directory, set in main)
WORK = Path(tempfile.gettempdir())


def load_model(name: str) -> tuple[ProcessModel, str, dict[str, Any]]:
    """(model, path for the child, description) for ``physics`` (the metamodel of the
    bundled physics DOE, cached), ``analytic`` or a metamodel file."""
    if name == "physics":
        model, path, info = bundled_metamodel()
        return model, str(path), info
    if name == "analytic":
        return (AnalyticModel(load_spec()), name,
                {"name": "analytic stand-in (formtwin.physics.analytic), not the product"})
    from formtwin.metamodel import Metamodel

    mm = Metamodel.load(name)
    return mm, name, {"name": f"metamodel file {name} (not the bundled default)",
                      "physics_version": mm.model_version, "doe_sha256_16": None}


def make_data(model: ProcessModel, n: int, seed: int) -> dict[str, Any]:
    """Series-3-like data: state by eq. 4, curves from the model, deviated by g."""
    spec = model.spec
    run = draw_production_run(spec, n, np.random.default_rng(seed))
    X, theta_d = run.inputs, run.theta_d
    clean = model.predict_curves(X)
    curves = DeviationModel.from_spec(spec).apply(clean, np.tile(theta_d, (n, 1)))
    return {"mu": run.mu, "X": X, "theta_d": theta_d, "clean": clean, "curves": curves}


def timed_run(tracker: Tracker, curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wall and CPU (this thread) seconds of each step."""
    wall, cpu = np.empty(len(curves)), np.empty(len(curves))
    for i, c in enumerate(curves):
        t0, c0 = time.perf_counter(), time.thread_time()
        tracker.step(c)
        wall[i], cpu[i] = time.perf_counter() - t0, time.thread_time() - c0
    return wall, cpu


def median_ms(fn: Any, reps: int = 100) -> float:
    """Median CPU ms (this thread) of ``fn()``: insensitive to other load on the machine."""
    ts = []
    for _ in range(reps):
        c0 = time.thread_time()
        fn()
        ts.append(time.thread_time() - c0)
    return float(np.median(ts) * 1e3)


def breakdown(tracker: Tracker, curve: np.ndarray) -> dict[str, float]:
    """Median ms of each part of a step at the tracker's current particles."""
    ssm, f, rng = tracker.ssm, tracker.filter, np.random.default_rng(0)
    x = f.x if f.x is not None else ssm.sample_initial(f.n, rng)
    n_in = tracker.spec.n_inputs
    td = x[:, n_in:ssm.n_aug]
    clean = tracker.model.predict_curves(x[:, :n_in])
    w = np.full(f.n, 1.0 / f.n)
    # two inputs in turn, so that a model caching its last batch is timed honestly
    xs = [x[:, :n_in], x[:, :n_in] * (1.0 + 1e-9)]
    turn = iter(range(10**9))
    parts: dict[str, Any] = {
        "transition": lambda: ssm.sample_transition(x, rng),
        "predict_curves": lambda: tracker.model.predict_curves(xs[next(turn) % 2]),
        "predict_angles": lambda: tracker.model.predict_angles(xs[next(turn) % 2]),
    }
    if not tracker.config.estimate_deviation:  # no g: the model's curves are compared
        model_side, obs = clean, curve
    elif tracker.config.compare == "model":  # paper eq. 12: g^-1 of the measured curve
        parts["deviation_invert"] = lambda: ssm.deviation.invert(curve, td)
        model_side, obs = clean, ssm.deviation.invert(curve, td)
    else:  # default: the deviated model curves against the measured curve
        parts["deviation_apply"] = lambda: ssm.deviation.apply(clean, td)
        model_side, obs = ssm.deviation.apply(clean, td), curve
    r = np.atleast_2d(obs - model_side)
    disc = ssm.discrepancy
    if disc is not None:  # adaptive / discrepancy likelihood: whiten, density per share
        stats = x[:, ssm._disc:] if disc.shared else None
        parts["likelihood"] = lambda: ssm.mix_share(disc.loglik(r, stats, disc.whiten(r)))
    else:
        parts["likelihood"] = lambda: tracker.measurement.loglik(model_side, obs)
    parts["resample"] = lambda: f.resample(w, rng, f.n)
    return {f"breakdown_n{f.n}_{k}_ms": round(median_ms(v), 4) for k, v in parts.items()}


def profile_top(tracker: Tracker, curves: np.ndarray, n: int = 12) -> dict[str, float]:
    """ms per step of own time (cProfile) of the ``n`` costliest functions over the steps
    of ``curves``, keyed ``file:line(function)`` within the package."""
    import cProfile
    import pstats

    pr = cProfile.Profile(time.thread_time)  # CPU time: other load does not count
    pr.enable()
    for c in curves:
        tracker.step(c)
    pr.disable()
    stats = pstats.Stats(pr).stats  # type: ignore[attr-defined]
    total = sum(v[2] for v in stats.values())
    rows = sorted(((v[2], k) for k, v in stats.items()), reverse=True)[:n]
    out = {"total_ms_per_step": round(total / len(curves) * 1e3, 3)}
    for own, (path, line, name) in rows:
        where = path.split("/src/", 1)[-1].split("site-packages/", 1)[-1]
        out[f"{where}:{line}({name}) %"] = round(100 * own / total, 1)
    return out


def state_bytes_ms(tracker: Tracker, model: ProcessModel, mm: MeasurementModel
                   ) -> tuple[float, float]:
    """Median ms of encode + decode of the tracker's state bytes, and their size (KB);
    checks that the bytes restore exactly."""
    from formtwin.tracker import state as state_codec

    def both() -> bytes:
        data = tracker.state_bytes()
        state_codec.decode(data)
        return data

    data = both()
    assert Tracker.from_state_bytes(data, model, mm).state_bytes() == data
    ts = []
    for _ in range(50):
        t0 = time.perf_counter()
        both()
        ts.append(time.perf_counter() - t0)
    return round(float(np.median(ts)) * 1e3, 3), round(len(data) / 1024, 1)


def scaling(model: ProcessModel, mm: MeasurementModel, curves: np.ndarray,
            n: int, steps: int) -> dict[str, float]:
    tr = Tracker(model, mm, TrackerConfig(n_particles=n, seed=1))
    tr.step(curves[0])
    ms = float(np.median(timed_run(tr, curves[1:steps + 1])[1]) * 1e3)
    tracemalloc.start()
    tr.step(curves[steps + 1])
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    tag = f"n{n:.0e}".replace("+0", "").replace("+", "")
    return {f"step_cpu_ms_{tag}": round(ms, 3), f"peak_mb_{tag}": round(peak, 1)}


def ensure_venv() -> Path | None:
    py = VENV / "bin" / "python"
    if py.exists():
        return py
    print(f"building {VENV} for particles (numpy < 2) ...", file=sys.stderr)
    try:
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", "particles", "scipy",
                        "threadpoolctl"], check=True)
    except (subprocess.CalledProcessError, OSError) as exc:
        print(f"could not build the particles venv: {exc}", file=sys.stderr)
        return None
    return py


def run_particles(model_name: str, mm_path: Path, data_path: Path, n: int,
                  n_products: int) -> dict[str, Any] | None:
    py = ensure_venv()
    if py is None:
        return None
    out = WORK / "particles_result.json"
    cmd = [str(py), str(HERE / "_particles_child.py"), "--model", model_name,
           "--measurement", str(mm_path), "--data", str(data_path), "--particles", str(n),
           "--products", str(n_products), "--out", str(out), "--src", str(ROOT / "src")]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        return None
    res: dict[str, Any] = json.loads(out.read_text())
    return res


def nrmse(est_mean: np.ndarray, X: np.ndarray, col: int, scale: float) -> float:
    half = slice(len(X) // 2, None)
    return float(np.sqrt(np.mean((est_mean[half, col] - X[half, col]) ** 2)) / scale)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="physics",
                    help="'physics' (default: the metamodel of the bundled physics DOE, "
                         "fitted once and cached in benchmarks/.cache), 'analytic', or a "
                         "metamodel file")
    ap.add_argument("--products", type=int, default=1000)
    ap.add_argument("--no-particles", action="store_true", help="skip the particles peer")
    ap.add_argument("--no-scaling", action="store_true", help="skip N = 1e3..1e5")
    ap.add_argument("--profile-before", metavar="FILE.json",
                    help="a profile_top recorded before (by --profile-only on an earlier "
                         "version), kept in the result as profile_top_before")
    ap.add_argument("--profile-only", metavar="FILE.json",
                    help="only write profile_top of this version to FILE.json and stop")
    args = ap.parse_args()
    global WORK
    tmp = tempfile.TemporaryDirectory(prefix="bench_filter_")
    WORK = Path(tmp.name)
    model, child_model, model_info = load_model(args.model)
    spec = model.spec
    figures: dict[str, Any] = {"model": model_info["name"]}
    with single_blas_thread():
        data = make_data(model, args.products, seed=2024)
        mm = MeasurementModel.from_monte_carlo(model, mu=data["mu"], n=10_000,
                                               rng=np.random.default_rng(7))
        mm_path = mm.save(WORK / "bench_filter_measurement.npz")
        data_path = WORK / "bench_filter_data.npz"
        np.savez(data_path, curves=data["curves"], mu=data["mu"], X=data["X"])
        curves = data["curves"]

        cfg = TrackerConfig(n_particles=500, mu=tuple(data["mu"]), seed=3)
        if args.profile_only:
            tr_p = Tracker(model, mm, cfg)
            tr_p.run(curves[:50])
            Path(args.profile_only).write_text(json.dumps(profile_top(tr_p, curves[50:300]),
                                                          indent=1), encoding="utf-8")
            return
        tr = Tracker(model, mm, cfg)
        figures["load_average_1min_start"] = round(os.getloadavg()[0], 2)
        t0 = time.perf_counter()
        ts, cpu = timed_run(tr, curves)
        figures["run_1000_s" if args.products == 1000 else f"run_{args.products}_s"] = \
            round(time.perf_counter() - t0, 3)
        figures["step_ms_n500"] = round(float(np.median(ts) * 1e3), 3)
        figures["step_ms_n500_p90"] = round(float(np.percentile(ts, 90) * 1e3), 3)
        figures["step_cpu_ms_n500"] = round(float(np.median(cpu) * 1e3), 3)
        figures.update(breakdown(tr, curves[-1]))
        model_ms = sum(figures.get(f"breakdown_n500_{k}_ms", 0.0) for k in (
            "predict_curves", "predict_angles", "deviation_apply", "deviation_invert"))
        figures["model_ms_n500"] = round(model_ms, 3)
        figures["step_over_model"] = round(figures["step_cpu_ms_n500"] / model_ms, 2)
        figures["state_bytes_ms"], figures["state_kb"] = state_bytes_ms(tr, model, mm)
        tr_lr = Tracker(model, mm, TrackerConfig(n_particles=500, mu=tuple(data["mu"]),
                                                 seed=3, learn_residuals=True))
        tr_lr.run(curves[:60])  # the moment folded once (every 50 products)
        figures["state_bytes_ms_learn_residuals"], figures["state_kb_learn_residuals"] = \
            state_bytes_ms(tr_lr, model, mm)
        tr_p = Tracker(model, mm, cfg)
        tr_p.run(curves[:50])
        figures["profile_top"] = profile_top(tr_p, curves[50:300])
        if args.profile_before:
            figures["profile_top_before"] = json.loads(
                Path(args.profile_before).read_text(encoding="utf-8"))
        tr2 = Tracker(model, mm, TrackerConfig(n_particles=500, mu=tuple(data["mu"]), seed=3,
                                               estimate_deviation=False))
        figures["step_cpu_ms_n500_nodev"] = round(float(np.median(
            timed_run(tr2, data["clean"][:300])[1]) * 1e3), 3)
        # accuracy of the timed run, to compare with the peer's
        tr3 = Tracker(model, mm, cfg)
        e = tr3.run(curves)
        k = spec.augmented.index["punch_end_distance"]
        figures["nrmse_punch_end_distance"] = round(
            nrmse(e.mean, data["X"], k, spec.state.sigma[k]), 3)
        figures["mean_ess_n500"] = round(float(e.ess.mean()), 1)
        if not args.no_scaling:
            for n, steps in ((1_000, 50), (10_000, 10), (100_000, 3)):
                figures.update(scaling(model, mm, curves, n, steps))
    if not args.no_particles:
        res = run_particles(child_model, mm_path, data_path, 500, args.products)
        if res is None:
            figures["particles_step_ms_n500"] = None
        else:
            figures["particles_step_ms_n500"] = round(res["step_ms"], 3)
            figures["particles_step_cpu_ms_n500"] = round(res["step_cpu_ms"], 3)
            figures["particles_version"] = res["version"]
            figures["particles_nrmse_punch_end_distance"] = round(
                nrmse(np.asarray(res["mean"]), data["X"], k, spec.state.sigma[k]), 3)
            figures["step_cpu_ms_n500_in_particles_venv"] = round(
                res["formtwin_step_cpu_ms_same_numpy"], 3)
            figures["particles_numpy"] = res["numpy"]
            figures["filter_overhead_cpu_ms_n500"] = round(res["overhead_formtwin_ms"], 4)
            figures["particles_filter_overhead_cpu_ms_n500"] = round(
                res["overhead_particles_ms"], 4)
            # as installed: particles is tied to numpy < 2, formtwin runs on numpy 2
            figures["speedup_vs_particles"] = round(
                res["step_cpu_ms"] / figures["step_cpu_ms_n500"], 2)
            # same process and numpy, interleaved: the filters themselves
            figures["speedup_vs_particles_same_numpy"] = round(
                res["step_cpu_ms"] / res["formtwin_step_cpu_ms_same_numpy"], 2)
    figures["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    write_result("filter", figures, model=model_info)
    tmp.cleanup()


if __name__ == "__main__":
    main()
