"""A user's own FE dataset as the study's physics data (series 5 and 6, ``FE`` and ``gFE``).

The study's pseudo-data come from two sources: the metamodel and the physics. For the
demonstrator the physics is a process model formtwin can run at any point; for a user's own
process it is usually an external FE code that has been run once, over a design
(``formtwin doe design`` -> FE -> ``formtwin doe import``). :class:`DatasetSimulator` makes
that dataset a :class:`~formtwin.simulator.Simulator`: the curves and outputs at a point are
a thin-plate-spline RBF interpolation (:class:`scipy.interpolate.RBFInterpolator`, a
degree-1 polynomial tail) of **all** successful FE runs, on the unit box of the run inputs,
curve samples interpolated directly (no reduction).

What the series then measure (say so when reading them): the metamodel (POD + cubic RBF
on least-squares centres, per-dimension length scales) and this interpolant are two
different approximations of the same FE runs; they agree exactly at no point the study
draws, so the ``FE`` series see the metamodel's approximation error relative to an
independent interpolant of the FE data, not the gap between FE and the real press. When
the metamodel was fitted on part of the FE runs (e.g. ``formtwin metamodel fit`` on a
training split) the held-out runs still shape this interpolant, so the difference also
holds the metamodel's held-out error. A dataset with fewer successful runs than
:data:`MIN_RUNS_PER_INPUT` per run input is refused.

>>> from formtwin.defaults import analytic_dataset
>>> sim = DatasetSimulator(analytic_dataset(120, seed=3))
>>> r = sim.run(sim.data.inputs[5])
>>> bool(np.allclose(r.curve, sim.data.curves[5], atol=1e-6 * np.abs(r.curve).max()))
True
"""

from __future__ import annotations

import hashlib

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RBFInterpolator

from formtwin.dataset import DoeDataset
from formtwin.simulator import RunResult
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

#: successful FE runs needed per run input (the interpolant's polynomial tail needs d + 1)
MIN_RUNS_PER_INPUT = 3


class DatasetSimulator:
    """The successful runs of an FE dataset as a simulator (thin-plate RBF interpolation).

    Parameters
    ----------
    data : the FE dataset (``formtwin doe import``), its spec the study's.
    """

    def __init__(self, data: DoeDataset) -> None:
        ok = np.asarray(data.ok, dtype=bool)
        d = data.spec.n_run_inputs
        if int(ok.sum()) < MIN_RUNS_PER_INPUT * d:
            raise ValueError(f"FE dataset ({data.model_version}): {int(ok.sum())} successful "
                             f"runs, expected at least {MIN_RUNS_PER_INPUT * d} "
                             f"({MIN_RUNS_PER_INPUT} per run input) to interpolate")
        self.data = data.successful()
        box = data.spec.run_inputs
        self._lo, self._hi = box.lo, box.hi
        U = self._unit(self.data.inputs)
        values = np.hstack([self.data.curves, self.data.angles])
        self._rbf = RBFInterpolator(U, values, kernel="thin_plate_spline", degree=1)
        h = hashlib.sha256()
        for a in (self.data.inputs, self.data.curves, self.data.angles):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        self._version = f"fe-data:{data.model_version}:{h.hexdigest()[:12]}"

    def _unit(self, X: FloatArray) -> FloatArray:
        out: FloatArray = (np.asarray(X, dtype=np.float64) - self._lo) / (self._hi - self._lo)
        return out

    @property
    def spec(self) -> ProcessSpec:
        """The FE dataset's process spec."""
        return self.data.spec

    @property
    def version(self) -> str:
        """The FE model's label and a digest of the runs interpolated."""
        return self._version

    def run_batch(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Curves (N, n_t) N and outputs (N, n_outputs) at run inputs ``X`` (N, d)."""
        v = self._rbf(self._unit(np.atleast_2d(X)))
        n_t = self.spec.n_t
        return v[:, :n_t], v[:, n_t:]

    def run(self, inputs: FloatArray) -> RunResult:
        """One point ``(n_run_inputs,)``, internal units."""
        x = np.asarray(inputs, dtype=np.float64)
        if not np.all(np.isfinite(x)):
            return RunResult.failure(self.spec.n_t, "non-finite input", self.spec.n_outputs)
        curves, outputs = self.run_batch(x[None, :])
        return RunResult(curve=curves[0], angles=outputs[0])


def check_physics(simulator: object, spec: ProcessSpec, what: str) -> None:
    """Refuse a physics model that cannot make this spec's data: run it at the middle of
    the spec's box and raise ``ValueError`` naming ``what`` and the reason if it fails."""
    mid = 0.5 * (spec.run_inputs.lo + spec.run_inputs.hi)
    try:
        result = simulator.run(mid)  # type: ignore[attr-defined]
        reason = "" if result.ok else result.reason
    except Exception as exc:  # noqa: BLE001 - the reason goes into the message
        reason = f"{type(exc).__name__}: {exc}"
    if reason:
        raise ValueError(
            f"study: the physics data of series 5 and 6 (sources FE, gFE) cannot be made for "
            f"spec {spec.name!r} with {what} ({reason}). Pass --fe-data with the spec's own "
            f"FE dataset (formtwin doe import), or a physics model of this spec.")
