"""Keys of the study's cached files: a cached file is reused only if it was made from the
same inputs.

The study folder caches realisations, measurement models and filter runs, so that an
interrupted study resumes. A file made by another metamodel (a refit, another residual
rule), another interval calibration or other tracker settings must not be reused: each
carries (or is named by) the key of what made it, and a file with another key is made
again.

>>> a = cache_key({"n": 500}, 0)
>>> len(a), a == cache_key({"n": 500}, 0), a == cache_key({"n": 501}, 0)
(16, True, False)
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path

import numpy as np


def cache_key(*parts: object, files: tuple[str | Path, ...] = ()) -> str:
    """16 hex digits of a SHA-256 over ``parts`` (as JSON; ``str`` for what JSON has no
    form of) and the contents of ``files``."""
    h = hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode())
    for f in files:
        h.update(_file_digest(str(Path(f).resolve()), Path(f).stat().st_mtime_ns))
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=64)
def _file_digest(path: str, mtime_ns: int) -> bytes:
    """SHA-256 of a file's bytes (cached per path and modification time)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.digest()


def stored_key(path: Path) -> str | None:
    """The key saved in an ``.npz`` (array ``key``), or None (no file, no key, unreadable)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            return str(f["key"]) if "key" in f.files else None
    except (OSError, ValueError):
        return None
