"""What a service computes at the first start of a store from its inputs alone, kept in a
cache folder under a digest of everything it depends on, so that a new store with the same
inputs (a second service beside the first, a store started afresh) reuses it.

Three results are kept: the control charts' calibration (seconds of simulated in-control
runs; :func:`formtwin.service.alarms.monitor_config`), the alarm episodes' clear-after
products (simulated run lengths; :class:`formtwin.service.alarms.ServiceMonitor`) and the
measurement model (:func:`formtwin.tracker.build_measurement`). The key of an entry is the
SHA-256 of a JSON document of its inputs (the model file's digest, the tracker's settings,
the measurement model's fingerprint, the calibration's settings) and of the source of the
``formtwin`` package that computes it (:func:`code_digest`): a new version of the code or
any other input gives another key, never a stale entry. An entry is written atomically (a
temporary file, then a rename), so services starting side by side never read half a file;
one that cannot be read is computed again. While a process computes an entry it holds the
entry's lock (:func:`computing`, a file lock beside it): a second service starting beside
it with the same inputs waits for that result and reads it instead of computing it too.
The folder: ``serve --cache DIR``, by default
``$FORMTWIN_CACHE``, else ``$XDG_CACHE_HOME/formtwin``, else ``~/.cache/formtwin``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any

import formtwin

log = logging.getLogger(__name__)


def default_dir() -> Path:
    """The cache folder when none is given (see the module doc)."""
    if os.environ.get("FORMTWIN_CACHE"):
        return Path(os.environ["FORMTWIN_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "formtwin"


@lru_cache(maxsize=1)
def code_digest() -> str:
    """First 16 hex digits of the SHA-256 of the ``formtwin`` package's Python sources
    (path and content, in path order): what computed a cached result."""
    root = Path(formtwin.__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def entry(directory: str | Path, kind: str, inputs: dict[str, Any], suffix: str) -> Path:
    """The cache file of a ``kind`` of result computed from ``inputs`` (JSON-able):
    ``DIR/KIND-DIGEST.SUFFIX``, the digest that of the inputs and of :func:`code_digest`.

    >>> a = entry("c", "charts", {"seed": 1}, ".json")
    >>> b = entry("c", "charts", {"seed": 2}, ".json")
    >>> a.parent.name, a.name.startswith("charts-"), a.suffix, a != b
    ('c', True, '.json', True)
    """
    doc = json.dumps({"kind": kind, "code": code_digest(), "inputs": inputs},
                     sort_keys=True, default=repr)
    return Path(directory) / f"{kind}-{hashlib.sha256(doc.encode()).hexdigest()[:24]}{suffix}"


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (readers never see
    a part); an unwritable cache is logged, not raised (the result is still used)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("cache %s not written: %s", path, exc)


@contextmanager
def computing(path: Path | None) -> Iterator[None]:
    """Hold the lock of the entry ``path`` (an exclusive ``flock`` on ``.NAME.lock`` beside
    it) for the block that reads the entry and, when it is missing, computes and writes it:
    another process in the same block for the same entry waits, then finds the result. The
    lock is released when the block ends, also by an exception or the process's death.
    ``None`` (no cache) or a folder where no lock file can be made: no lock (the block
    runs at once, as without it; the result is still computed)."""
    if path is None:
        yield
        return
    import fcntl  # POSIX; a service's store needs it too

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(path.with_name(f".{path.name}.lock"), "a+b")  # noqa: SIM115 (held below)
    except OSError as exc:
        log.warning("cache %s not locked: %s", path, exc)
        yield
        return
    with fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        yield
