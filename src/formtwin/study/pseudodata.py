"""Pseudo-data of the study: realisations of a production run with known truth.

A realisation draws its statistics and constants once (paper, "Simulation runs"):
``mu ~ U(mu_min, mu_max)``, ``theta ~ U(bounds)``, ``theta_d ~ U(bounds)``; then the state
sequence ``x_1..x_n`` follows eq. 4 from the stationary law (reflected into the box).
Force curves and angles come from two sources, the metamodel (``MM``) and the physics
model (``FE``), each also distorted by the deviation model, ``gMM = g(MM, theta_d)`` and
``gFE = g(FE, theta_d)``. The angles come from the same source as the curve; the
deviation acts on the force curve only. Physics runs that fail are kept as missing
(``ok = False``): the study skips those products, as a press line would skip a stroke
whose curve was not recorded.

A realisation is stored as NetCDF (``realisation_K.nc``) and reloaded when present.
"""

from __future__ import annotations

import hashlib
import logging
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr
from numpy.typing import NDArray

from formtwin.dataset import DoeDataset
from formtwin.deviation import DeviationModel
from formtwin.doe import run_design
from formtwin.measurement import ProcessModel
from formtwin.production import ProductionRun, draw_production_run
from formtwin.simulator import Simulator
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
SOURCES = ("MM", "gMM", "FE", "gFE")
#: physics runs per task of the pool: ~1-2 s of work, so a realisation's last task keeps
#: one core busy while the other idles for about that long (the DOE runner's default,
#: n / 16 = 63 runs on 2 cores, left one core idle ~5 s per realisation on average)
PHYSICS_CHUNK = 8
log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Realisation(ProductionRun):
    """Truth and measurements of one pseudo production run of ``n`` products.

    The truth is the :class:`~formtwin.production.ProductionRun` (``mu``, ``theta``,
    ``theta_d``, ``x``, ``u``: nominal in the study); per source in :data:`SOURCES`:
    ``curves[source] (n, n_t)`` N, ``angles[source] (n, 2)`` degrees and ``ok[source] (n,)``.
    """

    index: int
    curves: dict[str, FloatArray]
    angles: dict[str, FloatArray]
    ok: dict[str, BoolArray]

    def to_dataset(self, spec: ProcessSpec) -> xr.Dataset:
        """The realisation as an xarray Dataset (written as NetCDF)."""
        return xr.Dataset(
            {
                "mu": (("state",), self.mu),
                "theta": (("param",), self.theta),
                "theta_d": (("deviation",), self.theta_d),
                "x": (("product", "state"), self.x),
                "curves": (("source", "product", "time"),
                           np.stack([self.curves[s] for s in SOURCES])),
                "angles": (("source", "product", "angle"),
                           np.stack([self.angles[s] for s in SOURCES])),
                "ok": (("source", "product"), np.stack([self.ok[s] for s in SOURCES])),
                "u": (("product", "control"), self.u),
            },
            coords={"state": list(spec.state.names), "param": list(spec.params.names),
                    "control": list(spec.controls.names),
                    "deviation": list(spec.deviation.names), "source": list(SOURCES),
                    "time": spec.time, "angle": list(spec.output_names),
                    "product": np.arange(self.n)},
            attrs={"realisation": self.index, "units": "mm, N, s, MPa; angles in degrees",
                   "description": "formtwin study pseudo-data (truth and force curves)"},
        )

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> Realisation:
        """Inverse of :meth:`to_dataset` (files without ``u``: zero columns)."""
        src = [str(s) for s in ds["source"].values]
        n = int(ds["x"].shape[0])
        return cls(
            index=int(ds.attrs["realisation"]),
            mu=ds["mu"].values, theta=ds["theta"].values, theta_d=ds["theta_d"].values,
            x=ds["x"].values,
            curves={s: ds["curves"].values[i] for i, s in enumerate(src)},
            angles={s: ds["angles"].values[i] for i, s in enumerate(src)},
            ok={s: ds["ok"].values[i].astype(bool) for i, s in enumerate(src)},
            u=ds["u"].values if "u" in ds else np.zeros((n, 0)),
        )


def make_realisation(
    spec: ProcessSpec,
    index: int,
    n: int,
    seed: int,
    metamodel: ProcessModel,
    physics: Simulator,
    folder: Path,
    executor: str | Executor | None = None,
    key: str = "",
) -> Realisation:
    """Create (or reload from ``folder``) realisation ``index`` of ``n`` products.

    The physics runs go through the DOE runner (parallel, resumable): its dataset
    ``fe_K.nc`` in ``folder`` is the cache of the ``FE`` curves. ``key`` names what made
    the file (seed, models: :func:`~formtwin.study.keys.cache_key`); a file with another
    is made again.
    """
    path = folder / f"realisation_{index}.nc"
    if path.exists():
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            real, stored = Realisation.from_dataset(ds.load()), ds.attrs.get("key", "")
        if real.n == n and real.u.shape[1] == len(spec.controls) and stored == key:
            return real
        log.info("%s holds %d products of key %r, %d of key %r wanted: regenerating", path,
                 real.n, stored, n, key)
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    run = draw_production_run(spec, n, rng)
    inputs = run.inputs
    fe_path = folder / f"fe_{index}.nc"
    run_design(physics, run.run_inputs, fe_path, executor=executor, seed=seed,
               chunk_size=PHYSICS_CHUNK)
    fe = DoeDataset.load(fe_path)
    g = DeviationModel.from_spec(spec)
    mm_curves = metamodel.predict_curves(inputs)
    curves = {"MM": mm_curves, "gMM": g.apply(mm_curves, np.tile(run.theta_d, (n, 1))),
              "FE": fe.curves, "gFE": g.apply(np.nan_to_num(fe.curves),
                                              np.tile(run.theta_d, (n, 1)))}
    curves["gFE"][~fe.ok] = np.nan
    mm_angles = metamodel.predict_angles(run.run_inputs)
    angles = {"MM": mm_angles, "gMM": mm_angles, "FE": fe.angles, "gFE": fe.angles}
    all_ok = np.ones(n, dtype=bool)
    ok = {"MM": all_ok, "gMM": all_ok, "FE": fe.ok.copy(), "gFE": fe.ok.copy()}
    real = Realisation(mu=run.mu, theta=run.theta, theta_d=run.theta_d, x=run.x, u=run.u,
                       index=index, curves=curves, angles=angles, ok=ok)
    folder.mkdir(parents=True, exist_ok=True)
    ds = real.to_dataset(spec)
    ds.attrs["key"] = key
    ds.to_netcdf(path, engine="h5netcdf")
    log.info("realisation %d: %d products, %d physics failures", index, n, int((~fe.ok).sum()))
    return real


def data_digest(realisations: list[Realisation]) -> dict[str, str]:
    """Per source in :data:`SOURCES`, 16 hex digits of a SHA-256 over every realisation's
    curves, angles and ``ok`` flags (float64 bytes, in realisation order).

    A record, not a key: two studies whose digests agree filtered bit-for-bit identical
    pseudo-data; a changed physics model, platform or library that moves one force value by
    one unit in the last place changes the digest of its source.
    """
    out = {}
    for src in SOURCES:
        h = hashlib.sha256()
        for r in realisations:
            for a in (r.curves[src], r.angles[src], r.ok[src]):
                h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        out[src] = h.hexdigest()[:16]
    return out
