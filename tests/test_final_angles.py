"""The particles' final angles kept from the step (:mod:`formtwin.tracker.final_angles`):
the same numbers as the model evaluated again at the particles and their ancestors, the
camera's fusion and the issued interval as with the angles evaluated afresh, through the
state bytes, with filters that move their particles and with a setting other than the
step's."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_fusion import TOL_ANGLE

from formtwin.defaults import analytic_model
from formtwin.tracker import Tracker, TrackerConfig, build_tracker
from formtwin.tracker.final_angles import FinalAngles


def _tracker(**kw: object) -> Tracker:
    config = TrackerConfig(n_particles=200, n_mc=1000, estimate_deviation=False, seed=3,
                           sensors=("camera",), **kw)  # type: ignore[arg-type]
    return build_tracker(analytic_model(), config)


def _curves(n: int) -> np.ndarray:
    model = analytic_model()
    spec = model.spec
    rng = np.random.default_rng(5)
    X = spec.inputs.lo + (spec.inputs.hi - spec.inputs.lo) * (0.4 + 0.2 * rng.random((n, 10)))
    return model.predict_curves(X)


def _fresh(tr: Tracker, lag: int, u: object = None) -> np.ndarray:
    assert tr.particles is not None
    x = tr.ssm.lagged_inputs(tr.particles, lag)
    return tr.ssm.predict_angles(x, u)[:, 1]


@pytest.mark.parametrize("kw", [{}, {"sensor_lag": 3}, {"ess_threshold": 0.5}])
def test_kept_angles_are_the_model_at_the_particles_and_their_ancestors(
        kw: dict[str, object]) -> None:
    """After every step each known kept angle (column ``l``: the ancestor ``l`` products
    back) is the model's final angle of that ancestor's inputs at its product's setting;
    with resampling at every step the heaviest particles' own angles are all known."""
    tr = _tracker(**kw)
    u_lo = tr.spec.controls.lo
    settings = [None if k % 2 else u_lo + 0.1 * k * (tr.spec.controls.hi - u_lo)
                for k in range(8)]
    known = 0
    for k, c in enumerate(_curves(8)):
        tr.step(c, settings[k])
        assert tr.finals is not None and tr.finals.angles is not None
        for lag in range(min(k, tr.ssm.lag_depth) + 1):
            kept = tr.finals.angles[:, lag]
            ok = ~np.isnan(kept)
            known += int(ok.sum())
            np.testing.assert_allclose(kept[ok], _fresh(tr, lag, settings[k - lag])[ok],
                                       rtol=TOL_ANGLE, atol=0)
    assert known > 8 * 200 * 0.9  # nearly all kept: the model is not evaluated again


def test_fuse_and_issue_with_kept_angles_match_fresh_evaluation() -> None:
    """A tracker whose kept angles are dropped (as a state of an older version) evaluates
    them where needed: its issued intervals, camera fusions and weights agree with the
    tracker that kept them; a camera value at another setting than the step's is
    evaluated, not taken from the kept column."""
    a, b = _tracker(), _tracker()
    rng = np.random.default_rng(1)
    for k, c in enumerate(_curves(12)):
        for tr in (a, b):
            tr.step(c)
        assert b.finals is not None
        b.finals.set_state({})  # forget them: everything evaluated where needed
        (fa, ia), (fb, ib) = a.issue_final(), b.issue_final()
        assert (fa, *ia) == pytest.approx((fb, *ib), rel=TOL_ANGLE)
        if k:
            value = 90.0 + 0.5 * float(rng.standard_normal())
            ea, eb = (tr.fuse(k - 1, "camera", value) for tr in (a, b))
            assert ea == pytest.approx(eb, rel=TOL_ANGLE, abs=TOL_ANGLE)
            np.testing.assert_allclose(a.filter.logw, b.filter.logw, rtol=TOL_ANGLE,
                                       atol=TOL_ANGLE)
    other = np.array([a.spec.controls.hi[0]])
    c = _curves(13)[-1]
    a.step(c)
    assert a.finals is not None and a.finals.angles is not None
    col = a.finals.column(0, other, a.particles[:, :a.ssm.n_in],  # type: ignore[index]
                          lambda r: a.ssm.predict_angles(r, other)[:, 1])
    np.testing.assert_allclose(col, _fresh(a, 0, other), rtol=TOL_ANGLE)
    assert not np.allclose(col, a.finals.angles[:, 0])


