"""The embedded default: the bundled DOE matches the current spec and physics model."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from formtwin.dataset import DoeDataset
from formtwin.defaults import bundled_doe, default_doe, physics_model
from formtwin.doe import paper_design
from formtwin.spec import load_spec


def test_bundled_doe_is_the_paper_design_over_the_current_physics_model() -> None:
    path = bundled_doe("bending")
    assert path.exists(), "regenerate: formtwin doe run --physics bending --out " + str(path)
    data = DoeDataset.load(path)
    spec = load_spec()
    # everything of the spec but the line's sensors ([[sensor]]) and the outputs' names
    # and units ([[output]], the two angles the DOE's runs have) enters a physics run
    def physics_part(text: str) -> dict[str, object]:
        return {k: v for k, v in tomllib.loads(text).items() if k not in ("sensor", "output")}

    assert physics_part(data.spec.text) == physics_part(spec.text), \
        "the bundled DOE was made with another spec"
    assert data.spec.output_names == spec.output_names
    assert data.model_version == physics_model("bending").version, (
        "the physics model changed since the bundled DOE was made: regenerate it")
    np.testing.assert_array_equal(data.inputs, paper_design(spec))
    assert data.ok.mean() >= 0.99
    assert set(data.reason[~data.ok]) <= {r for r in data.reason if r}


def test_unknown_physics_model_is_named() -> None:
    with pytest.raises(ValueError, match="'fem' unknown; known: bending, analytic"):
        physics_model("fem")
    assert default_doe("bending", cache=bundled_doe("bending").parent).n == 7048
