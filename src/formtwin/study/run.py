"""Run the study: pseudo-data, 6 series x realisations x repetitions filter runs, metrics.

Every piece is cached in the study folder (realisations as NetCDF, each filter run as npz),
so an interrupted study resumes and a finished one is re-reported instantly. The filter
runs are independent and go to a process pool (or a Dask cluster); each runs BLAS
single-threaded.
"""

from __future__ import annotations

import dataclasses
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
from formtwin.measurement import ProcessModel, monte_carlo_inputs
from formtwin.simulator import Simulator
from formtwin.spec import ProcessSpec
from formtwin.study.keys import cache_key, stored_key
from formtwin.study.metrics import run_scores
from formtwin.study.pseudodata import Realisation, make_realisation
from formtwin.study.series import (
    PAPER_SERIES,
    SERIES,
    Task,
    forget_files,
    measurement_file,
    measurement_task,
    run_task,
)
from formtwin.tracker import TrackerConfig
from formtwin.tracker.intervals import calibration_path

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
    #: repetitions per dataset of every series with the paper's likelihood (eq. 12) beside
    #: the tracker's (calibrated by default), on the same data; 0: none
    paper_repetitions: int = 1
    #: the series that also run the paper's likelihood: no model error (1), the
    #: metamodel's error (5), and that with the deviation and mu assumed (6); series 2-4
    #: have metamodel data like 1
    paper_series: tuple[int, ...] = (1, 5, 6)
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
        if self.paper_repetitions < 0:
            raise ValueError(f"paper_repetitions = {self.paper_repetitions}, expected >= 0")

    @property
    def compares_paper(self) -> bool:
        """Whether the study also runs the paper's likelihood (the tracker's is another)."""
        return self.paper_repetitions > 0 and self.tracker.likelihood != "paper"

    @property
    def n_filter_runs(self) -> int:
        """Filter runs of the study: every series with the tracker's likelihood, plus the
        paper's likelihood in :attr:`paper_series` when the study compares it."""
        n = len(self.series) * self.n_repetitions
        if self.compares_paper:
            n += sum(s in self.paper_series for s in self.series) * self.paper_repetitions
        return n * self.n_realisations


@dataclass
class StudyResult:
    """Normalised RMSE ``nrmse[series - 1, realisation, repetition, component]`` (the
    augmented state, then the spec's outputs: 18 + 2 for the demonstrator; rows for series
    1..6, or up to the largest series run, NaN for series not run) and the paths of every
    run. ``timings`` are those of the run that computed the filter runs (``cached`` = 1
    when this call only re-reported).

    ``skill`` and ``coverage`` have the shape of ``nrmse`` (:mod:`formtwin.study.metrics`);
    ``ess`` and ``log_evidence`` are ``(series, realisation, repetition)``: mean ESS and
    cumulative log-evidence ``sum_i log p(z_i | z_1..i-1)`` of each run. ``paper`` holds
    the same five arrays for the runs with the paper's likelihood (``paper_repetitions``
    per dataset), or is empty.
    """

    settings: StudySettings
    nrmse: FloatArray
    run_paths: dict[tuple[int, int, int], Path]
    realisations: list[Realisation]
    timings: dict[str, float] = field(default_factory=dict)
    skill: FloatArray = field(default_factory=lambda: np.zeros(0))
    coverage: FloatArray = field(default_factory=lambda: np.zeros(0))
    ess: FloatArray = field(default_factory=lambda: np.zeros(0))
    log_evidence: FloatArray = field(default_factory=lambda: np.zeros(0))
    paper: dict[str, FloatArray] = field(default_factory=dict)

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
    # one pool for the physics runs and the filter runs: each worker compiles the physics
    # (Numba, ~11 s) once, not once per realisation (one worker: this process)
    forget_files()
    with make_executor(_executor_name(settings), settings.workers) as pool:
        data_key = cache_key(settings.seed, physics.version, files=(metamodel_path,))
        realisations = [make_realisation(spec, k, settings.n_products, settings.seed,
                                         metamodel, physics, data_dir, executor=pool,
                                         key=data_key)
                        for k in range(settings.n_realisations)]
        t_data = time.perf_counter() - t0
        tasks = _tasks(settings, folder, metamodel_path, data_dir)
        todo = [t for t in tasks if stored_key(Path(t.out_path)) != t.key]
        # K_MC once per (realisation, mu known or assumed, likelihood) file, in the pool,
        # before the filter runs that read it
        needed = {t.measurement_path: t for t in todo if not Path(t.measurement_path).exists()}
        for fut in [pool.submit(measurement_task, t.metamodel_path, t.realisation_path,
                                SERIES[t.series - 1].mu_known, settings.seed, t.tracker,
                                path) for path, t in sorted(needed.items())]:
            fut.result()
        log.info("%d filter runs, %d cached", len(tasks), len(tasks) - len(todo))
        t1 = time.perf_counter()
        # the longest runs first, so that no core idles at the end on one long run
        futures = [pool.submit(run_task, t) for t in sorted(todo, key=_cost, reverse=True)]
        for fut in tqdm(as_completed(futures), total=len(futures), desc="filter runs",
                        disable=not progress):
            fut.result()
    t_filters = time.perf_counter() - t1
    prior_angles = _prior_angles(metamodel, realisations, settings.seed)
    arrays, paths = _score(spec, settings, tasks, realisations, prior_angles, paper=False)
    paper = _score(spec, settings, tasks, realisations, prior_angles, paper=True)[0] \
        if settings.compares_paper else {}
    timings = {"pseudo_data_s": t_data, "filter_runs_s": t_filters,
               "filter_runs_computed": float(len(todo)),
               "total_s": time.perf_counter() - t0}
    record = folder / "timings.json"
    if todo or not record.exists():  # keep the figures of the run that computed them
        record.write_text(json.dumps(timings, indent=2), encoding="utf-8")
    else:
        timings = {**json.loads(record.read_text(encoding="utf-8")), "cached": 1.0}
    return StudyResult(settings, arrays["nrmse"], paths, realisations, timings,
                       skill=arrays["skill"], coverage=arrays["coverage"], ess=arrays["ess"],
                       log_evidence=arrays["log_evidence"], paper=paper)


