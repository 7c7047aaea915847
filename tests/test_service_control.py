"""Feedforward control in the service: each accepted estimate carries the suggested press
setting, within the actuator's limits and maximum step, with the predicted final angle
on target when the setting is not limited; the trim follows the measured angles; a restart
continues from the stored setting and trim."""

from __future__ import annotations

from pathlib import Path

import pytest

from formtwin.service.control import ControlSettings, ServiceController
from formtwin.service.messages import dumps
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.tracker import TrackerConfig

SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))


def test_estimates_carry_the_suggested_setting(tmp_path: Path) -> None:
    payloads = [dumps(s.to_message()) for s in read_stream(make_stream(
        tmp_path / "s.npz", 30, seed=1))]
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    spec = proc.tracker.spec  # type: ignore[attr-defined]
    lo, hi = float(spec.controls.lo[0]), float(spec.controls.hi[0])
    step = 0.1 * (hi - lo)
    target = float(proc.handle(payloads[0]).message["angles_mean"][1]) + 0.5
    proc.controller = ServiceController(proc.tracker, ControlSettings(target, 0.1, lam=0.5),
                                        proc.store)
    outs = [proc.handle(p) for p in payloads[1:20]]
    ctl = [o.message["control"] for o in outs]
    u = [c["u"][0] for c in ctl]
    assert all(lo <= v <= hi for v in u)
    assert all(abs(b - a) <= step + 1e-12 for a, b in zip(u, u[1:], strict=False))
    free = [c for c in ctl if not c["limited"]]
    assert free  # the target is reachable: most suggestions hit it in expectation
    for c in free:  # the prediction includes the trim in use
        assert c["final_angle_deg"] == pytest.approx(target, abs=0.05)
        assert c["interval_deg"][0] <= c["interval_deg"][1]
    assert ctl[0]["target_deg"] == target and ctl[0]["u_unit"] == "mm"
    # the trim: an EWMA (lam 0.5) of the measured minus predicted final angle at the u used
    trim = 0.0
    for o in outs:
        m = o.message
        assert "measured_angles_deg" in m  # the stream carries the measured angles
        trim = 0.5 * (m["measured_angles_deg"][1] - m["angles_mean"][1]) + 0.5 * trim
        assert m["control"]["trim_deg"] == pytest.approx(trim, abs=1e-12)
    proc.close()
    proc.store.close()
    # a restart continues from the last stored suggestion and trim
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    again = ServiceController(proc.tracker, ControlSettings(target, 0.1), proc.store)
    assert again.u_prev == u[-1]
    assert again.controller.bias == pytest.approx(trim, abs=1e-12)
    with pytest.raises(ValueError, match="lam"):
        ControlSettings(target, 0.1, lam=1.5)
    proc.close()
    proc.store.close()
