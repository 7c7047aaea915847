"""Production runs with a known change, to measure how fast the charts see it.

A run's state sequence is drawn in control (eq. 4-5 about the line's means ``mu``, by
:func:`~formtwin.production.draw_production_run`), then a :class:`Change` adds an offset
to some state variables from product ``at`` on:

* ``step``: the mean of each named variable moves by ``size`` (its sigma units) at ``at``
  and stays there. This is the textbook mean shift of an autocorrelated process
  (``x_i = mu_i + eps_i`` with the AR(1) deviation ``eps`` unchanged; Montgomery ch. 10.4):
  the level jumps at once.
* ``drift``: the mean moves by ``size`` sigma per product from ``at`` on (a slow drift: tool
  wear, a warming press).
* ``batch``: a new material batch: the means of the material variables (yield stress, the
  two Cowper-Symonds parameters, thickness) jump together, each by ``size`` sigma with its
  own sign, drawn at random.

Values that leave the design box are reflected into it, as the in-control state is.

A :class:`Fault` is a change of the measurement, not of the process: from product ``at``
on, the force sensor's gain and zero change (the measured curves ``(1 + gain) y + offset``),
a model mismatch that persists (for the mismatch charts, which should keep signalling it).

>>> import numpy as np
>>> from formtwin.spec import load_spec
>>> spec = load_spec()
>>> x = np.tile(spec.state.mu_mid, (4, 1))
>>> dx = Change("step", ("thickness",), at=2, size=2.0).apply(x, spec) - x
>>> np.round(dx[:, spec.state.names.index("thickness")] / spec.state.sigma[3], 6)
array([0., 0., 2., 2.])
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from formtwin.evolution import reflect
from formtwin.production import ProductionRun, draw_production_run
from formtwin.spec import ProcessSpec

FloatArray = NDArray[np.float64]

#: the kinds of change
KINDS = ("none", "step", "drift", "batch")
#: the state variables a new material batch changes
MATERIAL = ("yield_stress", "log_rate", "rate_exponent", "thickness")


@dataclass(frozen=True)
class Change:
    """A change of the state means from product ``at`` on (see the module doc).

    Attributes
    ----------
    kind : one of :data:`KINDS`.
    variables : names of the state variables it moves (``batch``: :data:`MATERIAL`).
    at : index of the first changed product.
    size : step (``step``, ``batch``) or drift per product (``drift``), in the variable's
        sigma (``spec.state.sigma``).
    signs : (len(variables),) +-1 per variable (``batch``); default all +1.
    """

    kind: str
    variables: tuple[str, ...] = ()
    at: int = 0
    size: float = 0.0
    signs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"change kind {self.kind!r} unknown; known: {', '.join(KINDS)}")
        if self.at < 0:
            raise ValueError(f"change at = {self.at}, expected >= 0")
        if self.signs and len(self.signs) != len(self.variables):
            raise ValueError(f"{len(self.signs)} signs for {len(self.variables)} variables")

    @classmethod
    def batch(cls, at: int, size: float, rng: np.random.Generator) -> Change:
        """A new material batch with random signs."""
        signs = tuple(float(s) for s in rng.choice([-1.0, 1.0], len(MATERIAL)))
        return cls("batch", MATERIAL, at, size, signs)

    def offset(self, n: int, spec: ProcessSpec) -> FloatArray:
        """The change of the state means (n, 7), internal units."""
        out = np.zeros((n, len(spec.state)))
        if self.kind == "none" or self.at >= n:
            return out
        signs = self.signs or (1.0,) * len(self.variables)
        after = np.arange(n - self.at, dtype=np.float64)
        shape = after + 1.0 if self.kind == "drift" else np.ones_like(after)
        for name, sign in zip(self.variables, signs, strict=True):
            j = spec.state.names.index(name)
            out[self.at:, j] = sign * self.size * spec.state.sigma[j] * shape
        return out

    def apply(self, x: FloatArray, spec: ProcessSpec) -> FloatArray:
        """The changed state sequence (n, 7), reflected into the design box."""
        s = spec.state
        return reflect(x + self.offset(x.shape[0], spec), s.lo, s.hi)


@dataclass(frozen=True)
class Fault:
    """A persistent force-sensor fault from product ``at`` on: relative ``gain`` error and
    zero ``offset`` (N).

    >>> Fault(at=1, gain=0.1, offset=-2.0).apply(np.full((3, 2), 100.0))
    array([[100., 100.],
           [108., 108.],
           [108., 108.]])
    """

    at: int
    gain: float = 0.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        if self.at < 0 or not self.gain > -1.0:
            raise ValueError(f"fault at = {self.at}, gain = {self.gain}: expected at >= 0 "
                             "and gain > -1")

    def apply(self, curves: FloatArray) -> FloatArray:
        """The measured curves (n, n_t) N with the fault from row ``at`` on."""
        out = np.array(curves, dtype=np.float64)
        out[self.at:] = (1.0 + self.gain) * out[self.at:] + self.offset
        return out


def changed_run(spec: ProcessSpec, n: int, mu: FloatArray, rng: np.random.Generator,
                change: Change, deviation: bool = False) -> ProductionRun:
    """A production run of ``n`` products of a line with state means ``mu`` (7,), drawn by
    :func:`~formtwin.production.draw_production_run` (machine parameters uniform in their
    bounds, the deviation's theta_d too with ``deviation``, else 0; states by eq. 4-5),
    with ``change`` applied."""
    run = draw_production_run(spec, n, rng, mu=mu, deviation=deviation)
    return replace(run, x=change.apply(run.x, spec))


__all__ = ["KINDS", "MATERIAL", "Change", "Fault", "changed_run"]
