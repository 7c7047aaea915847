"""The model's final-angle discrepancy, learned online from the camera's late values.

Where the model is right (series 1), a camera reading of 0.2 deg tells little about a
product whose final angle spreads ~0.1 deg within a run, and a correction learned from
it only adds the camera's noise to the prediction. Where the model is wrong (physics
data, an assumed mu: series 5 and 6), its predicted final angle is off by a bias and
follows the true angle only weakly, and the camera's residuals are the only evidence of
it. Both cases are one model: the measured final angle ``y_j`` of product ``j`` and the
model's angle ``a_j`` predicted for it (before its camera value arrived) follow a dynamic
linear regression (West & Harrison 1997, ch. 4: unknown observation variance, discount
factor ``delta``)::

    y_j = a_ref + b0_j + b1_j (a_j - a_ref) + e_j,   e_j ~ N(0, V),
    b_j = b_{j-1} + w_j,   w_j ~ N(0, W_j) with W_j = C_{j-1} (1 / delta - 1),

so ``b = (0, 1)`` is the model as it is, ``b0`` its bias (a level that may drift), ``b1``
how much of its predicted variation is real. Which of these the data support is decided
by Bayes' rule over a small grid of hypotheses (:data:`HYPOTHESES`): the model exact
(only ``V`` learned), the bias learned, bias and slope learned, each static or drifting,
weighted by their evidence (the product of their one-step Student-t predictive densities,
a Bayes factor with its Occam penalty: the camera's noise alone does not buy a
correction). The prediction is the evidence-weighted mixture.

Known answer: with ``delta = 1`` a hypothesis is the conjugate Normal-inverse-gamma
regression of all values so far (``tests/test_angle_discrepancy.py``).

>>> d = AngleDiscrepancy(noise_var=0.04)
>>> d.predict(88.0)[0]                 # no value yet: the model's angle
88.0
>>> for k in range(200):
...     _ = d.update(88.0, 88.5)     # the model is 0.5 deg low, every time
>>> round(d.predict(88.0)[0], 2), bool(d.weights()[0] < 1e-6)
(88.5, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaln

from formtwin.tracker._fusion_kernels import discrepancy_update, mixture_forecast

FloatArray = NDArray[np.float64]

#: the hypotheses: (bias learned, slope learned, discount delta); the first is the model as
#: it is
HYPOTHESES: tuple[tuple[bool, bool, float], ...] = (
    (False, False, 1.0),
    (True, False, 1.0), (True, False, 0.999), (True, False, 0.99),
    (True, True, 1.0), (True, True, 0.999), (True, True, 0.99),
)
#: the hypotheses' discount factors (H,)
_DELTA = np.array([d for _, _, d in HYPOTHESES])
#: prior std of the bias b0 (degrees) and of the slope b1 about 1
PRIOR_SD = (1.0, 1.0)
#: prior degrees of freedom of the variance V (its prior guess: the caller's noise_var)
PRIOR_DOF = 5.0


@dataclass
class AngleDiscrepancy:
    """The evidence-weighted dynamic regression of the module doc.

    Parameters
    ----------
    noise_var : the prior guess of ``V``, degrees^2 (the camera's noise and the model's
        error: the spread of a measured angle about a correct model's prediction).

    Attributes (the state, saved by :meth:`state`): ``ref`` the first predicted angle
    (NaN before), ``a`` (H, 2), ``C`` (H, 2, 2), ``S`` (H,) and ``n`` (H,) each
    hypothesis' coefficient mean and covariance and variance estimate with its degrees of
    freedom, ``logw`` (H,) the normalised log posterior of the hypotheses, ``pending``
    product -> the model angle predicted for it.
    """

    noise_var: float
    ref: float = math.nan
    a: FloatArray = field(default_factory=lambda: np.zeros(0))
    C: FloatArray = field(default_factory=lambda: np.zeros(0))
    S: FloatArray = field(default_factory=lambda: np.zeros(0))
    n: FloatArray = field(default_factory=lambda: np.zeros(0))
    logw: FloatArray = field(default_factory=lambda: np.zeros(0))
    pending: dict[int, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.noise_var) and self.noise_var > 0):
            raise ValueError(f"noise_var = {self.noise_var}, expected a positive number of "
                             "degrees^2")
        if self.a.size == 0:
            h = len(HYPOTHESES)
            self.a = np.tile([0.0, 1.0], (h, 1))
            mask = np.array([[b, s] for b, s, _ in HYPOTHESES], dtype=np.float64)
            self.C = np.einsum("hi,ij->hij", mask, np.diag(np.square(PRIOR_SD)))
            self.S = np.full(h, float(self.noise_var))
            self.n = np.full(h, PRIOR_DOF)
            self.logw = np.full(h, -math.log(h))
        # the last update's gammaln((n + 1) / 2) with that n + 1 (replaced by an update,
        # never changed in place): the next update's gammaln(n / 2)
        self._gammaln_of: tuple[FloatArray | None, FloatArray] = (None, self.n)

    @property
    def _delta(self) -> FloatArray:
        return _DELTA

    def weights(self) -> FloatArray:
        """Posterior probabilities (H,) of :data:`HYPOTHESES`."""
        w = np.exp(self.logw - self.logw.max())
        out: FloatArray = w / w.sum()
        return out

    def predict(self, model_angle: float) -> tuple[float, float]:
        """The measured final angle predicted from the model's ``model_angle`` (degrees):
        mean and variance (degrees^2) of the hypotheses' mixture (each a Student-t with
        ``n`` degrees of freedom, its variance ``Q n / (n - 2)``), in one pass
        (:func:`~formtwin.tracker._fusion_kernels.mixture_forecast`; the NumPy formula's
        numbers to rounding)."""
        x = float(model_angle)
        ref = x if math.isnan(self.ref) else self.ref
        mean, var = mixture_forecast(self.a, self.C, self.S, self.n, self.logw, _DELTA, ref, x)
        return float(mean), float(var)

    def coefficients(self) -> tuple[float, float, float]:
        """``(ref, b0, b1)``, the coefficients averaged over the hypotheses: the measured
        angle of a model angle ``a`` is ``ref + b0 + b1 (a - ref)`` (its residual
        variance: :meth:`variance`)."""
        b = self.weights() @ self.a
        return (self.ref, float(b[0]), float(b[1]))

    def variance(self) -> float:
        """The mixture's estimate of ``V`` (degrees^2)."""
        return float(self.weights() @ self.S)

    def mapping(self) -> tuple[float, float, float, float]:
        """``(ref, b0, b1, V)``: :meth:`coefficients` and :meth:`variance` (the same
        numbers) from one evaluation of the weights."""
        w = self.weights()
        b = w @ self.a
        return (self.ref, float(b[0]), float(b[1]), float(w @ self.S))

    def issue(self, product: int, model_angle: float) -> tuple[float, float]:
        """:meth:`predict` for ``product``, remembering ``model_angle`` until its measured
        value arrives (:meth:`update_product`); the first one sets ``ref``."""
        if not math.isfinite(model_angle):
            return math.nan, math.nan
        if math.isnan(self.ref):
            self.ref = float(model_angle)
        self.pending[int(product)] = float(model_angle)
        return self.predict(model_angle)

    def update_product(self, product: int, value: float) -> float | None:
        """:meth:`update` with the model angle issued for ``product`` (None if none was)."""
        issued = self.pending.pop(int(product), None)
        if issued is None or not math.isfinite(value):
            return None
        return self.update(issued, value)

    def update(self, model_angle: float, value: float) -> float:
        """Take the measured ``value`` (degrees) of a product whose model angle was
        ``model_angle``: every hypothesis' conjugate update and its weight times the
        predictive density (a Student-t with ``n`` degrees of freedom), in one pass
        (:func:`~formtwin.tracker._fusion_kernels.discrepancy_update`; the NumPy
        formula's numbers to rounding). Returns the log evidence of the value under the
        mixture."""
        if math.isnan(self.ref):
            self.ref = float(model_angle)
        n = self.n
        n1 = n + 1.0
        g_n, g_up = self._gammaln_of
        if g_n is not n:  # gammaln(n / 2): the last update's gammaln((n + 1) / 2)
            g_up = gammaln(n / 2)
        g_next = gammaln(n1 / 2)
        self.a, self.C, self.S, self.logw, norm = discrepancy_update(
            self.a, self.C, self.S, n, n1, self.logw, _DELTA, self.ref, float(model_angle),
            float(value), g_next - g_up)
        self.n = n1
        self._gammaln_of = (n1, g_next)
        return float(norm)

    def state(self) -> list[float]:
        """The state as one list of JSON numbers (:meth:`set_state` reads it back)."""
        pend = [v for p, a in sorted(self.pending.items()) for v in (float(p), a)]
        return [self.ref, *self.a.ravel(), *self.C.ravel(), *self.S, *self.n, *self.logw,
                *pend]

    def set_state(self, flat: list[float]) -> None:
        """Inverse of :meth:`state`."""
        h = len(HYPOTHESES)
        v = np.asarray(flat, dtype=np.float64)
        self.ref = float(v[0])
        i = 1
        self.a = v[i:i + 2 * h].reshape(h, 2).copy()
        i += 2 * h
        self.C = v[i:i + 4 * h].reshape(h, 2, 2).copy()
        i += 4 * h
        self.S, self.n, self.logw = (v[i + k * h:i + (k + 1) * h].copy() for k in range(3))
        rest = v[i + 3 * h:]
        self.pending = {int(rest[k]): float(rest[k + 1]) for k in range(0, rest.size, 2)}

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, AngleDiscrepancy):
            return NotImplemented
        return self.noise_var == other.noise_var and self.state() == other.state()


__all__ = ["HYPOTHESES", "AngleDiscrepancy"]
