"""The monitor's arrays and kernels (:mod:`formtwin.monitoring.bank`) against the scalar
charts they replace (``tests/monitor_reference.py``: one Python object per chart state):
on streams with steps, spikes, NaN values and heavy tails, every product's alarms, chart
statistics and the saved state are the same, bit for bit, and each loads the other's
state."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from monitor_reference import ScalarMonitor
from scipy.special import ndtri

from formtwin.monitoring.bank import ewma_limits
from formtwin.monitoring.charts import Cusum, Ewma, ewma_limit
from formtwin.monitoring.glr import Glr, level_signature
from formtwin.monitoring.incontrol import InControl, Reference
from formtwin.monitoring.monitor import Monitor, MonitorConfig

QUANTITIES = ("a", "b", "c", "angle")
HEALTH = ("loglik", "ess", "fit")


def _quantiles(rng: np.random.Generator, m: int) -> tuple[float, ...]:
    """Sorted in-control quantiles of a heavy-tailed residual (Student-t, 4 dof), with a
    tie (a zero-width span)."""
    q = np.sort(rng.standard_t(4, m) / math.sqrt(2.0))
    q[m // 2] = q[m // 2 + 1]
    return tuple(q)


def _config(per_line: bool = False, level: float | None = 0.02) -> MonitorConfig:
    rng = np.random.default_rng(1)
    quantities = {
        "a": InControl(1.0, 0.1, (0.8, 0.05), _quantiles(rng, 300)),
        "b": InControl(-2.0, 0.5, (0.6,)),
        "c": InControl(0.0, 1.0),
        "angle": InControl(None, 0.2, (0.85, -0.04), _quantiles(rng, 200)),
    }
    ref = Reference(tuple(10.0 + ndtri((np.arange(400) + 0.5) / 400)), "low")
    health = {"loglik": ref, "ess": Reference(tuple(np.round(rng.normal(5, 1, 300), 1)), "low"),
              "fit": Reference(tuple(rng.normal(0, 1, 250)), "high")}
    models = {"loglik": InControl(0.0, 1.0, (0.1,), _quantiles(rng, 100)),
              "ess": InControl(0.0 if per_line else None, 0.9)}
    return MonitorConfig(
        quantities, health, models, ewma=Ewma(0.2, 2.6), cusum=Cusum(0.5, 4.0),
        mismatch=Cusum(1.0, 3.0, "high"), warmup=5, phase1=30, cusum_on=("a", "b", "angle"),
        shewhart=3.2, widen={"b": {"ewma": 1.3, "cusum": 1.1}, "ess": {"mismatch": 1.2}},
        glr={"a": Glr(level_signature((0.8, 0.05)), 6.0, window=40, clip=3.0),
             "c": Glr((1.0, 0.3), 7.0, window=25)},
        health_per_line=per_line, health_level=level)


def _stream(n: int, seed: int) -> list[dict[str, float]]:
    """AR(1) quantities and health values with steps, spikes and NaN values."""
    rng = np.random.default_rng(seed)
    out, prev = [], np.zeros(len(QUANTITIES))
    for i in range(n):
        prev = 0.8 * prev + rng.standard_normal(len(QUANTITIES)) * [0.1, 0.5, 1.0, 0.2]
        shift = np.array([0.4, -1.5, 2.0, 0.3]) * (150 <= i < 260)
        v = dict(zip(QUANTITIES, (prev + [1.0, -2.0, 0.0, 88.0] + shift).tolist(),
                     strict=True))
        h = {"loglik": 10.0 + rng.standard_normal() - 3.0 * (300 <= i < 330),
             "ess": float(np.round(5.0 + rng.standard_normal(), 1)),
             "fit": rng.standard_normal() + 4.0 * (i % 97 == 0)}
        if i % 41 == 7:
            v["b"] = math.nan
        if i % 53 == 11:
            h["fit"] = math.nan
        if i % 67 == 3:
            v["c"] += 9.0  # a spike: the Shewhart limit, a GLR up-crossing
        if i == 400:
            h["loglik"] = -math.inf
        out.append({**v, **h})
    return out


@pytest.mark.parametrize(("per_line", "level"), [(False, 0.02), (True, None), (True, 0.05)])
def test_arrays_chart_as_the_scalar_charts_bit_for_bit(per_line: bool, level: float | None
                                                       ) -> None:
    config = _config(per_line, level)
    new, old = Monitor(config), ScalarMonitor(config)
    n_alarms = 0
    charts = set()
    for i, v in enumerate(_stream(600, seed=int(per_line) + 7)):
        a_new, a_old = new.update_values(v, i), old.update_values(v, i)
        assert a_new == a_old, i
        assert new.last == old.last, i
        n_alarms += len(a_new)
        charts.update(a.chart for a in a_new)
        if i % 50 == 0 or a_new:
            assert json.dumps(new.state()) == json.dumps(old.state()), i
    assert charts == {"ewma", "cusum", "glr", "shewhart", "mismatch"} and n_alarms > 20
    assert json.dumps(new.state()) == json.dumps(old.state())
    assert new.means == old.means


def test_each_loads_the_others_state_and_a_copy_is_independent() -> None:
    config, stream = _config(), _stream(500, seed=3)
    new, old = Monitor(config), ScalarMonitor(config)
    for i, v in enumerate(stream[:200]):
        new.update_values(v, i)
        old.update_values(v, i)
    saved = json.loads(json.dumps(old.state()))
    resumed, back = Monitor(config, saved), ScalarMonitor(config, new.state())
    twin, saved_new = new.copy(), new.save()
    for i, v in enumerate(stream[200:260], 200):
        new.update_values(v, i)
    new.restore(saved_new)  # back: the same numbers again
    assert json.dumps(new.state()) == json.dumps(twin.state())
    for i, v in enumerate(stream[200:], 200):
        a = old.update_values(v, i)
        assert resumed.update_values(v, i) == a == back.update_values(v, i), i
        assert new.update_values(v, i) == a
    assert json.dumps(resumed.state()) == json.dumps(old.state()) == json.dumps(back.state())
    assert twin.n == 200 and twin.state() == Monitor(config, saved).state()


def test_copies_chart_in_threads_as_one_alone() -> None:
    """Copies share no array that charting writes (states, work space): four copies
    charting the same stream in four threads at once raise the alarms of one monitor
    charting it alone."""
    from concurrent.futures import ThreadPoolExecutor

    config, stream = _config(), _stream(400, seed=5)
    alone, first = Monitor(config), Monitor(config)
    for i, v in enumerate(stream[:150]):
        alone.update_values(v, i)
        first.update_values(v, i)
    expected = [alone.update_values(v, i) for i, v in enumerate(stream[150:], 150)]
    copies = [first.copy() for _ in range(4)]
    written = [a for t in (first._work, first._out, first._buffers) for a in t]
    for c in copies:  # what charting writes: the states' buffers and the work space
        mine = [a for t in (c._work, c._out, c._buffers) for a in t]
        assert not any(np.shares_memory(a, b) for a in mine for b in written)

    def chart(mon: Monitor) -> list[tuple[object, ...]]:
        return [mon.update_values(v, i) for i, v in enumerate(stream[150:], 150)]

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(chart, copies))
    assert sum(len(a) for a in expected) > 5
    assert all(r == expected for r in results)


@pytest.mark.parametrize(("lam", "L"), [(0.2, 2.6), (0.05, 3.0), (1.0, 3.0), (0.5, 2.0)])
def test_ewma_limit_table_is_the_closed_form(lam: float, L: float) -> None:
    table = ewma_limits(lam, L)
    for i in [*range(1, table.size + 5), 10 * table.size + 3]:
        assert table[min(i, table.size) - 1] == ewma_limit(i, lam, L)


def test_load_kernels_compiles_what_charting_calls_and_leaves_the_monitor() -> None:
    """:func:`~formtwin.monitoring.bank.load_kernels` (a service's start) gives the kernels
    the signatures of the monitor's charted products, on a copy: the monitor is as new."""
    from formtwin.monitoring import bank

    config = _config()
    mon = Monitor(config)
    bank.load_kernels(mon)
    assert mon.n == 0 and json.dumps(mon.state()) == json.dumps(Monitor(config).state())
    kernels = (bank.reference_probabilities, bank.residual_probabilities, bank.chart_step)
    before = [list(k.signatures) for k in kernels]
    for i, v in enumerate(_stream(60, seed=2)):
        mon.update_values(v, i)
    assert mon.charting and [list(k.signatures) for k in kernels] == before
