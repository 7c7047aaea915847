"""Control of the final angle: the feedforward choice against closed-form optima on synthetic
plants (linear, multiplicative, curved), actuator limits and maximum step, the reported
interval, and the run-to-run EWMA controller's fixed point."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.control import Actuator, EwmaRunToRun, Feedforward, weighted_quantile

T = 90.0


def linear_plant(c: np.ndarray, b: float):  # type: ignore[no-untyped-def]
    """Angles (N, n_u) = c_k + b u."""
    return lambda u: c[:, None] + b * np.asarray(u)[None, :]


def test_linear_plant_exact_optimum_and_cost() -> None:
    rng = np.random.default_rng(0)
    c, w = 88.0 + rng.normal(0, 0.4, 500), rng.uniform(0.1, 1.0, 500)
    b = -0.05  # deg per um
    ff = Feedforward(T, Actuator(-100.0, 100.0), grid=7)
    s = ff.choose(linear_plant(c, b), w)
    wn = w / w.sum()
    u_star = (T - wn @ c) / b  # E[a(u)] = T; J(u*) = Var(c)
    assert s.u == pytest.approx(u_star, abs=1e-9)
    assert s.angle_mean == pytest.approx(T, abs=1e-9)
    var = wn @ (c - wn @ c) ** 2
    assert s.expected_sq_error == pytest.approx(var, rel=1e-9)
    assert s.angle_std == pytest.approx(np.sqrt(var), rel=1e-9)
    assert not s.limited
    # no setting on a fine grid does better
    dense = np.linspace(-100, 100, 20001)
    assert s.expected_sq_error <= ff.cost(linear_plant(c, b)(dense), wn).min() + 1e-12


def test_limits_and_maximum_step() -> None:
    c = np.array([88.0, 88.5, 89.5])  # E = 88.667: u* = -26.67 um
    plant = linear_plant(c, -0.05)
    s = Feedforward(T, Actuator(-100.0, 100.0, max_step=5.0)).choose(plant, u_prev=0.0)
    assert s.u == pytest.approx(-5.0) and s.limited
    s = Feedforward(T, Actuator(-20.0, 100.0)).choose(plant)
    assert s.u == pytest.approx(-20.0) and s.limited
    s = Feedforward(T, Actuator(-100.0, 100.0, max_step=50.0)).choose(plant, u_prev=-10.0)
    assert s.u == pytest.approx(-26.6666667) and not s.limited
    assert Actuator(-100, 100, 5.0).feasible(98.0) == (93.0, 100.0)
    with pytest.raises(ValueError, match="limits"):
        Actuator(1.0, 1.0)
    with pytest.raises(ValueError, match="shape"):
        Feedforward(T, Actuator(-1, 1)).choose(lambda u: np.zeros((4, 2)))


def test_posterior_expectation_not_plug_in() -> None:
    """a(x, u) = x u: E[(x u - T)^2] is least at u = T E[x] / E[x^2], below the plug-in
    T / E[x] by the factor 1 / (1 + cv^2)."""
    rng = np.random.default_rng(1)
    x = rng.normal(1.0, 0.3, 4000)
    ff = Feedforward(T, Actuator(0.0, 200.0), grid=5)
    s = ff.choose(lambda u: x[:, None] * np.asarray(u)[None, :])
    exact = T * x.mean() / np.mean(x * x)
    assert s.u == pytest.approx(exact, rel=1e-9)  # J is quadratic in u: exact
    assert s.u < T / x.mean() * 0.95


def test_curved_plant_matches_brute_force() -> None:
    rng = np.random.default_rng(2)
    c, q = 88.0 + rng.normal(0, 0.3, 300), 1e-4 * (1 + rng.uniform(0, 1, 300))
    plant = lambda u: (c[:, None] - 0.04 * np.asarray(u)[None, :]  # noqa: E731
                       + q[:, None] * np.asarray(u)[None, :] ** 2)
    ff = Feedforward(T, Actuator(-100.0, 100.0), grid=9)
    s = ff.choose(plant)
    dense = np.linspace(-100, 100, 40001)
    j = ff.cost(plant(dense), np.full(300, 1 / 300))
    assert abs(s.u - dense[np.argmin(j)]) < 0.5  # um, of a 200 um range
    assert s.expected_sq_error <= j.min() * (1 + 1e-3)


def test_interval_is_the_posterior_quantiles() -> None:
    rng = np.random.default_rng(3)
    c = 88.0 + rng.normal(0, 0.5, 20000)
    s = Feedforward(T, Actuator(-100, 100), coverage=0.9).choose(linear_plant(c, -0.05))
    half = 1.6449 * 0.5
    assert s.interval[0] == pytest.approx(T - half, abs=0.03)
    assert s.interval[1] == pytest.approx(T + half, abs=0.03)
    v = np.arange(1.0, 5.0)
    assert weighted_quantile(v, np.array([1.0, 1, 1, 5]), np.array([0.5]))[0] == \
        pytest.approx(3.5)  # mid-point CDF: 0.3125 at 3, 0.6875 at 4


def test_nonfinite_particle_angles_count_as_worst() -> None:
    c = np.array([88.0, 88.0, np.nan])
    s = Feedforward(T, Actuator(-100, 100)).choose(linear_plant(c, -0.05))
    assert s.u == pytest.approx(-40.0)
    assert s.angle_mean == pytest.approx(T)


def test_ewma_run_to_run() -> None:
    act = Actuator(-100.0, 100.0)
    # exact gain, lam = 1: deadbeat
    r = EwmaRunToRun(T, -0.05, 1.0, act)
    assert r.update(88.0, 0.0) == pytest.approx(-40.0)
    assert r.update(88.0 - 0.05 * -40.0, -40.0) == pytest.approx(-40.0)
    # a constant offset with a wrong gain (b_model = 2 b): the EWMA still removes it
    b, d = -0.05, 88.0
    r = EwmaRunToRun(T, 2 * b, 0.3, act)
    u = 0.0
    for _ in range(200):
        u = r.update(b * u + d, u)
    assert b * u + d == pytest.approx(T, abs=1e-6)
    # the maximum step limits each change
    r = EwmaRunToRun(T, -0.05, 1.0, Actuator(-100, 100, max_step=10.0))
    assert r.update(88.0, 0.0) == pytest.approx(-10.0)
    with pytest.raises(ValueError, match="gain"):
        EwmaRunToRun(T, 0.0, 0.5, act)


def test_combined_removes_a_constant_model_bias() -> None:
    """Plant a = c_i + b u + d with the model missing the offset d: the open feedforward
    misses by d, the combined controller's trim converges to d and puts the plant on
    target; with lam = 0 it is the open feedforward."""
    from formtwin.control import Combined

    rng = np.random.default_rng(4)
    b, d = -0.05, 0.7
    act = Actuator(-100.0, 100.0)
    for lam, miss in ((0.0, d), (0.3, 0.0)):
        ctl = Combined(Feedforward(T, act), lam)
        u_prev, pred, err = None, None, []
        for _ in range(60):
            ci = 88.0 + rng.normal(0, 0.3)
            s = ctl.choose(lambda u, ci=ci: np.array([[ci]]) + b * np.asarray(u)[None, :],
                           u_prev=u_prev)
            pred = s.angle_mean - ctl.bias  # the model's own prediction at s.u
            assert pred == pytest.approx(ci + b * s.u, abs=1e-9)
            angle = ci + b * s.u + d  # the plant
            err.append(angle - T)
            ctl.measured(angle, pred)
            u_prev = s.u
        assert np.mean(err[-10:]) == pytest.approx(miss, abs=1e-6)
        assert np.std(err[-10:]) < 1e-6  # the feedforward takes out the product's own c_i
    with pytest.raises(ValueError, match="lam"):
        Combined(Feedforward(T, act), 1.5)


def test_combined_weight_between_ewma_and_full_feedforward() -> None:
    """Linear plant a = d_i + b u, the posterior's angle c_i + b u with c_i a noisy
    estimate of d_i: with weight 0 (lam 1) the combined controller makes the run-to-run
    EWMA's settings from the second product on; for any weight its predicted angle at the
    reference setting is (b + k) + w (c_i - k)."""
    from formtwin.control import Combined

    rng = np.random.default_rng(5)
    b = -0.05
    act = Actuator(-100.0, 100.0)
    d = 88.0 + np.cumsum(rng.normal(0, 0.2, 40))
    c = d + rng.normal(0, 0.3, 40) + 0.4
    r2r = EwmaRunToRun(T, b, 1.0, act)
    for w in (0.0, 0.4, 1.0):
        ctl = Combined(Feedforward(T, act), 1.0, weight=w, u_ref=0.0)
        u_r2r, u_prev = 0.0, None
        for i in range(40):
            ci = c[i]
            model = lambda u, ci=ci: np.array([[ci]]) + b * np.asarray(u)[None, :]  # noqa: E731
            expected = ci + ctl.bias if ctl.level is None else \
                ctl.bias + ctl.level + w * (ci - ctl.level)
            s = ctl.choose(model, u_prev=u_prev)
            assert s.angle_mean == pytest.approx(T, abs=1e-6)  # aimed there, within reach
            assert ctl.offset(ci) + ci == pytest.approx(expected, abs=1e-9)
            if w == 0.0 and i >= 1:
                assert s.u == pytest.approx(u_r2r, abs=1e-6)
            angle = d[i] + b * s.u
            ctl.measured(angle, ci + b * s.u, reference=ci)
            if w == 0.0:
                u_r2r = r2r.update(angle, s.u)
            u_prev = s.u
    with pytest.raises(ValueError, match="weight"):
        Combined(Feedforward(T, act), 0.5, weight=1.5)


def test_combined_rho_predicts_an_ar1_around_the_level() -> None:
    """With rho the predicted angle at the reference setting is
    L + rho (A_j - L) + w ((c_i - k) - rho (c_j - k)), L = b + k the level of the measured
    angles moved there (A_j = e_j + c_j); for a plant whose deviation from a constant level
    is an AR(1) with that rho and a posterior that knows nothing (w = 0), the error of each
    product is its AR(1) innovation once the level has settled (lam small)."""
    from formtwin.control import Combined

    rng = np.random.default_rng(6)
    b, rho, level = -0.05, 0.7, 88.0
    act = Actuator(-100.0, 100.0)
    x, d = 0.0, np.empty(400)
    for i in range(d.size):
        x = rho * x + rng.normal(0, 0.1)
        d[i] = level + x
    c = 87.5 + 0.3 * rng.normal(0, 1, d.size)  # an uninformative posterior, 0.5 deg low
    for w in (0.0, 0.6):
        ctl = Combined(Feedforward(T, act), 0.01, weight=w, rho=rho)
        u_prev, innov = None, []
        for i in range(d.size):
            ci = c[i]
            model = lambda u, ci=ci: np.array([[ci]]) + b * np.asarray(u)[None, :]  # noqa: E731
            if ctl.last_error is not None:  # the prediction at u_ref = 0, by hand
                lv = ctl.bias + ctl.level
                a_j = ctl.last_error + ctl.last_reference
                k = ctl.level
                expected = lv + rho * (a_j - lv) + w * ((ci - k) - rho * (ctl.last_reference - k))
                assert ctl.offset(ci) + ci == pytest.approx(expected, abs=1e-9)
            s = ctl.choose(model, u_prev=u_prev)
            angle = d[i] + b * s.u
            if i == 0:
                assert ctl.measured(angle, ci + b * s.u, reference=ci) == \
                    pytest.approx(angle - ci - b * s.u, abs=1e-12)  # the trim starts there
            else:
                ctl.measured(angle, ci + b * s.u, reference=ci)
                innov.append(angle - T - (d[i] - rho * d[i - 1] - (1 - rho) * level))
            u_prev = s.u
        if w == 0.0:  # only the level's estimation error is left
            assert np.std(innov[200:]) < 0.01
    with pytest.raises(ValueError, match="rho"):
        Combined(Feedforward(T, act), 0.5, rho=1.0)


def test_combined_adaptive_weight_is_the_slope_of_the_angle_on_the_posterior() -> None:
    """A plant whose angle at the reference setting (u = 0) moves by ``s`` times the
    posterior's change plus noise: the learned weight tends to ``s`` (clipped to [0, 1]:
    0 for a negative slope); with rho the slope is taken on the AR(1) innovations of both."""
    from formtwin.control import Combined

    rng = np.random.default_rng(8)
    act = Actuator(-100.0, 100.0)
    n = 3000
    for rho, s, expected in ((0.0, 0.5, 0.5), (0.7, 0.3, 0.3), (0.0, -0.4, 0.0)):
        ctl = Combined(Feedforward(T, act), 0.01, weight=0.0, rho=rho, adaptive=True)
        cp, ap = 0.0, 0.0
        for _ in range(n):
            # posterior c_i: an AR(1) about 88; plant a_i = 88.5 + s (c_i - 88) plus an own
            # AR(1) part whose innovations are independent of the posterior's
            cp = rho * cp + rng.normal(0, 0.2)
            ap = rho * ap + rng.normal(0, 0.05)
            c, a = 88.0 + cp, 88.5 + s * cp + ap
            ctl.measured(a, c, reference=c)  # at u = 0: predicted = c
        assert ctl.weight == pytest.approx(expected, abs=0.04)
        assert ctl.sxx > 0


@pytest.mark.parametrize(("rho", "expected"), [(0.0, 0.8), (0.7, 0.01 / (0.01 + 1.49 * 0.01))])
def test_combined_adaptive_weight_converges_to_the_least_squares_weight(
        rho: float, expected: float) -> None:
    """Closed loop on a synthetic line whose angle at the reference setting is
    ``88.5 + z_i + eps_i`` and whose posterior says ``c_i = 88 + z_i + eta_i``: the state
    ``z`` an AR(1) (coefficient ``rho``, innovations sd 0.1 deg; i.i.d. sd 0.2 for rho 0),
    the estimate's error ``eta`` and the plant's own noise ``eps`` i.i.d. (sd 0.1 and 0.05).
    The trim removes what its AR(1) predicts, so the weight regresses the innovation
    ``v_j + eps_j - rho eps_{j-1}`` on ``v_j + eta_j - rho eta_{j-1}``: its least-squares
    value is ``var v / (var v + (1 + rho^2) var eta)`` (0.8 for rho 0, 0.40 for rho 0.7).
    The learned weight reaches it, and the closed loop's angles are then as good as those
    of a controller given that weight from the start."""
    from formtwin.control import Combined

    rng = np.random.default_rng(21)
    b, n = -0.05, 6000
    sd_v = 0.2 if rho == 0 else 0.1
    z, zs = 0.0, np.empty(n)
    for i in range(n):
        z = rho * z + rng.normal(0, sd_v)
        zs[i] = z
    c = 88.0 + zs + rng.normal(0, 0.1, n)
    a_ref = 88.5 + zs + rng.normal(0, 0.05, n)

    def run(ctl: Combined) -> np.ndarray:
        u_prev, out = None, np.empty(n)
        for i in range(n):
            model = lambda u, ci=c[i]: np.array([[ci]]) + b * np.asarray(u)[None, :]  # noqa: E731
            s = ctl.choose(model, u_prev=u_prev)
            out[i] = a_ref[i] + b * s.u  # the plant at the chosen setting
            ctl.measured(out[i], c[i] + b * s.u, reference=c[i])
            u_prev = s.u
        return out

    act = Actuator(-100.0, 100.0)
    learned = Combined(Feedforward(T, act), 0.01, weight=0.0, rho=rho, adaptive=True)
    got = run(learned)
    assert learned.weight == pytest.approx(expected, abs=0.03)
    given = run(Combined(Feedforward(T, act), 0.01, weight=expected, rho=rho))
    none = run(Combined(Feedforward(T, act), 0.01, weight=0.0, rho=rho))
    assert np.std(got[1000:]) == pytest.approx(np.std(given[1000:]), rel=0.01)
    assert np.std(got[1000:]) < 0.95 * np.std(none[1000:])  # the estimates pay
