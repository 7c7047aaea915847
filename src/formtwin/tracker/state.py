"""A tracker's state as bytes (in memory) or as a checkpoint file, restored bit for bit.

The state is the particles, their log-weights, the step count, the RNG state, the config
and the names of the estimated quantities, plus a fingerprint of the measurement model
(a restore with a different one is logged). Two encodings of the same content:

* :func:`encode` / :func:`decode`: compact bytes (the service stores them in its SQLite
  transaction): ``MAGIC``, an 8-byte little-endian header length, a JSON header, then the
  raw little-endian float64 particles and log-weights;
* :func:`save_npz` / :func:`load_npz`: an ``.npz`` file (no pickle), atomically replaced.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.measurement import MeasurementModel

FloatArray = NDArray[np.float64]

#: format tag of both encodings
FORMAT = "formtwin.tracker/1"
#: first bytes of :func:`encode`'s output
MAGIC = b"FTWTRK1\n"


@dataclass(frozen=True)
class TrackerState:
    """Everything a tracker needs to continue exactly where it stopped.

    Attributes
    ----------
    particles : (N, d) current particles (``(0, d)`` before the first step).
    logw : (N,) log-weights (empty before the first step).
    t : products assimilated so far.
    rng : the ``bit_generator.state`` of the tracker's generator.
    config : the :class:`~formtwin.tracker.TrackerConfig` as a dict (``to_dict``).
    names : the estimated quantities (the spec's augmented names).
    measurement : fingerprint of the measurement model (:func:`fingerprint`).
    model : small learned state of the model beyond the particles, JSON numbers (the
        log-posterior of the likelihood scale with ``learn_scale``); empty otherwise.
    """

    particles: FloatArray
    logw: FloatArray
    t: int
    rng: dict[str, Any]
    config: dict[str, Any]
    names: tuple[str, ...]
    measurement: str
    model: dict[str, list[float]] = field(default_factory=dict)


def fingerprint(m: MeasurementModel) -> str:
    """A short hash of the measurement model's numbers (detects a swapped model)."""
    h = hashlib.sha256()
    for a in (m.basis, m.lam, np.array([m.s2, m.nu])):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _header(s: TrackerState) -> dict[str, Any]:
    return {"format": FORMAT, "t": s.t, "rng": s.rng, "config": s.config,
            "names": list(s.names), "measurement": s.measurement,
            "shape": list(s.particles.shape), "n_logw": int(s.logw.size),
            "model": s.model}


def encode(s: TrackerState) -> bytes:
    """The state as bytes (see the module doc)."""
    head = json.dumps(_header(s), separators=(",", ":")).encode()
    x = np.ascontiguousarray(s.particles, dtype="<f8")
    w = np.ascontiguousarray(s.logw, dtype="<f8")
    return b"".join((MAGIC, len(head).to_bytes(8, "little"), head, x.tobytes(), w.tobytes()))


def decode(data: bytes) -> TrackerState:
    """Inverse of :func:`encode`; ``ValueError`` for bytes that are not a tracker state."""
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + 8:
        raise ValueError("not a tracker state (bad magic bytes)")
    i = len(MAGIC)
    n = int.from_bytes(data[i:i + 8], "little")
    try:
        head = json.loads(data[i + 8:i + 8 + n])
    except ValueError as exc:
        raise ValueError(f"tracker state header unreadable: {exc}") from exc
    if head.get("format") != FORMAT:
        raise ValueError(f"tracker state format {head.get('format')!r}, expected {FORMAT!r}")
    shape, n_w = tuple(int(v) for v in head["shape"]), int(head["n_logw"])
    start = i + 8 + n
    n_x = int(np.prod(shape))
    if len(data) != start + 8 * (n_x + n_w):
        raise ValueError(f"tracker state has {len(data)} bytes, expected "
                         f"{start + 8 * (n_x + n_w)}")
    x = np.frombuffer(data, dtype="<f8", count=n_x, offset=start).reshape(shape)
    w = np.frombuffer(data, dtype="<f8", count=n_w, offset=start + 8 * n_x)
    return TrackerState(particles=x.astype(np.float64), logw=w.astype(np.float64),
                        t=int(head["t"]), rng=head["rng"], config=head["config"],
                        names=tuple(head["names"]), measurement=str(head["measurement"]),
                        model=head.get("model", {}))


def save_npz(s: TrackerState, path: str | Path) -> Path:
    """Write the state to ``path`` (.npz, no pickle, atomic replace); return the path."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    buf = io.BytesIO()
    np.savez(buf, format=np.array(FORMAT), particles=s.particles, logw=s.logw,
             t=np.array(s.t), rng=np.array(json.dumps(s.rng)),
             config=np.array(json.dumps(s.config, sort_keys=True)),
             names=np.array(s.names), measurement=np.array(s.measurement),
             model=np.array(json.dumps(s.model)))
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, p)
    return p


def load_npz(path: str | Path) -> TrackerState:
    """Read a file written by :func:`save_npz`; ``ValueError`` if it is not one."""
    with np.load(Path(path), allow_pickle=False) as z:
        fmt = str(z["format"]) if "format" in z else ""
        if fmt != FORMAT:
            raise ValueError(f"{path}: not a tracker checkpoint (format {fmt!r})")
        return TrackerState(particles=z["particles"], logw=z["logw"], t=int(z["t"]),
                            rng=json.loads(str(z["rng"])),
                            config=json.loads(str(z["config"])),
                            names=tuple(str(n) for n in z["names"]),
                            measurement=str(z["measurement"]),
                            model=json.loads(str(z["model"])) if "model" in z else {})
