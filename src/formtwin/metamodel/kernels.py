"""RBF kernels ``phi(r^2)`` of the squared scaled distance, their slopes, and the
polynomial tail (monomials of ``2u - 1``) of :class:`~formtwin.metamodel.rbf.RBF`.

The kernels work in place on their argument's copy and keep its dtype (float32 on the
evaluation hot path).

>>> import numpy as np
>>> float(kernel_function("cubic")(np.array([4.0]))[0])
8.0
>>> monomial_powers(2, 1).tolist()
[[0, 0], [1, 0], [0, 1]]
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import combinations_with_replacement

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Kernel = Callable[[np.ndarray], np.ndarray]


def _tps(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.log(np.maximum(r2, np.finfo(r2.dtype).tiny))
    out *= r2
    out *= 0.5
    return out


def _cubic(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2)
    out *= r2
    return out


def _quintic(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2)
    out *= r2
    out *= -r2
    return out


def _linear(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2)
    out *= -1.0
    return out


def _gaussian(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.exp(-r2)
    return out


def _multiquadric(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2 + 1.0)
    out *= -1.0
    return out


def _inverse_multiquadric(r2: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.sqrt(r2 + 1.0)
    np.reciprocal(out, out=out)
    return out


#: kernel name -> (phi of the squared scaled distance, lowest polynomial degree it needs)
KERNELS: dict[str, tuple[Kernel, int]] = {
    "thin_plate_spline": (_tps, 1),
    "cubic": (_cubic, 1),
    "quintic": (_quintic, 2),
    "linear": (_linear, 0),
    "gaussian": (_gaussian, -1),
    "multiquadric": (_multiquadric, 0),
    "inverse_multiquadric": (_inverse_multiquadric, -1),
}

#: d phi / d(r^2) per kernel (its value at r = 0 is never used)
KERNEL_SLOPES: dict[str, Kernel] = {
    "thin_plate_spline": lambda r2: 0.5 * (np.log(np.maximum(r2, 1e-300)) + 1.0),
    "cubic": lambda r2: 1.5 * np.sqrt(r2),
    "quintic": lambda r2: -2.5 * r2 * np.sqrt(r2),
    "linear": lambda r2: -0.5 / np.sqrt(np.maximum(r2, 1e-300)),
    "gaussian": lambda r2: -np.exp(-r2),
    "multiquadric": lambda r2: -0.5 / np.sqrt(1.0 + r2),
    "inverse_multiquadric": lambda r2: -0.5 * (1.0 + r2) ** -1.5,
}

#: kernels whose interpolant does not change when all length scales are multiplied
SCALE_FREE = frozenset({"thin_plate_spline", "cubic", "quintic", "linear"})


def kernel_function(name: str) -> Kernel:
    """The kernel ``phi`` of the squared scaled distance named ``name`` (:data:`KERNELS`)."""
    try:
        return KERNELS[name][0]
    except KeyError:
        raise ValueError(f"unknown RBF kernel {name!r}; known: {', '.join(KERNELS)}") from None


def monomial_powers(d: int, degree: int) -> NDArray[np.int64]:
    """Exponents (q, d) of all monomials in d variables up to ``degree`` (none if < 0)."""
    rows = [np.zeros(d, dtype=np.int64)] if degree >= 0 else []
    for deg in range(1, degree + 1):
        for combo in combinations_with_replacement(range(d), deg):
            p = np.zeros(d, dtype=np.int64)
            np.add.at(p, list(combo), 1)
            rows.append(p)
    return np.array(rows, dtype=np.int64).reshape(-1, d)


#: for exponents of degree at most 1: the column of ``V`` of each monomial and where it
#: is the constant (:func:`linear_plan`)
LinearPlan = tuple[NDArray[np.intp], NDArray[np.bool_]]


def linear_plan(powers: NDArray[np.int64]) -> LinearPlan | None:
    """For exponents ``powers`` (q, d) of degree at most 1: the column of ``V`` of each
    monomial and where it is the constant (read-only); None for higher degrees. Made once
    per set of exponents by its owner (:class:`~formtwin.metamodel.RBF` keeps it with
    its ``powers``) and passed to :func:`polynomial`."""
    powers = np.asarray(powers, dtype=np.int64)
    degrees = powers.sum(axis=1)
    if not np.all(degrees <= 1):
        return None
    cols = powers.argmax(axis=1) if powers.shape[1] else np.zeros(powers.shape[0], np.intp)
    const = degrees == 0
    cols.flags.writeable = const.flags.writeable = False
    return cols, const


def polynomial(U: FloatArray, powers: NDArray[np.int64],
               plan: LinearPlan | None = None) -> FloatArray:
    """Monomials (n, q) of ``2U - 1`` for unit-box inputs ``U`` (n, d); ``plan`` the
    exponents' :func:`linear_plan` when the caller keeps it (None: made here)."""
    V = 2.0 * U - 1.0
    if plan is None:
        plan = linear_plan(powers)
    if plan is not None:  # constant and linear terms: columns of V (the same numbers)
        lin: FloatArray = V[:, plan[0]]
        lin[:, plan[1]] = 1.0
        return lin
    out = np.ones((U.shape[0], powers.shape[0]))
    for j, p in enumerate(powers):
        for i in np.flatnonzero(p):
            out[:, j] *= V[:, i] ** p[i]
    return out


def polynomial_gradient(U: FloatArray, powers: NDArray[np.int64],
                        plan: LinearPlan | None = None) -> FloatArray:
    """Derivatives (n, d, q) of the monomials (:func:`polynomial`) of ``2U - 1`` by the
    unit-box inputs ``U`` (n, d): ``d p_j / d u_i``; ``plan`` as in :func:`polynomial`.

    >>> polynomial_gradient(np.array([[0.5, 0.25]]), monomial_powers(2, 2))[0].tolist()
    [[0.0, 2.0, 0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 2.0, 0.0, 0.0, -2.0]]
    """
    n, d = U.shape
    out = np.zeros((n, d, powers.shape[0]))
    if plan is None:
        plan = linear_plan(powers)
    if plan is not None:  # d (2 u_i - 1) / d u_i = 2; the constant's derivative is 0
        lin = np.flatnonzero(~plan[1])
        out[:, plan[0][lin], lin] = 2.0
        return out
    V = 2.0 * U - 1.0
    for j, p in enumerate(powers):
        for i in np.flatnonzero(p):  # 2 p_i V_i^(p_i - 1) times the other factors
            term = 2.0 * p[i] * V[:, i] ** (p[i] - 1)
            for k in np.flatnonzero(p):
                if k != i:
                    term = term * V[:, k] ** p[k]
            out[:, i, j] = term
    return out
