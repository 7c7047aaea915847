"""The seam between process models and everything that runs them.

A simulator maps one point of the input box (state ``x``, parameters ``theta`` and the
press settings ``u``, in internal units, shape ``(n_run_inputs,)``) to the stage-1 force
curve on the spec's curve grid (N, shape ``(n_t,)``) and the spec's scalar outputs
(``spec.outputs``, shape ``(n_outputs,)``: for the demonstrator the bend angles after stage 1
and stage 2, degrees, after springback). A run that fails returns ``ok=False``
and a reason instead of raising, so one bad point never stops a design of experiments.

:class:`SimulatorModel` makes any simulator a process model for the tracker (curves and
angles of a batch of particles), so nothing above this seam names a physics module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

@dataclass(frozen=True)
class RunResult:
    """Outcome of one simulator run: curve ``(n_t,)`` in N, outputs ``angles``
    ``(n_outputs,)`` in their spec units."""

    curve: FloatArray
    angles: FloatArray
    ok: bool = True
    reason: str = ""
    info: dict[str, float] = field(default_factory=dict)

    @classmethod
    def failure(cls, n_t: int, reason: str, n_outputs: int = 2) -> RunResult:
        """A failed run: NaN curve ``(n_t,)`` and outputs ``(n_outputs,)``, and the reason."""
        return cls(np.full(n_t, np.nan), np.full(n_outputs, np.nan), ok=False, reason=reason)


class Simulator(Protocol):
    """A process model that can be run point by point (and pickled to worker processes)."""

    @property
    def spec(self) -> ProcessSpec:
        """The process definition whose inputs the model takes."""
        ...

    @property
    def version(self) -> str:
        """Changes whenever the model's outputs change; stored with every dataset."""
        ...

    def run(self, inputs: FloatArray) -> RunResult:
        """Run one input point ``(n_run_inputs,)`` in internal units."""
        ...


class SimulatorModel:
    """A simulator as a :class:`~formtwin.measurement.ProcessModel` (batch curves, angles).

    Uses the simulator's vectorised ``run_batch(X) -> (curves, angles)`` when it has one,
    else runs the points one by one (failed runs give NaN rows). Curves and angles come
    from one run: the last batch is remembered, so asking for the angles of the particles
    whose curves were just computed costs nothing; angles of other inputs come from the
    simulator's ``run_angles(X) -> angles`` when it has one (the same numbers as its
    ``run_batch``'s, without the curves).

    Parameters
    ----------
    simulator : the process model to run.
    """

    def __init__(self, simulator: Simulator) -> None:
        self.simulator = simulator
        self._last: tuple[FloatArray, FloatArray, FloatArray] | None = None

    @property
    def spec(self) -> ProcessSpec:
        """The simulator's process definition."""
        return self.simulator.spec

    def _run(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        X = self.spec.run_columns(X)
        last = self._last
        if last is not None and last[0].shape == X.shape and np.array_equal(last[0], X):
            return last[1], last[2]
        batch = getattr(self.simulator, "run_batch", None)
        if batch is not None:
            curves, angles = batch(X)
        else:
            runs = [self.simulator.run(x) for x in X]
            curves = np.array([r.curve for r in runs]).reshape(len(runs), -1)
            angles = np.array([r.angles for r in runs]).reshape(len(runs),
                                                                self.spec.n_outputs)
        self._last = (X.copy(), curves, angles)
        return curves, angles

    def predict_curves(self, X: FloatArray) -> FloatArray:
        """Stage-1 force curves (N, n_t), N, for inputs ``X`` (N, 10) ``[x, theta]`` (the
        controls act after stage 1) or (N, 11) ``[x, theta, u]``."""
        return self._run(X)[0]

    def predict_angles(self, X: FloatArray, u: FloatArray | float | None = None) -> FloatArray:
        """Scalar outputs (N, n_outputs) (the demonstrator: bend angles, degrees) for inputs
        ``X`` (N, 10) at the controls ``u`` (scalar or (N,); None: nominal), or ``X``
        (N, 11) with ``u`` None."""
        X = self.spec.run_columns(X, u)
        last, angles_only = self._last, getattr(self.simulator, "run_angles", None)
        if angles_only is None or (last is not None and last[0].shape == X.shape
                                   and np.array_equal(last[0], X)):
            return self._run(X)[1]
        out: FloatArray = angles_only(X)  # the same angles without computing the curves
        return out
