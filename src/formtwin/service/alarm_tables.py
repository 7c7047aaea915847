"""The service's alarm tables: ``alarms`` (one row per signal: a chart beyond its limit on
a product) and ``alarm_episodes`` (one row per episode of a chart on a variable,
:mod:`formtwin.monitoring.episodes`; acknowledged there), written by
:class:`formtwin.service.alarms.ServiceMonitor` inside each product's transaction. A store
of the schema before the episodes is migrated (:func:`ensure`, :func:`backfill`).
"""

from __future__ import annotations

import math
import sqlite3
from typing import Any

from formtwin.monitoring.episodes import Episode
from formtwin.service.store import Store

_DDL = """
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY,
    seq INTEGER NOT NULL,
    part_id TEXT NOT NULL,
    product_index INTEGER NOT NULL,
    variable TEXT NOT NULL,
    chart TEXT NOT NULL,
    side TEXT NOT NULL,
    statistic REAL NOT NULL,
    limit_value REAL NOT NULL,
    raised_at REAL NOT NULL,
    acked_at REAL,
    ack_note TEXT,
    episode_id INTEGER,
    UNIQUE (seq, variable, chart)
);
CREATE TABLE IF NOT EXISTS alarm_episodes (
    id INTEGER PRIMARY KEY,
    variable TEXT NOT NULL,
    chart TEXT NOT NULL,
    side TEXT NOT NULL,
    raised_seq INTEGER NOT NULL,
    raised_part TEXT NOT NULL,
    raised_at REAL NOT NULL,
    last_seq INTEGER NOT NULL,
    signals INTEGER NOT NULL,
    ratio REAL NOT NULL,
    statistic REAL,
    limit_value REAL,
    cleared_seq INTEGER,
    cleared_at REAL,
    updated_at REAL NOT NULL,
    acked_at REAL,
    ack_note TEXT,
    UNIQUE (variable, chart, raised_seq)
);
"""


def ensure(store: Store) -> bool:
    """Create the tables (add ``alarms.episode_id`` to an older store); whether the
    episodes table was there before (False: its episodes need a :func:`backfill`)."""
    had = bool(store.query("SELECT 1 FROM sqlite_master WHERE type = 'table' AND "
                           "name = 'alarm_episodes'"))
    store.ensure_tables(_DDL)
    if "episode_id" not in {r[1] for r in store.query("PRAGMA table_info(alarms)")}:
        store.execute("ALTER TABLE alarms ADD COLUMN episode_id INTEGER")
    return had


def insert_signal(cur: sqlite3.Cursor, seq: int, part_id: str, a: dict[str, Any], now: float,
                  episode_id: int | None) -> None:
    """Insert one signal (an alarm dict of the estimate message) of product ``seq``."""
    cur.execute("INSERT INTO alarms(seq, part_id, product_index, variable, chart, side, "
                "statistic, limit_value, raised_at, episode_id) VALUES (?,?,?,?,?,?,?,?,?,?)",
                (seq, part_id, int(a["index"]), str(a["variable"]), str(a["chart"]),
                 str(a["side"]), _real(a["statistic"]), _real(a["limit"]), now, episode_id))


def put(cur: sqlite3.Cursor, ch: dict[str, Any], part_id: str, now: float) -> int:
    """Insert (raised) or update an episode's row from its change; its id."""
    key = (str(ch["variable"]), str(ch["chart"]), int(ch["first"]))
    cleared = ch["cleared"]
    if ch["event"] == "raised":
        cur.execute("INSERT INTO alarm_episodes(variable, chart, side, raised_seq, "
                    "raised_part, raised_at, last_seq, signals, ratio, statistic, "
                    "limit_value, updated_at) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                    (*key[:2], ch["side"], key[2], part_id, now, ch["last"], ch["signals"],
                     _real(ch["ratio"]), ch["statistic"], ch["limit"], now))
        return int(cur.lastrowid or 0)
    cur.execute("UPDATE alarm_episodes SET last_seq = ?, signals = ?, ratio = ?, "
                "statistic = ?, limit_value = ?, cleared_seq = ?, cleared_at = ?, "
                "updated_at = ? WHERE variable = ? AND chart = ? AND raised_seq = ?",
                (ch["last"], ch["signals"], _real(ch["ratio"]), ch["statistic"], ch["limit"],
                 cleared, None if cleared is None else now, now, *key))
    got = cur.execute("SELECT id FROM alarm_episodes WHERE variable = ? AND chart = ? AND "
                      "raised_seq = ?", key).fetchone()
    if got is None:
        raise RuntimeError(f"alarm episode {key} is not stored")
    return int(got[0])


