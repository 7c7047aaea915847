"""Fixtures shared by the tracker tests: the demonstrator spec and the analytic stand-in."""

from __future__ import annotations

import os
from collections.abc import Iterator

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


@pytest.fixture(scope="session", autouse=True)
def service_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The services the tests start keep their chart calibrations and measurement models in
    one folder of this test session (``serve --cache``'s default, ``$FORMTWIN_CACHE``), not
    in the user's cache: a later service with the same inputs reuses them, as in use.
    Under pytest-xdist the workers of one session share the folder (its entries are
    written by an atomic rename), so a calibration is made once per session, not per
    worker."""
    old = os.environ.get("FORMTWIN_CACHE")
    if os.environ.get("PYTEST_XDIST_WORKER"):  # basetemp is .../popen-gwN, one per worker
        folder = tmp_path_factory.getbasetemp().parent / "formtwin-cache"
        folder.mkdir(exist_ok=True)
    else:
        folder = tmp_path_factory.mktemp("formtwin-cache")
    os.environ["FORMTWIN_CACHE"] = str(folder)
    yield
    if old is None:
        del os.environ["FORMTWIN_CACHE"]
    else:
        os.environ["FORMTWIN_CACHE"] = old