def test_kept_angles_go_through_the_state_bytes_bit_for_bit() -> None:
    """Restored from its state bytes after any step, a tracker continues with the same
    kept angles, issued intervals and fused weights, bit for bit."""
    tr = _tracker()
    curves = _curves(10)
    for k in range(5):
        tr.step(curves[k])
        tr.issue_final()
        if k:
            tr.fuse(k - 1, "camera", 90.0 + 0.1 * k)
    again = Tracker.from_state_bytes(tr.state_bytes(), tr.model, tr.measurement)
    assert again.finals is not None and tr.finals is not None
    assert np.array_equal(again.finals.angles, tr.finals.angles, equal_nan=True)
    for k in range(5, 10):
        outs = []
        for t in (tr, again):
            t.step(curves[k])
            outs.append((t.issue_final(), t.fuse(k - 1, "camera", 90.0 + 0.1 * k)))
        assert outs[0] == outs[1]
    assert again.state_bytes() == tr.state_bytes()


@pytest.mark.parametrize("kw", [{"filter": "move"}, {"filter": "regularised"}])
def test_moved_particles_have_their_angles_evaluated(kw: dict[str, object]) -> None:
    """A filter that moves its particles after resampling leaves nothing known (their
    inputs changed): the interval and the camera's fusion evaluate the model, and the
    result is the model at the moved particles."""
    tr = _tracker(**kw)
    for c in _curves(4):
        tr.step(c)
    assert tr.finals is not None and tr.finals.angles is not None
    assert np.isnan(tr.finals.angles).all()
    final, (lo, hi) = tr.issue_final()
    assert math.isfinite(final) and lo < final < hi
    np.testing.assert_allclose(tr.finals.angles[:, 0], _fresh(tr, 0), rtol=TOL_ANGLE)


def test_states_without_kept_angles_and_bad_shapes_leave_them_unknown() -> None:
    """An older state (no kept angles) or arrays of another shape: nothing kept."""
    f = FinalAngles(depth=1, n_controls=1)
    f.set_state({"final_angles": np.zeros((5, 3)), "final_angles_u": np.zeros((2, 1))})
    assert f.angles is None and f.state() == {}
    f.set_state({"final_angles": np.ones((5, 2)), "final_angles_u": np.zeros((2, 1))})
    assert f.angles is not None and f.state()["final_angles"].shape == (5, 2)


def test_the_fusion_log_density_is_scipys_normal() -> None:
    """The camera's and gauge's log density in the fusion is ``scipy.stats.norm.logpdf``
    (its operations written out): within a few ulps, NaN and infinite predictions alike."""
    from scipy.stats import norm

    tr = _tracker()
    tr.step(_curves(1)[0])
    rng = np.random.default_rng(0)
    for _ in range(20):
        pred = 90.0 + rng.standard_normal(200)
        pred[::50], pred[3] = np.nan, np.inf
        value, sd = 90.0 + float(rng.standard_normal()), float(np.exp(rng.standard_normal()))
        logw = tr.filter.logw.copy()
        inc = tr._reweight(pred, value, sd, "test")
        expect = norm.logpdf(value, loc=pred, scale=sd)
        new = np.where(np.isnan(expect) | np.isposinf(expect), -np.inf, expect) + logw
        top = np.max(new)
        lse = top + math.log(float(np.sum(np.exp(new - top))))
        assert inc == pytest.approx(lse, rel=1e-14)
        np.testing.assert_allclose(tr.filter.logw, new - lse, rtol=1e-13, atol=1e-13)
        tr.filter.logw = logw


def test_the_settings_test_is_numpys_array_equal_with_nan() -> None:
    """A column's setting matches ``u`` as ``np.array_equal(..., equal_nan=True)`` says:
    NaN rows (nominal) against None, equal and different values, other shapes."""
    from formtwin.tracker.final_angles import _same_setting

    nominal = np.full(1, np.nan)
    cases = [(nominal, None), (nominal, np.array([0.3])), (np.array([0.3]), None),
             (np.array([0.3]), np.array([0.3])), (np.array([0.3]), np.array([0.30001])),
             (np.array([0.3]), np.array([0.3, 0.3])), (np.array([0.3, np.nan]), None),
             (np.array([0.3, np.nan]), np.array([0.3, np.nan])),
             (np.array([0.3]), np.array(0.3))]
    for kept, u in cases:
        code = np.full(kept.shape, np.nan) if u is None else np.asarray(u, np.float64)
        assert _same_setting(kept, u) == np.array_equal(kept, code, equal_nan=True), (kept, u)
