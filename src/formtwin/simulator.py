"""The seam between process models and everything that runs them.

A simulator maps one point of the input box (state ``x`` then parameters ``theta``, in
internal units, shape ``(n_inputs,)``) to the stage-1 force curve on the spec's time grid
(N, shape ``(n_t,)``) and the bend angles after stage 1 and stage 2 (degrees, after
springback, shape ``(2,)``). A run that fails returns ``ok=False`` and a reason instead of
raising, so one bad point never stops a design of experiments.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

ANGLE_NAMES = ("angle_stage1", "angle_stage2")


@dataclass(frozen=True)
class RunResult:
    """Outcome of one simulator run: curve ``(n_t,)`` in N, angles ``(2,)`` in degrees."""

    curve: FloatArray
    angles: FloatArray
    ok: bool = True
    reason: str = ""
    info: dict[str, float] = field(default_factory=dict)

    @classmethod
    def failure(cls, n_t: int, reason: str) -> RunResult:
        """A failed run: NaN outputs and the reason."""
        return cls(np.full(n_t, np.nan), np.full(2, np.nan), ok=False, reason=reason)


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
        """Run one input point ``(n_inputs,)`` in internal units."""
        ...
