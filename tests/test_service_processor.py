"""The broker-free service core: idempotent redelivery, rejections that leave the tracker
untouched, restart from the store, the outlier gate, export."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from formtwin.service.export import export_store
from formtwin.service.messages import dumps
from formtwin.service.processor import Processor
from formtwin.service.runtime import ServiceSettings, open_processor
from formtwin.service.streams import make_stream, read_stream
from formtwin.tracker import TrackerConfig

SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))


@pytest.fixture(scope="module")
def payloads(tmp_path_factory: pytest.TempPathFactory) -> list[bytes]:
    path = make_stream(tmp_path_factory.mktemp("stream") / "s.npz", 40, seed=1)
    return [dumps(s.to_message()) for s in read_stream(path)]


def run(proc: Processor, items: list[bytes]) -> list[dict[str, object]]:
    return [proc.handle(p).message for p in items]


def strip(msg: dict[str, object]) -> dict[str, object]:
    return {k: v for k, v in msg.items() if k not in ("flags", "received_at")}


def test_redelivery_is_idempotent(tmp_path: Path, payloads: list[bytes]) -> None:
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    first = run(proc, payloads[:5])
    again = proc.handle(payloads[2])
    assert again.kind == "redelivered"
    assert strip(again.message) == strip(first[2])
    assert again.message["flags"]["redelivered"] is True  # type: ignore[index]
    assert proc.store.counts() == {"accepted": 5, "gated": 0, "rejected": 0}
    nxt = proc.handle(payloads[5])
    assert nxt.kind == "accepted" and nxt.seq == 6 and nxt.message["index"] == 5
    proc.close()
    proc.store.close()


def test_poison_messages_are_rejected_not_fatal(tmp_path: Path) -> None:
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    poison = [b'{"schema": "formtwin.stroke/1", "part_id": "\\ud800"}',
              b'{"schema": "formtwin.stroke/1", "cycle": ' + b"9" * 5000 + b"}",
              b"[" * 20_000 + b"]" * 20_000, b"\xed\xa0\x80"]
    assert [proc.handle(p).kind for p in poison] == ["rejected"] * len(poison)
    assert proc.store.counts()["rejected"] == len(poison)
    proc.close()
    proc.store.close()


def test_duplicate_and_out_of_order(tmp_path: Path, payloads: list[bytes]) -> None:
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    run(proc, payloads[:3])
    msg = json.loads(payloads[1])
    msg["force_N"][10] += 1.0  # same part id, different curve
    out = proc.handle(dumps(msg))
    assert out.kind == "rejected" and out.message["reason"] == "duplicate_part_id"
    late = json.loads(payloads[5])
    late["cycle"] = 2  # a new part with an old cycle count
    out = proc.handle(dumps(late))
    assert out.kind == "rejected" and out.message["reason"] == "out_of_order"
    assert "cycle 2" in str(out.message["detail"])
    # the same bad payload redelivered is counted once
    proc.handle(dumps(late))
    assert proc.store.rejection_counts() == {"duplicate_part_id": 1, "out_of_order": 1}
    proc.close()
    proc.store.close()


def test_rejections_leave_the_tracker_untouched(tmp_path: Path,
                                                payloads: list[bytes]) -> None:
    clean = open_processor(tmp_path / "clean.sqlite", SETTINGS)
    ref = run(clean, payloads[:12])
    dirty = open_processor(tmp_path / "dirty.sqlite", SETTINGS)
    bad = [b"{", b'{"schema": "x"}', dumps({**json.loads(payloads[0]), "force_N": [1.0]}),
           payloads[0].replace(b'"force_N":[', b'"force_N":[NaN,'), b"x" * 70_000]
    got = []
    for i, p in enumerate(payloads[:12]):
        out = dirty.handle(bad[i % len(bad)])
        assert out.kind == "rejected"
        got.append(dirty.handle(p).message)
    assert [strip(m) for m in got] == [strip(m) for m in ref]
    assert dirty.store.counts()["rejected"] == len(bad)
    for p in (clean, dirty):
        p.close()
        p.store.close()


def test_restart_continues_bit_for_bit(tmp_path: Path, payloads: list[bytes]) -> None:
    ref_proc = open_processor(tmp_path / "ref.sqlite", SETTINGS)
    ref = run(ref_proc, payloads[:20])
    path = tmp_path / "crash.sqlite"
    proc = open_processor(path, SETTINGS)
    got = run(proc, payloads[:7])
    proc.tracker.step(json.loads(payloads[7])["force_N"])  # stepped, then "killed" pre-commit
    proc.close()
    proc.store.close()
    proc = open_processor(path, SETTINGS)
    got += run(proc, payloads[7:20])
    assert [strip(m) for m in got] == [strip(m) for m in ref]
    assert proc.store.counts()["accepted"] == 20
    with pytest.raises(ValueError, match="in use by another"):
        open_processor(path, SETTINGS)
    proc.close()
    proc.store.close()
    with pytest.raises(ValueError, match="n_particles"):
        open_processor(path, dataclasses.replace(
            SETTINGS, tracker=dataclasses.replace(SETTINGS.tracker, n_particles=65)))
    for p in (proc, ref_proc):
        p.close()
        p.store.close()


def test_gate_skips_a_single_outlier(tmp_path: Path, payloads: list[bytes]) -> None:
    gated = dataclasses.replace(SETTINGS, gate_k=50.0)
    ref_proc = open_processor(tmp_path / "ref.sqlite", gated)
    ref = run(ref_proc, payloads[:30])
    proc = open_processor(tmp_path / "g.sqlite", gated)
    got = run(proc, payloads[:22])
    window = list(proc.gate.history)  # type: ignore[union-attr]
    proc.close()
    proc.store.close()
    proc = open_processor(tmp_path / "g.sqlite", gated)  # the gate's window survives
    assert proc.gate is not None and proc.gate.history == window
    got += run(proc, payloads[22:25])
    odd = json.loads(payloads[25])
    odd["part_id"] += "-odd"
    odd["cycle"] = json.loads(payloads[24])["cycle"] * 1000 + 1
    odd["force_N"] = [3.0 * f + 300.0 for f in odd["force_N"]]
    out = proc.handle(dumps(odd))
    assert out.kind == "gated" and out.message["reason"] == "outlier_gated"
    again = proc.handle(dumps(odd))  # its redelivery is recognised, not counted again
    assert again.kind == "gated" and "redelivered" in str(again.message["detail"])
    # the tracker continues as if the outlier had not come (cycle counts aside)
    for p in payloads[25:30]:
        m = json.loads(p)
        m["cycle"] += odd["cycle"]
        got.append(proc.handle(dumps(m)).message)
    keep = ("mean", "std", "angles_mean", "angles_std", "ess", "loglik")
    assert [{k: m[k] for k in keep} for m in got] == [{k: m[k] for k in keep} for m in ref]
    assert proc.store.counts() == {"accepted": 30, "gated": 1, "rejected": 0}
    for p in (proc, ref_proc):
        p.close()
        p.store.close()


@pytest.mark.parametrize("k", [3, 7])
def test_restart_replays_the_products_after_the_checkpoint(
        tmp_path: Path, payloads: list[bytes], k: int, caplog: pytest.LogCaptureFixture) -> None:
    """The tracker's state is stored with every k-th accepted product; a restart replays
    the curves stored after it (skipping a gated product, whose step was undone) and the
    service continues bit for bit."""
    import logging

    gated = dataclasses.replace(SETTINGS, gate_k=50.0)
    odd = json.loads(payloads[24])
    odd["part_id"] += "-odd"
    odd["cycle"] = json.loads(payloads[23])["cycle"] * 1000 + 1
    odd["force_N"] = [3.0 * f + 300.0 for f in odd["force_N"]]
    after = []
    for p in payloads[24:30]:
        m = json.loads(p)
        m["cycle"] += odd["cycle"]
        after.append(dumps(m))
    stream = [*payloads[:24], dumps(odd), *after]
    ref_proc = open_processor(tmp_path / "ref.sqlite", gated)  # checkpoint_every=10
    ref = [proc_out.message for proc_out in map(ref_proc.handle, stream)]
    assert ref[24]["reason"] == "outlier_gated"
    proc = open_processor(tmp_path / "k.sqlite", gated, checkpoint_every=k)
    got = run(proc, stream[:27])  # 24 accepted, the gated one, 2 accepted
    ck = proc.store.checkpoint()
    assert ck is not None and ck[0] == 24 // k * k  # seq of the k-th, 2k-th, ... product
    proc.close()
    with caplog.at_level(logging.INFO, logger="formtwin.service.restore"):
        proc = open_processor(tmp_path / "k.sqlite", gated, checkpoint_every=k)
    assert f"replayed {27 - ck[0] - 1} products" in caplog.text  # the gated one skipped
    assert not [r for r in caplog.records if r.levelname == "ERROR"]
    got += run(proc, stream[27:])
    keep = ("mean", "std", "angles_mean", "angles_std", "ess", "loglik", "seq")
    assert [{x: m.get(x) for x in keep} for m in got] == \
        [{x: m.get(x) for x in keep} for m in ref]
    assert proc.store.counts() == {"accepted": 30, "gated": 1, "rejected": 0}
    for p in (proc, ref_proc):
        p.close()


def test_export_parquet_and_csv(tmp_path: Path, payloads: list[bytes]) -> None:
    import pyarrow.parquet as pq

    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    msgs = run(proc, payloads[:6])
    proc.handle(b"{")
    proc.close()
    proc.store.close()
    path, n = export_store(tmp_path / "a.sqlite", tmp_path / "e.parquet", curves=True)
    t = pq.read_table(path)
    assert n == 6 and t.num_rows == 6
    assert t.column("part_id").to_pylist() == [m["part_id"] for m in msgs]
    assert np.allclose(t.column("mean_yield_stress").to_pylist(),
                       [m["mean"]["yield_stress"] for m in msgs])  # type: ignore[index]
    assert "f100" in t.column_names and "angle2_measured" in t.column_names
    assert t.column("health").to_pylist() == [m["health"] for m in msgs]
    assert t.column("model_mismatch").to_pylist() == [False] * 6
    path, n = export_store(tmp_path / "a.sqlite", tmp_path / "r.csv", rejections=True)
    rows = list(csv.DictReader(open(path, encoding="utf-8")))
    assert n == 1 and rows[0]["reason"] == "malformed_json"
    with pytest.raises(ValueError, match="format"):
        export_store(tmp_path / "a.sqlite", tmp_path / "x.xlsx")


def test_any_interleaving_of_redeliveries_and_bad_input_stores_the_clean_run(
        tmp_path_factory: pytest.TempPathFactory, payloads: list[bytes]) -> None:
    """Property: whatever mix of redeliveries and bad messages arrives between the good
    strokes, the store ends up with exactly the clean run's products and estimates."""
    import shutil

    from hypothesis import given, settings
    from hypothesis import strategies as st

    from formtwin.service.runtime import measurement_path

    cpath = tmp_path_factory.mktemp("clean") / "c.sqlite"
    clean = open_processor(cpath, SETTINGS)
    ref = [strip(m) for m in run(clean, payloads[:8])]
    clean.close()
    clean.store.close()
    bad = [b"", b"{}", b"null", b'{"schema": "formtwin.stroke/1"}', b"\x00" * 10]

    @settings(max_examples=10, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 7)), max_size=12))
    def check(noise: list[tuple[int, int]]) -> None:
        path = tmp_path_factory.mktemp("p") / "p.sqlite"
        shutil.copy(measurement_path(cpath), measurement_path(path))  # skip Monte Carlo
        proc = open_processor(path, SETTINGS)
        extra = iter(noise)
        done = 0
        for i, p in enumerate(payloads[:8]):
            proc.handle(p)
            done = i + 1
            for kind, k in [next(extra, (-1, 0))]:
                if kind == 0:  # redeliver an already processed stroke
                    assert proc.handle(payloads[k % done]).kind == "redelivered"
                elif kind == 1:
                    assert proc.handle(bad[k % len(bad)]).kind == "rejected"
                elif kind == 2 and done < 8:  # an old cycle under a new part id
                    m = json.loads(payloads[k % done])
                    m["part_id"] += "-x"
                    assert proc.handle(dumps(m)).message["reason"] == "out_of_order"
        got = [strip(r.estimate) for r in proc.store.products()]  # type: ignore[arg-type]
        assert got == ref
        proc.close()
        proc.store.close()

    check()


