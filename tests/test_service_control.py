"""Feedforward control in the service: each accepted estimate carries the suggested press
setting, within the actuator's limits and maximum step, with the predicted final angle
on target when the setting is not limited; the trim and the level follow the measured
angles and the posterior; the defaults are the control study's tuning; a restart continues
bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from formtwin.control import (
    TUNED_FIXED_LAM,
    TUNED_FIXED_RHO,
    TUNED_FIXED_WEIGHT,
    TUNED_LAM,
    TUNED_RHO,
)
from formtwin.service.control import ControlSettings, ServiceController
from formtwin.service.messages import dumps
from formtwin.service.processor import Processor
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.tracker import TrackerConfig

SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def payloads(tmp_path_factory: pytest.TempPathFactory) -> list[bytes]:
    path = make_stream(tmp_path_factory.mktemp("stream") / "s.npz", 30, seed=1)
    return [dumps(s.to_message()) for s in read_stream(path)]


def _start(path: Path, payloads: list[bytes], adaptive: bool = False
           ) -> tuple[Processor, float]:
    """A processor that has taken the first product without control, then control on (weight
    0.6, rho 0.5: every part of the state in use; ``adaptive``: the weight learned), with the
    target 0.5 deg above that product's predicted final angle."""
    proc = open_processor(path, SETTINGS)
    target = float(proc.handle(payloads[0]).message["angles_mean"][1]) + 0.5
    proc.controller = ServiceController(
        proc.tracker, ControlSettings(target, 0.1, weight=0.6, rho=0.5, adaptive=adaptive),
        proc.store)
    return proc, target


def test_estimates_carry_the_suggested_setting(tmp_path: Path, payloads: list[bytes]) -> None:
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    spec = proc.tracker.spec  # type: ignore[attr-defined]
    lo, hi = float(spec.controls.lo[0]), float(spec.controls.hi[0])
    step = 0.1 * (hi - lo)
    target = float(proc.handle(payloads[0]).message["angles_mean"][1]) + 0.5
    proc.controller = ServiceController(
        proc.tracker, ControlSettings(target, 0.1, lam=0.5, weight=0.6, rho=0.5,
                                      adaptive=False), proc.store)
    ctl, refs, model, outs = [], [], [], []
    for p in payloads[1:20]:
        outs.append(proc.handle(p))
        ctl.append(outs[-1].message["control"])
        # c_i: the posterior mean of the final angle at the nominal setting after the curve,
        # and m_i(u_i) at the suggested setting
        a = proc.tracker.final_angle(np.array([float(spec.controls.nominal[0]),
                                               ctl[-1]["u"][0]]))
        w = proc.tracker.weights()  # None: equal (after resampling)
        w = np.ones(a.shape[0]) if w is None else w
        refs.append(float(w @ a[:, 0] / w.sum()))
        model.append(float(w @ a[:, 1] / w.sum()))
    u = [c["u"][0] for c in ctl]
    assert all(lo <= v <= hi for v in u)
    assert all(abs(b - a) <= step + 1e-12 for a, b in zip(u, u[1:], strict=False))
    free = [c for c in ctl if not c["limited"]]
    assert free  # the target is reachable: most suggestions hit it in expectation
    for c in free:  # the prediction includes the shift in use
        assert c["final_angle_deg"] == pytest.approx(target, abs=0.05)
        assert c["interval_deg"][0] <= c["interval_deg"][1]
    assert ctl[0]["target_deg"] == target and ctl[0]["u_unit"] == "mm"
    assert (ctl[0]["lam"], ctl[0]["weight"], ctl[0]["rho"]) == (0.5, 0.6, 0.5)
    # the trim: an EWMA (lam 0.5) of the measured minus predicted final angle at the u used,
    # the level an EWMA of c_i, both starting at the first
    trim = level = None
    for o, c_i in zip(outs, refs, strict=True):
        m = o.message
        assert "measured_angles_deg" in m  # the stream carries the measured angles
        e = m["measured_angles_deg"][1] - m["angles_mean"][1]
        trim = e if trim is None else 0.5 * e + 0.5 * trim
        level = c_i if level is None else 0.5 * c_i + 0.5 * level
        assert m["control"]["trim_deg"] == pytest.approx(trim, abs=1e-12)
        assert m["control"]["level_deg"] == pytest.approx(level, abs=1e-12)
        assert m["control"]["last_error_deg"] == pytest.approx(e, abs=1e-12)
        assert m["control"]["last_reference_deg"] == pytest.approx(c_i, abs=1e-12)
    # the predicted angle: the posterior's at u plus the shift: the trim b before the product
    # minus the untrusted share of the posterior's change, (1 - 0.6) (c_i - k), plus
    # 0.5 ((e_j - b) + (1 - 0.6) (c_j - k)) for the last product j (k: the level before)
    assert ctl[0]["final_angle_deg"] == pytest.approx(model[0], abs=1e-9)  # no trim yet
    for prev, c, c_i, m_i in zip(ctl[:-1], ctl[1:], refs[1:], model[1:], strict=True):
        b, k = prev["trim_deg"], prev["level_deg"]
        shift = b - 0.4 * (c_i - k) + 0.5 * ((prev["last_error_deg"] - b)
                                             + 0.4 * (prev["last_reference_deg"] - k))
        assert c["final_angle_deg"] == pytest.approx(m_i + shift, abs=1e-9)
    with pytest.raises(ValueError, match="lam"):
        ControlSettings(target, 0.1, lam=1.5)
    with pytest.raises(ValueError, match="weight"):
        ControlSettings(target, 0.1, weight=-0.1)
    with pytest.raises(ValueError, match="rho"):
        ControlSettings(target, 0.1, rho=1.0)
    proc.close()


