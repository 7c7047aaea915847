"""Cross-check of the beam model against the plane-strain CalculiX model.

Points: the centre of Table 1, each main input (yield stress, thickness, punch end
distance, tool-flap friction) at its minimum and maximum with the others at the centre
(the 9 one-at-a-time cases), and with ``--corners`` the 16 corners of the box of the main
inputs. CalculiX runs on a coarse and a fine mesh (``--meshes``, elements through the
thickness); the fine mesh is the reference, ``|fine - coarse|`` its mesh-error estimate.

Figures: ``peak_rel_err_max``, ``plateau_rel_err_max`` (plateau = mean force over
-40..-20 ms), ``peak_time_err_max_ms``, ``angle1_err_max_deg``, ``angle2_err_max_deg``
(final angle) over all points; ``sensitivity_sign_agreement`` (stage 1: peak, plateau,
angle 1) and ``sensitivity_sign_agreement_final`` (angle 2): the fraction of input effects
(max minus min) with the same sign in both models, counting only effects larger than
CalculiX's own mesh error; the mesh errors; ccx version, meshes, seconds per FE run.
Targets: peak <= 0.05, plateau <= 0.03, angle 1 <= 0.5 deg, agreement 1.0.

With ``--lock FILE`` (or ``FORMTWIN_HEAVY_LOCK``) every ccx run takes that lock by itself,
so other heavy jobs on the machine take turns (no lock by default);
FE results are cached in ``benchmarks/.cache/fe_runs.json`` by model version, geometry and
input, so a rerun after a beam-model change only runs the beam model.
``--reference PATH`` also writes the 9 cases' stage-1 figures (the FE reference for the
beam model) there.

Run: ``python benchmarks/bench_physics_fe.py [--meshes 4,6] [--corners] [--reference F]``;
with ``--stage1-only`` the stage-1 figures come from stage-1-only runs and the final-angle
figures (``--final-meshes 2,4``) from cheaper two-stage runs on the coarse mesh, whose
mesh error is measured at the centre.

Diagnostics: ``--table`` prints both models' figures point by point (Markdown);
``--beam KEY=VALUE,...`` runs a variant of the beam model (fields of
:class:`~formtwin.physics.bending.model.Discretisation`, e.g. ``n_elements=64`` or
``pressure_spread=0``) against the same (cached) FE runs and writes
``bench_physics_fe_variant.json`` instead, with the overrides recorded.

Independent check: ``--independent N`` adds N points the pinch rule was not set on (Latin-
hypercube rows of the bundled DOE, 2/3 at punch end distance 310-340 um, 1/3 at 340-410 um,
seeded by ``--independent-seed``; :mod:`fe_independent`), each with a stage-1 FE run on the
fine mesh and a two-stage run on the final-angle mesh, and writes both beam models' errors
(2.4 and 2.3 = ``pinch_reach=0``) there under ``independent``. Several seeds
(``--independent-seed 2026,2027``): the first under ``independent``, each other under
``independent_seed<seed>``, and the figures over all their points under
``independent_combined``.
"""

from __future__ import annotations

import argparse
import dataclasses
import fcntl
import hashlib
import json
import os
import resource
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from fe_independent import independent_points, parse_seeds, summarise, table  # noqa: E402

from formtwin._bench import CACHE, write_result  # noqa: E402
from formtwin.physics.bending import BendingModel  # noqa: E402
from formtwin.physics.bending.model import Discretisation  # noqa: E402
from formtwin.physics.calculix import CalculixModel, ccx_version  # noqa: E402

MAIN = ("yield_stress", "thickness", "punch_end_distance", "friction_tool_flap")
QUANTITIES = ("peak", "plateau", "peak_time_ms", "angle1", "angle2")


