"""A tracker's state as bytes (in memory) or as a checkpoint file, restored bit for bit.

The state is the particles, their log-weights, the step count, the RNG state, the config
and the names of the estimated quantities, plus a fingerprint of the measurement model
(a restore with a different one is logged) and the model's learned state beyond the
particles (``model``: named entries, each a short list of JSON numbers or a float64
array). Two encodings of the same content:

* :func:`encode` / :func:`decode`: compact bytes (the service stores them in its SQLite
  transaction), version 2 (:data:`MAGIC`): the 8 magic bytes, an 8-byte little-endian
  header length, a JSON header, then the arrays as raw little-endian float64 blocks (C
  order, ``8 * prod(shape)`` bytes each) one after the other, listed in the header's
  ``"arrays"`` as ``[name, shape]`` in their order: ``particles``, ``logw``, then the
  array entries of ``model`` (their names in the header's ``"model_arrays"``; the list
  entries stay in the header's ``"model"``). Version 1 (:data:`MAGIC_V1`: particles and
  log-weights as blocks, every ``model`` entry as JSON numbers) is still read, its numbers
  kept exactly;
* :func:`save_npz` / :func:`load_npz`: an ``.npz`` file (no pickle), atomically replaced;
  ``model``'s arrays are entries ``model/NAME``, its lists one JSON entry ``model``.
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

#: format tag of both encodings (version 1's bytes: :data:`FORMAT_V1`)
FORMAT = "formtwin.tracker/2"
FORMAT_V1 = "formtwin.tracker/1"
#: first bytes of :func:`encode`'s output (version 1's: :data:`MAGIC_V1`)
MAGIC = b"FTWTRK2\n"
MAGIC_V1 = b"FTWTRK1\n"


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
    model : learned state of the model beyond the particles, named entries: short lists
        of numbers (the log-posterior of the likelihood scale with ``learn_scale``) or
        float64 arrays (the sandwich's sensitivities, the learned residual moment); empty
        when there is none.
    """

    particles: FloatArray
    logw: FloatArray
    t: int
    rng: dict[str, Any]
    config: dict[str, Any]
    names: tuple[str, ...]
    measurement: str
    model: dict[str, Any] = field(default_factory=dict)


def fingerprint(m: MeasurementModel) -> str:
    """A short hash of the measurement model's numbers (detects a swapped model)."""
    h = hashlib.sha256()
    for a in (m.basis, m.lam, np.array([m.s2, m.nu])):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _header(s: TrackerState, arrays: list[tuple[str, FloatArray]]) -> dict[str, Any]:
    return {"format": FORMAT, "t": s.t, "rng": s.rng, "config": s.config,
            "names": list(s.names), "measurement": s.measurement,
            "model": {k: v for k, v in s.model.items() if not isinstance(v, np.ndarray)},
            "model_arrays": [k for k, v in s.model.items() if isinstance(v, np.ndarray)],
            "arrays": [[k, list(a.shape)] for k, a in arrays]}


def encode(s: TrackerState) -> bytes:
    """The state as bytes (version 2, see the module doc)."""
    arrays = [("particles", s.particles), ("logw", s.logw)] + [
        (k, v) for k, v in s.model.items() if isinstance(v, np.ndarray)]
    head = json.dumps(_header(s, arrays), separators=(",", ":")).encode()
    blocks = [np.ascontiguousarray(a, dtype="<f8").tobytes() for _, a in arrays]
    return b"".join((MAGIC, len(head).to_bytes(8, "little"), head, *blocks))


def decode(data: bytes) -> TrackerState:
    """Inverse of :func:`encode` (and of version 1's); ``ValueError`` for bytes that are
    not a tracker state. The arrays are copies (the tracker changes particles in place)."""
    v1 = data.startswith(MAGIC_V1)
    if not (v1 or data.startswith(MAGIC)) or len(data) < len(MAGIC) + 8:
        raise ValueError("not a tracker state (bad magic bytes)")
    i = len(MAGIC)
    n = int.from_bytes(data[i:i + 8], "little")
    try:
        head = json.loads(data[i + 8:i + 8 + n])
    except ValueError as exc:
        raise ValueError(f"tracker state header unreadable: {exc}") from exc
    if head.get("format") != (FORMAT_V1 if v1 else FORMAT):
        raise ValueError(f"tracker state format {head.get('format')!r}, expected {FORMAT!r}")
    layout = [("particles", head["shape"]), ("logw", [head["n_logw"]])] if v1 \
        else head["arrays"]
    arrays, start = {}, i + 8 + n
    for name, shape in layout:
        size = int(np.prod(shape))
        if len(data) < start + 8 * size:
            raise ValueError(f"tracker state has {len(data)} bytes, expected at least "
                             f"{start + 8 * size} (its {name} {tuple(shape)})")
        arrays[str(name)] = np.frombuffer(data, dtype="<f8", count=size, offset=start
                                          ).reshape([int(v) for v in shape]).astype(np.float64)
        start += 8 * size
    if len(data) != start:
        raise ValueError(f"tracker state has {len(data)} bytes, expected {start}")
    model: dict[str, Any] = dict(head.get("model", {}))
    model.update({k: arrays[k] for k in head.get("model_arrays", [])})
    return TrackerState(particles=arrays["particles"], logw=arrays["logw"],
                        t=int(head["t"]), rng=head["rng"], config=head["config"],
                        names=tuple(head["names"]), measurement=str(head["measurement"]),
                        model=model)


def save_npz(s: TrackerState, path: str | Path) -> Path:
    """Write the state to ``path`` (.npz, no pickle, atomic replace); return the path."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    buf = io.BytesIO()
    lists = {k: v for k, v in s.model.items() if not isinstance(v, np.ndarray)}
    entries: dict[str, Any] = {
        "format": np.array(FORMAT), "particles": s.particles, "logw": s.logw,
        "t": np.array(s.t), "rng": np.array(json.dumps(s.rng)),
        "config": np.array(json.dumps(s.config, sort_keys=True)),
        "names": np.array(s.names), "measurement": np.array(s.measurement),
        "model": np.array(json.dumps(lists))}
    entries.update({f"model/{k}": v for k, v in s.model.items() if isinstance(v, np.ndarray)})
    np.savez(buf, **entries)
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, p)
    return p


def load_npz(path: str | Path) -> TrackerState:
    """Read a file written by :func:`save_npz` (either version); ``ValueError`` if it is
    not one."""
    with np.load(Path(path), allow_pickle=False) as z:
        fmt = str(z["format"]) if "format" in z else ""
        if fmt not in (FORMAT, FORMAT_V1):
            raise ValueError(f"{path}: not a tracker checkpoint (format {fmt!r})")
        model: dict[str, Any] = json.loads(str(z["model"])) if "model" in z else {}
        model.update({k.removeprefix("model/"): z[k] for k in z.files
                      if k.startswith("model/")})
        return TrackerState(particles=z["particles"], logw=z["logw"], t=int(z["t"]),
                            rng=json.loads(str(z["rng"])),
                            config=json.loads(str(z["config"])),
                            names=tuple(str(n) for n in z["names"]),
                            measurement=str(z["measurement"]), model=model)
