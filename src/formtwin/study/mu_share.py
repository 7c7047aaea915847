"""The particle filter's shares of the linearised filter's removal of an assumed mu's offset,
learned on the interval calibration's physics runs (:mod:`formtwin.study.calibrate`).

Where the tracker assumes mu, the line's state means are ``mu + d``; the linearised filter
keeps ``G_mu d`` of the offset in the estimate and removes ``([I; 0] - G_mu) d``
(:mod:`formtwin.tracker.sandwich`). The particle filter removes less for some states: on
the calibration's series-6 runs (deviation model estimated, mu assumed mid-range) it keeps
most of the offset of the states that the curves and theta_d do not tell apart from it
(docs/likelihood.md). Each such run is replayed product by product (the same tracker, seed
and curves; its means are checked bit for bit against the stored run) to record the
linearised ``G_mu``. Over the last ``window`` products, per state
``j`` and run, the particle filter's removal is ``d_j + mean(err_j)`` (the error of the
estimate, estimate minus truth) and the linearised one ``mean(([I; 0] - G_mu) d)_j``; the
share ``s_j`` is the least-squares slope through the origin of the first on the second
over the runs, at least 0. The tracker's term then uses ``I - s (I - G_mu)`` for the
state's rows (:func:`formtwin.tracker.sandwich.shared_removal`), and the runs' std are
recomputed with it (:func:`shared_std`) before the floors are learned on them.

>>> import numpy as np   # runs whose filter removes half of what the linear one predicts
>>> lin = np.array([[1.0, 2.0], [-2.0, 0.5]])
>>> learn_share(0.5 * lin, lin).tolist(), learn_share(-lin, lin).tolist()
([0.5, 0.5], [0.0, 0.0])
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin._threads import single_blas_thread
from formtwin.doe import make_executor
from formtwin.study.run import _tasks  # the study's own runs: their paths and keys
from formtwin.study.series import SERIES, Task, prepare
from formtwin.tracker.sandwich import shared_removal

FloatArray = NDArray[np.float64]


def replay(task: Task) -> dict[str, FloatArray]:
    """Re-run the filter run ``task`` (mu assumed, an interval setting with the assumed mu's
    term) product by product: its ``G_mu`` (n_ok, m, n_x) after each product, ``mu_half``
    (n_x, k) with ``E[d d^T] = mu_half mu_half^T``, the offset ``d`` (n_x,) and ``ok``.
    Raises ``ValueError`` if the means differ from the stored run's."""
    tracker, real, curves, u = prepare(task)
    sw = tracker.sandwich
    if sw is None or not sw.mu_half.size:
        raise ValueError(f"series {task.series}: the run has no assumed mu's term")
    G, means = [], []
    with single_blas_thread():
        for i, y in enumerate(curves):
            est = tracker.step(y, None if u is None else u[i])
            G.append(sw.G_mu)
            means.append(est.mean)
    ok = real.ok[SERIES[task.series - 1].data]
    with np.load(task.out_path) as run:
        if not np.array_equal(run["mean"][ok], np.array(means)):
            raise ValueError(f"{task.out_path}: the replay's means differ from the run's")
    return {"G": np.array(G), "mu_half": sw.mu_half,
            "d": real.mu - np.asarray(tracker.config.mu), "ok": ok}


def replay_runs(result: Any, folder: Path, metamodel_path: Path, series: int
                ) -> dict[tuple[int, int, int], dict[str, FloatArray]]:
    """:func:`replay` of every run of ``series`` in the study ``result`` (made in
    ``folder`` with the metamodel at ``metamodel_path``), in a process pool."""
    st = result.settings
    tasks = {(t.series, t.realisation, t.repetition): t
             for t in _tasks(st, folder, metamodel_path, folder / "data")
             if t.series == series and t.tracker == st.tracker}
    with make_executor(None, st.workers) as pool:
        futures = {key: pool.submit(replay, tasks[key])
                   for key in sorted(result.run_paths) if key[0] == series}
        return {key: f.result() for key, f in futures.items()}


