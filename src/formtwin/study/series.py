"""The six simulation series of the paper's Fig. 4 (plus two of ours) and one filter run.

=====  ==========  =========================  ================
series  data        filter model               statistics mu
=====  ==========  =========================  ================
1       MM          MM                         known
2       g(MM)       MM (no deviation model)    known
3       g(MM)       g(MM), estimates theta_d   known
4       MM          MM                         (mu_min+mu_max)/2
5       FE          MM                         known
6       g(FE)       g(MM), estimates theta_d   (mu_min+mu_max)/2
7       MM          MM                         learned (prior U(mu_min, mu_max))
8       g(FE)       g(MM), estimates theta_d   learned (prior U(mu_min, mu_max))
=====  ==========  =========================  ================

Series 7 and 8 are not the paper's: they are series 4 and 6 with the improvement its
Discussion suggests, the statistics mu estimated as hyperparameters
(``TrackerConfig(learn_mu=True)``, see ``docs/notes/learned-mu.md``). Their K_MC is that of
series 4 and 6 (mid-range mu), so the pairs differ only in the filter. The default study
(``StudySettings.series``) stays the paper's six.

The measurement model's K_MC is computed with the mu the filter assumes (paper,
"Simulation runs"): the realisation's true mu when known, the mid-range otherwise. Its
likelihood is the tracker config's (``"calibrated"`` by default; the study also runs the
paper's, ``StudySettings.paper_repetitions``). Series 7 and 8 learn mu by conjugate updates.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.estimates import HEALTH
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.metamodel import Metamodel
from formtwin.study.keys import stored_key
from formtwin.study.pseudodata import Realisation
from formtwin.tracker import Tracker, TrackerConfig, build_measurement, build_tracker

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Series:
    """One simulation series: which data, whether theta_d is estimated, whether mu is known
    (else assumed mid-range), whether the filter learns mu (then ``mu_known`` is False)."""

    number: int
    data: str
    deviation: bool
    mu_known: bool
    learn_mu: bool = False

    @property
    def data_label(self) -> str:
        """The data source as the paper writes it: MM, g(MM), FE, g(FE)."""
        return {"MM": "MM", "gMM": "g(MM)", "FE": "FE", "gFE": "g(FE)"}[self.data]

    @property
    def label(self) -> str:
        """A one-line description: number, data, filter model, statistics."""
        model = "g(MM)" if self.deviation else "MM"
        data = self.data_label
        stats = ("mu known" if self.mu_known else "mu learned" if self.learn_mu
                 else "mu assumed")
        return f"{self.number}: data {data}, filter {model}, {stats}"


SERIES: tuple[Series, ...] = (
    Series(1, "MM", deviation=False, mu_known=True),
    Series(2, "gMM", deviation=False, mu_known=True),
    Series(3, "gMM", deviation=True, mu_known=True),
    Series(4, "MM", deviation=False, mu_known=False),
    Series(5, "FE", deviation=False, mu_known=True),
    Series(6, "gFE", deviation=True, mu_known=False),
    Series(7, "MM", deviation=False, mu_known=False, learn_mu=True),
    Series(8, "gFE", deviation=True, mu_known=False, learn_mu=True),
)

#: the paper's six series, the default of a study
PAPER_SERIES: tuple[int, ...] = (1, 2, 3, 4, 5, 6)


@dataclass(frozen=True)
class Task:
    """One filter run: series x realisation x repetition, with everything it needs by path."""

    series: int
    realisation: int
    repetition: int
    metamodel_path: str
    realisation_path: str
    measurement_path: str
    out_path: str
    tracker: TrackerConfig
    seed: int
    #: :func:`~formtwin.study.keys.cache_key` of what makes the run (saved with it: a run
    #: file with another key is made again)
    key: str


@functools.lru_cache(maxsize=2)
def _metamodel(path: str) -> Metamodel:
    return Metamodel.load(path)


@functools.lru_cache(maxsize=8)
def _realisation(path: str) -> Realisation:
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        return Realisation.from_dataset(ds.load())


@functools.lru_cache(maxsize=16)
def _measurement(path: str) -> MeasurementModel:
    return MeasurementModel.load(path)


def forget_files() -> None:
    """Drop the files the tasks of this process have read (each study reads its own: a
    study run in the calling process, ``workers=1``, starts afresh as a new pool's
    workers do)."""
    for read in (_metamodel, _realisation, _measurement):
        read.cache_clear()


def measurement_file(folder: Path, realisation: int, mu_known: bool,
                     likelihood: str = "calibrated", key: str = "") -> Path:
    """Where the study keeps the measurement model of a realisation (mu known or assumed,
    calibrated likelihood, or the paper's, which the discrepancy likelihood builds on),
    named by the ``key`` of what makes it (:func:`~formtwin.study.keys.cache_key`)."""
    kind = "known" if mu_known else "assumed"
    tail = "" if likelihood == "calibrated" else "_paper"  # discrepancy: the paper's
    tail += f"_{key}" if key else ""
    return folder / "measurement" / f"real{realisation}_mu_{kind}{tail}.npz"


def series_config(base: TrackerConfig, series: Series, mu: FloatArray,
                  seed: int) -> TrackerConfig:
    """The filter settings of ``series``: ``base`` with the series' deviation switch,
    learned-mu switch and whether mu is known (else the intervals carry the assumed mu's
    error; ``base.mu_known`` drops that term in every series, the intervals before
    0.1.0.dev10), the assumed state means ``mu`` (7,) and the tracker ``seed``."""
    return dataclasses.replace(base, estimate_deviation=series.deviation,
                               mu=tuple(float(v) for v in mu), seed=seed,
                               learn_mu=series.learn_mu,
                               mu_known=series.mu_known or base.mu_known)


def make_measurement(model: Metamodel | ProcessModel, real: Realisation, mu_known: bool,
                     seed: int, base: TrackerConfig, path: Path) -> Path:
    """Build and save the measurement model of a realisation: ``K_MC`` about the mu the
    filter assumes (the true mu when known, the mid-range otherwise; paper, "Simulation
    runs"), from ``base.n_mc`` curves, seeded by the study ``seed``."""
    mu = real.mu if mu_known else model.spec.state.mu_mid
    config = dataclasses.replace(base, mu=tuple(float(v) for v in mu))
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7919, int(mu_known)]))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = build_measurement(model, config, rng).save(path.with_suffix(".tmp.npz"))
    tmp.replace(path)
    return path


