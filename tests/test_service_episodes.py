"""Alarm episodes in the service's store (broker- and tracker-free: estimate messages of a
known quantity committed as the processor does): an acknowledged episode closes when it
clears, a restart rebuilds the same episodes, and a store of the schema before the
episodes opens with its episodes rebuilt and linked."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from formtwin.monitoring.charts import Cusum, Ewma
from formtwin.monitoring.incontrol import InControl
from formtwin.monitoring.monitor import MonitorConfig
from formtwin.service.alarms import ServiceMonitor
from formtwin.service.store import Store

CONFIG = MonitorConfig({"thickness": InControl(mean=0.0, sigma=1.0)}, warmup=0, phase1=0,
                       ewma=Ewma(0.2, 3.5), cusum=Cusum(0.5, 8.0))
UNTIMED = ("raised_at", "updated_at", "cleared_at")


def values(n: int = 900) -> list[float]:
    """In control, a 3-sigma excursion of 40 products at 100, another from 600 on."""
    y = np.random.default_rng(2).standard_normal(n)
    y[100:140] += 3.0
    y[600:] += 3.0
    return [float(v) for v in y]


def feed(store: Store, mon: ServiceMonitor, ys: list[float], start: int = 0,
         fail_at: int | None = None) -> list[dict[str, Any]]:
    """Commit one product per value as the processor does; the published messages."""
    out: list[dict[str, Any]] = []
    for i, v in enumerate(ys, start):
        seq = store.next_seq()
        msg: dict[str, Any] = {"seq": seq, "index": i, "mean": {"thickness": v}}
        entry = mon.observe(msg)
        msg["monitoring"] = entry

        def within(cur: sqlite3.Cursor, s: int, entry: dict[str, Any] = entry,
                   i: int = i) -> None:
            out.extend(mon.write(cur, s, f"P{i}", entry, float(i)))
            if i == fail_at:
                raise sqlite3.OperationalError("disk I/O error")

        try:
            store.commit_product(part_id=f"P{i}", cycle=i, timestamp=str(i), status="accepted",
                                 digest="d", curve=np.zeros(2), measured_angles=None,
                                 estimate=msg, checkpoint=None, received_at=float(i),
                                 within=within)
        except sqlite3.OperationalError:
            mon.rollback()
            raise
        mon.committed()
    return out


def untimed(eps: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in e.items() if k not in UNTIMED} for e in eps]


def test_episodes_clear_close_and_survive_a_restart(tmp_path: Path) -> None:
    ys = values()
    ref_store = Store(tmp_path / "ref.sqlite")
    ref = ServiceMonitor(ref_store, CONFIG)
    published = feed(ref_store, ref, ys)
    eps = ref.alarms()
    # two excursions: per chart two episodes, the first cleared, the second active
    for chart in ("ewma", "cusum"):
        mine = [e for e in eps if e["chart"] == chart]
        assert [e["state"] for e in mine] == ["cleared", "active"]
        sig = [a for a in ref.signals() if a["chart"] == chart]
        first = [a for a in sig if a["seq"] <= 140]
        assert (mine[0]["raised_seq"], mine[0]["last_seq"], mine[0]["signals"]) == (
            first[0]["seq"], first[-1]["seq"], len(first))
        after = ref.clear_after[f"thickness/{chart}"]
        assert mine[0]["cleared_seq"] == first[-1]["seq"] + after
        assert mine[1]["raised_seq"] == next(a["seq"] for a in sig if a["seq"] > 600)
    # the alarms topic: raised, updated, cleared; no more than one message per clear-after
    kinds = [m["event"] for m in published]
    assert kinds.count("raised") == 4 and kinds.count("cleared") == 2
    assert len(published) < len(ref.signals()) / 3

    # acknowledgement: an acknowledged active episode closes when it clears; a cleared
    # one closes when acknowledged
    store = Store(tmp_path / "a.sqlite")
    mon = ServiceMonitor(store, CONFIG)
    feed(store, mon, ys[:110])
    state = mon.episodes.state()
    ewma, cusum = mon.alarms()
    assert ewma["state"] == cusum["state"] == "active"
    assert mon.acknowledge(ewma["id"], "seen", now=5.0)["state"] == "active"
    store.close()
    store = Store(tmp_path / "a.sqlite")  # a restart in the excursion
    mon = ServiceMonitor(store, CONFIG)
    assert mon.episodes.state() == state and state["open"]
    feed(store, mon, ys[110:400], start=110)
    ewma, cusum = mon.alarms()
    assert (ewma["state"], cusum["state"]) == ("closed", "cleared")
    assert mon.acknowledge(cusum["id"], now=6.0)["state"] == "closed"
    assert mon.alarms(unacked=True) == []
    # a failed commit leaves no row and the episodes' state as before
    with pytest.raises(sqlite3.OperationalError):
        feed(store, mon, ys[400:620], start=400, fail_at=610)
    assert store.next_seq() == 611 and max(a["seq"] for a in mon.signals()) <= 610
    assert mon.episodes.state() == ServiceMonitor(store, CONFIG).episodes.state()
    assert max(e["last_seq"] for e in mon.alarms()) <= 610
    feed(store, mon, ys[610:], start=610)
    # the restarted, acknowledged, interrupted service has the reference's episodes
    assert [{k: v for k, v in e.items() if k not in ("acked_at", "ack_note", "state")}
            for e in untimed(mon.alarms())] == \
        [{k: v for k, v in e.items() if k not in ("acked_at", "ack_note", "state")}
         for e in untimed(eps)]
    assert mon.signals() == ref.signals()
    assert ServiceMonitor(store, CONFIG).episodes.state() == ref.episodes.state()
    store.close()
    ref_store.close()


_OLD_ALARMS = """
CREATE TABLE alarms (
    id INTEGER PRIMARY KEY, seq INTEGER NOT NULL, part_id TEXT NOT NULL,
    product_index INTEGER NOT NULL, variable TEXT NOT NULL, chart TEXT NOT NULL,
    side TEXT NOT NULL, statistic REAL NOT NULL, limit_value REAL NOT NULL,
    raised_at REAL NOT NULL, acked_at REAL, ack_note TEXT, UNIQUE (seq, variable, chart));