def _tasks(settings: StudySettings, folder: Path, metamodel_path: Path,
           data_dir: Path) -> list[Task]:
    """Every filter run of the study: the tracker's likelihood, then the paper's."""
    lik = settings.tracker.likelihood  # a non-default likelihood's runs are named for it
    runs = [(settings.tracker, settings.n_repetitions,
             "" if lik == TrackerConfig().likelihood else f"_{lik}", settings.series)]
    if settings.compares_paper:
        # eq. 12 as the paper writes it: its covariance, compared in model space, and the
        # particles' std as its intervals (eq. 14)
        runs.append((dataclasses.replace(settings.tracker, likelihood="paper", compare="model",
                                         intervals="cloud"),
                     settings.paper_repetitions, "_paper", settings.paper_series))
    tasks, runs_dir = [], folder / "runs"
    for tracker, reps, tag, series in runs:
        # the interval calibration a run's tracker reads (one per learn_residuals setting)
        cal = calibration_path(tracker.learn_residuals)
        calibrated = (cal,) if cal.exists() else ()
        for s in (s for s in settings.series if s in series):
            known = SERIES[s - 1].mu_known
            for k in range(settings.n_realisations):
                real = data_dir / f"realisation_{k}.nc"
                # what makes the measurement model, and (with it) a filter run
                made_of = (tracker.to_dict(), settings.seed, known)
                files = (metamodel_path, real)
                measurement = measurement_file(folder, k, known, tracker.likelihood,
                                               cache_key(*made_of, files=files))
                tasks += [Task(series=s, realisation=k, repetition=r,
                               metamodel_path=str(metamodel_path), realisation_path=str(real),
                               measurement_path=str(measurement),
                               out_path=str(runs_dir / f"series{s}_real{k}_rep{r}{tag}.npz"),
                               tracker=tracker, seed=settings.seed,
                               key=cache_key(*made_of, s, r, files=(*files, *calibrated)))
                          for r in range(reps)]
    return tasks


def _cost(task: Task) -> float:
    """Relative CPU of a filter run (for the order of the pool's queue): the deviation
    model (~1.3x), learned mu (~1.1x), the two-evaluation filters (~2x)."""
    series = SERIES[task.series - 1]
    cost = (1.3 if series.deviation else 1.0) * (1.1 if series.learn_mu else 1.0)
    return cost * {"guided": 2.0, "move": 2.0, "guided_lin": 1.5}.get(task.tracker.filter, 1.0)


def _prior_angles(model: ProcessModel, realisations: list[Realisation],
                  seed: int) -> dict[tuple[int, bool], FloatArray]:
    """Prior-only angle prediction (2,) per (realisation, mu known): the mean angle of the
    model over 2000 draws of the filter's initial law (x about the assumed mu, theta
    uniform)."""
    spec = model.spec
    out = {}
    for real in realisations:
        for known in (True, False):
            rng = np.random.default_rng(np.random.SeedSequence([seed, 104729, real.index]))
            X = monte_carlo_inputs(spec, 2000, rng, real.mu if known else spec.state.mu_mid)
            out[(real.index, known)] = np.nanmean(model.predict_angles(X), axis=0)
    return out


def _score(spec: ProcessSpec, settings: StudySettings, tasks: list[Task],
           realisations: list[Realisation], prior_angles: dict[tuple[int, bool], FloatArray],
           paper: bool) -> tuple[dict[str, FloatArray], dict[tuple[int, int, int], Path]]:
    """nRMSE, skill, coverage (series, realisation, repetition, 20), mean ESS and
    log-evidence (series, realisation, repetition) of the tracker's or the paper's runs."""
    chosen = [t for t in tasks if (t.tracker.likelihood == "paper") == paper
              and (t.tracker.likelihood == settings.tracker.likelihood or paper)]
    reps = settings.paper_repetitions if paper and settings.compares_paper \
        else settings.n_repetitions
    n_series = max(len(PAPER_SERIES), *settings.series)  # the paper's 6 unless 7, 8 asked
    shape = (n_series, settings.n_realisations, reps)
    n_comp = len(spec.augmented) + spec.n_outputs
    out = {name: np.full(shape + (n_comp,), np.nan) for name in ("nrmse", "skill", "coverage")}
    out.update({name: np.full(shape, np.nan) for name in ("ess", "log_evidence")})
    paths: dict[tuple[int, int, int], Path] = {}
    for task in chosen:
        series = SERIES[task.series - 1]
        real = realisations[task.realisation]
        key = (task.series - 1, task.realisation, task.repetition)
        with np.load(task.out_path, allow_pickle=False) as f:
            run = {k: f[k] for k in f.files}
        data = series.data
        scores = run_scores(spec, run, real.truth,
                            np.where(real.ok[data][:, None], real.angles[data], np.nan),
                            real.mu if series.mu_known else spec.state.mu_mid,
                            prior_angles[(real.index, series.mu_known)], series.deviation,
                            settings.window)
        for name, value in scores.items():
            out[name][key] = value
        paths[(task.series, task.realisation, task.repetition)] = Path(task.out_path)
    return out, paths
