"""Designs, the parallel resumable runner (process pool, Dask) and the dataset file."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from formtwin.dataset import DatasetError, DoeDataset, import_csv
from formtwin.doe import full_factorial, latin_hypercube, paper_design, run_design
from formtwin.physics.analytic import AnalyticBending
from formtwin.simulator import RunResult
from formtwin.spec import ProcessSpec, load_spec

SPEC = load_spec()


def test_full_factorial_is_every_corner_once() -> None:
    X = full_factorial(SPEC)  # Table 1 plus the stage-2 setting u
    assert X.shape == (2048, 11)
    at_lo = np.isclose(X, SPEC.run_inputs.lo)
    assert np.all(at_lo | np.isclose(X, SPEC.run_inputs.hi))
    assert len({tuple(r) for r in at_lo}) == 2048


def test_latin_hypercube_is_seeded_stratified_and_inside() -> None:
    a, b = latin_hypercube(SPEC, 200, seed=3), latin_hypercube(SPEC, 200, seed=3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, latin_hypercube(SPEC, 200, seed=4))
    u = (a - SPEC.run_inputs.lo) / (SPEC.run_inputs.hi - SPEC.run_inputs.lo)
    for j in range(11):  # one point per stratum in every dimension
        assert sorted(np.floor(u[:, j] * 200).astype(int)) == list(range(200))
    assert paper_design(SPEC, 50).shape == (2098, 11)


@dataclass(frozen=True)
class Flaky:
    """A simulator that fails on some points and can be told to interrupt the run."""

    spec: ProcessSpec
    version: str = "flaky-1"
    interrupt_at: float = np.nan  # yield stress of the run during which Ctrl-C is hit

    def run(self, inputs: np.ndarray) -> RunResult:
        if inputs[0] == self.interrupt_at:
            raise KeyboardInterrupt
        if inputs[3] > 0.3045:
            raise RuntimeError("contact did not converge")
        curves, angles = AnalyticBending(self.spec).run_batch(inputs[None, :])
        return RunResult(curves[0], angles[0])


def test_failures_are_recorded_with_their_reason(tmp_path: Path) -> None:
    X = latin_hypercube(SPEC, 40, seed=1)
    data = run_design(Flaky(SPEC), X, tmp_path / "d.h5", executor="serial", chunk_size=7)
    failed = X[:, 3] > 0.3045
    assert failed.any()
    np.testing.assert_array_equal(~data.ok, failed)
    assert all("RuntimeError: contact did not converge" == r for r in data.reason[failed])
    assert np.isnan(data.curves[failed]).all() and np.isfinite(data.curves[~failed]).all()
    assert data.successful().n == int((~failed).sum())


def test_angles_alone_are_the_batch_angles() -> None:
    """The stand-in's ``run_angles`` (what a process model's ``predict_angles`` runs when no
    curves are wanted) gives the angles of ``run_batch`` to the bit (the same expressions
    on the same inputs), failed runs NaN in both, with and without the control column."""
    from formtwin.simulator import SimulatorModel

    X = latin_hypercube(SPEC, 200, seed=3)
    for sim in (AnalyticBending(SPEC), AnalyticBending(SPEC, failure_clearance=0.005)):
        _, angles = sim.run_batch(X)
        np.testing.assert_array_equal(sim.run_angles(X), angles)
        np.testing.assert_array_equal(sim.run_angles(X[:, :10]), sim.run_batch(X[:, :10])[1])
        model = SimulatorModel(sim)
        u = np.linspace(-0.1, 0.1, len(X))
        np.testing.assert_array_equal(model.predict_angles(X[:, :10], u),
                                      sim.run_batch(SPEC.run_columns(X[:, :10], u))[1])
    assert np.isnan(angles).any() and not np.isnan(angles).all()


def test_interrupted_run_resumes_to_the_same_dataset(tmp_path: Path) -> None:
    X = latin_hypercube(SPEC, 60, seed=2)
    whole = run_design(Flaky(SPEC), X, tmp_path / "whole.h5", executor="serial", chunk_size=5)
    part = tmp_path / "part.h5"
    with pytest.raises(KeyboardInterrupt):
        run_design(Flaky(SPEC, interrupt_at=X[47, 0]), X, part,
                   executor="serial", chunk_size=5)
    with h5py.File(part) as f:
        done = int(f["done"][...].sum())
    assert 0 < done < 60
    with pytest.raises(DatasetError, match="not done"):
        DoeDataset.load(part)
    resumed = run_design(Flaky(SPEC), X, part, executor="serial", chunk_size=5)
    for name in ("inputs", "curves", "angles", "ok", "reason"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name))
    with pytest.raises(DatasetError, match="different design"):
        run_design(Flaky(SPEC), X[:10], part, executor="serial")
    with pytest.raises(DatasetError, match="model_version"):
        run_design(Flaky(SPEC, version="flaky-2"), X, part, executor="serial")


def test_process_pool_matches_serial_and_file_round_trips(tmp_path: Path) -> None:
    X = latin_hypercube(SPEC, 30, seed=5)
    sim = AnalyticBending(SPEC)
    a = run_design(sim, X, tmp_path / "a.h5", executor="serial")
    b = run_design(sim, X, tmp_path / "b.h5", executor="processes", workers=2, chunk_size=4)
    np.testing.assert_array_equal(a.curves, b.curves)
    b.save(tmp_path / "c.h5")
    c = DoeDataset.load(tmp_path / "c.h5")
    np.testing.assert_array_equal(c.angles, a.angles)
    assert c.model_version == sim.version and c.spec.text == SPEC.text
    with h5py.File(tmp_path / "c.h5") as f:
        assert f["curves"].attrs["units"] == "N" and "yield_stress" in f["inputs"].attrs["names"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_runs_on_a_real_dask_cluster(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    port = _free_port()
    bindir = Path(sys.executable).parent
    sched = subprocess.Popen([str(bindir / "dask"), "scheduler", "--host", "127.0.0.1",
                              "--port", str(port), "--no-dashboard"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([str(bindir / "dask"), "worker", f"tcp://127.0.0.1:{port}",
                               "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                               "--host", "127.0.0.1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.0)
        X = latin_hypercube(SPEC, 24, seed=6)
        sim = AnalyticBending(SPEC)
        got = run_design(sim, X, tmp_path / "dask.h5", executor=f"dask tcp://127.0.0.1:{port}",
                         chunk_size=6)
        ref = run_design(sim, X, tmp_path / "ref.h5", executor="serial")
        np.testing.assert_array_equal(got.curves, ref.curves)
    finally:
        for proc in (worker, sched):
            proc.terminate()
            proc.wait(timeout=20)


def _write_csv(path: Path, rows: list[list[str]], times: np.ndarray) -> None:
    header = list(SPEC.inputs.names) + ["angle_stage1", "angle_stage2", "status"] + [
        f"F@{t:g}" for t in times]
    path.write_text("\n".join(",".join(r) for r in [header] + rows) + "\n")


def _csv_row(x_display: np.ndarray, curve: np.ndarray, status: str = "ok") -> list[str]:
    return [f"{v:.10g}" for v in x_display] + ["44.5", "88.0", status] + [
        f"{v:.10g}" for v in curve]


def test_csv_import_interpolates_converts_units_and_keeps_failures(tmp_path: Path) -> None:
    times = np.linspace(-90, 30, 241)  # ms, finer and wider than the spec grid
    centre = 0.5 * (SPEC.inputs.lo + SPEC.inputs.hi)
    display = centre / np.array([v.scale for v in SPEC.inputs])  # Table 1 units
    curve = 100 + times**2
    p = tmp_path / "fe.csv"
    _write_csv(p, [_csv_row(display, curve), _csv_row(display, curve * np.nan, "diverged")],
               times)
    data = import_csv(p, SPEC)
    # no control column: the nominal stage-2 setting
    np.testing.assert_allclose(data.inputs[0], np.r_[centre, SPEC.controls.nominal])
    np.testing.assert_allclose(data.curves[0], 100 + (SPEC.time * 1e3) ** 2, rtol=1e-3)
    assert data.ok.tolist() == [True, False] and data.reason[1] == "diverged"


@pytest.mark.parametrize(("mutate", "words"), [
    (lambda r: r.__setitem__(0, "abc"), "'yield_stress' = 'abc'"),
    (lambda r: r.__setitem__(0, "500"), "'yield_stress' = 500 MPa is outside [275, 336]"),
    (lambda r: r.__setitem__(14, "inf"), "not finite"),
])
def test_csv_import_errors_name_line_and_column(tmp_path: Path, mutate, words: str) -> None:
    times = np.linspace(-80, 20, 11)
    display = 0.5 * (SPEC.inputs.lo + SPEC.inputs.hi) / np.array([v.scale for v in SPEC.inputs])
    row = _csv_row(display, np.ones(11))
    mutate(row)
    _write_csv(tmp_path / "bad.csv", [row], times)
    with pytest.raises(DatasetError, match="line 2") as info:
        import_csv(tmp_path / "bad.csv", SPEC)
    assert words in str(info.value)


def test_csv_import_rejects_short_time_window_and_missing_columns(tmp_path: Path) -> None:
    _write_csv(tmp_path / "short.csv", [], np.linspace(-50, 20, 5))
    (tmp_path / "short.csv").write_text((tmp_path / "short.csv").read_text() + "1\n")
    with pytest.raises(DatasetError, match="do not cover"):
        import_csv(tmp_path / "short.csv", SPEC)
    (tmp_path / "cols.csv").write_text("yield_stress,F@-80,F@20\n300,1,2\n")
    with pytest.raises(DatasetError, match="missing column"):
        import_csv(tmp_path / "cols.csv", SPEC)
