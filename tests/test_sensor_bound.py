"""The linear-Gaussian bound per sensor set (formtwin.study.sensor_bound, ``formtwin
sensors``): closed forms for a scalar AR(1), the curve-only filter of the monitoring bound
as a reference, and the command on the analytic stand-in."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from formtwin.cli import main
from formtwin.metamodel import Metamodel
from formtwin.monitoring.bound import steady_filter
from formtwin.study.sensor_bound import SensorRow, final_bound


def _scalar_filter(rho: float, r: float) -> float:
    """Steady filtering variance of an AR(1) with unit stationary variance seen with noise
    variance ``r`` (the positive root of the Riccati equation)."""
    q = 1 - rho**2
    # P = Pp r / (Pp + r), Pp = rho^2 P + q  ->  rho^2 P^2 + (q + r - rho^2 r) P - q r = 0
    b = q + r - rho**2 * r
    return (-b + math.sqrt(b * b + 4 * rho**2 * q * r)) / (2 * rho**2)


def test_scalar_closed_forms() -> None:
    """A state seen by a curve (noise 1) and a sensor (noise 0.25): the filtering variance
    of the combined noise; the same sensor one product late: the curve's filter then the
    sensor's news about the previous state, carried one step by the AR(1)."""
    rho, J, R = 0.7, np.ones((1, 1)), np.eye(1)
    one = np.ones(1)
    b = final_bound(J, R, one, np.array([rho]), one, [SensorRow(one, 0.25)])
    r = 1 / (1 / 1 + 1 / 0.25)  # two independent looks at x_k
    assert b.final == pytest.approx(math.sqrt(_scalar_filter(rho, r)), rel=1e-8)
    assert b.states[0] == pytest.approx(b.final, rel=1e-12)
    late = final_bound(J, R, one, np.array([rho]), one, [SensorRow(one, 0.25, delay=1)])
    # the joint filter of (x_k, x_{k-1}) by brute force on a long path's information form
    n = 400
    prec = np.zeros((n, n))
    q = 1 - rho**2
    prec[0, 0] = 1.0
    for k in range(1, n):  # AR(1) path precision
        prec[k - 1:k + 1, k - 1:k + 1] += np.array([[rho**2, -rho], [-rho, 1.0]]) / q
    prec += np.eye(n)  # the curve of every product
    prec[np.arange(n - 1), np.arange(n - 1)] += 1 / 0.25  # the sensor, all but the last
    cov_last = np.linalg.inv(prec)[-1, -1]
    assert late.final == pytest.approx(math.sqrt(cov_last), rel=1e-6)
    assert b.final < late.final < final_bound(J, R, one, np.array([rho]), one, []).final


def test_curve_only_matches_the_monitoring_filter() -> None:
    rng = np.random.default_rng(0)
    J = rng.standard_normal((12, 3))
    R = np.diag(rng.uniform(0.5, 2.0, 12))
    rho, sigma = np.array([0.8, 0.9, 0.7]), np.array([1.0, 2.0, 0.5])
    g = np.array([0.3, -1.0, 2.0])
    P = steady_filter(J, R, rho, sigma).posterior
    b = final_bound(J, R, g, rho, sigma, [])
    assert b.final == pytest.approx(math.sqrt(g @ P @ g / np.sum((g * sigma) ** 2)), rel=1e-6)
    np.testing.assert_allclose(b.states, np.sqrt(np.diag(P)) / sigma, rtol=1e-6)


def test_command_on_the_analytic_stand_in(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                          analytic_mm: tuple[Metamodel, Path]) -> None:
    path = analytic_mm[1]  # the session's fit of the analytic stand-in (600 runs)
    assert main(["sensors", "--out", str(tmp_path / "s"), "--metamodel", str(path),
                 "--realisations", "2", "--n-mc", "500", "--noise-factors", "1,2"]) == 0
    text = capsys.readouterr().out
    assert "gauge_0.5um" in text and "camera_0.2deg" in text and "assumptions" in text
    table = json.loads((tmp_path / "s" / "sensors.json").read_text())["bound"]
    f = {k: v["final"] for k, v in table.items()}
    # more information never hurts the bound: a sensor, or a less noisy one
    assert f["all"] <= min(f["gauge_0.5um"], f["camera_0.2deg"]) + 1e-9
    assert f["gauge_0.5um"] <= f["gauge_1um"] + 1e-9 <= f["curve"] + 2e-9
    assert f["camera_0.2deg"] <= f["camera_0.4deg"] + 1e-9 <= f["curve"] + 2e-9
    assert table["gauge_0.5um"]["states"]["thickness"] < table["curve"]["states"]["thickness"]
