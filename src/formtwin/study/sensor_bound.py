"""Which sensor pays: the linear-Gaussian bound of each state's and the final angle's
error for a set of sensors (``formtwin sensors``).

Linearise the process about a line's mean (state means ``mu``, machine parameters
``theta`` known, nominal setting): the curve ``z_k = z(mu) + J (x_k - mu) + v_k`` with ``J``
(n_t, 7) the metamodel's curve Jacobian and ``v_k ~ N(0, R)`` the tracker's likelihood
covariance (the paper's ``K_MC / 4``, :func:`~formtwin.tracker.build_measurement`); the
final angle ``a_k = a(mu) + g^T (x_k - mu)``; the state an AR(1) (eq. 4-5). A sensor adds
a row: the gauge ``e_j^T x_k + n``, the camera ``g^T x_{k-d} + n`` (delay ``d``, the state
augmented by its last ``d`` values). The steady-state Kalman filter of this model is the
best any tracker can do with the same model and data; :func:`final_bound` gives its
final-angle error over the angle's in-run std (the study's nRMSE normalisation) and each
state's error over its sigma.

Assumptions (stated with every table): the curve and angle linear in the state over its
in-run spread (central differences of half a sigma), Gaussian noise with the likelihood's
covariance, theta and mu known (the study's series 1), the metamodel exact (series 1's
data), no deviation model. The particle filter also estimates theta and works with the
nonlinear model, so it can only be worse; a ratio near 1 says it loses nothing more.

>>> import numpy as np
>>> b = final_bound(np.ones((1, 1)), np.eye(1), np.ones(1), np.array([0.5]), np.ones(1), [])
>>> round(b.final, 4)      # one scalar state seen with unit noise, rho 0.5
0.6813
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from formtwin.measurement import ProcessModel
from formtwin.monitoring.bound import curve_jacobian
from formtwin.spec import Sensor
from formtwin.tracker import TrackerConfig, build_measurement

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SensorRow:
    """A scalar sensor in the linear model: ``h^T x_{k - delay} + N(0, var)``."""

    h: FloatArray
    var: float
    delay: int = 0


@dataclass(frozen=True)
class Bound:
    """The steady-state filter's errors: ``final`` the final angle's posterior std over its
    in-run std; ``states`` (n_x,) each state's posterior std over its sigma."""

    final: float
    states: FloatArray


def final_bound(J: FloatArray, R: FloatArray, g: FloatArray, rho: FloatArray,
                sigma: FloatArray, sensors: Sequence[SensorRow],
                iterations: int = 3000) -> Bound:
    """The bound for curves ``J`` (n_t, n_x) with noise ``R`` (n_t, n_t), final-angle
    gradient ``g`` (n_x,), AR(1) ``rho`` and ``sigma`` (n_x,) and the extra ``sensors``
    (each seen once per product, after its delay), by the Riccati recursion of the state
    augmented with its last ``max(delay)`` values, from the stationary law."""
    nx = sigma.size
    depth = max((s.delay for s in sensors), default=0)
    m = nx * (depth + 1)
    A = np.diag(rho)
    F = np.zeros((m, m))
    F[:nx, :nx] = A
    F[nx:, :-nx] = np.eye(m - nx)  # the lags shift down
    Q = np.zeros((m, m))
    Q[:nx, :nx] = np.diag(sigma**2 * (1.0 - rho**2))
    P = np.zeros((m, m))
    for i in range(depth + 1):  # stationary: Cov(x_{k-i}, x_{k-j}) = A^|i-j| Sigma
        for j in range(depth + 1):
            P[i * nx:(i + 1) * nx, j * nx:(j + 1) * nx] = \
                np.diag(rho ** abs(i - j) * sigma**2)
    rows = [np.hstack([J, np.zeros((J.shape[0], m - nx))])]
    noise = [np.asarray(R, dtype=np.float64)]
    for s in sensors:
        h = np.zeros(m)
        h[s.delay * nx:(s.delay + 1) * nx] = s.h
        rows.append(h[None, :])
        noise.append(np.array([[s.var]]))
    H = np.vstack(rows)
    n_obs = H.shape[0]
    Rf = np.zeros((n_obs, n_obs))
    i = 0
    for block in noise:
        k = block.shape[0]
        Rf[i:i + k, i:i + k] = block
        i += k
    for _ in range(iterations):
        Pp = F @ P @ F.T + Q
        S = H @ Pp @ H.T + Rf
        K = np.linalg.solve(S, H @ Pp).T
        new = Pp - K @ H @ Pp
        new = 0.5 * (new + new.T)
        done = bool(np.allclose(new, P, rtol=1e-10, atol=0.0))
        P = new
        if done:
            break
    Px = P[:nx, :nx]
    final = float(np.sqrt(g @ Px @ g / np.sum((g * sigma) ** 2)))
    return Bound(final, np.sqrt(np.diag(Px)) / sigma)


