"""Fixtures shared by the tracker tests: the demonstrator spec and the analytic stand-in."""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

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
def one_blas_thread() -> Iterator[None]:
    """Every test runs with one BLAS thread, as ``make test`` (``OMP_NUM_THREADS=1``), the
    tracker's run, the study's workers and the service do: a bare ``pytest`` then gives the
    same numbers (with two threads OpenBLAS may sum a product in another order, and the
    bit-for-bit tests compare runs made apart)."""
    from formtwin._threads import single_blas_thread

    with single_blas_thread():
        yield


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


#: an OpenBLAS kernel other than the one this CPU would pick, that runs on any CPU of the
#: architecture (OPENBLAS_CORETYPE of the wheels' DYNAMIC_ARCH OpenBLAS)
OTHER_KERNEL = {"x86_64": "Sandybridge", "AMD64": "Sandybridge", "aarch64": "ARMV8"}
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def tutorial_fit(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """docs/tutorials/live-line.md's fit line (``formtwin metamodel fit`` of the bundled
    DOE with its 5-fold calibration, ~55 s), run as written in a scratch folder whose
    ``src`` links to the repository's, in a process whose OpenBLAS runs another kernel than
    this CPU's (where one is known). Shared by the tutorial's test (which goes on with the
    service) and test_same_twin's refit under another kernel, so the fit is made once:
    both tests use this fixture, and ``GROUPS`` keeps them on one worker.

    The process keeps the held-out predictions of the calibration's folds (the
    ``CrossValidation`` its ``cross_validate`` returned, as ``cv.npz`` in the folder; the
    command runs unchanged): test_same_twin builds another estimate of the residual
    statistics from them instead of fitting other folds again.

    Returns ``folder`` (the scratch folder, ``out/mm.npz`` in it), ``returncode``,
    ``stderr``, ``kernel`` (the kernel asked for, None: the CPU's) and ``kernels``
    (the OpenBLAS kernels the fitting process ran, from threadpoolctl)."""
    from service_fixtures import doc_commands

    doc = REPO / "docs" / "tutorials" / "live-line.md"
    fit = doc_commands(doc, "<!-- the block below is run by tests/test_service_docs.py -->")[0]
    argv = shlex.split(fit)
    assert argv[:3] == ["formtwin", "metamodel", "fit"], fit
    folder = tmp_path_factory.mktemp("tutorial")
    (folder / "src").symlink_to(REPO / "src")
    kernel = OTHER_KERNEL.get(platform.machine())
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    if kernel is not None:
        env["OPENBLAS_CORETYPE"] = kernel
    # the command, its folds' predictions kept, then the kernels its OpenBLAS ran (on the
    # last line of stdout)
    code = ("import json, sys\n"
            "import numpy as np\n"
            "import formtwin.metamodel.validate\n"
            "validate = sys.modules['formtwin.metamodel.validate']  # not the function\n"
            "from formtwin.cli import main\n"
            "def keep(*args, made=validate.cross_validate, **kwargs):\n"
            "    cv = made(*args, **kwargs)\n"
            "    np.savez('cv.npz', inputs=cv.inputs, curves=cv.curves, angles=cv.angles,\n"
            "             predicted_curves=cv.predicted_curves, fold=cv.fold,\n"
            "             predicted_angles=cv.predicted_angles)\n"
            "    return cv\n"
            "validate.cross_validate = keep\n"
            "rc = main()\n"
            "from threadpoolctl import threadpool_info\n"
            "print(json.dumps([i.get('architecture') for i in threadpool_info() "
            "if i.get('internal_api') == 'openblas']))\n"
            "sys.exit(rc)\n")
    run = subprocess.run([sys.executable, "-c", code, *argv[1:]], cwd=folder, env=env,
                         capture_output=True, text=True, timeout=900, check=False)
    kernels = json.loads(run.stdout.strip().splitlines()[-1]) if run.returncode == 0 else []
    return {"folder": folder, "returncode": run.returncode, "stderr": run.stderr,
            "stdout": run.stdout, "kernel": kernel, "kernels": kernels}


@pytest.fixture(scope="session")
def analytic_mm(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    """The default metamodel fitted to 600 runs of the analytic stand-in (the optimised
    Latin hypercube of seed 11, ~20 s with the fit) and its file: the study's tests and
    the sensor study's share it (``SHARED``: on one worker)."""
    from formtwin.doe import latin_hypercube, run_design
    from formtwin.metamodel import Metamodel
    from formtwin.physics.analytic import AnalyticBending

    spec = load_spec()
    folder = tmp_path_factory.mktemp("analytic_mm")
    data = run_design(AnalyticBending(spec), latin_hypercube(spec, 600, seed=11),
                      folder / "doe.h5", executor="serial")
    mm = Metamodel().fit(data)
    return mm, mm.save(folder / "mm.npz")


#: the long tests (seconds of one worker in ``make test``'s two-worker run, from
#: ``pytest --durations``; keys are node ids without the ``tests/`` folder; a shared
#: fixture's setup counted in its first test). ``pytest -n 2 --dist loadgroup`` hands the
#: workers one unit (a test, or a group below) at a time in the order of the collection:
#: the longest first, so that the two end within a short test of each other (a
#: longest-first schedule) instead of one waiting on the other
LONG_TESTS = {
    # tutorial_fit: the tutorial's fit (~75 s under the other kernel, in the first test's
    # setup) and what each test does with it
    "test_same_twin.py::test_a_refit_under_another_blas_kernel_is_the_same_twin": 77,
    "test_service_docs.py::test_docs_quick_start_check_passes": 33,
    # analytic_mm: the 600-run metamodel (~15 s, in the first test's setup) and the studies
    "test_sensor_study.py::test_gauge_pins_the_thickness_and_the_camera_calibrates": 20,
    "test_study.py::test_quick_study_end_to_end": 27,
    "test_study.py::test_cached_runs_of_other_settings_are_made_again": 2,
    "test_study.py::test_study_is_reproducible_from_its_seed": 2,
    "test_learn_mu.py::test_a_study_of_series_4_and_7_runs_and_reports": 5,
    "test_study.py::test_cli_quick_study_on_the_embedded_default": 65,
    "test_physics_calculix.py::test_coarse_two_stage_run_is_flap_bending": 34,
    "test_service_mqtt.py::test_sigkill_restarts_lose_nothing_and_double_nothing": 39,
    "test_howto_connect_press.py::test_howto_connect_press_runs_as_written": 38,
    "test_own_process.py::test_howto_chain_runs_as_documented": 34,
    "test_service_sensors_mqtt.py::"
    "test_sigkill_with_sensor_messages_loses_nothing_and_doubles_nothing": 35,
    "test_learn_mu.py::test_learned_mu_moves_to_the_truth_and_beats_the_midrange": 24,
    "test_defaults.py::test_bundled_doe_is_the_paper_design_over_the_current_physics_model": 22,
    "test_monitoring.py::test_in_control_runs_give_the_same_draws_with_their_true_states": 14,
    # line_config: the monitor's calibration (~9 s) and the runs charted with it
    "test_monitoring.py::test_step_in_a_state_mean_is_detected": 11,
    "test_monitoring.py::test_model_mismatch_raises_the_mismatch_alarm": 2,
    "test_examples.py::test_tracking_example_estimates_the_observable_components": 18,
    "test_service_opcua.py::test_docs_simulated_press_block_runs_as_written": 17,
    "test_service_page.py::test_live_page_in_chromium": 17,
    "test_service_opcua.py::test_serve_from_opcua_with_a_server_restart": 14,
    "test_service_health.py::"
    "test_matched_model_raises_no_mismatch_over_2000_products_series_6": 14,
    "test_control_study.py::test_control_study_on_the_analytic_stand_in": 8,
    "test_service_alarms.py::test_calibrated_charts_are_fixed_with_the_store": 12,
    # below the 25 slowest of that run (under 11.6 s): their earlier figures, at most 11
    "test_service_health.py::"
    "test_matched_model_raises_no_mismatch_over_2000_products_series_1": 11,
    "test_service_page_sensors.py::"
    "test_page_shows_camera_against_prediction_and_last_values": 11,
    "test_own_process.py::test_fresh_serve_after_check_stores_only_its_own_topic": 11,
    "test_same_twin.py::test_calibrate_command_stores_a_calibration_the_tracker_uses": 10,
    "test_service_page_health.py::test_mismatch_banner_in_chromium": 10,
    "test_doe.py::test_runs_on_a_real_dask_cluster": 10,
    "test_service_mqtt.py::test_password_and_tls": 10,
    "test_service_page_alarms.py::test_page_shows_charts_and_alarms_and_acknowledges": 10,
    "test_service_page_health.py::test_serve_check_exits_nonzero_with_the_message": 10,
    "test_physics_determinism.py::test_fresh_compile_equals_cached_code": 8,
    "test_guided.py::test_bending_proposal_gives_the_bootstrap_posterior_with_a_larger_ess"
    "[True]": 6,
    "test_guided.py::test_bending_proposal_gives_the_bootstrap_posterior_with_a_larger_ess"
    "[False]": 6,
}
#: tests that must run one after the other on one worker: they share a costly module fixture
#: (test file -> fixture)
GROUPS = {"test_monitoring.py": "line_config", "test_guided.py": "bootstrap"}
#: session fixtures that tests of several files share: their tests run on one worker
SHARED = ("tutorial_fit", "analytic_mm")


def _unit(item: pytest.Item) -> str:
    """The scheduling unit of an item: its group if it uses a shared session fixture or a
    grouped module fixture."""
    for shared in SHARED:
        if shared in getattr(item, "fixturenames", ()):
            return shared
    fixture = GROUPS.get(item.path.name)
    if fixture is not None and fixture in getattr(item, "fixturenames", ()):
        return f"{item.path.name}:{fixture}"
    return item.nodeid


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Order the collection longest unit first (a group's length is the sum of its tests',
    other tests keep their order) and mark each group with ``xdist_group``, so that
    ``--dist loadgroup`` keeps a group on one worker."""
    seconds: dict[str, float] = {}
    for item in items:
        key = item.nodeid.removeprefix("tests/")
        unit = _unit(item)
        seconds[unit] = seconds.get(unit, 0.0) + LONG_TESTS.get(key, 0.0)
        if unit != item.nodeid:
            item.add_marker(pytest.mark.xdist_group(unit.replace(":", "-")))
    first = {unit: k for k, unit in reversed(list(enumerate(map(_unit, items))))}
    items.sort(key=lambda item: (-seconds[_unit(item)], first[_unit(item)]))
