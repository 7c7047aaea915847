"""The tracker's state bytes, version 2 (arrays as binary blocks) and version 1 (every
learned array as JSON numbers), on the analytic stand-in with the learned residual moment
(the largest state: the (n_t, n_t) moment and the sandwich's sensitivities)."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest

from formtwin.defaults import AnalyticModel
from formtwin.measurement import MeasurementModel
from formtwin.production import draw_production_run
from formtwin.tracker import Tracker, TrackerConfig
from formtwin.tracker import state as st

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def mm(model: AnalyticModel) -> MeasurementModel:
    return MeasurementModel.from_monte_carlo(model, n=2000, rng=np.random.default_rng(1))


@pytest.fixture(scope="module")
def curves(model: AnalyticModel) -> np.ndarray:
    run = draw_production_run(model.spec, 60, np.random.default_rng(2))
    out: np.ndarray = model.predict_curves(run.inputs)
    return out


def _header(data: bytes) -> dict[str, object]:
    n = int.from_bytes(data[8:16], "little")
    out: dict[str, object] = json.loads(data[16:16 + n])
    return out


def test_learned_state_is_binary_and_continues_bit_for_bit(
        tmp_path: Path, model: AnalyticModel, mm: MeasurementModel,
        curves: np.ndarray) -> None:
    cfg = TrackerConfig(n_particles=40, learn_residuals=True, seed=5)
    a = Tracker(model, mm, cfg)
    a.run(curves[:53])  # the moment folded once (every 50 products), 3 since
    assert a.ssm.learned is not None and a.ssm.learned.n == 50
    saved = a.state_bytes()
    assert saved.startswith(st.MAGIC)
    head = _header(saved)
    n_t = model.spec.n_t
    # the arrays are blocks, the header only names them: a few KB of JSON at most
    assert len(json.dumps(head)) < 8192
    shapes = {k: tuple(v) for k, v in head["arrays"]}  # type: ignore[attr-defined]
    assert shapes["residual_total"] == (n_t, n_t) and shapes["residual_recent"] == (3, n_t)
    assert shapes["particles"] == (40, 18) and shapes["sandwich_J"][0] == n_t
    raw = 8 * sum(int(np.prod(s)) for s in shapes.values())
    assert raw < len(saved) < raw + 8192
    want = a.run(curves[53:])
    # from the bytes and from a checkpoint file: the same numbers, bit for bit
    a.checkpoint(tmp_path / "ck.npz")
    for b in (Tracker.from_state_bytes(saved, model, mm), None):
        if b is None:  # the checkpoint taken after the run: rewind by bytes, then compare
            b = Tracker.restore(tmp_path / "ck.npz", model, mm)
            assert b.state_bytes() == a.state_bytes()
            continue
        got = b.run(curves[53:])
        for f in ("mean", "std", "angles_mean", "angles_std", "ess", "loglik"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
        assert b.state_bytes() == a.state_bytes()
    decoded = st.decode(saved)
    assert isinstance(decoded.model["residual_total"], np.ndarray)
    assert decoded.particles.flags.writeable  # the filter changes particles in place
    with pytest.raises(ValueError, match="bytes, expected"):
        st.decode(saved[:-8])
    with pytest.raises(ValueError, match="bytes, expected"):
        st.decode(saved + b"\0" * 8)


def test_version_1_state_is_read_exactly_and_migrated(
        model: AnalyticModel, mm: MeasurementModel, curves: np.ndarray) -> None:
    """A state written by version 1 (stored: 5 products, N = 40, learn_residuals; every
    learned array as JSON numbers) restores, every number kept exactly; written again it
    is version 2, and that restores the same numbers."""
    old = gzip.decompress((DATA / "tracker_state_v1.bin.gz").read_bytes())
    assert old.startswith(st.MAGIC_V1)
    numbers = _header(old)["model"]
    assert isinstance(numbers, dict)
    s1 = st.decode(old)
    assert s1.t == 5 and s1.particles.shape == (40, 18)
    tr = Tracker.from_state(s1, model, mm)
    assert tr.n_steps == 5 and tr.config.learn_residuals
    s2 = st.decode(tr.state_bytes())
    assert tr.state_bytes().startswith(st.MAGIC)
    np.testing.assert_array_equal(s2.particles, s1.particles)
    np.testing.assert_array_equal(s2.logw, s1.logw)
    assert s2.rng == s1.rng and s2.t == 5  # the config: with any newer settings' defaults
    assert TrackerConfig.from_dict(s2.config) == TrackerConfig.from_dict(s1.config)
    for k, v in numbers.items():  # the JSON numbers of version 1, bit for bit
        np.testing.assert_array_equal(np.ravel(s2.model[k]), np.array(v, dtype=np.float64),
                                      err_msg=k)
    # the migrated state continues like the version-1 one
    t1 = Tracker.from_state(s1, model, mm)
    t2 = Tracker.from_state_bytes(tr.state_bytes(), model, mm)
    e1, e2 = t1.step(curves[5]), t2.step(curves[5])
    np.testing.assert_array_equal(e1.mean, e2.mean)
    assert np.all(np.isfinite(e1.mean)) and e1.index == 5
