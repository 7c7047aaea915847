"""The guided filters (``filter="guided"`` and ``"guided_lin"``): with a proposal that is
not the posterior their weights still give the exact Kalman filter of a linear-Gaussian
model; the bending model's proposals (with a pilot evaluation per particle, or linearised
about the cloud's mean) give the bootstrap posterior at a larger ESS; the linearisation's
residuals match the model's to second order; a tracker with either continues bit for bit
and refuses what it cannot do."""

from __future__ import annotations

import numpy as np
import pytest
from filter_refs import (
    analytic_tracker,
    assert_continues_bit_for_bit,
    interior_curves,
    kalman_filter,
)
from scipy import stats

from formtwin.defaults import analytic_model
from formtwin.filters import SIR, GuidedLinSIR, GuidedSIR
from formtwin.tracker import TrackerConfig, build_tracker


class LinearGaussian:
    """x_i = A x_(i-1) + N(0, Q), y = H x + N(0, R); a deliberately imperfect guided
    proposal: the Kalman step with 0.8 of its gain and 1.5 times its covariance."""

    def __init__(self, H: np.ndarray, R: np.ndarray, A: np.ndarray, Q: np.ndarray) -> None:
        self.H, self.R, self.A, self.Q = H, R, A, Q
        d = len(Q)
        self.S = np.linalg.inv(np.linalg.inv(Q) + H.T @ np.linalg.solve(R, H))
        self.K = self.S @ H.T @ np.linalg.inv(R)
        self.q_cov = 1.5 * self.S
        self.d = d

    def sample_initial(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.standard_normal((n, self.d))

    def sample_transition(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return x @ self.A.T + rng.multivariate_normal(np.zeros(self.d), self.Q, len(x))

    def loglik(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return stats.multivariate_normal(np.zeros(len(y)), self.R).logpdf(y - x @ self.H.T)

    def sample_guided(self, x: np.ndarray, y: np.ndarray, rng: np.random.Generator
                      ) -> tuple[np.ndarray, np.ndarray]:
        a = x @ self.A.T
        mean = a + 0.8 * (y - a @ self.H.T) @ self.K.T
        new = mean + rng.multivariate_normal(np.zeros(self.d), self.q_cov, len(x))
        lp = stats.multivariate_normal(np.zeros(self.d), self.Q).logpdf(new - a)
        lq = stats.multivariate_normal(np.zeros(self.d), self.q_cov).logpdf(new - mean)
        return new, lp - lq


def test_guided_filter_matches_the_kalman_filter_with_an_imperfect_proposal() -> None:
    rng = np.random.default_rng(12)
    n_t, d = 8, 2
    H = rng.standard_normal((n_t, d)) * 3.0  # the curve pins x far tighter than Q spreads it
    R = np.eye(n_t)
    A, Q = np.diag([0.8, 0.9]), np.diag([0.5, 0.4])
    lg = LinearGaussian(H, R, A, Q)
    x = rng.standard_normal(d)
    ys = []
    for _ in range(5):
        x = A @ x + rng.multivariate_normal(np.zeros(d), Q)
        ys.append(H @ x + rng.standard_normal(n_t))
    f = GuidedSIR(lg, 20_000, np.random.default_rng(5))
    f.initialise()
    boot = SIR(lg, 20_000, np.random.default_rng(5))
    ev_kf = ev_pf = 0.0
    kf = kalman_filter(A, Q, H, R, np.zeros(d), np.eye(d), ys)
    for y, (m, P, ev) in zip(ys, kf, strict=True):
        ev_kf += ev
        s = f.step(y)
        ev_pf += s.loglik
        sd = np.sqrt(np.diag(P))
        np.testing.assert_allclose(s.mean(), m, atol=0.05 * sd.max())
        np.testing.assert_allclose(s.std(), sd, rtol=0.05)
        assert s.ess > 3 * boot.step(y).ess  # the point of the proposal
    assert ev_pf == pytest.approx(ev_kf, abs=0.1)
    with pytest.raises(ValueError, match="sample_guided"):
        GuidedSIR(object(), 10, np.random.default_rng(0))  # type: ignore[arg-type]


def _tracker(filter: str = "guided", **kw: object) -> tuple[object, object]:
    return analytic_tracker(filter=filter, **kw)


def _weighted(x: np.ndarray, logw: np.ndarray, nx: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Mean and std of the first ``nx`` columns of draws ``x`` weighted by ``exp(logw)``,
    and the draws' ESS."""
    w = np.exp(logw - logw.max())
    w /= w.sum()
    m = w @ x[:, :nx]
    return m, np.sqrt(w @ (x[:, :nx] - m) ** 2), float(1.0 / np.sum(w * w))


@pytest.fixture(scope="module")
def bootstrap() -> dict[str, object]:
    """One parent in the box (the state's mean), a curve from a state 0.5 sigma off it, the
    transition's 200 000 draws weighted by the likelihood (mean, std, ESS), and the state of
    the generator after them (seed 2): the reference both proposals are checked against."""
    model, tr = _tracker()
    ssm = tr.ssm  # type: ignore[attr-defined]
    nx, n_in = ssm.n_x, ssm.n_in
    rng = np.random.default_rng(2)
    parent = 0.5 * (ssm._lo + ssm._hi)
    parent[:nx] = ssm._mu
    truth = parent.copy()
    truth[:nx] += 0.5 * ssm._sigma
    y = model.predict_curves(truth[None, :n_in])[0]  # type: ignore[attr-defined]
    xb = ssm.sample_transition(np.repeat(parent[None, :], 200_000, axis=0), rng)
    mb, sb, essb = _weighted(xb, ssm.loglik_fixed(xb, y), nx)
    return {"parent": parent, "y": y, "mb": mb, "sb": sb, "essb": essb,
            "rng_state": rng.bit_generator.state}


@pytest.mark.parametrize("pilot", [True, False])
def test_bending_proposal_gives_the_bootstrap_posterior_with_a_larger_ess(
        pilot: bool, bootstrap: dict[str, object]) -> None:
    """One parent in the box, a curve from a state off the transition's mean: the draws
    weighted by likelihood x ratio have the posterior mean of the transition's draws
    weighted by the likelihood (within both Monte-Carlo errors), at a far larger ESS."""
    b = bootstrap
    parent, y, mb, sb, essb = b["parent"], b["y"], b["mb"], b["sb"], b["essb"]
    model, tr = _tracker("guided" if pilot else "guided_lin")
    ssm = tr.ssm  # type: ignore[attr-defined]
    nx, n_in = ssm.n_x, ssm.n_in
    rng = np.random.default_rng()
    rng.bit_generator.state = b["rng_state"]  # the draws after the bootstrap's, as before
    parents = np.repeat(parent[None, :], 20_000, axis=0)
    if not pilot:  # the parent's curve in the columns of guided_lin
        parents = np.c_[parents, np.tile(model.predict_curves(parent[None, :n_in]),  # type: ignore[attr-defined]
                                         (20_000, 1))]
    xg, ratio = ssm.sample_guided(parents, y, rng, pilot=pilot)
    mg, sg, essg = _weighted(xg, ssm.loglik_fixed(xg, y) + ratio, nx)
    assert essg / 20_000 > 1.3 * essb / 200_000  # share of the draws that count
    tol = 5 * np.maximum(sb, sg) * np.sqrt(1 / essb + 1 / essg)
    np.testing.assert_array_less(np.abs(mg - mb), tol)
    np.testing.assert_allclose(sg, sb, rtol=0.3)


@pytest.mark.parametrize("name", ["guided", "guided_lin"])
def test_guided_tracker_continues_bit_for_bit_and_refuses_learned_statistics(name: str) -> None:
    model, tr = _tracker(name)
    assert type(tr.filter) is {"guided": GuidedSIR, "guided_lin": GuidedLinSIR}[name]  # type: ignore[attr-defined]
    curves = interior_curves(model)
    for c in curves[:3]:
        tr.step(c)  # type: ignore[attr-defined]
    assert_continues_bit_for_bit(model, tr, curves[3:])
    for bad in ({"learn_mu": True}, {"likelihood": "discrepancy"}):
        with pytest.raises(ValueError, match="guided"):
            TrackerConfig(filter=name, **bad)  # type: ignore[arg-type]


@pytest.mark.parametrize(("deviation", "share"), [(False, 0.1), (True, 0.5)])
def test_parent_curve_moved_by_the_jacobian_is_the_models_curve(deviation: bool,
                                                                share: float) -> None:
    """Children a transition away from their parents (x by the AR(1) mean, theta by the
    jitter, in a cloud 4 % of the box wide): the parents' curves moved by the Jacobian at
    the cloud's mean err by at most ``share`` of the children's own change of residual
    (the deviation's interpolation between samples has kinks: less is gained there)."""
    model = analytic_model()
    ssm = build_tracker(model, TrackerConfig(n_particles=10, n_mc=1000, filter="guided_lin",
                                             estimate_deviation=deviation)).ssm
    y = interior_curves(model, 1)[0]
    rng = np.random.default_rng(4)
    width = ssm._hi[:ssm.n_aug] - ssm._lo[:ssm.n_aug]
    x = 0.5 * (ssm._lo[:ssm.n_aug] + ssm._hi[:ssm.n_aug]) + 0.02 * width * rng.uniform(
        -1, 1, (200, width.size))
    if not deviation:
        x[:, ssm.n_in:] = 0.0
    at = ssm.sample_transition(x, rng)
    at[:, :ssm.n_x] = (1.0 - ssm._rho) * ssm._mu + ssm._rho * x[:, :ssm.n_x]
    parents = ssm.residuals(x, y)
    exact = ssm.residuals(at, y)
    lin, H = ssm._linear_residuals(at, y, x, y - parents)
    assert np.abs(lin - exact).max() < share * np.abs(parents - exact).max()
    assert H.shape == (model.spec.n_t, ssm.n_x)