def learn_share(removed_pf: FloatArray, removed_lin: FloatArray) -> FloatArray:
    """The shares ``s`` (n_x,): per column the least-squares slope through the origin of
    the particle filter's removal of the offset ``removed_pf`` on the linearised filter's
    ``removed_lin`` (runs, n_x), at least 0."""
    den = np.sum(removed_lin**2, axis=0)
    slope = np.divide(np.sum(removed_pf * removed_lin, axis=0), den,
                      out=np.ones(den.shape), where=den > 0)
    out: FloatArray = np.maximum(slope, 0.0)
    return out


def removals(rep: dict[str, FloatArray], err: FloatArray, window: int
             ) -> tuple[FloatArray, FloatArray]:
    """The particle filter's and the linearised filter's removal (n_x,) of the offset over
    the last ``window`` products of a replayed run ``rep`` (:func:`replay`) with the
    estimate's errors ``err`` (n_ok, >= n_x)."""
    d, G = rep["d"], rep["G"][-window:]
    nx = d.size
    pf = d + np.nanmean(err[-window:, :nx], axis=0)
    lin = d - np.mean(G, axis=0)[:nx] @ d
    return pf, lin


def term_variances(rep: dict[str, FloatArray], share: FloatArray | None) -> FloatArray:
    """The assumed mu's term's variances (n_ok, m) of the estimated variables of a replayed
    run, with the shares ``share`` (:func:`shared_removal`; None: the linearised filter's;
    the angles' term is the linearised one in both)."""
    G, R = rep["G"], rep["mu_half"]
    if share is not None:
        G = np.array([shared_removal(g, share) for g in G])
    H = G @ R  # (n, m, k)
    out: FloatArray = np.sum(H * H, axis=2)
    return out


def shared_std(std: FloatArray, rep: dict[str, FloatArray], share: FloatArray) -> FloatArray:
    """A run's reported std (n, 20: 18 augmented, 2 angles; the cloud's plus the linearised
    term, rows where the replay's ``ok``) with the term's shares ``share`` instead."""
    v_lin, v_new = term_variances(rep, None), term_variances(rep, share)
    out = std.copy()
    ok, m = rep["ok"], v_lin.shape[1]
    var = out[ok, :m] ** 2 + v_new - v_lin
    out[np.flatnonzero(ok)[:, None], np.arange(m)] = np.sqrt(np.maximum(var, 0.0))
    return out


def run_arrays(result: Any, key: tuple[int, int, int]) -> tuple[FloatArray, FloatArray]:
    """The errors and reported std (n, 20: 18 augmented, 2 angles) of the run ``key``
    (series, realisation, repetition) of the study ``result``."""
    real = result.realisations[key[1]]
    with np.load(result.run_paths[key]) as run:
        err = np.c_[run["mean"] - real.truth,
                    run["angles_mean"] - real.angles[SERIES[key[0] - 1].data]]
        return err, np.c_[run["std"], run["angles_std"]]


def share_from_study(result: Any, reps: dict[tuple[int, int, int], dict[str, FloatArray]]
                     ) -> tuple[FloatArray, dict[tuple[int, int, int], FloatArray]]:
    """The shares (n_x,) learned on the replayed runs ``reps`` (:func:`replay_runs`) of the
    study ``result`` (its ``window``), and each run's std (n, 20) recomputed with them."""
    window = result.settings.window
    pf, lin, arrays = [], [], {}
    for key, rep in reps.items():
        err, std = run_arrays(result, key)
        arrays[key] = std
        a, b = removals(rep, err[rep["ok"]], window)
        pf.append(a)
        lin.append(b)
    share = learn_share(np.array(pf), np.array(lin))
    return share, {key: shared_std(std, reps[key], share) for key, std in arrays.items()}
