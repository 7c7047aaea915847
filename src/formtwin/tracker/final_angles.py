"""Each particle's predicted final angle and its ancestors', kept from the step.

A camera reads product ``j``'s final angle up to ``L`` products late; the likelihood of
its value needs the model's final angle at each current particle's ancestor ``j``
(:meth:`~formtwin.tracker.SensorFusion.fuse`), and the interval issued with product
``j``'s estimate needs it at product ``j``'s particles. The step has already evaluated the
angles of its particles at the product's setting (the estimate's predicted angles), so
:class:`FinalAngles` keeps them beside the particles, (N, L + 1) aligned with the filter's
rows: column 0 the particle's own final angle at its product's setting, column ``l`` its
ancestor's ``l`` products back. At the next step column ``l`` moves to ``l + 1`` with the
transition (row ``k`` of the predicted particles descends from row ``k`` of the filter's,
which the lag columns confirm) and all columns follow the resampling's ancestor indices.
A particle whose angle the step did not evaluate (one of the lightest, left out by the
estimate; every row after a filter's move or jitter) holds NaN and is evaluated where it
is needed (:meth:`FinalAngles.column`). The arrays go into the state bytes, so a restored
tracker uses the same numbers as an uninterrupted one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.filters.lagged import distinct_rows

FloatArray = NDArray[np.float64]

#: the state's keys of the angles (N, L + 1) and of the settings they were taken at
#: (L + 1, n_controls; NaN rows: the nominal setting)
STATE_KEYS = ("final_angles", "final_angles_u")


class FinalAngles:
    """The particles' final angles and their ancestors' (see the module doc).

    Parameters
    ----------
    depth : ``L``, the lag columns kept besides the particles' own.
    n_controls : the spec's number of controls.
    """

    def __init__(self, depth: int, n_controls: int) -> None:
        self.depth, self.n_controls = int(depth), int(n_controls)
        #: (N, L + 1) degrees, NaN where not known; None before the first step
        self.angles: FloatArray | None = None
        #: (L + 1, n_controls) the settings of the columns (NaN: nominal)
        self.u: FloatArray = np.full((self.depth + 1, self.n_controls), np.nan)
        #: :attr:`u` as lists of floats, by the array they came from (:attr:`u` is replaced
        #: at every step, never changed in place)
        self._u_rows: tuple[FloatArray | None, list[list[float]]] = (None, [])

    def _code(self, u: FloatArray | None) -> FloatArray:
        return np.full(self.n_controls, np.nan) if u is None else np.asarray(u, np.float64)

    def stepped(self, own: FloatArray, u: FloatArray | None, same_parents: bool,
                ancestors: NDArray[np.intp] | None) -> None:
        """After a step: ``own`` (N,) the final angles of the step's particles (before
        resampling) at their setting ``u`` (NaN: not evaluated); ``same_parents`` whether
        row ``k`` of those particles descends from row ``k`` of the previous filter rows;
        ``ancestors`` the resampling's indices (the filter's rows are ``x[ancestors]``;
        None: the rows were moved, nothing is known)."""
        n = own.shape[0]
        out = np.full((n, self.depth + 1), np.nan)
        out[:, 0] = own
        prev = self.angles
        if same_parents and prev is not None and prev.shape[0] == n and self.depth:
            out[:, 1:] = prev[:, :-1]
        self.angles = out[ancestors] if ancestors is not None else np.full_like(out, np.nan)
        self.u = np.vstack([self._code(u)[None, :], self.u[:-1]])

    def column(self, lag: int, u: FloatArray | None, inputs: FloatArray,
               evaluate: Callable[[FloatArray], FloatArray]) -> FloatArray:
        """The final angles (N,) of the particles' ancestors ``lag`` products back at
        setting ``u``: the kept ones where known and taken at ``u``, else ``evaluate``
        (the model's final angle of input rows (m, n_in) -> (m,)) on the distinct rows of
        ``inputs`` (N, n_in) left."""
        src, settings = self._u_rows
        if src is not self.u:
            settings = self.u.tolist()
            self._u_rows = (self.u, settings)
        kept = None if self.angles is None or not 0 <= lag <= self.depth \
            or inputs.shape[0] != self.angles.shape[0] \
            or not _same_setting(settings[lag], u) else self.angles[:, lag]
        if kept is None:
            kept = np.full(inputs.shape[0], np.nan)
        todo = np.flatnonzero(np.isnan(kept))
        if todo.size == 0:
            return kept
        rows, inverse = distinct_rows(inputs[todo])
        out = kept.copy()
        out[todo] = np.asarray(evaluate(rows), dtype=np.float64)[inverse]
        return out

    def fill_own(self, own: FloatArray) -> None:
        """Column 0 replaced by ``own`` (N,) (the angles the issued interval used); nothing
        to do when ``own`` is column 0 itself (:meth:`column` evaluated nothing)."""
        a = self.angles
        if a is not None and own.ndim == 1 and own.shape[0] == a.shape[0] \
                and own.__array_interface__["data"][0] == a.__array_interface__["data"][0] \
                and own.strides[0] == a.strides[0]:
            return
        if self.angles is not None and self.angles.shape[0] == own.shape[0]:
            angles = self.angles.copy()
            angles[:, 0] = own
            self.angles = angles

    def snapshot(self) -> tuple[FloatArray | None, FloatArray]:
        """What :meth:`restore` needs (the arrays are replaced, never changed in place)."""
        return self.angles, self.u

    def restore(self, snap: tuple[FloatArray | None, FloatArray]) -> None:
        """Back to a :meth:`snapshot`."""
        self.angles, self.u = snap

    def state(self) -> dict[str, Any]:
        """The arrays under :data:`STATE_KEYS` (none before the first step)."""
        if self.angles is None:
            return {}
        return {STATE_KEYS[0]: self.angles, STATE_KEYS[1]: self.u}

    def set_state(self, model: dict[str, Any]) -> None:
        """Inverse of :meth:`state`; a state without them (an older version's) leaves
        every angle to be evaluated where needed."""
        a, u = (model.get(k) for k in STATE_KEYS)
        shape = (self.depth + 1, self.n_controls)
        if a is None or u is None or np.shape(u) != shape or np.ndim(a) != 2 \
                or np.shape(a)[1] != shape[0]:
            self.angles, self.u = None, np.full(shape, np.nan)
            return
        self.angles = np.array(a, dtype=np.float64)
        self.u = np.array(u, dtype=np.float64)


def _same_setting(kept: FloatArray | list[float], u: FloatArray | None) -> bool:
    """Whether the setting ``kept`` (n_controls,) of a column (an array or its floats),
    NaN for nominal, is ``u`` (None: nominal): ``np.array_equal(kept, code(u),
    equal_nan=True)`` on Python floats, without its ~20 us of argument handling per
    call."""
    a = kept.tolist() if isinstance(kept, np.ndarray) else kept
    if u is None:
        return all(math.isnan(x) for x in a)
    b = np.asarray(u, np.float64)
    if b.shape != (len(a),):
        return False
    return all(x == y or (math.isnan(x) and math.isnan(y))
               for x, y in zip(a, b.tolist(), strict=True))


__all__ = ["STATE_KEYS", "FinalAngles"]
