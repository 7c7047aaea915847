"""Shared benchmark output: ``benchmarks/results/bench_NAME.json``.

Every benchmark script prints a table and writes
``{"figures": {...}, "machine": {...}, "date": ...}`` through :func:`write_result`.
"""

from __future__ import annotations

import json
import os
import platform
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

import formtwin


def machine() -> dict[str, Any]:
    """Facts about the machine a figure was measured on."""
    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "formtwin": formtwin.__version__,
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "system": platform.system(),
    }


def write_result(name: str, figures: dict[str, Any], directory: str | Path | None = None) -> Path:
    """Print ``figures`` as a table and save them as ``bench_<name>.json``; return the path."""
    out_dir = Path(directory) if directory else Path(__file__).resolve().parents[2] / \
        "benchmarks" / "results"
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"bench_{name}.json"
    doc = {"figures": figures, "machine": machine(),
           "date": datetime.now(UTC).isoformat(timespec="seconds")}
    path.write_text(json.dumps(doc, indent=2, default=float) + "\n", encoding="utf-8")
    width = max(len(k) for k in figures) if figures else 0
    lines = [f"bench_{name}"] + [f"  {k:<{width}}  {v}" for k, v in figures.items()]
    print("\n".join(lines))  # benchmarks are run as scripts: printing is their job
    print(f"  -> {path}")
    return path
