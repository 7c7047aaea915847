"""Readers of CalculiX output: the ``.dat`` tables written by ``*NODE PRINT``.

A ``.dat`` file is a sequence of blocks, each a header such as
``forces (fx,fy,fz) for set NRAM and time  0.1000000E-02`` (or ``total force ...``,
``displacements (vx,vy,vz) ...``) and rows of numbers (``node value value value``, or just
three values for totals). :func:`read_dat` returns them keyed by ``(quantity, set)``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_HEADER = re.compile(r"^\s*(.+?)\s+\(.*\)\s+for set\s+(\S+)\s+and time\s+(\S+)\s*$")


@dataclass(frozen=True)
class DatTable:
    """One quantity of one set over time: ``times (n_t,)``, ``ids (n_rows,)`` (node ids;
    empty for totals) and ``values (n_t, n_rows, 3)``."""

    times: FloatArray
    ids: NDArray[np.int64]
    values: FloatArray


def read_dat(path: str | Path) -> dict[tuple[str, str], DatTable]:
    """All ``*NODE PRINT`` blocks of a ``.dat`` file, ``{(quantity, set): DatTable}``.

    ``quantity`` is the header's first words (``"forces"``, ``"total force"``,
    ``"displacements"``); the set name is upper case as CalculiX writes it.
    """
    blocks: dict[tuple[str, str], list[tuple[float, list[list[float]]]]] = {}
    current: list[list[float]] | None = None
    for line in Path(path).read_text(errors="replace").splitlines():
        m = _HEADER.match(line)
        if m:
            key = (m.group(1).strip(), m.group(2).upper())
            current = []
            blocks.setdefault(key, []).append((float(m.group(3)), current))
            continue
        parts = line.split()
        if current is None or not parts:
            continue
        try:
            current.append([float(v) for v in parts])
        except ValueError:
            current = None
    out: dict[tuple[str, str], DatTable] = {}
    for key, items in blocks.items():
        times = np.array([t for t, _ in items])
        rows = [np.array(r, dtype=np.float64).reshape(len(r), -1) for _, r in items]
        n = min(r.shape[0] for r in rows)
        if n == 0:
            continue
        ids = rows[0][:n, 0].astype(np.int64) if rows[0].shape[1] == 4 else np.zeros(0, np.int64)
        vals = np.stack([r[:n, -3:] for r in rows])
        out[key] = DatTable(times, ids, vals)
    return out


def chord_angle(positions: FloatArray, s: FloatArray, length: float) -> float:
    """Bend angle (deg, downward positive) of the chord of the last ``length`` mm of a line.

    ``positions (n, 2)`` current points, ``s (n,)`` their reference abscissa (increasing),
    as the bending model's ``flap_angle``.
    """
    j = int(np.searchsorted(s, s[-1] - length))
    d = positions[-1] - positions[j]
    return math.degrees(math.atan2(-d[1], d[0]))
