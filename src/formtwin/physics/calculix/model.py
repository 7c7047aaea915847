"""The CalculiX flap-bending model behind the :class:`~formtwin.simulator.Simulator` seam.

Each run writes the deck (:mod:`.deck`) into a temporary directory, runs ``ccx`` there
(one thread) and reads the ``.dat`` tables (:mod:`.results`): the stage-1 force on the
spec's time grid and the angles after springback. Nothing is kept unless ``keep_dir`` is
given. A run that fails (ccx missing, non-convergence, timeout) returns
:meth:`RunResult.failure` with the reason, so a DOE keeps going.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.physics.bending.geometry import FlapGeometry
from formtwin.physics.bending.material import Material
from formtwin.physics.calculix.deck import (
    FeSettings,
    ProcessDeck,
    ProcessPoint,
    process_deck,
    ram_height,
)
from formtwin.physics.calculix.results import chord_angle, read_dat
from formtwin.simulator import RunResult
from formtwin.spec import ProcessSpec, load_spec

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

VERSION = "calculix-0.2"
#: the spec's name of the stage-2 depth setting u (a run input when the spec has it)
CONTROL = "stage2_depth"


class CcxError(RuntimeError):
    """A CalculiX run did not finish; the message says why (log tail)."""


@cache
def ccx_version(ccx: str = "ccx") -> str | None:
    """The version CalculiX prints (``"2.20"``), or None when ``ccx`` is not installed."""
    exe = shutil.which(ccx)
    if exe is None:
        return None
    try:
        out = subprocess.run([exe, "-v"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    for word in out.stdout.split():
        if word[:1].isdigit():
            return word
    return "unknown"


def run_ccx(text: str, workdir: Path, ccx: str = "ccx", timeout: float = 1800.0) -> Path:
    """Write ``job.inp`` into ``workdir``, run CalculiX on it single-threaded; the ``.dat``.

    Raises :class:`CcxError` with the tail of the log when the job fails.
    """
    exe = shutil.which(ccx)
    if exe is None:
        raise CcxError(f"CalculiX executable {ccx!r} not found (Debian: apt-get install "
                       "calculix-ccx; or `make fe-deps` as root)")
    (workdir / "job.inp").write_text(text)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CCX_NPROC_STIFFNESS": "1",
           "CCX_NPROC_EQUATION_SOLVER": "1", "CCX_NPROC_RESULTS": "1"}
    try:
        out = subprocess.run([exe, "-i", "job"], cwd=workdir, env=env, capture_output=True,
                             text=True, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        raise CcxError(f"CalculiX did not finish within {timeout:.0f} s") from exc
    errors = [ln.strip() for ln in out.stdout.splitlines() if "*ERROR" in ln]
    dat = workdir / "job.dat"
    if out.returncode != 0 or errors or not dat.exists():
        tail = "; ".join(errors[-3:]) or out.stdout.strip().splitlines()[-1:]
        raise CcxError(f"CalculiX failed (exit {out.returncode}): {tail}")
    return dat


class CalculixModel:
    """Two-stage flap bending as a plane-strain CalculiX model (``docs/explanation/calculix.md``).

    Satisfies :class:`formtwin.simulator.Simulator`; picklable (plain settings), so
    :func:`formtwin.doe.run_design` can run it in a process pool or on a Dask cluster
    (every worker needs ``ccx`` on its path).

    Parameters
    ----------
    spec
        Process spec (inputs in internal units); default: the bundled demonstrator.
    geometry
        Tools and press kinematics (the bending model's :class:`FlapGeometry`).
    settings
        Mesh, contact and increment settings (:class:`FeSettings`).
    ccx
        CalculiX executable.
    timeout
        Seconds a single ccx job may take.
    keep_dir
        Keep every run's files in a new subdirectory of this directory (debugging).
    stage2
        Run stage 2 as well (else angle 2 is NaN).
    **overrides
        Fields of :class:`FeSettings`, e.g. ``n_thick=6``.
    """

    def __init__(self, spec: ProcessSpec | None = None, geometry: FlapGeometry | None = None,
                 settings: FeSettings | None = None, *, ccx: str = "ccx",
                 timeout: float = 1800.0, keep_dir: str | Path | None = None,
                 stage2: bool = True, **overrides: Any) -> None:
        self.spec = spec if spec is not None else load_spec()
        self.geometry = geometry if geometry is not None else FlapGeometry()
        self.settings = replace(settings or FeSettings(), **overrides)
        if self.settings.n_thick % 2:
            raise ValueError(f"n_thick = {self.settings.n_thick}: must be even (the angle is "
                             "read on the mid-thickness line)")
        self.ccx = ccx
        self.stage2 = stage2
        self.timeout = timeout
        self.keep_dir = None if keep_dir is None else Path(keep_dir)
        # the run inputs: (x, theta) or, when the spec has a control, (x, theta, u)
        self._inputs = getattr(self.spec, "run_inputs", self.spec.inputs)
        self._ix = self._inputs.index

    @property
    def version(self) -> str:
        """Model version with the CalculiX version and the mesh (stored with datasets)."""
        s = self.settings
        return (f"{VERSION} ccx-{ccx_version(self.ccx)} mesh {s.n_thick}x{s.aspect:g} "
                f"K {s.contact_stiffness:g}" + ("" if self.stage2 else " stage 1 only"))

    def centre(self) -> FloatArray:
        """Centre of Table 1 as the bending model defines it (run inputs)."""
        from formtwin.physics.bending import BendingModel

        return BendingModel(self.spec).centre()

    def point(self, x: FloatArray) -> ProcessPoint:
        """The physical inputs of input vector ``x (n_inputs,)``."""
        ix = self._ix
        mat = Material(yield_stress=float(x[ix["yield_stress"]]),
                       log_rate=float(x[ix["log_rate"]]),
                       rate_exponent=float(x[ix["rate_exponent"]]))
        return ProcessPoint(mat, float(x[ix["thickness"]]), float(x[ix["friction_tool_tool"]]),
                            float(x[ix["friction_tool_flap"]]),
                            float(x[ix["punch_end_distance"]]),
                            float(x[ix["horizontal_alignment"]]),
                            float(x[ix["vertical_alignment"]]), float(x[ix["press_stiffness"]]))

    def deck(self, x: FloatArray) -> ProcessDeck:
        """The deck of input vector ``x`` (both stages unless ``stage2=False``)."""
        u = float(x[self._ix[CONTROL]]) if CONTROL in self._ix else 0.0
        return process_deck(self.point(x), self.geometry, self.settings,
                            np.asarray(self.spec.time, dtype=np.float64), self.stage2, u)

    def run(self, inputs: FloatArray) -> RunResult:
        """Run one input point ``(n_inputs,)`` (internal units); never raises for a run
        that fails (a failure record with the reason); ``ValueError`` for a bad shape."""
        n_t = self.spec.n_t
        x = np.asarray(inputs, dtype=np.float64)
        if x.shape != (len(self._inputs),):
            raise ValueError(f"inputs: expected shape ({len(self._inputs)},) in the order "
                             f"{', '.join(self._inputs.names)}; got {x.shape}")
        if not np.all(np.isfinite(x)):
            return RunResult.failure(n_t, "non-finite input")
        tic = time.perf_counter()
        try:
            with self._workdir() as wd:
                curve, angles, extra = self.solve(x, Path(wd))
        except (CcxError, ValueError, KeyError, IndexError) as exc:
            log.warning("calculix run failed: %s", exc)
            return RunResult.failure(n_t, str(exc))
        info = {"seconds": time.perf_counter() - tic, **extra}
        return RunResult(curve, angles, ok=True, info=info)

    def _workdir(self) -> Any:
        if self.keep_dir is None:
            return tempfile.TemporaryDirectory(prefix="formtwin-ccx-")
        self.keep_dir.mkdir(parents=True, exist_ok=True)
        return _Kept(tempfile.mkdtemp(prefix="run-", dir=self.keep_dir))

    def solve(self, x: FloatArray, workdir: Path
              ) -> tuple[FloatArray, FloatArray, dict[str, float]]:
        """Run in ``workdir``: stage-1 force on the grid (N), angles after springback (deg;
        angle 2 NaN without stage 2)."""
        g = self.geometry
        deck = self.deck(x)
        tables = read_dat(run_ccx(deck.text, workdir, self.ccx, self.timeout))
        ram = tables[("forces", "NRAM")]
        punch = tables[("total force", "NPUNCH")]
        mid = tables[("displacements", "NMID")]
        n_t = self.spec.n_t
        # output requests carry over to later steps: stage 1 ends at deck.times[-1]
        in1 = ram.times <= deck.times[-1] + 1e-6
        if not in1.any() or abs(ram.times[in1][-1] - deck.times[-1]) > 1e-6:
            done = ram.times[-1] if ram.times.size else 0.0
            raise CcxError(f"stage 1 stopped at t = {done + deck.t0:.4f} s "
                           "(increment below the minimum)")
        rows_t = _match(ram.times[in1], deck.times[:n_t])  # -1: the start, which CalculiX skips
        f_v = np.where(rows_t >= 0, -ram.values[rows_t, 0, 1], 0.0)
        f_lat = np.where(rows_t >= 0, punch.values[rows_t, 0, 0], 0.0)
        _, v = ram_height(np.asarray(self.spec.time, dtype=np.float64), g)
        sign = -np.tanh(v / 1.0)
        curve = (f_v + sign * self.point(x).mu_tool_tool * np.abs(f_lat)) * g.width
        idx = deck.sheet.node_index
        rows = np.array([idx(int(n)) for n in mid.ids])
        ref = deck.sheet.nodes[rows]
        k1 = int(np.argmin(np.abs(mid.times - deck.times[-1])))
        angles = np.array([chord_angle(ref + mid.values[k, :, :2], ref[:, 0], g.angle_length)
                           for k in (k1, -1)])
        if not deck.stage2:
            angles[1] = math.nan
        elif abs(mid.times[-1] - deck.end) > 1e-6:
            raise CcxError("stage 2 did not finish (increment below the minimum)")
        return np.asarray(curve, dtype=np.float64), angles, {
            "release_force": float(-ram.values[np.flatnonzero(in1)[-1], 0, 1] * g.width),
            "increments": float(ram.times.size)}


def _match(have: FloatArray, want: FloatArray) -> NDArray[np.intp]:
    """Row of each time ``want`` in ``have`` (1e-6 s), -1 for time 0 (not printed)."""
    j = np.clip(np.searchsorted(have, want - 1e-6), 0, have.size - 1)
    ok = np.abs(have[j] - want) < 1e-6
    if not np.all(ok | (np.abs(want) < 1e-9)):
        raise CcxError("CalculiX output misses time points of the force grid")
    return np.where(ok, j, -1)


class _Kept:
    """A directory context that is not deleted (``keep_dir``)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __enter__(self) -> str:
        return self.path

    def __exit__(self, *exc: object) -> None:
        return None