def test_student_t_option_keeps_the_cloud_on_an_outlier(tmp_path: Path,
                                                       payloads: list[bytes]) -> None:
    from formtwin.measurement import MeasurementModel
    from formtwin.service.runtime import measurement_path

    odd = json.loads(payloads[10])
    odd["force_N"] = [2.0 * f + 100.0 for f in odd["force_N"]]
    ess = {}
    for nu in (math.inf, 5.0):
        path = tmp_path / f"nu{nu}.sqlite"
        proc = open_processor(path, dataclasses.replace(
            SETTINGS, tracker=dataclasses.replace(SETTINGS.tracker, nu=nu)))
        assert MeasurementModel.load(measurement_path(path)).nu == nu
        run(proc, payloads[:10])
        out = proc.handle(dumps(odd))  # an outlier curve, no gate: accepted
        assert out.kind == "accepted"
        ess[nu] = float(out.message["ess"])  # type: ignore[arg-type]
        proc.close()
        proc.store.close()
    # the Gaussian puts (nearly) all weight on one particle; the Student-t keeps a cloud. Compared
    # in measurement space, the outlier's residual grows with each particle's force scaling, so
    # the weights spread more than in model space (ESS 12 of 64 here, 33 in model space)
    assert ess[math.inf] < 1.5 and ess[5.0] > 10.0 and ess[5.0] > 5.0 * ess[math.inf], ess