def test_defaults_are_the_control_studys_tuning() -> None:
    """One place for the weights: the service's defaults are what bench_control chose: the
    weight learned on the line (from 0, as in the study), its lam and rho; opted out, the
    best fixed weight with its own lam and rho."""
    s = ControlSettings(72.7)
    assert (s.lam, s.weight, s.rho, s.adaptive) == (TUNED_LAM, 0.0, TUNED_RHO, True)
    f = ControlSettings.fixed_weight(72.7)
    assert (f.lam, f.weight, f.rho, f.adaptive) == (TUNED_FIXED_LAM, TUNED_FIXED_WEIGHT,
                                                    TUNED_FIXED_RHO, False)
    res = json.loads((ROOT / "benchmarks" / "results" / "bench_control.json").read_text())
    figures = res.get("figures", res)
    assert (figures["ff_lam"], figures["ff_rho"]) == (TUNED_LAM, TUNED_RHO)
    assert (figures["fffixed_lam"], figures["fffixed_weight"], figures["fffixed_rho"]) == \
        (TUNED_FIXED_LAM, TUNED_FIXED_WEIGHT, TUNED_FIXED_RHO)


def test_serve_options_choose_the_controller() -> None:
    """serve: the learned weight by default, --control-fixed-weight opts out; options given
    replace the tuning, the others keep it."""
    from formtwin.cli import build_parser
    from formtwin.cli.serve import control_settings

    def parse(*extra: str) -> ControlSettings:
        args = build_parser().parse_args(["serve", "--analytic", *extra])
        out: ControlSettings = control_settings(args)
        return out

    assert control_settings(build_parser().parse_args(["serve", "--analytic"])) is None
    assert parse("--target-angle", "72.5") == ControlSettings(72.5)
    assert parse("--target-angle", "72.5", "--control-fixed-weight") == \
        ControlSettings.fixed_weight(72.5)
    s = parse("--target-angle", "72.5", "--control-fixed-weight", "--control-weight", "0.3",
              "--control-max-step", "0.1")
    assert (s.weight, s.adaptive, s.lam, s.max_step) == (0.3, False, TUNED_FIXED_LAM, 0.1)
    s = parse("--target-angle", "72.5", "--control-rho", "0.5", "--control-weight", "0.2")
    assert (s.weight, s.adaptive, s.lam, s.rho) == (0.2, True, TUNED_LAM, 0.5)


@pytest.mark.parametrize("adaptive", [False, True])
def test_restart_continues_bit_for_bit(tmp_path: Path, payloads: list[bytes],
                                       adaptive: bool) -> None:
    ref_proc, target = _start(tmp_path / "ref.sqlite", payloads, adaptive)
    ref = [ref_proc.handle(p).message for p in payloads[1:20]]
    assert all(m["control"]["level_deg"] is not None for m in ref)
    if adaptive:  # the weight is learned: it leaves its start and its sums are stored
        assert ref[-1]["control"]["weight"] != 0.6 and ref[-1]["control"]["weight_sxx"] > 0
    path = tmp_path / "crash.sqlite"
    proc, _ = _start(path, payloads, adaptive)
    got = [proc.handle(p).message for p in payloads[1:8]]
    # stepped and suggested (trim and level moved), then "killed" before the commit
    msg = json.loads(payloads[8])
    proc.tracker.step(msg["force_N"])
    proc.controller.observe({"measured_angles_deg": [0.0, target + 3.0],
                             "angles_mean": [0.0, target]})
    proc.close()
    proc = open_processor(path, SETTINGS)
    proc.controller = ServiceController(
        proc.tracker, ControlSettings(target, 0.1, weight=0.6, rho=0.5, adaptive=adaptive),
        proc.store)
    got += [proc.handle(p).message for p in payloads[8:20]]
    strip = ("flags", "received_at")
    assert [{k: v for k, v in m.items() if k not in strip} for m in got] == \
        [{k: v for k, v in m.items() if k not in strip} for m in ref]
    for p in (proc, ref_proc):
        p.close()


def test_rollback_restores_the_state(tmp_path: Path, payloads: list[bytes]) -> None:
    proc, target = _start(tmp_path / "r.sqlite", payloads, adaptive=True)
    for p in payloads[1:5]:
        proc.handle(p)
    c = proc.controller

    def state() -> tuple[object, ...]:
        k = c.controller
        return c.u_prev, k.bias, k.level, k.last_error, k.last_reference, k.sxy, k.sxx

    before = state()
    proc.tracker.step(json.loads(payloads[5])["force_N"])
    c.observe({"measured_angles_deg": [0.0, target + 3.0], "angles_mean": [0.0, target]})
    assert all(a != b for a, b in zip(state(), before, strict=True))
    c.rollback()
    assert state() == before
    proc.close()
