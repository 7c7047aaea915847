"""A stand-in for an external FE code: closed-form V-die air bending of a strip.

It plays the part of the process engineer's own FE model for ``air_bend.toml``: it reads the
design CSV written by ``formtwin doe design`` and writes one result row per run the way an
FE post-processor would (inputs, the output ``bend_angle``, ``status`` and the punch force
as ``F@<stroke in mm>`` columns on its own stroke grid, finer than the spec's). It also
writes a production run (``production``): curves of products whose state drifts as the
spec's statistics say, with load-cell noise, in the curve-CSV layout of ``formtwin track``
and ``formtwin replay``.

The model (three-point bending of a strip of width ``B`` over a die of opening ``W = 24 mm
+ die_opening_offset``, half span ``L = W / 2``):

* punch displacement ``d``, wing angle ``alpha = atan(d / L)``, curvature under the punch
  ``kappa = 6 tan(alpha / 2) / L`` (for small ``d`` this is the elastic beam's
  ``F = 48 E I d / W^3``);
* surface strain ``eps = t kappa / 2``, flow stress ``sigma_f = sigma_y (1 + eps /
  EPS0)^n`` (power-law hardening);
* moment of the rectangular section: elastic ``E I kappa`` up to ``kappa_e = 2 sigma_f /
  (E t)``, then elastic-plastic ``M_p (1 - (kappa_e / kappa)^2 / 3)``, ``M_p = sigma_f B
  t^2 / 4``;
* punch force ``F = 2 M / (L cos alpha)``; the ram stroke ``s = d + F / k`` with ``k`` the
  press and tool stiffness (the curve is over the ram stroke, as a stroke sensor sees it);
* after the stroke ``s_max``, elastic unloading: ``kappa_final = kappa_max - M_max / (E I)``,
  included bend angle ``180 - 4 atan(kappa_final L / 6)`` degrees.

Every number is in the spec's internal units (mm, N, MPa). Run::

    python examples/air_bend/fe_air_bend.py fe design.csv fe_results.csv
    python examples/air_bend/fe_air_bend.py production --n 200 --seed 1 --out line.csv
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec, load_spec

FloatArray = NDArray[np.float64]

SPEC = Path(__file__).with_name("air_bend.toml")
#: strip width, mm; nominal die opening, mm; reference strain of the hardening law
WIDTH, DIE_OPENING, EPS0 = 20.0, 24.0, 0.01
#: the FE code's own stroke grid, mm (finer than the spec's 61 samples; import interpolates)
FE_STROKE = np.linspace(0.0, 8.0, 81)


def air_bend(X: FloatArray, stroke: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Force curves (n, len(stroke)) N over the ram ``stroke`` (mm) and included bend angles
    (n,) deg after springback at the last stroke, for run inputs ``X`` (n, 6) in internal
    units: yield stress MPa, thickness mm, hardening exponent, Young's modulus MPa, die
    opening offset mm, stiffness N/mm."""
    X = np.atleast_2d(np.asarray(X, dtype=np.float64))
    sy, t, n, E, dw, k = (X[:, j:j + 1] for j in range(6))
    L = 0.5 * (DIE_OPENING + dw)
    d = np.linspace(0.0, 1.1 * float(stroke[-1]), 1201)[None, :]
    alpha = np.arctan(d / L)
    kappa = 6.0 * np.tan(alpha / 2.0) / L
    sf = sy * (1.0 + 0.5 * t * kappa / EPS0) ** n
    inertia = WIDTH * t**3 / 12.0
    kappa_e = 2.0 * sf / (E * t)
    plastic = sf * WIDTH * t**2 / 4.0 * (1.0 - (kappa_e / np.maximum(kappa, kappa_e)) ** 2 / 3)
    M = np.where(kappa < kappa_e, E * inertia * kappa, plastic)
    F = 2.0 * M / (L * np.cos(alpha))
    s = d + F / k
    curves = np.array([np.interp(stroke, s[i], F[i]) for i in range(X.shape[0])])
    # unloading at the end of the stroke: the displacement there, its moment and curvature
    d_end = np.array([np.interp(stroke[-1], s[i], d[0]) for i in range(X.shape[0])])[:, None]
    a_end = np.arctan(d_end / L)
    k_end = 6.0 * np.tan(a_end / 2.0) / L
    M_end = np.array([np.interp(stroke[-1], s[i], M[i]) for i in range(X.shape[0])])[:, None]
    k_final = k_end - M_end / (E * inertia)
    angle = 180.0 - 4.0 * np.degrees(np.arctan(k_final * L / 6.0))
    return curves, angle[:, 0]


