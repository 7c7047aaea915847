"""Designs of experiments and the parallel, resumable runner.

The paper's design is the 2^10 full factorial (the corners of the box of the ten inputs)
plus a Latin hypercube of 6000 points (7024 runs). formtwin's designs span the model-run
inputs ``(x, theta, u)`` (:attr:`~formtwin.spec.ProcessSpec.run_inputs`: Table 1 plus the
press setting), so the demonstrator's full factorial has 2^11 corners; with
:data:`LHS_POINTS` = 5000 Latin-hypercube points the default design has 7048 runs.

:func:`run_design` evaluates any :class:`~formtwin.simulator.Simulator` over a design
through a
``concurrent.futures.Executor`` — a local process pool by default, or a Dask cluster
(``client.get_executor()``) — in chunks (one task costs ~1-2 ms of overhead), and writes
each chunk to the dataset file as it arrives, so an interrupted run resumes where it
stopped. A run that raises is recorded as a failure with its reason.

>>> from formtwin.spec import load_spec
>>> spec = load_spec()
>>> X = paper_design(spec, n_lhs=10, seed=1)
>>> X.shape, bool(((X >= spec.run_inputs.lo) & (X <= spec.run_inputs.hi)).all())
((2058, 11), True)
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from formtwin.dataset import DoeDataset, open_for_run
from formtwin.simulator import RunResult, Simulator
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


def full_factorial(spec: ProcessSpec) -> FloatArray:
    """The ``2^d`` corners of the box of the run inputs, ``(2^d, d)``, in internal units."""
    box = spec.run_inputs
    d = len(box)
    levels = (np.arange(2**d)[:, None] >> np.arange(d)[None, ::-1]) & 1
    out: FloatArray = box.lo + levels * (box.hi - box.lo)
    return out


def latin_hypercube(spec: ProcessSpec, n: int, seed: int = 0) -> FloatArray:
    """A seeded, optimised (random-CD) Latin hypercube of ``n`` points, ``(n, d)``."""
    from scipy.stats import qmc  # on use: ~1.3 s CPU to import

    box = spec.run_inputs
    sampler = qmc.LatinHypercube(d=len(box), optimization="random-cd",
                                 rng=np.random.default_rng(seed))
    out: FloatArray = qmc.scale(sampler.random(n), box.lo, box.hi)
    return out


#: Latin-hypercube points of the default design (2^11 corners + 5000 = 7048 runs)
LHS_POINTS = 5000


def paper_design(spec: ProcessSpec, n_lhs: int = LHS_POINTS, seed: int = 0) -> FloatArray:
    """The paper's design: full factorial corners, then ``n_lhs`` Latin-hypercube points."""
    return np.vstack([full_factorial(spec), latin_hypercube(spec, n_lhs, seed)])


def _run_chunk(simulator: Simulator, rows: NDArray[np.intp], X: FloatArray
               ) -> tuple[NDArray[np.intp], list[RunResult]]:
    out = []
    for x in X:
        try:
            out.append(simulator.run(x))
        except Exception as exc:  # one bad point must not stop the DOE
            out.append(RunResult.failure(simulator.spec.n_t, f"{type(exc).__name__}: {exc}",
                                         simulator.spec.n_outputs))
    return rows, out


class _Serial(Executor):
    """Runs tasks in the calling process (tests, debugging, tiny designs)."""

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[no-untyped-def]
        fut: Future[object] = Future()
        fut.set_result(fn(*args, **kwargs))
        return fut


@contextmanager
def make_executor(executor: str | Executor | None = None,
                  workers: int | None = None) -> Iterator[Executor]:
    """``None``/``"processes"``: local process pool (all cores; ``workers=1``: in-process,
    as ``"serial"``: one worker would only add its start, ~2 s of imports and kernel loads);
    ``"serial"``: in-process; ``"dask tcp://HOST:PORT"``: a Dask cluster; an ``Executor``
    is used as it is.

    The local pool starts its workers from a fork server: a worker forked while the caller
    holds a data file open (the DOE runner's HDF5 output) would keep its lock."""
    if isinstance(executor, Executor):
        yield executor
    elif executor in (None, "processes") and workers == 1:
        yield _Serial()
    elif executor in (None, "processes"):
        with ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1,
                                 mp_context=multiprocessing.get_context("forkserver")) as pool:
            yield pool
    elif executor == "serial":
        yield _Serial()
    elif isinstance(executor, str) and executor.startswith("dask "):
        from distributed import Client

        with Client(executor.split(None, 1)[1], timeout="20s") as client:  # type: ignore[no-untyped-call]
            yield client.get_executor()
    else:
        raise ValueError(f"executor = {executor!r}, expected 'processes', 'serial', "
                         "'dask tcp://HOST:PORT' or a concurrent.futures.Executor")


def run_design(
    simulator: Simulator,
    X: FloatArray,
    path: str | Path,
    executor: str | Executor | None = None,
    chunk_size: int | None = None,
    workers: int | None = None,
    seed: int = 0,
    progress: bool = False,
) -> DoeDataset:
    """Evaluate ``simulator`` at every row of ``X (n, d)``, appending to the file ``path``.

    Rows already done in an existing file (same design, same model version) are skipped,
    so calling this again after an interruption completes the run. ``seed`` is recorded
    in the file (simulators are deterministic; it names the design's seed). Returns the
    complete dataset.
    """
    spec = simulator.spec
    X = np.ascontiguousarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != spec.n_run_inputs:
        raise ValueError(f"design has shape {X.shape}, expected (n, {spec.n_run_inputs}) "
                         f"({', '.join(spec.run_inputs.names)})")
    p = Path(path)
    t0 = time.perf_counter()
    with open_for_run(p, spec, X, simulator.version) as f:
        f.attrs["seed"] = seed
        todo = np.flatnonzero(~f["done"][...])
        n_workers = workers or os.cpu_count() or 1
        size = chunk_size or max(1, min(64, -(-todo.size // (8 * n_workers))))
        chunks = [todo[i:i + size] for i in range(0, todo.size, size)]
        log.info("%s: %d of %d runs to do in %d chunks", p, todo.size, X.shape[0], len(chunks))
        with make_executor(executor, workers) as pool, tqdm(
                total=todo.size, desc="DOE runs", disable=not progress) as bar:
            pending = {pool.submit(_run_chunk, simulator, rows, X[rows]) for rows in
                       chunks[: 2 * n_workers]}
            queued = iter(chunks[2 * n_workers:])
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    rows, results = fut.result()
                    _store(f, rows, results)
                    bar.update(len(rows))
                    nxt = next(queued, None)
                    if nxt is not None:
                        pending.add(pool.submit(_run_chunk, simulator, nxt, X[nxt]))
        f.attrs["elapsed_s"] = float(f.attrs.get("elapsed_s", 0.0)) + time.perf_counter() - t0
    data = DoeDataset.load(p)
    log.info("%s: %d runs, %d failed", p, data.n, int((~data.ok).sum()))
    return data


def _store(f: h5py.File, rows: NDArray[np.intp], results: list[RunResult]) -> None:
    """Write one chunk and mark it done (flushed, so a kill loses at most running chunks)."""
    order = np.argsort(rows)  # h5py fancy indexing needs increasing indices
    rows = rows[order]
    res = [results[i] for i in order]
    f["curves"][rows] = np.array([r.curve for r in res])
    f["angles"][rows] = np.array([r.angles for r in res])
    f["ok"][rows] = np.array([r.ok for r in res])
    f["reason"][rows] = np.array([r.reason for r in res], dtype=object)
    f["done"][rows] = True
    f.flush()