def beam_overrides(text: str) -> dict[str, Any]:
    """``"KEY=VALUE,..."`` -> Discretisation overrides (bool, int or float values).

    >>> beam_overrides("n_elements=64, pressure_spread=0.5, pinch_pressure=0.2/0.4")
    {'n_elements': 64, 'pressure_spread': 0.5, 'pinch_pressure': (0.2, 0.4)}
    """
    fields = {f.name: f.type for f in dataclasses.fields(Discretisation)}
    out: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise SystemExit(f"--beam: {item!r} is not KEY=VALUE with KEY one of "
                             f"{', '.join(fields)}")
        v = value.strip()
        if v.lower() in ("true", "false"):
            out[key] = v.lower() == "true"
        elif "/" in v:  # a pair, e.g. pinch_pressure=0.25/0.5
            try:
                out[key] = tuple(float(part) for part in v.split("/"))
            except ValueError:
                raise SystemExit(f"--beam: {key} needs numbers a/b, got {v!r}") from None
        else:
            try:
                out[key] = int(v) if fields[key] in ("int", int) else float(v)
            except ValueError:
                raise SystemExit(f"--beam: {key} needs a number, got {v!r}") from None
    return out


def point_table(rows: dict[str, dict[str, Any]], final: dict[str, dict[str, Any]] | None
                ) -> str:
    """Markdown table of both models' figures at every point (FE: the fine stage-1 mesh,
    the final angle from ``final`` when given)."""
    head = ("| point | peak FE / beam (N) | err | plateau FE / beam (N) | err | "
            "angle 1 FE / beam (deg) | diff |")
    if final:
        head += " final angle FE / beam (deg) | diff |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in rows.items():
        b, f = r["beam"], r["fine"]
        if not (b and f.get("ok")):
            lines.append(f"| {name} | failed: beam {bool(b)}, FE {f.get('reason', '')} |")
            continue
        line = (f"| {name} | {f['peak']:.1f} / {b['peak']:.1f} | {b['peak'] / f['peak'] - 1:+.3f} "
                f"| {f['plateau']:.2f} / {b['plateau']:.2f} | "
                f"{b['plateau'] / f['plateau'] - 1:+.4f} | {f['angle1']:.2f} / {b['angle1']:.2f} "
                f"| {b['angle1'] - f['angle1']:+.2f} |")
        fr = (final or {}).get(name)
        if fr and fr["beam"] and fr["fe"].get("ok"):
            line += (f" {fr['fe']['angle2']:.2f} / {fr['beam']['angle2']:.2f} | "
                     f"{fr['beam']['angle2'] - fr['fe']['angle2']:+.2f} |")
        lines.append(line)
    return "\n".join(lines)


def figures_of(curve: np.ndarray, angles: np.ndarray, t: np.ndarray) -> dict[str, float]:
    """Peak (N), plateau (mean over -40..-20 ms, N), peak time (ms, parabola through the
    three samples at the maximum), angles (deg)."""
    k = int(np.argmax(curve))
    dt = float(t[1] - t[0])
    tk = float(t[k])
    if 0 < k < curve.size - 1:
        a, b, c = curve[k - 1], curve[k], curve[k + 1]
        den = a - 2 * b + c
        tk += 0.5 * dt * (a - c) / den if den != 0 else 0.0
    window = (t >= -0.040 - 1e-9) & (t <= -0.020 + 1e-9)
    return {"peak": float(curve.max()), "plateau": float(curve[window].mean()),
            "peak_time_ms": 1e3 * tk, "angle1": float(angles[0]), "angle2": float(angles[1])}


def design(model: BendingModel, corners: bool) -> list[tuple[str, np.ndarray]]:
    """Named points: centre, min/max of each main input, optionally the 16 corners."""
    ix = model.spec.inputs.index
    lo, hi = model.spec.inputs.lo, model.spec.inputs.hi
    x0 = model.centre()
    pts = [("centre", x0)]
    for name in MAIN:
        for side, bound in (("min", lo), ("max", hi)):
            x = x0.copy()
            x[ix[name]] = bound[ix[name]]
            pts.append((f"{name}_{side}", x))
    if corners:
        for k in range(2 ** len(MAIN)):
            x = x0.copy()
            tag = []
            for j, name in enumerate(MAIN):
                up = (k >> j) & 1
                x[ix[name]] = (hi if up else lo)[ix[name]]
                tag.append("+" if up else "-")
            pts.append(("corner" + "".join(tag), x))
    return pts


