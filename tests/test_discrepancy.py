"""The discrepancy likelihood: a shared metamodel error b ~ N(0, K_res) integrated out per
particle, checked against closed forms (joint Gaussian of all residuals, the posterior of
b) and against the exact Kalman filter of a linear-Gaussian model augmented by b."""

from __future__ import annotations

import dataclasses
import math

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
from formtwin.filters import SIR
from formtwin.tracker import TrackerConfig, build_tracker
from formtwin.tracker.discrepancy import Discrepancy


def _spd(n: int, rng: np.random.Generator, scale: float, rank: int | None = None) -> np.ndarray:
    a = rng.standard_normal((n, rank or n))
    return scale * a @ a.T / n + (0 if rank else 0.1 * scale) * np.eye(n)


def test_sequential_predictives_multiply_to_the_joint_density_and_b_posterior() -> None:
    """Without forgetting, sum_i log p(r_i | r_<i) is the log-density of all residuals
    under their joint Gaussian (cov I x Sigma_e + 11^T x K_res), and the posterior mean of
    b is the closed form (K^-1 + n Sigma^-1)^-1 Sigma^-1 sum r."""
    rng = np.random.default_rng(4)
    n_t, n = 5, 6
    sig, k = _spd(n_t, rng, 1.0), _spd(n_t, rng, 3.0, rank=2)  # K_res singular, like K_res
    d = Discrepancy.from_covariances(sig, k)
    r = rng.multivariate_normal(np.zeros(n_t), k) + rng.multivariate_normal(
        np.zeros(n_t), sig, n)
    st = np.zeros((1, d.width))
    total = 0.0
    for i in range(n):
        total += float(d.loglik(r[i: i + 1], st)[0, 0])
        d.update(st, d.whiten(r[i: i + 1]))
    joint = np.kron(np.eye(n), sig) + np.kron(np.ones((n, n)), k)
    ref = stats.multivariate_normal(np.zeros(n * n_t), joint).logpdf(r.reshape(-1))
    assert total == pytest.approx(ref, rel=1e-10)
    si = np.linalg.inv(sig)
    post_cov = k - k @ np.linalg.solve(k + sig / n, k)  # (K^-1 + n S^-1)^-1, K singular
    b_hat = post_cov @ si @ r.sum(axis=0)
    one = np.ones(1)
    np.testing.assert_allclose(d.bias(st, one)[0], b_hat, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(d.predictive_cov(st, one), sig + post_cov, rtol=1e-8,
                               atol=1e-10)


def test_every_share_on_the_grid_is_its_own_joint_gaussian() -> None:
    """For each kappa, residuals r_i = b + e_i with b ~ N(0, (1 - kappa) K) and e_i ~ N(0,
    S + kappa K): the sequential predictives multiply to that joint density (kappa = 1:
    independent products under the calibrated S + K)."""
    rng = np.random.default_rng(6)
    n_t, n = 4, 5
    sig, k = _spd(n_t, rng, 1.0), _spd(n_t, rng, 2.0, rank=3)
    shares = np.array([0.0, 0.3, 1.0])
    d = Discrepancy.from_covariances(sig, k, shares)
    r = rng.standard_normal((n, n_t)) * 2
    st = np.zeros((1, d.width))
    total = np.zeros(3)
    for i in range(n):
        total += d.loglik(r[i: i + 1], st)[0]
        d.update(st, d.whiten(r[i: i + 1]))
    for j, kap in enumerate(shares):
        joint = np.kron(np.eye(n), sig + kap * k) + np.kron(np.ones((n, n)), (1 - kap) * k)
        ref = stats.multivariate_normal(np.zeros(n * n_t), joint).logpdf(r.reshape(-1))
        assert total[j] == pytest.approx(ref, rel=1e-10)


def test_adaptive_likelihood_is_the_gaussian_with_kappa_k_res_added() -> None:
    """Nothing shared (the adaptive likelihood): each kappa on the grid is N(0, S + kappa K)
    for every product, whatever came before."""
    rng = np.random.default_rng(7)
    sig, k = _spd(5, rng, 1.0), _spd(5, rng, 2.0, rank=2)
    shares = np.array([0.0, 0.5, 1.0])
    d = Discrepancy.from_covariances(sig, k, shares, shared=False)
    r = rng.standard_normal((4, 5)) * 2
    ll = d.loglik(r, None)
    for j, kap in enumerate(shares):
        ref = stats.multivariate_normal(np.zeros(5), sig + kap * k).logpdf(r)
        np.testing.assert_allclose(ll[:, j], ref, rtol=1e-10)
    np.testing.assert_allclose(d.predictive_cov(None, np.array([0.0, 0.0, 1.0])), sig + k,
                               rtol=1e-10, atol=1e-12)
    robust = Discrepancy.from_covariances(sig, k, shares, shared=False, nu=4.0)
    for j, kap in enumerate(shares):  # the robust option: multivariate t, same scale
        ref = stats.multivariate_t(np.zeros(5), sig + kap * k, df=4.0).logpdf(r)
        np.testing.assert_allclose(robust.loglik(r, None)[:, j], ref, rtol=1e-10)


def test_memory_of_one_product_remembers_only_the_last() -> None:
    """memory = 1 (lambda = 0): the predictive of r_i is its conditional on r_(i-1) alone
    under the pair's joint Gaussian [[S + K, K], [K, S + K]]."""
    rng = np.random.default_rng(5)
    sig, k = _spd(4, rng, 1.0), _spd(4, rng, 2.0)
    d = Discrepancy.from_covariances(sig, k, memory=1.0)
    st = np.zeros((3, d.width))
    joint = np.block([[sig + k, k], [k, sig + k]])
    prev = None
    for _ in range(4):
        r = rng.standard_normal((3, 4)) * 3
        ll = d.loglik(r, st)[:, 0]
        if prev is None:
            ref = stats.multivariate_normal(np.zeros(4), sig + k).logpdf(r)
        else:
            pair = stats.multivariate_normal(np.zeros(8), joint).logpdf(np.hstack([prev, r]))
            ref = pair - stats.multivariate_normal(np.zeros(4), sig + k).logpdf(prev)
        np.testing.assert_allclose(ll, ref, rtol=1e-9)
        d.update(st, d.whiten(r))
        prev = r
    with pytest.raises(ValueError, match="memory"):
        Discrepancy.from_covariances(sig, k, memory=0.5)


class BiasedLinearGaussian:
    """x_i = A x_{i-1} + v; curve y_i = H x_i + b + e_i, b ~ N(0, K) shared, e ~ N(0, S);
    particles [x, stats of b] with b integrated out by :class:`Discrepancy`."""

    def __init__(self, H: np.ndarray, A: np.ndarray, Q: np.ndarray, P0: np.ndarray,
                 disc: Discrepancy) -> None:
        self.H, self.A, self.Q, self.P0, self.disc = H, A, Q, P0, disc
        self.d = A.shape[0]

    def sample_initial(self, n: int, rng: np.random.Generator) -> np.ndarray:
        x = rng.multivariate_normal(np.zeros(self.d), self.P0, n)
        return np.hstack([x, np.zeros((n, self.disc.width))])

    def sample_transition(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = x.copy()
        out[:, :self.d] = x[:, :self.d] @ self.A.T + rng.multivariate_normal(
            np.zeros(self.d), self.Q, len(x))
        return out

    def loglik(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = y - x[:, :self.d] @ self.H.T
        c = self.disc.whiten(r)
        st = x[:, self.d:]
        ll = self.disc.loglik(r, st, c)[:, 0]
        self.disc.update(st, c)
        return ll


def test_particle_filter_with_discrepancy_matches_the_augmented_kalman_filter() -> None:
    """SIR with b integrated out per particle gives the exact posterior of x and the exact
    evidence of the Kalman filter on the augmented state [x, b]."""
    rng = np.random.default_rng(8)
    n_t, d = 6, 2
    H = rng.standard_normal((n_t, d))
    S, K = _spd(n_t, rng, 0.5), _spd(n_t, rng, 1.0, rank=3)
    A, Q, P0 = np.diag([0.7, 0.9]), np.diag([0.3, 0.2]), np.eye(d)
    b = rng.multivariate_normal(np.zeros(n_t), K)
    x = rng.multivariate_normal(np.zeros(d), P0)
    ys = []
    for _ in range(5):
        x = A @ x + rng.multivariate_normal(np.zeros(d), Q)
        ys.append(H @ x + b + rng.multivariate_normal(np.zeros(n_t), S))
    f = SIR(BiasedLinearGaussian(H, A, Q, P0, Discrepancy.from_covariances(S, K)), 40_000,
            np.random.default_rng(2))
    f.initialise()
    Aa = np.block([[A, np.zeros((d, n_t))], [np.zeros((n_t, d)), np.eye(n_t)]])
    Qa = np.block([[Q, np.zeros((d, n_t))], [np.zeros((n_t, d)), np.zeros((n_t, n_t))]])
    Ha = np.hstack([H, np.eye(n_t)])
    ma = np.zeros(d + n_t)
    Pa = np.block([[P0, np.zeros((d, n_t))], [np.zeros((n_t, d)), K]])
    ev_kf = ev_pf = 0.0
    for y, (m, P, ev) in zip(ys, kalman_filter(Aa, Qa, Ha, S, ma, Pa, ys), strict=True):
        ev_kf += ev
        s = f.step(y)
        ev_pf += s.loglik
        sd = np.sqrt(np.diag(P)[:d])
        np.testing.assert_allclose(s.mean()[:d], m[:d], atol=0.05 * sd.max() + 0.02)
        np.testing.assert_allclose(s.std()[:d], sd, rtol=0.06)
    assert ev_pf == pytest.approx(ev_kf, abs=0.15)


def _analytic_tracker(**kw: object) -> tuple[object, object]:
    return analytic_tracker(likelihood="discrepancy", **kw)


def test_tracker_with_discrepancy_continues_bit_for_bit_and_counts_products() -> None:
    model, tr = _analytic_tracker()
    curves = interior_curves(model)
    for c in curves[:3]:
        tr.step(c)  # type: ignore[attr-defined]
    stats_cols = tr.particles[:, tr.ssm._n_bounded:]  # type: ignore[attr-defined]
    np.testing.assert_array_equal(stats_cols[:, -1], 3.0)  # n = products seen, every path
    assert_continues_bit_for_bit(model, tr, curves[3:])


def test_config_of_the_discrepancy_likelihood_is_checked_and_saved() -> None:
    cfg = TrackerConfig(likelihood="discrepancy", discrepancy_memory=200.0,
                        error_share=0.3)
    assert TrackerConfig.from_json(cfg.to_json()) == cfg
    inf = TrackerConfig(likelihood="discrepancy")
    assert math.isinf(TrackerConfig.from_json(inf.to_json()).discrepancy_memory)
    with pytest.raises(ValueError, match="error_share"):
        TrackerConfig(error_share=1.5)
    with pytest.raises(ValueError, match="learn_scale"):
        TrackerConfig(likelihood="discrepancy", learn_scale=True)
    with pytest.raises(ValueError, match="learn_scale"):
        TrackerConfig(learn_scale=True)  # the adaptive default learns its own scale
    with pytest.raises(ValueError, match="nu"):
        TrackerConfig(likelihood="discrepancy", nu=5.0)
    with pytest.raises(ValueError, match="discrepancy_memory"):
        dataclasses.replace(cfg, discrepancy_memory=0.0)


class _ModelWithError:
    """The analytic stand-in with a stated metamodel error ``K_res`` (its residuals)."""

    def __init__(self, k_res: np.ndarray) -> None:
        from formtwin.metamodel import ResidualModel

        self._m = analytic_model()
        self.residuals = ResidualModel(k_res, np.zeros(len(k_res)), 0.01 * np.eye(2),
                                       np.zeros(2), k=5, n=100)

    def __getattr__(self, name: str) -> object:
        return getattr(self._m, name)


@pytest.mark.parametrize(("likelihood", "error"), [
    ("discrepancy", "shared"), ("discrepancy", "independent"), ("adaptive", "none"),
    ("adaptive", "independent")])
def test_the_evidence_finds_the_share_of_the_metamodel_error(likelihood: str,
                                                            error: str) -> None:
    """Curves = model + an error drawn from K_res once (shared), afresh per product
    (independent) or none: the posterior of kappa goes to 0, 1 and 0 (adaptive: the
    share of K_res present in the data)."""
    base = analytic_model()
    spec = base.spec
    t = np.arange(spec.n_t)
    probe = base.predict_curves(np.tile(0.5 * (spec.inputs.lo + spec.inputs.hi), (1, 1)))
    amp = 0.05 * float(np.abs(probe).max())  # an error of 5 % of the peak force
    k_res = amp**2 * np.exp(-0.5 * ((t[:, None] - t[None, :]) / 6.0) ** 2)
    model = _ModelWithError(k_res)
    cfg = TrackerConfig(n_particles=300, estimate_deviation=False, n_mc=1000, seed=3,
                        likelihood=likelihood)
    tr = build_tracker(model, cfg)  # type: ignore[arg-type]
    rng = np.random.default_rng(12)
    run, curves = tr.ssm.simulate(60, rng)
    err = rng.multivariate_normal(np.zeros(spec.n_t), k_res, 1 if error == "shared" else 60)
    tr.run(curves + (0.0 if error == "none" else err))
    assert tr.error_share is not None
    assert (tr.error_share > 0.75) if error == "independent" else (tr.error_share < 0.25)
    if likelihood == "adaptive":  # the angles' std carries the angle error iff kappa > 0
        present = 1.0 - float(np.exp(tr.ssm.share_logpost[0]))
        np.testing.assert_allclose(tr.ssm.angle_error(), 0.01 * present)
        assert (present > 0.9) if error == "independent" else (present < 0.1)
