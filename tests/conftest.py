"""Fixtures shared by the tracker tests: the demonstrator spec and the analytic stand-in."""

from __future__ import annotations

import pytest

from formtwin.defaults import AnalyticModel
from formtwin.spec import ProcessSpec, load_spec


@pytest.fixture(scope="session")
def spec() -> ProcessSpec:
    return load_spec()


@pytest.fixture(scope="session")
def model(spec: ProcessSpec) -> AnalyticModel:
    """The analytic stand-in as a ProcessModel (test files may override ``model`` locally)."""
    return AnalyticModel(spec)