def _cpu_now() -> float:
    """CPU seconds of this process and its finished children (ccx runs as a child)."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


class FeCache:
    """FE figures by model version, geometry and input (JSON, git-ignored)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}

    @staticmethod
    def key(fe: CalculixModel, x: np.ndarray) -> str:
        """Cache key of one FE run."""
        text = f"{fe.version}|{fe.stage2}|{fe.geometry!r}|{fe.settings!r}|{x.tolist()!r}"
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    def run(self, fe: CalculixModel, x: np.ndarray, lock: str) -> dict[str, Any]:
        """Figures of one FE run (cached), the run under ``lock`` if one is given."""
        k = self.key(fe, x)
        if k not in self.data:
            with open(lock or os.devnull, "a") as fh:
                if lock:
                    fcntl.flock(fh, fcntl.LOCK_EX)
                tic = _cpu_now()
                wall = time.perf_counter()
                r = fe.run(x)
                if lock:
                    fcntl.flock(fh, fcntl.LOCK_UN)
            rec: dict[str, Any] = {"ok": r.ok, "reason": r.reason,
                                   "cpu_s": _cpu_now() - tic,
                                   "wall_s": time.perf_counter() - wall}
            if r.ok:
                rec.update(figures_of(r.curve, r.angles, fe.spec.time))
            self.data[k] = rec
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.write_text(json.dumps(self.data, indent=1))
            print(f"  ccx {fe.settings.n_thick} through the thickness: {rec}", flush=True)
        return dict(self.data[k])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="4,6", help="coarse,fine elements through the "
                        "thickness (default: %(default)s)")
    parser.add_argument("--corners", action="store_true", help="add the 16 corners")
    parser.add_argument("--stage1-only", action="store_true", help="no stage 2 in CalculiX")
    parser.add_argument("--final-meshes", default="2,4", help="two-stage FE runs for the "
                        "final angle: mesh at every point, mesh at the centre for the error "
                        "estimate ('' for none; default: %(default)s)")
    parser.add_argument("--reference", help="also write the 9 cases' FE figures to this JSON")
    parser.add_argument("--table", action="store_true", help="print both models' figures "
                        "point by point (Markdown)")
    parser.add_argument("--beam", default="", help="beam-model variant: Discretisation "
                        "overrides KEY=VALUE,... (written to bench_physics_fe_variant.json)")
    parser.add_argument("--lock", default=os.environ.get("FORMTWIN_HEAVY_LOCK", ""),
                        help="lock file each ccx run takes, to share the machine with other "
                        "heavy jobs; '' for none (default: $FORMTWIN_HEAVY_LOCK or none)")
    parser.add_argument("--independent", type=int, default=0, metavar="N",
                        help="add N independent DOE points (see the module docstring)")
    parser.add_argument("--independent-seed", default="2026",
                        help="seed(s) of the independent points, e.g. 2026,2027 (default: "
                        "%(default)s)")
    args = parser.parse_args()
    try:
        seeds = parse_seeds(args.independent_seed)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    overrides = beam_overrides(args.beam)
    beam = BendingModel(**overrides)
    points = design(beam, args.corners)
    cache = FeCache(CACHE / "fe_runs.json")
    fine = {}
    meshes = [int(v) for v in args.meshes.split(",")]
    rows = _rows(beam, points, meshes, not args.stage1_only, cache, args.lock, fine)
    figures = compare(rows, not args.stage1_only)
    if args.reference:  # first, so the beam model's authors get it before the final angles
        _write_reference(args.reference, rows, fine["stage1"], meshes)
    if args.final_meshes:
        final = [int(v) for v in args.final_meshes.split(",")]
        figures.update(_final_angle(beam, points, final, cache, args.lock))
    if args.table:
        print(point_table(rows, figures.get("points_final")))
    if args.independent:
        final_mesh = int((args.final_meshes or "2").split(",")[0])
        merged: dict[str, dict[str, Any]] = {}
        for k, seed in enumerate(seeds):
            res = _independent(beam, args.independent, seed, meshes[1], final_mesh, cache,
                               args.lock, args.table)
            figures["independent" if k == 0 else f"independent_seed{seed}"] = res
            merged.update(res["points"])
        if len(seeds) > 1:
            figures["independent_combined"] = {
                "seeds": seeds, "points": len(merged),
                "figures": summarise(merged, tuple(res["models"]))}
    figures["ccx_version"] = ccx_version()
    figures["fe_model"] = fine["stage1"].version
    figures["fe_mesh_fine"] = _mesh(fine["stage1"], beam)
    figures["fe_mesh_coarse"] = f"{meshes[0]} through the thickness"
    figures["beam_model"] = beam.version
    if overrides:
        figures["beam_overrides"] = overrides
    figures["fe_cpu_s_per_run_fine"] = _cpu(rows)
    figures["points"] = rows
    write_result("physics_fe_variant" if overrides else "physics_fe", figures)


