"""DOE datasets: inputs, force curves, angles, failures and their provenance, in HDF5.

A dataset file is self-describing HDF5 (h5py): datasets ``inputs (n, 10)``,
``curves (n, n_t)``, ``angles (n, n_outputs)`` (the spec's scalar outputs), ``time (n_t,)``,
``ok (n,)``, ``done (n,)`` and
``reason (n,)``, each with its units and names as attributes; the root attributes hold
the process spec's TOML text, the model version and the formtwin version. ``done`` marks
rows already evaluated, so the DOE runner appends results as they arrive and resumes an
interrupted run. Nothing is pickled.

A user's own FE results come in through :func:`import_csv`; :func:`export_design` writes
the design an external FE code is to run (the input columns of that CSV).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

import formtwin
from formtwin.spec import ProcessSpec, parse_spec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
FORMAT = "formtwin.doe/1"


class DatasetError(ValueError):
    """A dataset file or CSV import is malformed; the message names the field."""


@dataclass(frozen=True)
class DoeDataset:
    """Results of a design of experiments, internal units (mm, N, s, MPa; degrees).

    ``inputs (n, n_run_inputs)`` the run inputs ``(x, theta, u)``, ``curves (n, n_t)``
    N, ``angles (n, n_outputs)`` the spec's scalar outputs (``spec.output_names``),
    ``ok (n,)`` run succeeded, ``reason (n,)`` why not, ``time (n_t,)`` s.
    """

    spec: ProcessSpec
    inputs: FloatArray
    curves: FloatArray
    angles: FloatArray
    ok: BoolArray
    reason: NDArray[np.str_]
    model_version: str

    @property
    def time(self) -> FloatArray:
        return self.spec.time

    @property
    def spec_text(self) -> str:
        return self.spec.text

    @property
    def n(self) -> int:
        return int(self.inputs.shape[0])

    def successful(self) -> DoeDataset:
        """Only the rows whose run succeeded."""
        m = self.ok
        return replace(self, inputs=self.inputs[m], curves=self.curves[m],
                       angles=self.angles[m], ok=self.ok[m], reason=self.reason[m])

    def save(self, path: str | Path) -> Path:
        """Write the dataset as HDF5 (every row marked done)."""
        p = Path(path)
        with h5py.File(p, "w") as f:
            _layout(f, self.spec, self.inputs, self.model_version)
            f["curves"][...] = self.curves
            f["angles"][...] = self.angles
            f["ok"][...] = self.ok
            f["reason"][...] = self.reason.astype(object)
            f["done"][...] = True
        return p

    @classmethod
    def load(cls, path: str | Path, complete: bool = True) -> DoeDataset:
        """Read a dataset; with ``complete`` (default) refuse one with rows not yet run."""
        p = Path(path)
        try:
            f = h5py.File(p, "r")
        except OSError as exc:
            raise DatasetError(f"{p}: not a readable HDF5 dataset ({exc})") from exc
        with f:
            if f.attrs.get("format") != FORMAT:
                raise DatasetError(f"{p}: format = {f.attrs.get('format')!r}, expected {FORMAT!r}")
            spec = parse_spec(str(f.attrs["spec_text"]), source=f"{p}[spec_text]")
            done = f["done"][...].astype(bool)
            if complete and not done.all():
                raise DatasetError(f"{p}: {int((~done).sum())} of {done.size} runs not done; "
                                   "resume the DOE run first")
            reason = np.array([r.decode() if isinstance(r, bytes) else str(r)
                               for r in f["reason"][...]])
            return cls(spec=spec, inputs=f["inputs"][...], curves=f["curves"][...],
                       angles=f["angles"][...], ok=f["ok"][...].astype(bool) & done,
                       reason=reason, model_version=str(f.attrs["model_version"]))


def _layout(f: h5py.File, spec: ProcessSpec, inputs: FloatArray, model_version: str) -> None:
    """Create the datasets and attributes of a new file for the design ``inputs``."""
    n = inputs.shape[0]
    f.attrs.update({"format": FORMAT, "spec_text": spec.text, "spec_source": spec.source,
                    "model_version": model_version, "formtwin_version": formtwin.__version__,
                    "units": "mm, N, s, MPa; angles in degrees"})
    d = f.create_dataset("inputs", data=inputs)
    d.attrs.update({"names": json.dumps(spec.run_inputs.names),
                    "units": json.dumps([v.internal_unit for v in spec.run_inputs])})
    f.create_dataset("time", data=spec.time).attrs["units"] = "s"
    f.create_dataset("curves", shape=(n, spec.n_t), dtype="f8", fillvalue=np.nan,
                     compression="gzip", shuffle=True).attrs["units"] = "N"
    a = f.create_dataset("angles", shape=(n, spec.n_outputs), dtype="f8", fillvalue=np.nan)
    a.attrs.update({"names": json.dumps(spec.output_names),
                    "units": json.dumps([o.unit for o in spec.outputs])})
    f.create_dataset("ok", shape=(n,), dtype="bool")
    f.create_dataset("done", shape=(n,), dtype="bool")
    f.create_dataset("reason", shape=(n,), dtype=h5py.string_dtype())


def open_for_run(path: Path, spec: ProcessSpec, inputs: FloatArray,
                 model_version: str) -> h5py.File:
    """Open (resume) or create the working file of a DOE run over ``inputs``.

    An existing file must hold the same design and model version, else it is refused.
    """
    if path.exists():
        f = h5py.File(path, "r+")
        same = (f.attrs.get("format") == FORMAT and f["inputs"].shape == inputs.shape
                and np.array_equal(f["inputs"][...], inputs))
        if not same:
            f.close()
            raise DatasetError(f"{path}: holds a different design; choose another file")
        if f.attrs["model_version"] != model_version:
            version = f.attrs["model_version"]
            f.close()
            raise DatasetError(f"{path}: model_version = {version!r}, the simulator is "
                               f"{model_version!r}; choose another file")
        return f
    path.parent.mkdir(parents=True, exist_ok=True)
    f = h5py.File(path, "w")
    _layout(f, spec, inputs, model_version)
    return f


def import_csv(path: str | Path, spec: ProcessSpec, model_version: str = "imported") -> DoeDataset:
    """Read a user's FE results: one row per run.

    Columns: the spec's input names (in the spec file's units, as in Table 1), optionally
    its control names (missing: the nominal setting), one column per output of the spec
    (``spec.output_names``, e.g. ``angle_stage1`` and ``angle_stage2`` in degrees), an
    optional ``status`` (``ok`` or a failure reason), and the force curve as columns
    ``F@<axis value>`` (N) with the axis value in the spec's ``[curve] unit`` (ms for the
    demonstrator, mm for a stroke axis). The curve is linearly interpolated onto the
    spec's grid, which its axis values must cover. :func:`curve_columns` names the columns
    of the spec's own grid (what :func:`export_design` writes).
    """
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise DatasetError(f"{p}: cannot read ({exc.strerror})") from exc
    if len(rows) < 2:
        raise DatasetError(f"{p}: needs a header and at least one row")
    header = [h.strip() for h in rows[0]]
    col = {h: i for i, h in enumerate(header)}
    outputs = spec.output_names
    missing = [n for n in (*spec.inputs.names, *outputs) if n not in col]
    if missing:
        raise DatasetError(f"{p}: missing column(s) {missing}")
    curve_cols = [h for h in header if h.startswith("F@")]
    try:
        t_csv = np.array([float(h[2:]) for h in curve_cols]) * spec.axis_scale
    except ValueError as exc:
        raise DatasetError(f"{p}: curve column names must be F@<{spec.axis} in "
                           f"{spec.axis_unit}> ({exc})") from exc
    unit, sc = spec.axis_unit, spec.axis_scale
    if t_csv.size < 2 or np.any(np.diff(t_csv) <= 0):
        raise DatasetError(f"{p}: the F@<{unit}> columns must be at least 2 increasing values")
    tol = 1e-9 * float(spec.time[-1] - spec.time[0])
    if t_csv[0] > spec.time[0] + tol or t_csv[-1] < spec.time[-1] - tol:
        raise DatasetError(f"{p}: curve {spec.axis}s [{t_csv[0] / sc:g}, {t_csv[-1] / sc:g}] "
                           f"{unit} do not cover the spec window [{spec.time[0] / sc:g}, "
                           f"{spec.time[-1] / sc:g}] {unit}")
    box = spec.run_inputs
    scale = np.array([v.scale for v in box])
    n = len(rows) - 1
    inputs, angles = np.empty((n, len(box))), np.empty((n, len(outputs)))
    curves = np.empty((n, spec.n_t))
    ok = np.ones(n, dtype=bool)
    reason = np.full(n, "", dtype=object)
    for r, row in enumerate(rows[1:]):
        line = r + 2

        def number(name: str, row: list[str] = row, line: int = line) -> float:
            try:
                v = float(row[col[name]])
            except (ValueError, IndexError):
                raise DatasetError(f"{p}: line {line}, column {name!r} = "
                                   f"{row[col[name]] if col[name] < len(row) else ''!r}, "
                                   "expected a number") from None
            return v

        status = row[col["status"]].strip() if "status" in col and col["status"] < len(row) \
            else "ok"
        inputs[r] = [number(v.name) if v.name in col else v.nominal / v.scale for v in box]
        if status != "ok":
            ok[r], reason[r] = False, status or "failed"
            angles[r], curves[r] = np.nan, np.nan
            continue
        angles[r] = [number(name) for name in outputs]
        values = np.array([number(h) for h in curve_cols])
        bad = [name for name, v in zip((*outputs, *curve_cols),
                                       np.r_[angles[r], values], strict=True)
               if not np.isfinite(v)]
        if bad:
            raise DatasetError(f"{p}: line {line}, column {bad[0]!r} is not finite")
        curves[r] = np.interp(spec.time, t_csv, values)
    inputs *= scale
    outside = (inputs < box.lo - 1e-12 * np.abs(box.lo)) | (
        inputs > box.hi + 1e-12 * np.abs(box.hi))
    if outside.any():
        r, c = np.argwhere(outside)[0]
        v = box.variables[c]
        raise DatasetError(f"{p}: line {r + 2}, column {v.name!r} = {inputs[r, c] / v.scale:g} "
                           f"{v.unit} is outside [{v.lo / v.scale:g}, {v.hi / v.scale:g}]")
    return DoeDataset(spec=spec, inputs=inputs, curves=curves, angles=angles, ok=ok,
                      reason=reason.astype(str), model_version=model_version)


def curve_columns(spec: ProcessSpec) -> list[str]:
    """The ``F@<axis value>`` column names of the spec's own curve grid (file units)."""
    return [f"F@{v / spec.axis_scale:.10g}" for v in spec.time]


def export_design(spec: ProcessSpec, X: FloatArray, path: str | Path) -> Path:
    """Write the design ``X`` (n, n_run_inputs), internal units, as a CSV for an external
    FE code: a ``run`` number and one column per run input in the spec file's units (as
    :func:`import_csv` reads them back). The FE code adds the output columns, ``status``
    and the curve (:func:`curve_columns`)."""
    X = np.asarray(X, dtype=np.float64)
    box = spec.run_inputs
    if X.ndim != 2 or X.shape[1] != len(box):
        raise DatasetError(f"design of shape {X.shape}, expected (n, {len(box)}) "
                           f"({', '.join(box.names)})")
    scale = np.array([v.scale for v in box])
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["run", *box.names])
        for i, row in enumerate(X / scale):
            w.writerow([i, *(f"{v:.12g}" for v in row)])
    return p
