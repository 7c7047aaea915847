"""``formtwin track``: run the tracker over a file of measured curves, write estimates."""

from __future__ import annotations

import argparse
import csv
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.cli.options import add_tracker_options, noise_note, spec_defaults, tracker_config

log = logging.getLogger(__name__)

#: variable names tried, in order, in npz and NetCDF curve files
CURVE_KEYS = ("curves", "curve", "force", "z")


def register(sub: Any) -> None:
    """Add the ``track`` command to the subparsers ``sub``."""
    p = sub.add_parser(
        "track", help="estimate state, parameters and angles from a file of force curves",
        description="Run the particle-filter tracker over the curves of FILE, one product a "
                    "row, and write per-product estimates (mean and std of the augmented "
                    "variables in internal units, the predicted outputs of the spec as "
                    "angle<k>_mean/_std in its [[output]] order, ESS, and the absolute goodness "
                    "of fit: health ok/degraded/no_fit, fit_distance2, fit_quantile). The "
                    "force sensor's std defaults to the spec's [curve] noise_sd (0 without "
                    "it: then any real sensor's noise reads as a model mismatch). With "
                    "--sensors, the file's values of those sensors (npz arrays or CSV columns "
                    "sensor_<name>, internal units) are fused when the line knew them: a "
                    "state variable's without delay before its product's step, the others "
                    "after the step of the product <delay> later; with a camera of the final "
                    "angle the issued final_predicted_deg and its calibrated 90 % interval "
                    "are written too.")
    p.add_argument("--metamodel", required=True,
                   help="metamodel file, or 'analytic' for the closed-form stand-in")
    p.add_argument("--curves", required=True, type=Path,
                   help="curves (n, n_t) in N: .npz (key 'curves'), .csv (one curve a row: "
                        "bare numbers, or the stream layout part_id, cycle, f0 .. f<n_t-1>, "
                        "angle<k>, sensor_<name> of replay; docs/reference/csv.md), a DOE "
                        "dataset .h5 "
                        "(formtwin.dataset) or a "
                        "NetCDF file with a variable 'curves' (study realisations: --source)")
    p.add_argument("--out", required=True, type=Path,
                   help="estimates: .csv, or .parquet (needs pyarrow)")
    p.add_argument("--source", help="for a study realisation file (curves by source): which "
                   "curves to track (MM, gMM, FE, gFE)")
    p.add_argument("--u", dest="settings",
                   help="each product's press setting (the spec's controls, mm as in the MQTT "
                        "payload): a number for every product, or a .csv/.npz file with one row "
                        "per curve; default: read from a DOE dataset or study realisation "
                        "file when it has them, else the nominal setting")
    p.add_argument("--measurement", type=Path,
                   help="measurement-model .npz; default: built by Monte Carlo on the model")
    add_tracker_options(p)
    p.add_argument("--checkpoint", type=Path, help="write the tracker state here at the end")
    p.set_defaults(run=_track)


def read_curves(path: Path, n_t: int, source: str | None = None) -> NDArray[np.float64]:
    """Curves (n, n_t) from an npz, CSV or NetCDF/HDF5 file; ``ValueError`` if absent.

    A NetCDF variable with a ``source`` dimension (the study's realisation files) needs
    ``source`` to pick one of them.
    """
    suffix = path.suffix.lower()
    if not path.exists():
        raise ValueError(f"--curves {path}: no such file")
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            keys = [k for k in CURVE_KEYS if k in z] or list(z.keys())[:1]
            if not keys:
                raise ValueError(f"{path}: empty npz")
            arr = np.asarray(z[keys[0]], dtype=np.float64)
    elif suffix in (".csv", ".txt"):
        with open(path, encoding="utf-8") as fh:
            first = fh.readline()
        header = [h.strip() for h in first.split(",")]
        fcols = [i for i, h in enumerate(header) if h[:1] == "f" and h[1:].isdigit()]
        try:
            [float(v) for v in header]
            skip = 0
        except ValueError:
            skip = 1  # a header line
        if skip and fcols:  # the stream layout of replay: part_id, cycle, f0 .., angle<k>
            order = sorted(fcols, key=lambda i: int(header[i][1:]))
            arr = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, usecols=order,
                             dtype=np.float64)
        else:
            arr = np.loadtxt(path, delimiter=",", skiprows=skip, ndmin=2)
    elif suffix in (".h5", ".hdf5") and _is_doe_dataset(path):
        from formtwin.dataset import DoeDataset

        data = DoeDataset.load(path, complete=False)
        arr = np.where(data.ok[:, None], data.curves, np.nan)  # failed runs: skipped
    elif suffix in (".nc", ".h5", ".hdf5", ".nc4"):
        import xarray as xr

        with xr.open_dataset(path, engine="h5netcdf") as ds:
            names = [k for k in CURVE_KEYS if k in ds.data_vars] or [
                str(k) for k, v in ds.data_vars.items() if v.ndim == 2 and v.shape[-1] == n_t]
            if not names:
                raise ValueError(f"{path}: no curve variable (tried {', '.join(CURVE_KEYS)})")
            var = ds[names[0]]
            if "source" in var.dims:
                known = [str(v) for v in ds["source"].values]
                if source not in known:
                    raise ValueError(f"{path}: pass --source, one of {', '.join(known)}")
                var = var.sel(source=source)
            arr = np.asarray(var.values, dtype=np.float64)
    else:
        raise ValueError(f"--curves {path}: unknown file type {suffix!r} "
                         "(expected .npz, .csv, .nc or .h5)")
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != n_t:
        raise ValueError(f"{path}: curves have shape {arr.shape}, expected (n, {n_t})")
    return arr