def _write_reference(path: str, rows: dict[str, dict[str, Any]], fe: CalculixModel,
                     meshes: list[int]) -> None:
    """The 9 cases' FE figures (fine mesh) with their mesh-error estimates, as JSON."""
    ref = {k: {"fe": v["fine"], "mesh_error": _mesh_error(v)} for k, v in
           list(rows.items())[:9]}
    Path(path).write_text(json.dumps({
        "what": "CalculiX plane-strain reference of formtwin's flap bending; fe = "
                "the finer mesh, mesh_error = |fine - coarse|; plateau = mean force -40..-20 "
                "ms; peak time by a parabola through the maximum; angles in deg, forces N",
        "fe_model": fe.version, "ccx_version": ccx_version(),
        "meshes_through_thickness": meshes, "cases": ref}, indent=1) + "\n")


def _rows(beam: BendingModel, points: list[tuple[str, np.ndarray]], meshes: list[int],
          stage2: bool, cache: FeCache, lock: str, fine: dict[str, CalculixModel]
          ) -> dict[str, dict[str, Any]]:
    """Beam and FE (fine mesh at every point, coarse at the first nine) figures."""
    t = np.asarray(beam.spec.time)
    fes = {n: CalculixModel(beam.spec, n_thick=n, stage2=stage2) for n in meshes}
    fine["final" if stage2 and "stage1" in fine else "stage1"] = fes[meshes[1]]
    rows: dict[str, dict[str, Any]] = {}
    for k, (name, x) in enumerate(points):
        b = beam.run(x)
        rows[name] = {"beam": figures_of(b.curve, b.angles, t) if b.ok else None,
                      "fine": cache.run(fes[meshes[1]], x, lock),
                      "coarse": cache.run(fes[meshes[0]], x, lock) if k < 9 else None}
    return rows


