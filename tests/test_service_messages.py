"""Stroke message validation: every rejection reason, and no crash on arbitrary bytes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from formtwin.service.messages import (
    REASONS,
    STROKE_SCHEMA,
    Limits,
    MessageError,
    dumps,
    parse_stroke,
)

N_T = 101
LIM = Limits(n_t=N_T)


def good(**over: object) -> dict[str, object]:
    msg: dict[str, object] = {"schema": STROKE_SCHEMA, "part_id": "P-1", "cycle": 5,
                              "timestamp": "2026-11-21T23:00:00Z",
                              "force_N": list(np.linspace(0.0, 400.0, N_T)),
                              "angles_deg": [44.0, 89.0]}
    msg.update(over)
    return msg


def reason_of(payload: bytes) -> str:
    with pytest.raises(MessageError) as info:
        parse_stroke(payload, LIM)
    return info.value.reason


def test_good_message_roundtrip() -> None:
    s = parse_stroke(dumps(good()), LIM)
    assert s.part_id == "P-1" and s.cycle == 5 and s.force_N.shape == (N_T,)
    assert s.angles_deg is not None and s.angles_deg.tolist() == [44.0, 89.0]
    again = parse_stroke(dumps(s.to_message()), LIM)
    assert again.digest == s.digest and np.array_equal(again.force_N, s.force_N)
    # angles are optional, the timestamp may be a number
    s2 = parse_stroke(dumps({k: v for k, v in good(timestamp=1.5).items()
                             if k != "angles_deg"}), LIM)
    assert s2.angles_deg is None and s2.timestamp == "1.5"


def _drop(key: str) -> bytes:
    return dumps({k: v for k, v in good().items() if k != key})


CASES: list[tuple[str, bytes]] = [
    ("oversized", dumps(good(pad="x" * 70_000))),
    ("malformed_json", b"{not json"),
    ("malformed_json", b"\xff\xfe\x00"),
    ("malformed_json", b"[1, 2, 3]"),
    ("malformed_json", b'{"schema": "formtwin.stroke/1", "cycle": ' + b"1" * 5000 + b"}"),
    ("malformed_json", b"[" * 20_000 + b"]" * 20_000),
    ("unknown_schema", dumps(good(schema="formtwin.stroke/2"))),
    ("unknown_schema", _drop("schema")),
    ("missing_field", _drop("part_id")),
    ("missing_field", _drop("cycle")),
    ("missing_field", _drop("timestamp")),
    ("missing_field", _drop("force_N")),
    ("bad_field", dumps(good(part_id=""))),
    ("bad_field", dumps(good(part_id=17))),
    ("bad_field", dumps(good(cycle=-1))),
    ("bad_field", dumps(good(cycle=True))),
    ("bad_field", dumps(good(cycle="7"))),
    ("bad_field", dumps(good(cycle=10**30))),  # beyond the store's 64-bit integers
    ("bad_field", dumps(good(cycle=2**63))),
    ("bad_field", dumps(good(timestamp=10**400))),
    ("bad_field", dumps(good(timestamp=None))),
    ("bad_field", dumps(good(timestamp="yesterday"))),
    ("bad_field", dumps(good(timestamp=-1))),
    ("bad_field", dumps(good(force_N="1,2,3"))),
    ("bad_field", dumps(good(force_N=[1.0] * 100 + ["x"]))),
    ("wrong_length", dumps(good(force_N=[1.0] * 100))),
    ("wrong_length", dumps(good(force_N=[]))),
    ("wrong_length", dumps(good(angles_deg=[1.0]))),
    ("non_finite", dumps(good()).replace(b"400.0", b"NaN")),
    ("non_finite", dumps(good()).replace(b"400.0", b"Infinity")),
    ("non_finite", dumps(good()).replace(b"400.0", b"1e999")),
    ("non_finite", dumps(good()).replace(b"400.0", b"1" + b"0" * 400)),
    ("negative_force", dumps(good(force_N=[-500.0] + [1.0] * 100))),
    ("absurd_force", dumps(good(force_N=[1.0] * 100 + [5e6]))),
]


@pytest.mark.parametrize(("reason", "payload"), CASES)
def test_each_rejection_has_its_reason(reason: str, payload: bytes) -> None:
    assert reason in REASONS
    assert reason_of(payload) == reason


def test_rejection_names_field_and_value() -> None:
    with pytest.raises(MessageError) as info:
        parse_stroke(dumps(good(force_N=[1.0] * 100)), LIM)
    assert "force_N" in str(info.value) and "100" in str(info.value) and "101" in str(info.value)
    assert info.value.part_id == "P-1"
    with pytest.raises(MessageError) as info:
        parse_stroke(dumps(good(force_N=[-500.0] + [1.0] * 100)), LIM)
    assert "force_N[0]" in info.value.detail and "-500" in info.value.detail


def test_invalid_part_id_is_not_attached_to_errors() -> None:
    for raw in (b'"\\ud800"', b'""', b'"' + b"x" * 200 + b'"', b"17"):
        payload = b'{"schema": "formtwin.stroke/1", "part_id": ' + raw + b"}"
        with pytest.raises(MessageError) as info:
            parse_stroke(payload, LIM)
        assert info.value.part_id is None


def test_every_reason_is_covered() -> None:
    parse_level = {r for r, _ in CASES}
    processor_level = {"duplicate_part_id", "out_of_order", "tracker_rejected", "outlier_gated"}
    plausibility_level = {"no_stroke", "clipped_sensor", "peak_outside_window"}  # own tests
    sensor_level = {"unknown_sensor", "duplicate_measurement", "hold_full", "hold_expired",
                    "fusion_rejected", "product_gated"}  # test_service_sensors.py
    assert parse_level | processor_level | plausibility_level | sensor_level == set(REASONS)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_arbitrary_bytes_never_crash(payload: bytes) -> None:
    try:
        parse_stroke(payload, LIM)
    except MessageError as e:
        assert e.reason in REASONS


@settings(max_examples=200, deadline=None)
@given(st.recursive(st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers()
                    | st.text(max_size=5),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=5), c,
                                                                         max_size=4),
                    max_leaves=20),
       st.sampled_from(["part_id", "cycle", "timestamp", "force_N", "angles_deg", "schema"]))
def test_arbitrary_field_values_never_crash(value: object, key: str) -> None:
    msg = good()
    msg[key] = value
    try:
        payload = json.dumps(msg).encode()
    except (ValueError, TypeError):
        return
    try:
        s = parse_stroke(payload, LIM)
    except MessageError as e:
        assert e.reason in REASONS
    else:
        assert np.all(np.isfinite(s.force_N)) and s.force_N.size == N_T
        assert not math.isnan(float(s.cycle))


def _outcome(read: object) -> object:
    """What a parse gave: the stroke's fields, or the rejection's reason and detail."""
    try:
        s = read()  # type: ignore[operator]
    except MessageError as e:
        return ("rejected", e.reason, e.detail, e.part_id)
    return (s.part_id, s.cycle, s.timestamp, s.force_N.tobytes(), s.digest,
            None if s.angles_deg is None else s.angles_deg.tobytes(),
            None if s.u is None else s.u.tobytes())


EDGES = [10**19, 2**64, -(2**63) - 1, 10**30, 10**400, 1e30, -1e19, 1.5e308, "\ud800",
         "x\ud800y", 0.1, 2**53 + 1]


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.sampled_from(EDGES), st.integers(), st.floats(allow_nan=True),
                 st.text(max_size=4), st.lists(st.sampled_from(EDGES) | st.floats()
                                               | st.integers(), min_size=1, max_size=3)),
       st.sampled_from(["part_id", "cycle", "timestamp", "force_N", "angles_deg", "u",
                        "extra"]),
       st.booleans())
def test_fast_read_is_the_standard_librarys(value: object, key: str, in_list: bool) -> None:
    # orjson's read (the fast path) and the standard library's give the same stroke, or
    # the same rejection with the same detail, also for integers beyond 64 bits (orjson
    # reads them as floats), lone surrogates and non-finite literals (orjson refuses them)
    from formtwin.service.messages import _stroke

    msg = good()
    if key == "force_N" and in_list:
        force = list(np.linspace(0.0, 400.0, N_T))
        force[3] = value
        msg[key] = force
    else:
        msg[key] = value
    try:
        payload = json.dumps(msg).encode()  # NaN and Infinity as their literals
    except (ValueError, TypeError):
        return
    assert _outcome(lambda: parse_stroke(payload, LIM)) == \
        _outcome(lambda: _stroke(payload, LIM, fast=False))


@settings(max_examples=150, deadline=None)
@given(st.one_of(st.sampled_from(EDGES), st.integers(), st.floats(allow_nan=True),
                 st.text(max_size=4)),
       st.sampled_from(["part_id", "sensor", "value", "timestamp"]))
def test_fast_read_of_a_sensor_message_is_the_standard_librarys(value: object,
                                                                 key: str) -> None:
    from formtwin.service.readings import SENSOR_SCHEMA, _reading, parse_reading

    msg = {"schema": SENSOR_SCHEMA, "part_id": "P-1", "sensor": "camera", "value": 86.5,
           "timestamp": "2026-11-21T23:00:00Z", key: value}
    try:
        payload = json.dumps(msg).encode()
    except (ValueError, TypeError):
        return

    def outcome(read: object) -> object:
        try:
            return read()  # type: ignore[operator]
        except MessageError as e:
            return ("rejected", e.reason, e.detail, e.part_id)

    assert outcome(lambda: parse_reading(payload, ("camera",))) == \
        outcome(lambda: _reading(payload, ("camera",), fast=False))