def read_settings(path: Path, n_controls: int, source: str | None = None
                  ) -> NDArray[np.float64] | None:
    """The press settings ``u`` (n, n_controls), internal units, stored with the curves.

    A DOE dataset holds them as the last columns of its run inputs, a study realisation
    (NetCDF) and an npz as a variable ``u``; a CSV of curves holds none (None).
    """
    suffix = path.suffix.lower()
    arr: NDArray[np.float64] | None = None
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            arr = np.asarray(z["u"], dtype=np.float64) if "u" in z else None
    elif suffix in (".h5", ".hdf5") and _is_doe_dataset(path):
        from formtwin.dataset import DoeDataset

        inputs = DoeDataset.load(path, complete=False).inputs
        arr = inputs[:, inputs.shape[1] - n_controls:] if n_controls else None
    elif suffix in (".nc", ".h5", ".hdf5", ".nc4"):
        import xarray as xr

        with xr.open_dataset(path, engine="h5netcdf") as ds:
            arr = np.asarray(ds["u"].values, dtype=np.float64) if "u" in ds else None
    if arr is None or arr.size == 0:
        return None
    return arr.reshape(arr.shape[0], -1)


def parse_settings(text: str, n: int, n_controls: int) -> NDArray[np.float64]:
    """``--u``: one number for every product, or a .csv/.npz file of (n, n_controls) values."""
    try:
        return np.full((n, n_controls), float(text))
    except ValueError:
        pass
    path = Path(text)
    if not path.exists():
        raise ValueError(f"--u {text}: neither a number nor an existing file")
    if path.suffix.lower() == ".npz":
        arr = read_settings(path, n_controls)
        if arr is None:
            raise ValueError(f"--u {path}: no array 'u' in the file")
    else:
        arr = np.loadtxt(path, delimiter=",", ndmin=2)
    if arr.shape != (n, n_controls):
        raise ValueError(f"--u {path}: settings have shape {arr.shape}, expected ({n}, "
                         f"{n_controls}): one row per curve")
    return arr


def _is_doe_dataset(path: Path) -> bool:
    """Whether ``path`` is a DOE dataset written by :mod:`formtwin.dataset`."""
    import h5py

    from formtwin.dataset import FORMAT

    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("format") == FORMAT)
    except OSError:
        return False