def _final_angle(beam: BendingModel, points: list[tuple[str, np.ndarray]], meshes: list[int],
                 cache: FeCache, lock: str) -> dict[str, Any]:
    """Final-angle figures from two-stage FE runs on mesh ``meshes[0]`` at every point; the
    mesh error is ``|angle2(meshes[1]) - angle2(meshes[0])|`` at the centre (for all)."""
    t = np.asarray(beam.spec.time)
    fe, fe_fine = (CalculixModel(beam.spec, n_thick=n) for n in meshes)
    rows = {}
    for name, x in points:
        b = beam.run(x)
        rows[name] = {"beam": figures_of(b.curve, b.angles, t) if b.ok else None,
                      "fe": cache.run(fe, x, lock)}
    centre_fine = cache.run(fe_fine, points[0][1], lock)
    ok = {k: v for k, v in rows.items() if v["beam"] and v["fe"].get("ok")}
    d = np.array([v["beam"]["angle2"] - v["fe"]["angle2"] for v in ok.values()])
    err = abs(centre_fine["angle2"] - rows["centre"]["fe"]["angle2"]) \
        if centre_fine.get("ok") and rows["centre"]["fe"].get("ok") else float("inf")
    effects = {}
    for name in MAIN:
        lo, hi = ok.get(f"{name}_min"), ok.get(f"{name}_max")
        if lo and hi:
            fe_eff = hi["fe"]["angle2"] - lo["fe"]["angle2"]
            effects[f"{name}:angle2"] = {"fe": fe_eff,
                                         "beam": hi["beam"]["angle2"] - lo["beam"]["angle2"],
                                         "fe_mesh_error": 2 * err,
                                         "counted": bool(abs(fe_eff) > 2 * err)}
    agree = [np.sign(e["fe"]) == np.sign(e["beam"]) for e in effects.values() if e["counted"]]
    return {"angle2_err_max_deg": float(np.max(np.abs(d))) if d.size else None,
            "angle2_err_mean_deg": float(np.mean(d)) if d.size else None,
            "sensitivity_sign_agreement_final": float(np.mean(agree)) if agree else None,
            "sensitivity_effects_counted_final": len(agree),
            "fe_mesh_error_angle2_centre": err,
            "fe_mesh_final": f"{meshes[0]} through the thickness (error: {meshes[1]} at the "
                             "centre)",
            "fe_cpu_s_per_run_final": _cpu({k: {"fine": v["fe"]} for k, v in rows.items()}),
            "effects_final": effects, "points_final": rows,
            "fe_centre_final_fine": centre_fine}


def _independent(beam: BendingModel, n: int, seed: int, mesh1: int, mesh2: int,
                 cache: FeCache, lock: str, show: bool) -> dict[str, Any]:
    """The independent check (:mod:`fe_independent`): ``beam`` (as configured) and the same
    model with ``pinch_reach=0`` (2.3) against a stage-1 FE run on ``mesh1`` and a two-stage
    run on ``mesh2`` elements through the thickness at each of ``n`` DOE points."""
    from formtwin.dataset import DoeDataset
    from formtwin.defaults import bundled_doe

    doe = DoeDataset.load(bundled_doe("bending"))
    names = tuple(doe.spec.run_inputs.names)
    pts = independent_points(doe.inputs, names, 2 ** len(names), n, seed)
    t = np.asarray(beam.spec.time)
    other = {f.name: getattr(beam.disc, f.name) for f in dataclasses.fields(Discretisation)
             if f.name != "pinch_reach" and getattr(beam.disc, f.name) != f.default}
    beams = {beam.version: beam,
             "bending-2.3 (pinch_reach=0" + "".join(f", {k}={v}" for k, v in other.items())
             + ")": BendingModel(beam.spec, beam.geometry, beam.disc, pinch_reach=0.0)}
    fe1 = CalculixModel(beam.spec, n_thick=mesh1, stage2=False)
    fe2 = CalculixModel(beam.spec, n_thick=mesh2)
    points: dict[str, dict[str, Any]] = {}
    for p in pts:
        x = p["x"]
        rec: dict[str, Any] = {"row": p["row"], "group": p["group"], "pe_um": p["pe_um"],
                               "x": x.tolist(), "beam": {}}
        for label, model in beams.items():
            b = model.run(x)
            rec["beam"][label] = figures_of(b.curve, b.angles, t) if b.ok else None
        rec["fe1"] = cache.run(fe1, x, lock)
        rec["fe2"] = cache.run(fe2, x, lock)
        points[p["name"]] = rec
    if show:
        print(table(points, tuple(beams)))
    return {"what": "DOE LHS rows the pinch rule was not set on; beam minus CalculiX",
            "seed": seed, "n": n, "doe_model": doe.model_version,
            "fe_model_stage1": fe1.version, "fe_model_final": fe2.version,
            "models": {label: {"pinch_reach": m.disc.pinch_reach} for label, m in beams.items()},
            "figures": summarise(points, tuple(beams)), "points": points}