def measurement_task(metamodel_path: str, realisation_path: str, mu_known: bool, seed: int,
                     base: TrackerConfig, path: str) -> str:
    """:func:`make_measurement` from files (for a worker process); returns ``path``."""
    if not Path(path).exists():
        with single_blas_thread():
            make_measurement(_metamodel(metamodel_path), _realisation(realisation_path),
                             mu_known, seed, base, Path(path))
    return path


def run_task(task: Task) -> str:
    """Run one filter over one realisation and save its estimates as npz; returns the path.

    Products whose curve is missing (failed physics run) are skipped and get NaN estimates.
    An existing output file with the task's key is reused (the study resumes).
    """
    out = Path(task.out_path)
    if stored_key(out) == task.key:
        return str(out)
    with single_blas_thread():
        _run(task, out)
    return str(out)


def prepare(task: Task) -> tuple[Tracker, Realisation, FloatArray, FloatArray | None]:
    """The tracker of a filter run as :func:`run_task` builds it, its realisation, the
    curves it assimilates (n_ok, n_t) and their settings (n_ok, n_controls) or ``None``."""
    series = SERIES[task.series - 1]
    model = _metamodel(task.metamodel_path)
    real = _realisation(task.realisation_path)
    spec = model.spec
    ss = np.random.SeedSequence([task.seed, task.series, task.realisation, task.repetition])
    config = series_config(task.tracker, series,
                           real.mu if series.mu_known else spec.state.mu_mid,
                           int(ss.generate_state(1)[0]))
    tracker = build_tracker(model, config, _measurement(task.measurement_path))
    ok = real.ok[series.data]
    u = real.u[ok] if real.u.shape[1] == len(spec.controls) and len(spec.controls) else None
    return tracker, real, real.curves[series.data][ok], u


def _run(task: Task, out: Path) -> None:
    series = SERIES[task.series - 1]
    tracker, real, curves, u = prepare(task)
    spec = tracker.spec
    ok = real.ok[series.data]
    est = tracker.run(curves, u=u)
    n, d = real.n, len(spec.augmented)
    mean, std = np.full((n, d), np.nan), np.full((n, d), np.nan)
    n_out = spec.n_outputs
    ang_mean, ang_std = np.full((n, n_out), np.nan), np.full((n, n_out), np.nan)
    mean[ok], std[ok] = est.mean, est.std
    ang_mean[ok], ang_std[ok] = est.angles_mean, est.angles_std
    ess, d2, loglik = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    ess[ok], loglik[ok] = est.ess, est.loglik
    if est.fit_distance2 is not None:
        d2[ok] = est.fit_distance2
    health = np.full(n, -1, dtype=np.int8)  # index into HEALTH; -1: product skipped
    if est.health is not None:
        health[ok] = [HEALTH.index(str(h)) for h in est.health]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp.npz")
    arrays: dict[str, Any] = {"mean": mean, "std": std, "angles_mean": ang_mean,
                              "angles_std": ang_std, "ess": ess,
                              "loglik": loglik, "collapsed": np.asarray(est.collapsed),
                              "fit_distance2": d2, "health": health,
                              "key": np.array(task.key)}
    if est.mu_mean is not None and est.mu_std is not None:  # learned mu, (n, 7)
        for key, value in (("mu_mean", est.mu_mean), ("mu_std", est.mu_std)):
            full = np.full((n, len(spec.state)), np.nan)
            full[ok] = value
            arrays[key] = full
    np.savez_compressed(tmp, **arrays)
    tmp.replace(out)