def test_serves_a_metamodel_and_restarts_on_it(tmp_path: Path, payloads: list[bytes]) -> None:
    metamodel = pytest.importorskip("formtwin.metamodel")
    testing = pytest.importorskip("formtwin.defaults")
    mm_path = tmp_path / "mm.npz"
    metamodel.Metamodel().fit(testing.analytic_dataset(50, seed=0)).save(mm_path)
    settings = dataclasses.replace(SETTINGS, model=str(mm_path))
    ref = open_processor(tmp_path / "ref.sqlite", settings)
    want = [strip(m) for m in run(ref, payloads[:8])]
    proc = open_processor(tmp_path / "a.sqlite", settings)
    got = run(proc, payloads[:4])
    proc.close()
    proc.store.close()
    proc = open_processor(tmp_path / "a.sqlite", settings)
    got += run(proc, payloads[4:8])
    assert [strip(m) for m in got] == want
    assert all(m["collapsed"] is False for m in got)
    proc.close()
    proc.store.close()
    # another model under the same store is refused
    with pytest.raises(ValueError, match="differs from the one"):
        open_processor(tmp_path / "a.sqlite", SETTINGS)
    ref.close()
    ref.store.close()


def test_tracker_refusal_is_a_rejection(tmp_path: Path, payloads: list[bytes]) -> None:
    """A curve the tracker refuses (ValueError) is rejected with its message; the tracker's
    contract is that its state is then untouched, so nothing is rolled back."""
    proc = open_processor(tmp_path / "a.sqlite", SETTINGS)
    real = proc.tracker

    class Refusing:
        def step(self, curve: object, u: object = None) -> object:
            raise ValueError("curve is not monotone before contact (test double)")

        def state_bytes(self) -> bytes:
            return real.state_bytes()

        def load_state_bytes(self, data: bytes) -> None:
            real.load_state_bytes(data)

    proc.tracker = Refusing()
    out = proc.handle(payloads[0])
    assert out.kind == "rejected" and out.message["reason"] == "tracker_rejected"
    assert "monotone" in str(out.message["detail"])
    proc.tracker = real
    assert proc.handle(payloads[1]).kind == "accepted"
    assert proc.store.rejection_counts() == {"tracker_rejected": 1}

    class Crashing:  # an unexpected error after touching the state: rolled back (the
        # undo replays the stored curves through the tracker: those step as before)
        crashed = False

        def step(self, curve: object, u: object = None) -> object:
            out = real.step(curve)
            if not self.crashed:
                self.crashed = True
                raise FloatingPointError("overflow in the model (test double)")
            return out

        def state_bytes(self) -> bytes:
            return real.state_bytes()

        def load_state_bytes(self, data: bytes) -> None:
            real.load_state_bytes(data)

    proc.tracker = Crashing()
    out = proc.handle(payloads[2])
    assert out.kind == "rejected" and "FloatingPointError" in str(out.message["detail"])
    proc.tracker = real  # the state was loaded back in place: one step so far
    assert proc.handle(payloads[3]).message["index"] == 1

    class NotJson:  # an estimate that cannot be stored as JSON: rejected, state restored
        def __init__(self, inner: object) -> None:
            self.inner = inner

        def step(self, curve: object, u: object = None) -> object:
            e = self.inner.step(curve)  # type: ignore[attr-defined]
            return dataclasses.replace(e, index=float("nan"))  # to_dict: int(nan) fails

        def state_bytes(self) -> bytes:
            return self.inner.state_bytes()  # type: ignore[attr-defined,no-any-return]

        def load_state_bytes(self, data: bytes) -> None:
            self.inner.load_state_bytes(data)  # type: ignore[attr-defined]

    proc.tracker = NotJson(proc.tracker)
    out = proc.handle(payloads[4])
    assert out.kind == "rejected" and "not storable" in str(out.message["detail"])
    proc.tracker = real
    assert proc.handle(payloads[5]).message["index"] == 2
    proc.close()
    proc.store.close()