def write_table(columns: dict[str, NDArray[Any]], path: Path) -> None:
    """Write equal-length columns as CSV or Parquet (by suffix)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError as exc:
            raise ValueError("writing Parquet needs pyarrow; use a .csv output") from exc
        pq.write_table(pa.table({k: np.asarray(v) for k, v in columns.items()}), path)
        return
    names = list(columns)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for row in zip(*(columns[k].tolist() for k in names), strict=True):
            w.writerow(row)


def sensor_values(path: Path, tracker: Any, ok: NDArray[np.bool_]
                  ) -> dict[str, NDArray[np.float64]]:
    """The values in the curves' file (``sensor_<name>`` arrays or columns) of the sensors
    ``tracker`` fuses, at the rows ``ok`` it tracks; a note for the file's other sensors
    and for a fused sensor without values."""
    from formtwin.service.streams import read_sensor_values

    found = read_sensor_values(path)
    fused = [s.name for s in tracker.sensors]
    other = sorted(set(found) - set(fused))
    if other:
        print(f"{path}: values of {', '.join(other)} not fused (not in --sensors)")
    for name in fused:
        if name not in found:
            print(f"{path}: no values of sensor {name} (array or column sensor_{name})")
        elif found[name].shape != ok.shape:
            raise ValueError(f"{path}: sensor_{name} has {found[name].shape[0]} values, "
                             f"expected {ok.shape[0]}: one per curve")
    return {name: found[name][ok] for name in fused if name in found}


def _track(args: argparse.Namespace) -> int:
    from formtwin.defaults import load_model
    from formtwin.estimates import HEALTH
    from formtwin.measurement import MeasurementModel
    from formtwin.tracker import build_tracker, track_recorded, validate_controls

    model = load_model(args.metamodel)
    spec = model.spec
    curves = read_curves(args.curves, spec.n_t, args.source)
    ok = np.all(np.isfinite(curves), axis=1)
    if not ok.all():
        print(f"skipping {int((~ok).sum())} curves with NaN/inf (failed runs)")
    n_u = len(spec.controls)
    u = (parse_settings(args.settings, len(curves), n_u) if args.settings is not None
         else read_settings(args.curves, n_u, args.source))
    if u is not None:
        if u.shape != (len(curves), n_u):
            raise ValueError(f"{args.curves}: settings u have shape {u.shape}, expected "
                             f"({len(curves)}, {n_u})")
        for i in np.flatnonzero(ok):  # every setting checked before the first step
            try:
                validate_controls(u[i], spec)
            except ValueError as exc:
                raise ValueError(f"row {i}: {exc}") from None
    config = tracker_config(args, spec_defaults(spec))
    measurement = MeasurementModel.load(args.measurement) if args.measurement else None
    tracker = build_tracker(model, config, measurement)
    values = sensor_values(args.curves, tracker, ok)
    rec = track_recorded(tracker, curves[ok], values, None if u is None else u[ok],
                         progress=sys.stderr.isatty())
    est = rec.estimates
    cols = est.columns()
    cols["index"] = np.flatnonzero(ok)  # row number in the input file
    if u is not None:  # the setting each product's angles were predicted at
        cols.update({f"u_{v.name}": u[ok, j] for j, v in enumerate(spec.controls)})
    if rec.final is not None:  # the camera's final angle, as the service issues it
        cols.update(final_predicted_deg=rec.final[:, 0], final_interval90_lo_deg=rec.final[:, 1],
                    final_interval90_hi_deg=rec.final[:, 2])
    write_table(cols, args.out)
    if values:
        print("sensor values fused: " + ", ".join(f"{k} {v}" for k, v in rec.fused.items())
              + (f"; {len(rec.refused)} refused, the first: {rec.refused[0]}" if rec.refused
                 else ""))
    if args.checkpoint:
        tracker.checkpoint(args.checkpoint)
    print(f"tracked {len(est)} products ({int(est.collapsed.sum())} collapsed, "
          f"median ESS {float(np.median(est.ess)) if len(est) else 0:.0f}) -> {args.out}")
    h = est.health if est.health is not None else np.zeros(0, dtype=str)
    counts = {k: int(np.sum(h == k)) for k in HEALTH}
    print("fit (the model's own check, columns health and fit_*): " +
          ", ".join(f"{v} {k}" for k, v in counts.items()))
    if len(est) and counts["no_fit"] > len(est) // 2:
        print(f"WARNING: the model does not explain {counts['no_fit']} of {len(est)} curves "
              "(distance beyond the 99.9 % quantile of the measurement model): the estimates "
              "are not supported by the data. Likely causes: a sensor noise set too small, "
              "a metamodel of another press or process, a faulty sensor, curves in other "
              "units.\n" + noise_note(config, spec))
    if tracker.intervals == "uncalibrated":
        from formtwin.tracker.intervals import find_calibration

        print(f"WARNING: the std columns are the particle cloud's (overconfident under model "
              f"error): {find_calibration(model).reason}")
    return 0