def _cpu(rows: dict[str, dict[str, Any]]) -> float:
    runs = [r["fine"]["cpu_s"] for r in rows.values() if r["fine"].get("ok")]
    return float(np.median(runs)) if runs else float("nan")


def _mesh(fe: CalculixModel, beam: BendingModel) -> str:
    s = fe.settings
    n_along = s.n_along(fe.geometry, float(beam.centre()[beam.spec.inputs.index["thickness"]]))
    return f"CPE8R {n_along} x {s.n_thick} (aspect {s.aspect:g})"


def _mesh_error(row: dict[str, Any]) -> dict[str, float]:
    f, c = row["fine"], row["coarse"]
    if not (c and f.get("ok") and c.get("ok")):
        return {}
    return {q: abs(float(f[q]) - float(c[q])) for q in QUANTITIES if np.isfinite(f[q])}


def compare(rows: dict[str, dict[str, Any]], stage2: bool) -> dict[str, Any]:
    """Errors of the beam model against the fine FE mesh and the sign agreement."""
    ok = {k: v for k, v in rows.items() if v["beam"] and v["fine"].get("ok")}
    b = {q: np.array([v["beam"][q] for v in ok.values()]) for q in QUANTITIES}
    f = {q: np.array([v["fine"][q] for v in ok.values()]) for q in QUANTITIES}
    err = {k: _mesh_error(v) for k, v in rows.items()}
    mesh = {q: max([e.get(q, 0.0) for e in err.values()] or [0.0]) for q in QUANTITIES}
    out: dict[str, Any] = {
        "points_compared": len(ok), "fe_failed": len(rows) - len(ok),
        "peak_rel_err_max": float(np.max(np.abs(b["peak"] / f["peak"] - 1))),
        "plateau_rel_err_max": float(np.max(np.abs(b["plateau"] / f["plateau"] - 1))),
        "peak_time_err_max_ms": float(np.max(np.abs(b["peak_time_ms"] - f["peak_time_ms"]))),
        "angle1_err_max_deg": float(np.max(np.abs(b["angle1"] - f["angle1"]))),
        "angle1_err_mean_deg": float(np.mean(b["angle1"] - f["angle1"])),
    }
    if stage2:
        out["angle2_err_max_deg"] = float(np.max(np.abs(b["angle2"] - f["angle2"])))
        out["angle2_err_mean_deg"] = float(np.mean(b["angle2"] - f["angle2"]))
    out.update({f"fe_mesh_error_{q}": mesh[q] for q in QUANTITIES if stage2 or q != "angle2"})
    effects: dict[str, dict[str, Any]] = {}
    for name in MAIN:
        lo, hi = rows.get(f"{name}_min"), rows.get(f"{name}_max")
        if not (lo and hi and lo["beam"] and hi["beam"] and lo["fine"].get("ok")
                and hi["fine"].get("ok")):
            continue
        for q in ("peak", "plateau", "angle1", "angle2"):
            fe_eff = float(hi["fine"][q]) - float(lo["fine"][q])
            tol = err[f"{name}_min"].get(q, np.inf) + err[f"{name}_max"].get(q, np.inf)
            effects[f"{name}:{q}"] = {
                "fe": fe_eff, "beam": hi["beam"][q] - lo["beam"][q], "fe_mesh_error": tol,
                "counted": bool(abs(fe_eff) > tol and np.isfinite(fe_eff))}
    for label, qs in (("", ("peak", "plateau", "angle1")), ("_final", ("angle2",))):
        counted = [e for k, e in effects.items() if k.split(":")[1] in qs and e["counted"]]
        agree = [np.sign(e["fe"]) == np.sign(e["beam"]) for e in counted]
        out[f"sensitivity_sign_agreement{label}"] = float(np.mean(agree)) if agree else None
        out[f"sensitivity_effects_counted{label}"] = len(agree)
    out["effects"] = effects
    return out


if __name__ == "__main__":
    main()
