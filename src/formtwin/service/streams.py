"""Stroke streams: what ``formtwin replay`` publishes, as a press line would.

A stream is a sequence of :class:`~formtwin.service.messages.Stroke`. It is read from

* ``.npz`` (``allow_pickle=False``): ``curves (n, n_t)`` N, optional ``angles (n, 2)``
  degrees, ``part_ids (n,)`` strings, ``cycles (n,)`` integers and ``u (n, n_controls)``
  press settings (sent as each stroke's ``u``);
* ``.nc`` (NetCDF, e.g. a study realisation or a DOE dataset): the variable ``curves``
  (``product``/``run`` x ``time``; a ``source`` dimension is selected with ``source``), and
  ``angles`` and ``ok`` when present (products with ``ok = False`` are skipped);
* ``.csv``: one product per row, columns ``part_id, cycle, f0 .. f{n_t-1}`` and optionally
  ``angle1 .. angleK`` (the spec's K outputs, in their ``[[output]]`` order).

The sensor values of a stream (:func:`read_sensor_values`): the arrays ``sensor_<name>``
of an ``.npz`` or the columns ``sensor_<name>`` of a ``.csv``, one per product, NaN or an
empty cell where a product has none; ``formtwin replay`` sends them as sensor messages
when the line would (:func:`read_readings`), ``formtwin track`` fuses them.

:func:`make_stream` writes a synthetic stream from a process model (default the analytic
stand-in; the line's state means ``mu`` drawn in the spec's ``[mu_min, mu_max]``, state
evolving by eq. 4-5, constant machine parameters and deviation, Gaussian sensor noise) for
the demo, the tests and the benchmark; the file keeps the truth (``truth``, ``mu``).
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.deviation import DeviationModel
from formtwin.measurement import ProcessModel
from formtwin.production import draw_production_run
from formtwin.service.messages import Stroke, stroke_digest
from formtwin.service.readings import Reading
from formtwin.spec import ProcessSpec
from formtwin.spec.sensors import line_sensors, output_column, sensor_by_name

FloatArray = NDArray[np.float64]

_T0 = datetime(2026, 1, 1, tzinfo=UTC)


def make_stream(path: str | Path, n: int, seed: int = 0, noise_N: float = 2.0,
                spec: ProcessSpec | None = None, deviation: bool = True,
                period_s: float = 0.5, model: ProcessModel | None = None,
                sensors: tuple[str, ...] = ()) -> Path:
    """Write ``n`` synthetic strokes to an ``.npz`` stream file and return its path.

    Parameters
    ----------
    path : str or Path
        Output file (``.npz``).
    n : int
        Number of products.
    seed : int
        Seed of everything random in the stream.
    noise_N : float
        Std of the Gaussian sensor noise added to each sample, N.
    spec : ProcessSpec, optional
        Defaults to the bundled demonstrator (ignored when ``model`` is given).
    deviation : bool
        Distort the curves with a deviation ``theta_d`` drawn in its bounds.
    period_s : float
        Nominal time between strokes (for the timestamps), s.
    model : ProcessModel, optional
        The model making the curves and angles; default the analytic stand-in.
    sensors : tuple of str
        The spec's ``[[sensor]]`` entries to draw for every product besides the curve
        (the measured state variable or model output plus the sensor's Gaussian noise),
        saved as ``sensor_<name> (n,)`` and sent by ``formtwin replay`` as sensor messages
        (:func:`read_readings`).
    """
    if n < 1:
        raise ValueError(f"n = {n}, expected >= 1")
    if model is None:
        from formtwin.defaults import analytic_model

        model = analytic_model(spec)
    spec = model.spec
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    run = draw_production_run(spec, n, rng, deviation=deviation)
    X, theta_d = run.inputs, run.theta_d
    curves, angles = model.predict_curves(X), model.predict_angles(run.run_inputs)
    if deviation:
        curves = DeviationModel.from_spec(spec).apply(curves, np.tile(theta_d, (n, 1)))
    curves = curves + noise_N * rng.standard_normal(curves.shape)
    cycles = np.arange(1, n + 1, dtype=np.int64)
    stamps = [(_T0 + timedelta(seconds=period_s * float(c))).isoformat().replace("+00:00", "Z")
              for c in cycles]
    extra: dict[str, Any] = {}
    srng = np.random.default_rng(np.random.SeedSequence([seed, 11]))
    for name in sensors:
        sensor = sensor_by_name(line_sensors(spec), name)
        true = X[:, spec.state.index[sensor.measures]] if sensor.kind == "state" else \
            angles[:, output_column(spec, sensor.measures)]
        extra[f"sensor_{name}"] = true + sensor.noise * srng.standard_normal(n)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **extra, curves=curves, angles=angles, part_ids=np.array(
        [f"P{seed:03d}-{c:07d}" for c in cycles]), cycles=cycles,
        timestamps=np.array(stamps), truth=np.hstack([X, np.tile(theta_d, (n, 1))]),
        names=np.array(spec.augmented.names), mu=run.mu)
    return out if out.suffix == ".npz" else out.with_name(out.name + ".npz")


def _strokes(curves: FloatArray, angles: FloatArray | None, part_ids: list[str],
             cycles: NDArray[np.int64], stamps: list[str],
             u: FloatArray | None = None) -> Iterator[Stroke]:
    for i in range(curves.shape[0]):
        a = None if angles is None or not np.all(np.isfinite(angles[i])) else angles[i]
        c = np.asarray(curves[i], dtype=np.float64)
        yield Stroke(part_id=part_ids[i], cycle=int(cycles[i]), timestamp=stamps[i],
                     force_N=c, angles_deg=a, digest=stroke_digest(c),
                     u=None if u is None else np.asarray(u[i], dtype=np.float64).reshape(-1))


def _defaults(n: int, stem: str) -> tuple[list[str], NDArray[np.int64], list[str]]:
    cycles = np.arange(1, n + 1, dtype=np.int64)
    ids = [f"{stem}-{c:07d}" for c in cycles]
    stamps = [(_T0 + timedelta(seconds=0.5 * float(c))).isoformat().replace("+00:00", "Z")
              for c in cycles]
    return ids, cycles, stamps


def read_stream(path: str | Path, source: str = "gFE") -> list[Stroke]:
    """Read a stream file (``.npz``, ``.nc`` or ``.csv``, see the module doc).

    Parameters
    ----------
    path : str or Path
        The file.
    source : str
        For NetCDF files with a ``source`` dimension: which source to replay.
    """
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: no such stream file")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        with np.load(p, allow_pickle=False) as z:
            if "curves" not in z:
                raise ValueError(f"{p}: no 'curves' array (keys: {', '.join(z.files)})")
            curves = np.asarray(z["curves"], dtype=np.float64)
            n = curves.shape[0]
            ids, cycles, stamps = _defaults(n, p.stem)
            angles = np.asarray(z["angles"], np.float64) if "angles" in z else None
            if "part_ids" in z:
                ids = [str(s) for s in z["part_ids"]]
            if "cycles" in z:
                cycles = np.asarray(z["cycles"], dtype=np.int64)
            if "timestamps" in z:
                stamps = [str(s) for s in z["timestamps"]]
            u = np.asarray(z["u"], dtype=np.float64) if "u" in z else None
        return list(_strokes(curves, angles, ids, cycles, stamps, u))
    if suffix == ".nc":
        import xarray as xr

        with xr.open_dataset(p, engine="h5netcdf") as ds:
            if "curves" not in ds:
                raise ValueError(f"{p}: no 'curves' variable")
            sel = ds.sel(source=source) if "source" in ds["curves"].dims else ds
            curves = np.asarray(sel["curves"].values, dtype=np.float64)
            angles = np.asarray(sel["angles"].values, np.float64) if "angles" in sel else None
            ok = np.asarray(sel["ok"].values, bool) if "ok" in sel else \
                np.all(np.isfinite(curves), axis=1)
        ids, cycles, stamps = _defaults(curves.shape[0], p.stem)
        keep = np.flatnonzero(ok)
        return list(_strokes(curves[keep], None if angles is None else angles[keep],
                             [ids[i] for i in keep], cycles[keep], [stamps[i] for i in keep]))
    if suffix == ".csv":
        with open(p, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        if not rows:
            return []
        fcols = sorted((k for k in rows[0] if k and k[0] == "f" and k[1:].isdigit()),
                       key=lambda k: int(k[1:]))
        curves = np.array([[float(r[k]) for k in fcols] for r in rows])
        acols = [f"angle{k}" for k in range(1, len(rows[0]) + 1) if f"angle{k}" in rows[0]]
        angles = np.array([[float(r[k]) for k in acols] for r in rows]) if acols else None
        d_ids, _, d_stamps = _defaults(len(rows), p.stem)
        ids = [r.get("part_id") or d_ids[i] for i, r in enumerate(rows)]
        cycles = np.array([int(r.get("cycle") or i + 1) for i, r in enumerate(rows)])
        stamps = [r.get("timestamp") or d_stamps[i] for i, r in enumerate(rows)]
        return list(_strokes(curves, angles, ids, cycles, stamps))
    raise ValueError(f"{p}: unknown stream format {suffix!r} (expected .npz, .nc or .csv)")


def read_sensor_values(path: str | Path) -> dict[str, FloatArray]:
    """The sensor values of a stream file by sensor name, each (n,) in the measured
    quantity's internal unit (NaN: none): the arrays ``sensor_<name>`` of an ``.npz``, the
    columns ``sensor_<name>`` of a ``.csv`` (an empty cell: none); none in other files.
    ``ValueError`` naming the row and column of a value that is not a number."""
    return _sensor_table(Path(path))[1]


def _sensor_table(p: Path) -> tuple[list[str], dict[str, FloatArray]]:
    """The products' part ids (as :func:`read_stream` gives them) and
    :func:`read_sensor_values`, in one read of the file (no ids without sensor values)."""
    suffix = p.suffix.lower()
    if suffix == ".npz":
        with np.load(p, allow_pickle=False) as z:
            values = {k[len("sensor_"):]: np.asarray(z[k], dtype=np.float64)
                      for k in sorted(z.files) if k.startswith("sensor_")}
            if not values:
                return [], {}
            n = int(z["curves"].shape[0])
            ids = [str(v) for v in z["part_ids"]] if "part_ids" in z \
                else _defaults(n, p.stem)[0]
        return ids, values
    if suffix != ".csv":
        return [], {}
    with open(p, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    out: dict[str, FloatArray] = {}
    for col in sorted(c for c in (rows[0] if rows else {}) if c and c.startswith("sensor_")):
        vals = np.full(len(rows), np.nan)
        for i, r in enumerate(rows):
            cell = (r.get(col) or "").strip()
            if cell:
                try:
                    vals[i] = float(cell)
                except ValueError:
                    raise ValueError(f"{p}: row {i + 2}, column {col}: {cell!r} is not a "
                                     "number") from None
        out[col[len("sensor_"):]] = vals
    d_ids = _defaults(len(rows), p.stem)[0]
    return [r.get("part_id") or d_ids[i] for i, r in enumerate(rows)], out


def read_readings(path: str | Path, spec: ProcessSpec | None = None
                  ) -> list[tuple[int, Reading]]:
    """The sensor values of a stream (:func:`read_sensor_values`) as ``(k, reading)``:
    sent after the ``k``-th stroke, ``k`` the product plus the sensor's delay in ``spec``
    (default the demonstrator's; the last stroke at the most); a state variable's value
    without delay (a strip gauge, upstream of the press) before its product's stroke:
    ``k`` the product minus one (-1: before the first stroke)."""
    p = Path(path)
    ids, values = _sensor_table(p)
    if not values:
        return []
    if spec is None:
        from formtwin.spec import load_spec

        spec = load_spec()
    delays = {s.name: s.delay if s.delay or s.kind != "state" else -1
              for s in line_sensors(spec)}
    unknown = sorted(set(values) - set(delays))
    if unknown:
        raise ValueError(f"{p}: sensor_{unknown[0]}: not a sensor of spec {spec.name!r} "
                         f"(its sensors: {', '.join(delays) or 'none'}; --spec)")
    n = len(ids)
    out: list[tuple[int, Reading]] = []
    for name, vals in values.items():
        for i, v in enumerate(vals[:n]):
            if np.isfinite(v):
                out.append((min(i + delays[name], n - 1), Reading(ids[i], name, float(v))))
    out.sort(key=lambda t: t[0])  # stable: by product within a position
    return out


def interleave(strokes: list[Stroke], readings: list[tuple[int, Reading]], start: int = 0
               ) -> list[Stroke | Reading]:
    """``strokes`` (the stream's from its ``start``-th) with each reading after the stroke
    it is due after (:func:`read_readings`; a reading of one of ``strokes`` due after
    stroke ``start - 1``: before the first); readings due outside them are left out."""
    by: dict[int, list[Reading]] = {}
    for k, r in readings:
        by.setdefault(k - start, []).append(r)
    sent = {s.part_id for s in strokes}
    out: list[Stroke | Reading] = [r for r in by.get(-1, ()) if r.part_id in sent]
    for k, s in enumerate(strokes):
        out.append(s)
        out.extend(by.get(k, ()))
    return out
