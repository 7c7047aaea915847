"""The metamodel's exact derivatives by its inputs (a mixin of
:class:`~formtwin.metamodel.Metamodel`), for a linearisation at a point.

The curve is ``mean + s(u) @ modes`` with ``u = (x - lo) / (hi - lo)`` and ``s`` the RBF
of the mode coefficients, so by the chain rule

    d curve / d x_i = (d s / d u_i) @ modes / (hi_i - lo_i),

with ``d s / d u`` the interpolant's closed-form gradient
(:meth:`~formtwin.metamodel.RBF.value_and_gradient`); the angles likewise without the
modes. In float64: the exact derivative of the interpolant that the evaluation
(float32 by default) rounds, where forward differences of the rounded evaluation carry its
rounding divided by the step (``tests/test_metamodel_gradient.py`` holds both to
finite differences and to an interpolated linear function).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Gradients:
    """``curve_jacobian`` and ``angle_gradient`` of a fitted POD + RBF metamodel."""

    curve_model: Any
    angle_models: tuple[Any, ...]
    reduction: Any
    lo: FloatArray
    hi: FloatArray
    _angle_dims: tuple[int, ...]
    _unit_in: Any
    _inputs: Any
    scale: Any

    @property
    def differentiable(self) -> bool:
        """Every fitted part has its closed-form gradient (``value_and_gradient``, as
        :class:`~formtwin.metamodel.RBF`): :meth:`curve_jacobian` and
        :meth:`angle_gradient` work."""
        parts = (self.curve_model, *self.angle_models)
        return all(hasattr(m, "value_and_gradient") for m in parts)

    def curve_jacobian(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The curves (N, n_t) N at inputs ``X`` (N, 10) ``[x, theta]``, internal units,
        and their derivatives (N, n_t, 10) N per internal unit, in float64."""
        U = self._unit_in(X)
        if self.curve_model is None:
            raise RuntimeError("Metamodel is not fitted: call fit(dataset) or Metamodel.load")
        coef, grad = self.curve_model.value_and_gradient(U)
        grad /= (self.hi - self.lo)[None, :U.shape[1], None]
        modes = self.reduction.modes
        curves: FloatArray = coef @ modes + self.reduction.mean
        jac: FloatArray = np.matmul(grad, modes).transpose(0, 2, 1)
        return curves, jac

    def angle_gradient(self, X: FloatArray, u: FloatArray | float | None = None
                       ) -> FloatArray:
        """Derivatives (N, n_outputs, 10) of the scalar outputs (degrees per internal
        unit) by ``[x, theta]`` at inputs ``X`` (N, 10) and controls ``u`` (as
        :meth:`~formtwin.metamodel.Metamodel.predict_angles`), in float64."""
        U = self.scale(self._inputs(X, u))
        n_in = self._unit_in(X).shape[1]
        width = (self.hi - self.lo)[:n_in]
        out = np.empty((U.shape[0], len(self.angle_models), n_in))
        for j, (m, n) in enumerate(zip(self.angle_models, self._angle_dims, strict=True)):
            out[:, j] = m.value_and_gradient(U[:, :n])[1][:, :n_in, 0] / width
        return out