"""


def test_a_store_of_the_schema_before_the_episodes_opens(tmp_path: Path) -> None:
    """An ``alarms`` table without episodes (the schema until 0.1.0.dev12) with signals, some
    acknowledged: it opens, gets ``episode_id``, and its episodes are the ones a service
    with episodes would have written, linked to their signals, acknowledged where every
    signal was; it then continues as that service."""
    ys = values()
    ref_store = Store(tmp_path / "ref.sqlite")
    ref = ServiceMonitor(ref_store, CONFIG)
    feed(ref_store, ref, ys)
    # the old store: the same products and signal rows up to product 300, the old table,
    # no episodes
    old = tmp_path / "old.sqlite"
    db = sqlite3.connect(old)
    src = sqlite3.connect(tmp_path / "ref.sqlite")
    src.backup(db)
    src.close()
    cut = 300  # the old service stopped here
    db.executescript(_OLD_ALARMS.replace("CREATE TABLE alarms", "CREATE TABLE old_alarms") + f"""
        INSERT INTO old_alarms SELECT id, seq, part_id, product_index, variable, chart, side,
            statistic, limit_value, raised_at, NULL, NULL FROM alarms WHERE seq <= {cut};
        DROP TABLE alarms;
        DROP TABLE alarm_episodes;
        ALTER TABLE old_alarms RENAME TO alarms;
        DELETE FROM products WHERE seq > {cut};
        DELETE FROM meta WHERE key = 'alarm_clear_after';
        UPDATE alarms SET acked_at = seq, ack_note = 'ok' WHERE chart = 'ewma';
        UPDATE alarms SET acked_at = 1, ack_note = 'ok' WHERE id = (SELECT MIN(id) FROM alarms
            WHERE chart = 'cusum');
    """)
    db.commit()
    db.close()
    store = Store(old)
    mon = ServiceMonitor(store, CONFIG)
    got = {e["chart"]: e for e in mon.alarms()}
    want = {e["chart"]: e for e in ref.alarms() if e["raised_seq"] <= cut}
    for chart in ("ewma", "cusum"):
        g, w = got[chart], want[chart]
        assert {k: g[k] for k in ("raised_seq", "raised_part", "last_seq", "signals", "ratio",
                                  "cleared_seq")} == \
            {k: w[k] for k in ("raised_seq", "raised_part", "last_seq", "signals", "ratio",
                               "cleared_seq")}
        assert {a["episode_id"] for a in mon.signals() if a["chart"] == chart} == {g["id"]}
    assert got["ewma"]["state"] == "closed" and got["ewma"]["acked_at"] == got["ewma"][
        "last_seq"]
    assert got["cusum"]["state"] == "cleared" and got["cusum"]["acked_at"] is None
    feed(store, mon, ys[cut:], start=cut)
    assert mon.episodes.state() == ref.episodes.state()
    assert [(e["chart"], e["raised_seq"], e["signals"], e["cleared_seq"]) for e in mon.alarms()] \
        == [(e["chart"], e["raised_seq"], e["signals"], e["cleared_seq"]) for e in ref.alarms()]
    store.close()
    ref_store.close()


def test_rollback_after_every_product_gives_the_undisturbed_charts(tmp_path: Path) -> None:
    """Each product charted, rolled back and charted again, through warm-up, Phase I (the
    mean learned) and charting with alarms: the charts' state after every product is the
    state of a monitor that charted each product once."""
    from formtwin.monitoring.glr import Glr, level_signature

    cfg = MonitorConfig({"thickness": InControl(mean=None, sigma=1.0, phi=(0.3,))},
                        warmup=5, phase1=20, ewma=Ewma(0.2, 3.5), cusum=Cusum(0.5, 8.0),
                        glr={"thickness": Glr(level_signature((0.9,)), h=12.0, window=30)})
    ref, mon = (ServiceMonitor(Store(tmp_path / f"{k}.sqlite"), cfg) for k in "ab")
    charts = set()
    for i, v in enumerate(values(300)):
        msg: dict[str, Any] = {"seq": i + 1, "index": i, "mean": {"thickness": v}}
        want = ref.observe(dict(msg))
        ref.committed()
        charts |= {a["chart"] for a in want["alarms"]}
        before = mon.monitor.state()
        mon.observe(dict(msg))
        mon.rollback()
        assert mon.monitor.state() == before
        assert mon.observe(dict(msg)) == want
        mon.committed()
        assert mon.monitor.state() == ref.monitor.state()
    assert {"ewma", "cusum", "glr"} <= charts  # the excursions signalled on every chart