@dataclass(frozen=True)
class Linearised:
    """The process linearised about a line's ``mu`` and ``theta``: curve Jacobian ``J``
    (n_t, n_x), output gradients ``G`` (n_outputs, n_x) (output unit per internal unit), the
    likelihood covariance ``R`` (n_t, n_t), the state's ``rho``, ``sigma`` (n_x,), and the
    spec's output names (the rows of ``G``; the last: the final output)."""

    J: FloatArray
    G: FloatArray
    R: FloatArray
    rho: FloatArray
    sigma: FloatArray
    outputs: tuple[str, ...] = ("angle_stage1", "angle_stage2")

    def gradient(self, output: str | None = None) -> FloatArray:
        """``G``'s row of ``output`` (None: the last output); ``KeyError`` naming the
        outputs."""
        name = self.outputs[-1] if output is None else output
        if name not in self.outputs:
            raise KeyError(f"no model output {name!r}; known: {', '.join(self.outputs)}")
        row: FloatArray = self.G[self.outputs.index(name)]
        return row


def linearise(model: ProcessModel, mu: FloatArray, theta: FloatArray, seed: int = 0,
              n_mc: int = 10_000) -> Linearised:
    """:class:`Linearised` at ``(mu, theta)``: central differences of half a sigma, nominal
    setting; ``R`` the paper's likelihood covariance (``K_MC / 4`` about ``mu``,
    ``n_mc`` Monte-Carlo curves seeded by ``seed``)."""
    st = model.spec.state
    sigma, rho = np.asarray(st.sigma, dtype=np.float64), np.asarray(st.rho, dtype=np.float64)
    x0 = np.r_[mu, theta].astype(np.float64)
    h = 0.5 * sigma
    J = curve_jacobian(model, x0, h)
    eye = np.eye(sigma.size, x0.size)
    diff = np.asarray(model.predict_angles(x0 + np.diag(h) @ eye)) - np.asarray(
        model.predict_angles(x0 - np.diag(h) @ eye))
    G = (diff / (2.0 * h[:, None])).T
    config = TrackerConfig(mu=tuple(float(v) for v in mu), likelihood="paper", n_mc=n_mc)
    R = build_measurement(model, config, np.random.default_rng([seed, 7919, 1])).covariance()
    return Linearised(J, G, np.asarray(R, dtype=np.float64), rho, sigma,
                      tuple(model.spec.output_names))


def sensor_rows(lin: Linearised, sensors: Sequence[Sensor], spec_names: Sequence[str],
                noise: Mapping[str, float] | None = None) -> list[SensorRow]:
    """The rows of ``sensors`` (noise overridden by name, internal units), ``spec_names``
    the state's names."""
    out = []
    for s in sensors:
        if s.kind == "state":
            h = np.zeros(lin.sigma.size)
            h[list(spec_names).index(s.measures)] = 1.0
        else:
            h = lin.gradient(s.measures)
        sd = (noise or {}).get(s.name, s.noise)
        out.append(SensorRow(h, float(sd) ** 2 + 1e-30, s.delay))
    return out


def set_bound(lin: Linearised, rows: Sequence[SensorRow], output: str | None = None
              ) -> Bound:
    """:func:`final_bound` of the linearised line with ``rows``, for ``output``'s error
    (None: the spec's last output, the demonstrator's final angle)."""
    return final_bound(lin.J, lin.R, lin.gradient(output), lin.rho, lin.sigma, rows)


__all__ = ["Bound", "Linearised", "SensorRow", "final_bound", "linearise", "sensor_rows",
           "set_bound"]