def run_fe(design: Path, out: Path, spec: ProcessSpec | None = None) -> int:
    """Read a design CSV (``formtwin doe design``), write the FE results CSV; returns rows."""
    spec = spec or load_spec(SPEC)
    box = spec.run_inputs
    with open(design, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    scale = np.array([v.scale for v in box])
    X = np.array([[float(r[name]) for name in box.names] for r in rows]) * scale
    curves, angles = air_bend(X, FE_STROKE)
    with open(out, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["run", *box.names, *spec.output_names, "status",
                    *(f"F@{s:g}" for s in FE_STROKE)])
        for r, a, c in zip(rows, angles, curves, strict=True):
            ok = bool(np.all(np.isfinite(c)) and np.isfinite(a))
            w.writerow([r["run"], *(r[name] for name in box.names), f"{a:.9g}",
                        "ok" if ok else "non-finite result", *(f"{v:.9g}" for v in c)])
    return len(rows)


def production(n: int, seed: int, spec: ProcessSpec | None = None
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A production run of ``n`` products: state by eq. 4-5 about means drawn in
    ``[mu_min, mu_max]``, constant machine parameters drawn in their bounds, load-cell noise
    ``[curve] noise_sd``. Returns the run inputs (n, 6), curves (n, n_t) on the spec's
    grid and bend angles (n,)."""
    spec = spec or load_spec(SPEC)
    rng = np.random.default_rng(seed)
    st, pa = spec.state, spec.params
    mu = rng.uniform(st.mu_min, st.mu_max)
    theta = rng.uniform(pa.lo, pa.hi)
    x = np.empty((n, len(st)))
    x[0] = mu + st.sigma * rng.standard_normal(len(st))
    for i in range(1, n):
        x[i] = mu + st.rho * (x[i - 1] - mu) + np.sqrt(1 - st.rho**2) * st.sigma * \
            rng.standard_normal(len(st))
    X = np.hstack([np.clip(x, st.lo, st.hi), np.tile(theta, (n, 1))])
    curves, angles = air_bend(X, spec.time)
    curves += spec.noise_sd * rng.standard_normal(curves.shape)
    return X, curves, angles


def sensor_values(X: FloatArray, angles: FloatArray, seed: int,
                  spec: ProcessSpec | None = None) -> dict[str, FloatArray]:
    """Each ``[[sensor]]`` of the spec's value of every product (n,): the measured state
    variable or output plus the sensor's Gaussian noise, internal units."""
    spec = spec or load_spec(SPEC)
    rng = np.random.default_rng([seed, 1])
    out = {}
    for s in spec.sensors:
        true = X[:, spec.state.index[s.measures]] if s.kind == "state" else angles
        out[s.name] = true + s.noise * rng.standard_normal(true.shape[0])
    return out


def write_line(path: Path, curves: FloatArray, angles: FloatArray,
               sensors: dict[str, FloatArray] | None = None) -> None:
    """The curve-CSV layout of ``formtwin track`` and ``formtwin replay``: ``part_id, cycle,
    f0 .. f{n_t-1}, angle1`` and a ``sensor_<name>`` column per sensor."""
    sensors = sensors or {}
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["part_id", "cycle", *(f"f{j}" for j in range(curves.shape[1])), "angle1",
                    *(f"sensor_{n}" for n in sensors)])
        for i, (c, a) in enumerate(zip(curves, angles, strict=True)):
            w.writerow([f"AB-{i + 1:05d}", i + 1, *(f"{v:.6g}" for v in c), f"{a:.6g}",
                        *(f"{v[i]:.7g}" for v in sensors.values())])


def main(argv: list[str] | None = None) -> int:
    """Command line: ``fe DESIGN OUT`` or ``production --n N --seed S --out OUT``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    fe = sub.add_parser("fe", help="run the design CSV, write the FE results CSV")
    fe.add_argument("design", type=Path)
    fe.add_argument("out", type=Path)
    pr = sub.add_parser("production", help="write a production run's curves (track/replay)")
    pr.add_argument("--n", type=int, default=200)
    pr.add_argument("--seed", type=int, default=1)
    pr.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if args.cmd == "fe":
        print(f"{args.out}: {run_fe(args.design, args.out)} FE runs")
    else:
        X, curves, angles = production(args.n, args.seed)
        write_line(args.out, curves, angles, sensor_values(X, angles, args.seed))
        print(f"{args.out}: {args.n} products")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
