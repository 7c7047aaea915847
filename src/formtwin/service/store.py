"""The service's durable store: SQLite in WAL mode.

One file holds everything a restart needs:

* ``products`` -- every accepted (or gated) product, keyed by its unique part id, with its
  curve (float64 bytes), its digest, the measured angles and the estimate (JSON);
* ``rejections`` -- rejected messages, keyed by the SHA-256 of the raw payload so a
  redelivered bad message is counted once;
* ``checkpoint`` -- one row: the tracker's state as bytes and the seq of the product it
  follows, written in the *same* transaction as that product (the service writes it with
  every k-th product and replays the curves stored after it at a restart), so the stored
  estimates and the tracker state can never disagree after a crash;
* ``meta`` -- the service configuration the store was created with;
* tables of the service's parts (alarms, model-health episodes), created with
  :meth:`Store.ensure_tables` and written by :meth:`Store.commit_product`'s ``within`` in the
  product's own transaction.

>>> import tempfile, os
>>> d = tempfile.mkdtemp()
>>> st = Store(os.path.join(d, "s.sqlite"))
>>> st.counts()
{'accepted': 0, 'gated': 0, 'rejected': 0}
>>> st.close()
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

SCHEMA_VERSION = "1"

_DDL = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS products (
    seq INTEGER PRIMARY KEY,
    part_id TEXT NOT NULL UNIQUE,
    cycle INTEGER NOT NULL,
    timestamp TEXT NOT NULL,
    received_at REAL NOT NULL,
    status TEXT NOT NULL,
    digest TEXT NOT NULL,
    curve BLOB NOT NULL,
    measured_angles TEXT,
    estimate TEXT
);
CREATE TABLE IF NOT EXISTS rejections (
    id INTEGER PRIMARY KEY,
    payload_digest TEXT NOT NULL UNIQUE,
    reason TEXT NOT NULL,
    detail TEXT NOT NULL,
    part_id TEXT,
    received_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS checkpoint (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    seq INTEGER NOT NULL,
    data BLOB NOT NULL
);
"""


@dataclass(frozen=True)
class ProductRow:
    """A stored product (``status`` is ``"accepted"`` or ``"gated"``)."""

    seq: int
    part_id: str
    cycle: int
    timestamp: str
    received_at: float
    status: str
    digest: str
    curve: FloatArray
    measured_angles: list[float] | None
    estimate: dict[str, Any] | None


