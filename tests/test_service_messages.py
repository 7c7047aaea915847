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
