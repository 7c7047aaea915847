"""The embedded default: the bundled DOE matches the current spec and physics model."""

from __future__ import annotations

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
    # the line's sensors ([[sensor]], last in the file) do not enter a physics run
    text = spec.text[:spec.text.index("\n[[sensor]]")] if spec.sensors else spec.text
    assert data.spec.text == text, "the bundled DOE was made with another spec"
    assert data.model_version == physics_model("bending").version, (
        "the physics model changed since the bundled DOE was made: regenerate it")
    np.testing.assert_array_equal(data.inputs, paper_design(spec))
    assert data.ok.mean() >= 0.99
    assert set(data.reason[~data.ok]) <= {r for r in data.reason if r}


def test_unknown_physics_model_is_named() -> None:
    with pytest.raises(ValueError, match="'fem' unknown; known: bending, analytic"):
        physics_model("fem")
    assert default_doe("bending", cache=bundled_doe("bending").parent).n == 7048