def backfill(cur: sqlite3.Cursor, episodes: list[Episode],
              products: dict[int, tuple[str, float]]) -> None:
    """Store the episodes of a store's earlier products (rebuilt), link their signal rows
    and acknowledge those whose every signal row was acknowledged."""
    for ep in episodes:
        part, raised_at = products[ep.first]
        last_at = products[ep.last if ep.cleared is None else ep.cleared][1]
        cur.execute("INSERT INTO alarm_episodes(variable, chart, side, raised_seq, "
                    "raised_part, raised_at, last_seq, signals, ratio, statistic, limit_value, "
                    "cleared_seq, cleared_at, updated_at) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                    (ep.variable, ep.chart, ep.side, ep.first, part, raised_at, ep.last,
                     ep.signals, ep.ratio, num(ep.statistic), num(ep.limit), ep.cleared,
                     None if ep.cleared is None else last_at, last_at))
        eid = int(cur.lastrowid or 0)
        where = "variable = ? AND chart = ? AND seq BETWEEN ? AND ?"
        span = (ep.variable, ep.chart, ep.first, ep.last)
        cur.execute(f"UPDATE alarms SET episode_id = ? WHERE {where}", (eid, *span))
        n, unacked, last_ack = cur.execute(
            f"SELECT COUNT(*), SUM(acked_at IS NULL), MAX(acked_at) FROM alarms WHERE {where}",
            span).fetchone()
        if n and not unacked:
            cur.execute("UPDATE alarm_episodes SET acked_at = ?, ack_note = ? WHERE id = ?",
                        (last_ack, "its signals were acknowledged before the episodes", eid))


EPISODE_COLS = ("id, variable, chart, side, raised_seq, raised_part, raised_at, last_seq, "
                 "signals, ratio, statistic, limit_value, cleared_seq, cleared_at, updated_at, "
                 "acked_at, ack_note")
_EPISODE_KEYS = ("id", "variable", "chart", "side", "raised_seq", "raised_part", "raised_at",
                 "last_seq", "signals", "ratio", "statistic", "limit", "cleared_seq",
                 "cleared_at", "updated_at", "acked_at", "ack_note")
SIGNAL_COLS = ("id, seq, part_id, product_index, variable, chart, side, statistic, "
                "limit_value, raised_at, episode_id")
SIGNAL_KEYS = ("id", "seq", "part_id", "index", "variable", "chart", "side", "statistic",
                "limit", "raised_at", "episode_id")


def episode_by_id(cur: sqlite3.Cursor, eid: int) -> dict[str, Any]:
    """An episode's row as a dict, read with ``cur`` (inside a transaction)."""
    row = cur.execute(f"SELECT {EPISODE_COLS} FROM alarm_episodes WHERE id = ?",
                      (eid,)).fetchone()
    return episode(row)


def episode(row: tuple[Any, ...]) -> dict[str, Any]:
    """An episode as a JSON-safe dict with its ``state``: active, cleared (returned to
    normal, not acknowledged) or closed (cleared and acknowledged)."""
    d = row_dict(_EPISODE_KEYS, row)
    d["state"] = ("active" if d["cleared_seq"] is None else
                  "closed" if d["acked_at"] is not None else "cleared")
    return d


def row_dict(keys: tuple[str, ...], row: tuple[Any, ...]) -> dict[str, Any]:
    """A row as a JSON-safe dict."""
    return {k: num(v) if isinstance(v, float) else v for k, v in zip(keys, row, strict=True)}


def num(v: float) -> float | None:
    """A JSON-safe or nullable stored number (NaN, inf -> None)."""
    return float(v) if math.isfinite(v) else None


def _real(v: Any) -> float:
    """A stored statistic (None -> NaN)."""
    return math.nan if v is None else float(v)


__all__ = ["EPISODE_COLS", "SIGNAL_COLS", "SIGNAL_KEYS", "backfill", "ensure", "episode",
           "episode_by_id", "insert_signal", "num", "put", "row_dict"]
