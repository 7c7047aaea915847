"""References for the particle filters' tests: the exact Kalman filter of a linear-Gaussian
model, and a small tracker on the closed-form stand-in."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np
from scipy import stats

from formtwin.defaults import analytic_model
from formtwin.tracker import TrackerConfig, build_tracker


def kalman_filter(A: np.ndarray, Q: np.ndarray, H: np.ndarray, R: np.ndarray, m0: np.ndarray,
                  P0: np.ndarray, ys: Iterable[np.ndarray]
                  ) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """For ``x_i = A x_(i-1) + N(0, Q)``, ``y_i = H x_i + N(0, R)``, ``x_0 ~ N(m0, P0)``:
    after each ``y`` the posterior mean (d,), covariance (d, d) and log-evidence increment."""
    m, P = m0, P0
    for y in ys:
        m, P = A @ m, A @ P @ A.T + Q
        S = H @ P @ H.T + R
        ev = float(stats.multivariate_normal(H @ m, S).logpdf(y))
        K = P @ H.T @ np.linalg.inv(S)
        m, P = m + K @ (y - H @ m), (np.eye(len(m)) - K @ H) @ P
        yield m, P, ev


def analytic_tracker(**kw: object) -> tuple[object, object]:
    """The stand-in model and a 300-particle tracker on it without deviation; ``kw`` are
    further :class:`TrackerConfig` fields."""
    model = analytic_model()
    cfg = TrackerConfig(n_particles=300, estimate_deviation=False, n_mc=1000, seed=3,
                        **kw)  # type: ignore[arg-type]
    return model, build_tracker(model, cfg)


def interior_curves(model: object, n: int = 6, seed: int = 1) -> np.ndarray:
    """Curves (n, n_t) of the model at inputs drawn in the middle fifth of its box."""
    spec = model.spec  # type: ignore[attr-defined]
    rng = np.random.default_rng(seed)
    X = spec.inputs.lo + (spec.inputs.hi - spec.inputs.lo) * (0.4 + 0.2 * rng.random((n, 10)))
    return np.asarray(model.predict_curves(X))  # type: ignore[attr-defined]


def assert_continues_bit_for_bit(model: object, tracker: object, curves: np.ndarray) -> None:
    """A tracker restored from ``tracker``'s state bytes steps through ``curves`` with the
    same estimates as ``tracker`` itself."""
    tr: object = tracker
    back = type(tr).from_state_bytes(tr.state_bytes(), model, tr.measurement)  # type: ignore
    a = [tr.step(c).mean for c in curves]  # type: ignore[attr-defined]
    b = [back.step(c).mean for c in curves]
    np.testing.assert_array_equal(a, b)
