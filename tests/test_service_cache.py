"""A new store reuses the chart calibration and measurement model that an earlier store
with the same inputs computed (kept in the cache folder by a digest of those inputs), and
computes them afresh when any input differs."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from formtwin.monitoring.calibrate import ChartDesign
from formtwin.service import alarms, runtime
from formtwin.service.alarms import MonitorSource, ServiceMonitor, monitor_config
from formtwin.service.cache import computing, default_dir, entry
from formtwin.service.runtime import ServiceSettings, measurement_path, open_processor
from formtwin.service.store import Store
from formtwin.tracker import TrackerConfig

SETTINGS = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3))
DESIGN = ChartDesign(warmup=20, phase1=30, glr=False)  # the GLR tables: seconds, not needed here


def _refuse(*_: Any, **__: Any) -> Any:
    raise AssertionError("computed again although kept in the cache")


def test_a_new_store_reuses_what_an_earlier_one_computed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cache = tmp_path / "cache"
    source = MonitorSource(runs=1, products=120, design=DESIGN, seed=3, cache=str(cache))
    first = open_processor(tmp_path / "a" / "s.sqlite", SETTINGS, cache=cache)
    config = monitor_config(first.store, first.tracker, source)
    ServiceMonitor(first.store, config, str(cache))
    first_clear = first.store.get_meta("alarm_clear_after")
    first.close()
    kept = sorted(p.name for p in cache.iterdir() if not p.name.startswith("."))  # no locks
    assert [k.split("-")[0] for k in kept] == ["clear", "measurement", "monitor"]
    # a second, new store: nothing simulated, nothing built; the same numbers
    monkeypatch.setattr(alarms, "in_control_runs", _refuse)
    monkeypatch.setattr(runtime, "build_measurement", _refuse)
    monkeypatch.setattr(alarms, "clear_after", _refuse)
    second = open_processor(tmp_path / "b" / "s.sqlite", SETTINGS, cache=cache)
    again = monitor_config(second.store, second.tracker, source)
    assert again.to_json() == config.to_json()
    assert second.store.get_meta("monitor_config") == config.to_json()
    ServiceMonitor(second.store, again, str(cache))
    assert second.store.get_meta("alarm_clear_after") == first_clear
    assert measurement_path(tmp_path / "b" / "s.sqlite").read_bytes() == \
        measurement_path(tmp_path / "a" / "s.sqlite").read_bytes()
    # another input (the runs' seed, the tracker's settings): another key, computed
    with pytest.raises(AssertionError, match="computed again"):
        monitor_config(Store(tmp_path / "c.sqlite"), second.tracker,
                       dataclasses.replace(source, seed=4))
    other = ServiceSettings(tracker=TrackerConfig(n_particles=64, n_mc=1000, seed=3,
                                                  sensor_noise=1.0))
    with pytest.raises(AssertionError, match="computed again"):
        open_processor(tmp_path / "d" / "s.sqlite", other, cache=cache)
    # a damaged entry is computed again, not trusted
    (cache / kept[2]).write_text("{not json", encoding="utf-8")
    with pytest.raises(AssertionError, match="computed again"):
        monitor_config(Store(tmp_path / "e.sqlite"), second.tracker, source)
    second.close()
    assert entry(cache, "monitor-config", {"x": 1}, ".json").parent == cache


def test_default_folder_follows_the_environment(monkeypatch: pytest.MonkeyPatch,
                                                tmp_path: Path) -> None:
    monkeypatch.setenv("FORMTWIN_CACHE", str(tmp_path / "x"))
    assert default_dir() == tmp_path / "x"
    monkeypatch.delenv("FORMTWIN_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "y"))
    assert default_dir() == tmp_path / "y" / "formtwin"


#: a second process that takes the lock of an entry, says so, and writes the entry after
#: a pause (argv: the entry's path, the pause in seconds)
HOLDER = """
import sys, time
from pathlib import Path
from formtwin.service.cache import computing, write_atomic
path = Path(sys.argv[1])
with computing(path):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
    write_atomic(path, b"result of the first")
"""


def _holder(path: Path, pause: float) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(path), str(pause)],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_process_waits_for_the_entry_the_first_computes(tmp_path: Path) -> None:
    """Two services computing the same entry at once: the second waits for the first's
    result (and finds it) instead of computing it again; a holder killed mid-way releases
    the lock (the next one computes it); no cache, no lock."""
    path = entry(tmp_path / "cache", "monitor-config", {"seed": 1}, ".json")
    first = _holder(path, 1.0)
    t0 = time.perf_counter()
    with computing(path):
        waited = time.perf_counter() - t0
        assert path.read_bytes() == b"result of the first"
    assert waited > 0.5, waited
    assert first.wait(timeout=30) == 0
    # killed while it holds the lock: the lock goes with the process, nothing is written
    other = entry(tmp_path / "cache", "monitor-config", {"seed": 2}, ".json")
    killed = _holder(other, 60.0)
    killed.kill()
    killed.wait(timeout=30)
    t0 = time.perf_counter()
    with computing(other):
        assert time.perf_counter() - t0 < 30 and not other.exists()
    with computing(None):
        pass
