"""Shared benchmark plumbing: the model a fresh clone gets, and ``bench_NAME.json``.

Every benchmark script prints a table and writes
``{"figures": {...}, "model": {...}, "machine": {...}, "date": ...}`` through
:func:`write_result`; ``machine`` records the package versions and the machine's load
(other jobs share its cores). :func:`bundled_metamodel` is the fitted metamodel of the
physics DOE shipped with the package (``formtwin/data/metamodel_bending.npz``), so a
benchmark measures the product a user gets and never a file from outside the repository.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import subprocess
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import formtwin

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
#: where benchmarks cache what they build (git-ignored)
CACHE = ROOT / "benchmarks" / ".cache"
#: distributions whose versions every result records
PACKAGES = ("numpy", "scipy", "numba", "xarray", "h5py", "threadpoolctl", "paho-mqtt",
            "fastapi", "uvicorn")


def _git_commit() -> str | None:
    """The repository's HEAD commit, or None outside a git checkout."""
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, timeout=5, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def _cpu_and_blas() -> dict[str, Any]:
    """The CPU model (Linux: /proc/cpuinfo) and the BLAS libraries with their kernels."""
    from threadpoolctl import threadpool_info

    model = None
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    blas = [f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')}"
            for i in threadpool_info() if i.get("user_api") == "blas"]
    return {"cpu_model": model, "blas": blas}


def machine() -> dict[str, Any]:
    """Facts about the machine a figure was measured on: platform, package versions, load."""
    versions: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    load1, load5, load15 = os.getloadavg()
    return {
        "python": platform.python_version(),
        "formtwin": formtwin.__version__,
        "commit": _git_commit(),
        "packages": versions,
        "machine": platform.machine(),
        **_cpu_and_blas(),
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "system": platform.system(),
        "load_avg_1_5_15min": [round(load1, 2), round(load5, 2), round(load15, 2)],
    }


def file_digest(path: str | Path) -> str:
    """First 16 hex digits of the SHA-256 of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def bundled_metamodel(cache: Path = CACHE) -> tuple[Any, Path, dict[str, Any]]:
    """The metamodel of the bundled physics DOE, as a fresh clone gets it:
    ``(metamodel, file, description)``.

    The fitted file shipped with the package (:func:`formtwin.defaults.bundled_metamodel`;
    fitted into ``cache`` only if it is of another physics version). The description (for
    the result's ``model`` entry) names the physics model and its version, the DOE file and
    its hash, the fit's settings and id.
    """
    from formtwin.defaults import bundled_doe, default_metamodel
    from formtwin.metamodel import Metamodel

    doe = bundled_doe("bending")
    mm, path = default_metamodel(cache, "bending")
    assert mm.residuals is not None  # the bundled fit, or default_metamodel's own fit
    return mm, path, {
        "name": "metamodel of the bundled physics DOE",
        "physics": "bending",
        "physics_version": mm.model_version,
        "doe": str(doe.relative_to(ROOT)) if doe.is_relative_to(ROOT) else doe.name,
        "doe_sha256_16": file_digest(doe),
        "metamodel": repr(Metamodel()),
        "fit_id": mm.fit_id,
        "residual_rule": mm.residuals.rows,
        "residual_runs": mm.residuals.n,
        "metamodel_file": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT)
        else str(path),
    }


def study_metamodel_info(mm: Any, path: str | Path) -> dict[str, Any]:
    """The ``model`` entry of a result measured on a study folder's metamodel ``mm``
    (fitted by ``formtwin study`` on the bundled physics DOE, file ``path``)."""
    return {"name": "metamodel of a study folder (formtwin study on the bundled physics DOE)",
            "physics": "bending", "physics_version": mm.model_version,
            "metamodel": repr(mm), "metamodel_file": str(path),
            "metamodel_sha256_16": file_digest(path)}


def write_result(name: str, figures: dict[str, Any], directory: str | Path | None = None,
                 model: dict[str, Any] | None = None) -> Path:
    """Print ``figures`` as a table and save them as ``bench_<name>.json``; return the path.

    ``model`` describes the model the figures were measured on (see
    :func:`bundled_metamodel`); the machine's facts and load are added.
    """
    out_dir = Path(directory) if directory else ROOT / "benchmarks" / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"bench_{name}.json"
    doc: dict[str, Any] = {"figures": figures}
    if model is not None:
        doc["model"] = model
    doc["machine"] = machine()
    doc["date"] = datetime.now(UTC).isoformat(timespec="seconds")
    path.write_text(json.dumps(doc, indent=2, default=float) + "\n", encoding="utf-8")
    width = max(len(k) for k in figures) if figures else 0
    lines = [f"bench_{name}"] + [f"  {k:<{width}}  {v}" for k, v in figures.items()]
    if model is not None:
        doe = model.get("doe_sha256_16")
        where = f"DOE {doe}" if doe else f"file {model.get('metamodel_file')}"
        lines.append(f"  model: {model.get('name')} ({model.get('physics_version')}, {where})")
    print("\n".join(lines))  # benchmarks are run as scripts: printing is their job
    print(f"  -> {path}")
    return path