class Store:
    """SQLite store of products, rejections and the tracker checkpoint.

    Parameters
    ----------
    path : str or Path
        Database file; created when missing.
    synchronous : {"NORMAL", "FULL"}
        SQLite ``synchronous`` in WAL mode. ``NORMAL`` survives a killed process (the
        committed WAL is in the OS page cache); ``FULL`` also survives power loss, at the
        price of an fsync per product.
    exclusive : bool
        Hold an exclusive ``flock`` on ``<path>.lock`` while open, so that a second service
        cannot write to the same store (the lock dies with the process, even on SIGKILL).
    background_checkpoint_s : float
        If > 0, WAL checkpoints (copying the WAL into the database, with fsyncs) run every
        this many seconds in a background thread on a second connection instead of inside
        a commit, which keeps them off the per-product latency. 0 leaves SQLite's automatic
        checkpoints in the commits.
    """

    def __init__(self, path: str | Path, synchronous: str = "NORMAL",
                 background_checkpoint_s: float = 0.0, exclusive: bool = False) -> None:
        if synchronous.upper() not in ("NORMAL", "FULL"):
            raise ValueError(f"synchronous must be NORMAL or FULL, got {synchronous!r}")
        self.path = Path(path)
        self._lockfile: IO[bytes] | None = None
        if exclusive:
            import fcntl

            fh = open(self.path.with_name(self.path.name + ".lock"), "ab")  # noqa: SIM115
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                fh.close()
                raise ValueError(f"{self.path} is in use by another formtwin serve "
                                 "(one service per store)") from None
            self._lockfile = fh
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), isolation_level=None,
                                   check_same_thread=False, timeout=30.0)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        self._db.executescript(_DDL)
        version = self.get_meta("schema_version")
        if version is None:
            self.set_meta("schema_version", SCHEMA_VERSION)
        elif version != SCHEMA_VERSION:
            raise ValueError(f"{self.path}: store schema_version {version!r}, this formtwin "
                             f"reads {SCHEMA_VERSION!r}")
        self._stop = threading.Event()
        self._ckpt_thread: threading.Thread | None = None
        if background_checkpoint_s > 0:
            self._db.execute("PRAGMA wal_autocheckpoint=0")
            self._ckpt_thread = threading.Thread(
                target=self._checkpointer, args=(background_checkpoint_s,),
                name="formtwin-wal-checkpoint", daemon=True)
            self._ckpt_thread.start()

    def _checkpointer(self, interval: float) -> None:
        db = sqlite3.connect(str(self.path), isolation_level=None, timeout=30.0)
        try:
            while not self._stop.wait(interval):
                try:
                    db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                except sqlite3.Error as exc:  # busy or I/O: the next round retries
                    log.warning("WAL checkpoint failed: %s", exc)
            db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        finally:
            db.close()

    def close(self) -> None:
        """Stop the background checkpoints (if any) and close the connection (again: no
        effect)."""
        self._stop.set()
        if self._ckpt_thread is not None:
            self._ckpt_thread.join(timeout=30.0)
        with self._lock:
            self._db.close()
        if self._lockfile is not None:
            self._lockfile.close()  # releases the flock
            self._lockfile = None

    # -- meta -------------------------------------------------------------------------
    def get_meta(self, key: str) -> str | None:
        """The stored value of ``key``, or None."""
        with self._lock:
            row = self._db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def set_meta(self, key: str, value: str) -> None:
        """Store ``key`` = ``value``."""
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)",
                             (key, value))

    # -- the service's parts' tables ---------------------------------------------------
    def ensure_tables(self, ddl: str) -> None:
        """Create tables (``CREATE TABLE IF NOT EXISTS`` statements) in the store."""
        with self._lock:
            self._db.executescript(ddl)

    def query(self, sql: str, args: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        """All rows of a read-only statement."""
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    def execute(self, sql: str, args: Sequence[Any] = ()) -> int:
        """Run one writing statement in its own transaction; the number of rows changed."""
        with self._lock:
            return int(self._db.execute(sql, args).rowcount)

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Cursor]:
        """A cursor in one transaction (``with store.transaction() as cur``): all its
        writes are in, or none (rolled back on any exception)."""
        with self._lock:
            cur = self._db.cursor()
            cur.execute("BEGIN IMMEDIATE")
            try:
                yield cur
                cur.execute("COMMIT")
            except BaseException:
                cur.execute("ROLLBACK")
                raise

    # -- writes -----------------------------------------------------------------------
    def commit_product(self, *, part_id: str, cycle: int, timestamp: str, status: str,
                       digest: str, curve: FloatArray, measured_angles: list[float] | None,
                       estimate: dict[str, Any] | bytes | None, checkpoint: bytes | None,
                       received_at: float | None = None,
                       within: Callable[[sqlite3.Cursor, int], None] | None = None) -> int:
        """Insert a product and replace the checkpoint in one transaction; return its seq.

        ``estimate`` is the estimate message, or its JSON as UTF-8 bytes (the payload the
        service publishes, encoded once). ``within(cursor, seq)``, if given, writes the
        product's rows of other tables (alarms, model-health events) in the same
        transaction: all of them are in, or none.

        Raises
        ------
        sqlite3.IntegrityError
            If ``part_id`` is already stored (nothing is written then).
        """
        now = time.time() if received_at is None else received_at
        blob = np.ascontiguousarray(curve, dtype="<f8").tobytes()
        with self.transaction() as cur:
            cur.execute(
                "INSERT INTO products(part_id, cycle, timestamp, received_at, status, "
                "digest, curve, measured_angles, estimate) VALUES (?,?,?,?,?,?,?,?,?)",
                (part_id, cycle, timestamp, now, status, digest, blob,
                 None if measured_angles is None else json.dumps(measured_angles),
                 _json(estimate)))
            seq = int(cur.lastrowid or 0)
            if checkpoint is not None:  # the row in place (a state of the same size
                # overwrites its pages; REPLACE would free them and allocate new ones)
                if not cur.execute("UPDATE checkpoint SET seq = ?, data = ? WHERE id = 1",
                                   (seq, checkpoint)).rowcount:
                    cur.execute("INSERT INTO checkpoint(id, seq, data) VALUES (1, ?, ?)",
                                (seq, checkpoint))
            if within is not None:
                within(cur, seq)
        return seq

    def add_rejection(self, *, payload_digest: str, reason: str, detail: str,
                      part_id: str | None, received_at: float | None = None) -> bool:
        """Record a rejection; False if this exact payload was already recorded."""
        now = time.time() if received_at is None else received_at
        with self._lock:
            cur = self._db.execute(
                "INSERT OR IGNORE INTO rejections(payload_digest, reason, detail, part_id, "
                "received_at) VALUES (?,?,?,?,?)",
                (payload_digest, _utf8(reason), _utf8(detail[:500]),
                 None if part_id is None else _utf8(part_id), now))
            return cur.rowcount == 1

    # -- reads ------------------------------------------------------------------------
    def checkpoint(self) -> tuple[int, bytes] | None:
        """``(seq, bytes)`` of the last checkpoint, or None on a fresh store."""
        with self._lock:
            row = self._db.execute("SELECT seq, data FROM checkpoint WHERE id=1").fetchone()
        return None if row is None else (int(row[0]), bytes(row[1]))

    def product(self, part_id: str) -> ProductRow | None:
        """The stored product with this part id, or None."""
        with self._lock:
            row = self._db.execute(f"SELECT {_COLS} FROM products WHERE part_id=?",
                                   (part_id,)).fetchone()
        return None if row is None else _row(row)

    def next_seq(self) -> int:
        """The seq the next committed product will get."""
        with self._lock:
            row = self._db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM products").fetchone()
        return int(row[0])

    def last_status(self) -> str | None:
        """Status of the last stored product, or None."""
        with self._lock:
            row = self._db.execute("SELECT status FROM products ORDER BY seq DESC "
                                   "LIMIT 1").fetchone()
        return None if row is None else str(row[0])

    def last_cycle(self) -> int | None:
        """Cycle count of the last stored product (accepted or gated), or None."""
        with self._lock:
            row = self._db.execute("SELECT cycle FROM products ORDER BY seq DESC "
                                   "LIMIT 1").fetchone()
        return None if row is None else int(row[0])

    def products(self, since_seq: int = 0, limit: int | None = None,
                 status: str | None = None) -> Iterator[ProductRow]:
        """Products with ``seq > since_seq`` in commit order (optionally of one status)."""
        sql = f"SELECT {_COLS} FROM products WHERE seq > ?"
        args: list[Any] = [since_seq]
        if status is not None:
            sql += " AND status = ?"
            args.append(status)
        sql += " ORDER BY seq"
        if limit is not None:
            sql += " LIMIT ?"
            args.append(int(limit))
        with self._lock:
            rows = self._db.execute(sql, args).fetchall()
        for r in rows:
            yield _row(r)

    def recent_logliks(self, n: int) -> list[float]:
        """The last ``n`` finite ``loglik`` of accepted products, oldest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT json_extract(estimate, '$.loglik') AS ll FROM products WHERE status="
                "'accepted' AND ll IS NOT NULL ORDER BY seq DESC LIMIT ?", (int(n),)).fetchall()
        return [float(r[0]) for r in reversed(rows)]

    def rejections(self) -> list[tuple[int, float, str, str, str | None]]:
        """All rejections as ``(id, received_at, reason, detail, part_id)``, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT id, received_at, reason, detail, part_id FROM "
                                    "rejections ORDER BY id").fetchall()
        return [(int(a), float(b), str(c), str(d), None if e is None else str(e))
                for a, b, c, d, e in rows]

    def counts(self) -> dict[str, int]:
        """Numbers of accepted and gated products and of rejected messages."""
        with self._lock:
            acc = self._db.execute("SELECT status, COUNT(*) FROM products GROUP BY "
                                   "status").fetchall()
            rej = self._db.execute("SELECT COUNT(*) FROM rejections").fetchone()
        by = {str(s): int(c) for s, c in acc}
        return {"accepted": by.get("accepted", 0), "gated": by.get("gated", 0),
                "rejected": int(rej[0])}

    def rejection_counts(self) -> dict[str, int]:
        """Rejected messages by reason."""
        with self._lock:
            rows = self._db.execute("SELECT reason, COUNT(*) FROM rejections GROUP BY "
                                    "reason ORDER BY reason").fetchall()
        return {str(r): int(c) for r, c in rows}


def _json(estimate: dict[str, Any] | bytes | None) -> str | None:
    """The estimate column's text (JSON; bytes are taken as encoded JSON)."""
    if estimate is None:
        return None
    if isinstance(estimate, bytes):
        return estimate.decode("utf-8")
    return json.dumps(estimate, allow_nan=False)


def _utf8(text: str) -> str:
    """``text`` made storable: lone surrogates (possible in JSON) become escapes."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


_COLS = ("seq, part_id, cycle, timestamp, received_at, status, digest, curve, "
         "measured_angles, estimate")


def _row(r: tuple[Any, ...]) -> ProductRow:
    return ProductRow(
        seq=int(r[0]), part_id=str(r[1]), cycle=int(r[2]), timestamp=str(r[3]),
        received_at=float(r[4]), status=str(r[5]), digest=str(r[6]),
        curve=np.frombuffer(r[7], dtype="<f8").astype(np.float64),
        measured_angles=None if r[8] is None else list(json.loads(r[8])),
        estimate=None if r[9] is None else dict(json.loads(r[9])))
