"""The examples run and give the numbers their docstrings promise."""

from __future__ import annotations

import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).parents[1] / "examples"


def _load(name: str):  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_tracking_example_estimates_the_observable_components() -> None:
    score = _load("track_a_production_run").main(n_products=200, n_particles=300)
    assert len(score) == 12  # 7 state, 3 parameters, 2 angles
    assert score["punch_end_distance"] < 0.5
    assert score["press_stiffness"] < 0.5
    assert all(v < 3.0 for v in score.values()), score
