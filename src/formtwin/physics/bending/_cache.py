"""Numba's on-disk cache of the bending kernels, kept in step with their sources.

Numba invalidates a cached function only when its own file changes, and a cached caller
holds its own copy of the kernels it calls: after an update that changes ``kernels.py`` or
``contact.py`` but not ``solver.py``, the solver loaded from the cache runs the old
kernels' code (0.1.0.dev12: a clone whose solver was cached before the fast-math flags
changed computed the study's physics pseudo-data up to 0.9 N away from a fresh clone's,
every run different). :func:`sync_cache`, called when the package is imported, keeps a
stamp of the package's sources in its ``__pycache__`` and drops the Numba cache files
(``*.nbi``, ``*.nbc``) there when the stamp differs, so every kernel is compiled again from
the sources as they are. It covers Numba's default cache next to the sources (the
project's editable install); a cache elsewhere (``NUMBA_CACHE_DIR``) is the user's to clear.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

#: the package whose cache is kept in step
PACKAGE = Path(__file__).parent
#: name of the stamp file in ``__pycache__``
STAMP = "formtwin-numba-sources.sha256"


def sources_digest(folder: Path = PACKAGE) -> str:
    """SHA-256 (hex) over the names and bytes of the folder's ``*.py`` files."""
    h = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def sync_cache(folder: Path = PACKAGE) -> int:
    """Remove the Numba cache files of ``folder/__pycache__`` unless its stamp says they
    were made from the sources as they are now; record the sources' digest. Returns the
    number of files removed (0: the cache was in step). Errors of a read-only folder or of
    a file another process removed first are ignored (Numba recompiles what it cannot load).
    """
    cache = folder / "__pycache__"
    stamp = cache / STAMP
    digest = sources_digest(folder)
    try:
        if stamp.read_text(encoding="ascii") == digest:
            return 0
    except OSError:
        pass
    removed = 0
    for path in [*cache.glob("*.nbi"), *cache.glob("*.nbc")]:
        try:
            path.unlink()
            removed += 1
        except OSError:
            pass
    try:
        cache.mkdir(exist_ok=True)
        stamp.write_text(digest, encoding="ascii")
    except OSError:
        pass
    return removed
