"""Run the study: pseudo-data, 6 series x realisations x repetitions filter runs, metrics.

Every piece is cached in the study folder (realisations as NetCDF, each filter run as npz),
so an interrupted study resumes and a finished one is re-reported instantly. The filter
runs are independent and go to a process pool (or a Dask cluster); each runs BLAS
single-threaded.
"""

from __future__ import annotations

import json
import logging
import time
from concurrent.futures import as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from formtwin.doe import make_executor
from formtwin.measurement import ProcessModel
from formtwin.simulator import Simulator
from formtwin.study.metrics import normalised_rmse
from formtwin.study.pseudodata import Realisation, make_realisation
from formtwin.study.series import (
    PAPER_SERIES,
    SERIES,
    Task,
    make_measurement,
    measurement_file,
    run_task,
)
from formtwin.tracker import TrackerConfig

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StudySettings:
    """Size and seeds of a study; the defaults are the paper's."""

    n_products: int = 1000
    n_realisations: int = 5
    n_repetitions: int = 5
    window: int = 500
    seed: int = 0
    series: tuple[int, ...] = PAPER_SERIES  # 7, 8 (learned mu) on request
    workers: int | None = None
    scheduler: str | None = None
    #: the filters' settings; each series sets its own estimate_deviation, mu, learn_mu
    #: and seed (see :func:`formtwin.study.series.series_config`)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    def __post_init__(self) -> None:
        if not 0 < self.window <= self.n_products:
            raise ValueError(f"window = {self.window}, expected 0 < window <= n_products = "
                             f"{self.n_products}")
        bad = [s for s in self.series if s not in range(1, len(SERIES) + 1)]
        if bad:
            raise ValueError(f"series {bad} unknown, expected numbers 1..{len(SERIES)}")
        for name in ("n_realisations", "n_repetitions"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} = {getattr(self, name)}, expected >= 1")


@dataclass
class StudyResult:
    """Normalised RMSE ``nrmse[series - 1, realisation, repetition, component]`` (20
    components: 18 augmented, 2 angles; rows for series 1..6, or up to the largest series
    run, NaN for series not run) and the paths of every run. ``timings`` are those of the run
    that computed the filter runs (``cached`` = 1 when this call only re-reported)."""

    settings: StudySettings
    nrmse: FloatArray
    run_paths: dict[tuple[int, int, int], Path]
    realisations: list[Realisation]
    timings: dict[str, float] = field(default_factory=dict)

    def settings_dict(self) -> dict[str, object]:
        """The settings as a flat dict (the tracker's as ``tracker.NAME`` keys)."""
        d = asdict(self.settings)
        del d["tracker"]
        d.update({f"tracker.{k}": v for k, v in self.settings.tracker.to_dict().items()})
        return d


def _executor_name(settings: StudySettings) -> str:
    return f"dask {settings.scheduler}" if settings.scheduler else "processes"


def run_study(settings: StudySettings, folder: Path, metamodel: ProcessModel,
              metamodel_path: Path, physics: Simulator, progress: bool = False) -> StudyResult:
    """Generate (or reload) the pseudo-data and run (or reload) every filter run."""
    spec = metamodel.spec
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    data_dir = folder / "data"
    realisations = [make_realisation(spec, k, settings.n_products, settings.seed, metamodel,
                                     physics, data_dir, executor=_executor_name(settings))
                    for k in range(settings.n_realisations)]
    t_data = time.perf_counter() - t0
    tasks = [Task(series=s, realisation=k, repetition=r,
                  metamodel_path=str(metamodel_path),
                  realisation_path=str(data_dir / f"realisation_{k}.nc"),
                  measurement_path=str(measurement_file(folder, k, SERIES[s - 1].mu_known)),
                  out_path=str(folder / "runs" / f"series{s}_real{k}_rep{r}.npz"),
                  tracker=settings.tracker, seed=settings.seed)
             for s in settings.series for k in range(settings.n_realisations)
             for r in range(settings.n_repetitions)]
    todo = [t for t in tasks if not Path(t.out_path).exists()]
    # K_MC once per (realisation, mu known or assumed), here, not in every worker
    for path, real_k, known in sorted({(t.measurement_path, t.realisation,
                                        SERIES[t.series - 1].mu_known) for t in todo}):
        if not Path(path).exists():
            make_measurement(metamodel, realisations[real_k], known, settings.seed,
                             settings.tracker, Path(path))
    log.info("%d filter runs, %d cached", len(tasks), len(tasks) - len(todo))
    t1 = time.perf_counter()
    if todo:
        with make_executor(_executor_name(settings), settings.workers) as pool:
            futures = [pool.submit(run_task, t) for t in todo]
            for fut in tqdm(as_completed(futures), total=len(futures), desc="filter runs",
                            disable=not progress):
                fut.result()
    t_filters = time.perf_counter() - t1
    n_comp = len(spec.augmented) + 2
    n_series = max(len(PAPER_SERIES), *settings.series)  # the paper's 6 unless 7, 8 asked
    nrmse = np.full((n_series, settings.n_realisations, settings.n_repetitions, n_comp),
                    np.nan)
    paths: dict[tuple[int, int, int], Path] = {}
    for task in tasks:
        real = realisations[task.realisation]
        data = SERIES[task.series - 1].data
        with np.load(task.out_path, allow_pickle=False) as run:
            nrmse[task.series - 1, task.realisation, task.repetition] = normalised_rmse(
                spec, run["mean"], real.truth(), run["angles_mean"],
                np.where(real.ok[data][:, None], real.angles[data], np.nan),
                settings.window)
        if not SERIES[task.series - 1].deviation:
            nrmse[task.series - 1, task.realisation, task.repetition,
                  len(spec.inputs):len(spec.augmented)] = np.nan
        paths[(task.series, task.realisation, task.repetition)] = Path(task.out_path)
    timings = {"pseudo_data_s": t_data, "filter_runs_s": t_filters,
               "filter_runs_computed": float(len(todo)),
               "total_s": time.perf_counter() - t0}
    record = folder / "timings.json"
    if todo or not record.exists():  # keep the figures of the run that computed them
        record.write_text(json.dumps(timings, indent=2), encoding="utf-8")
    else:
        timings = {**json.loads(record.read_text(encoding="utf-8")), "cached": 1.0}
    return StudyResult(settings, nrmse, paths, realisations, timings)
