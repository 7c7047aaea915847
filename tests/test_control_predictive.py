"""The feedforward on the posterior predictive (:class:`formtwin.control.Predictive`) on a
linear plant whose answers are known: the camera's value moved to the reference setting by
the model's gain, a constant bias and an exaggerated product-to-product change learned and
cancelled, and, with a noisy camera, a final-angle spread that beats the run-to-run EWMA at
its best weight and approaches what the posterior's information allows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from formtwin.control import Actuator, EwmaRunToRun, Feedforward, Predictive
from formtwin.tracker.angle_discrepancy import AngleDiscrepancy

TARGET, GAIN = 90.0, -0.05  # deg, deg per unit of u
ACT = Actuator(-100.0, 100.0)


def model(c: float):  # one particle: the posterior's final angle c at u = 0, the model's gain
    return lambda u: c + GAIN * np.asarray(u, dtype=np.float64)[None, :]


def closed_loop(ctl: Predictive, c: np.ndarray, truth: np.ndarray, noise: np.ndarray
                ) -> np.ndarray:
    """The plant's angles (n,): product i's true angle at u = 0 is ``truth[i]``, the
    posterior says ``c[i]``, the camera reads product i - 1 with ``noise``."""
    n = c.size
    u, out = np.zeros(n), np.zeros(n)
    for i in range(n):
        if i >= 1:
            ctl.measured(i - 1, out[i - 1] + noise[i - 1])
        u[i] = ctl.choose(i, model(float(c[i])), u_prev=None).u
        out[i] = truth[i] + GAIN * u[i]
    return out


def test_the_camera_value_is_moved_to_the_reference_by_the_models_gain() -> None:
    d = AngleDiscrepancy(0.04)
    ctl = Predictive(Feedforward(TARGET, ACT), d, u_ref=0.0)
    s = ctl.choose(7, model(89.0))      # the model: 89 at u = 0, so u = -20 for 90
    assert s.u == pytest.approx(-20.0, abs=1e-6)
    assert ctl.measured(7, 90.3) == pytest.approx(89.3, abs=1e-9)   # 90.3 - (90 - 89)
    assert d.ref == pytest.approx(89.0) and not ctl.pending
    assert math.isnan(ctl.measured(7, 90.0))   # once per product
    # products whose value never comes are dropped when a later one arrives
    ctl.choose(8, model(89.0))
    ctl.choose(9, model(89.0))
    ctl.measured(9, 90.0)
    assert not ctl.pending


def test_a_constant_bias_and_an_exaggerated_change_are_learned_and_cancelled() -> None:
    rng = np.random.default_rng(1)
    n = 400
    x = 0.3 * rng.standard_normal(n)                 # the products' true change
    c = 89.0 + 2.0 * x                               # the model: twice the change, 1 deg low
    truth = 90.0 + x                                 # (so the slope b1 = 0.5, bias + 1)
    ctl = Predictive(Feedforward(TARGET, ACT), AngleDiscrepancy(1e-4), u_ref=0.0)
    out = closed_loop(ctl, c, truth, np.zeros(n))
    ref, b0, b1 = ctl.corrector.coefficients()
    assert b1 == pytest.approx(0.5, abs=1e-3)
    assert ref + b0 + b1 * (89.0 - ref) == pytest.approx(90.0, abs=1e-3)
    assert np.max(np.abs(out[50:] - TARGET)) < 1e-3


def test_a_noisy_camera_weighs_in_by_its_noise_and_beats_the_ewma() -> None:
    rng = np.random.default_rng(2)
    n, sd = 1500, 0.2
    x = np.zeros(n)
    for i in range(1, n):  # the in-run spread ~0.1 deg, persistent (AR(1), rho 0.7)
        x[i] = 0.7 * x[i - 1] + 0.1 * math.sqrt(1 - 0.49) * rng.standard_normal()
    known = 0.8  # the posterior knows part of it: corr(c, truth) = 0.8
    c = 88.5 + known * x + 0.1 * math.sqrt(1 - known**2) * rng.standard_normal(n)
    truth = 90.0 + x
    noise = sd * rng.standard_normal(n)
    ctl = Predictive(Feedforward(TARGET, ACT), AngleDiscrepancy(sd**2), u_ref=0.0)
    ff = np.std(closed_loop(ctl, c, truth, noise)[200:])
    # the run-to-run EWMA at its best weight on the same camera values
    ewma = []
    for lam in (0.02, 0.05, 0.1, 0.2, 0.5, 1.0):
        r = EwmaRunToRun(TARGET, GAIN, lam, ACT)
        u, a = np.zeros(n), np.zeros(n)
        for i in range(n):
            if i >= 1:
                r.update(a[i - 1] + noise[i - 1], u[i - 1])
            u[i] = r.u
            a[i] = truth[i] + GAIN * u[i]
        ewma.append(np.std(a[200:]))
    # best linear in c: the residual sqrt(1 - r^2) of the in-run std (r^2 = 0.64 / 0.74)
    r2 = np.corrcoef(c, truth)[0, 1] ** 2
    limit = math.sqrt(1 - r2) * np.std(x[200:])
    assert ff < 0.8 * min(ewma)
    assert ff < 1.15 * limit
