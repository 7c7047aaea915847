"""The mismatch chart's health level that follows the line (``health_level``): on a synthetic
health series with a known transient, the level lags a ramp by the EWMA's closed-form lag,
the transient raises no alarm, a sudden drop after it is still seen at once, and a drop
that persists stays signalled (the level pauses while its chart is in alarm)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.special import ndtri

from formtwin.monitoring.charts import Cusum, cusum_h
from formtwin.monitoring.incontrol import InControl, Reference
from formtwin.monitoring.monitor import Alarm, Monitor, MonitorConfig

#: the ESS of the pooled calibration lines: N(10, 1); a line's scores against it
POOLED = Reference(tuple(10.0 + ndtri((np.arange(5000) + 0.5) / 5000)), "low")
N, RAMP, DROP = 2000, 600, 3.0


def _config(level: float | None, warmup: int = 20, phase1: int = 100) -> MonitorConfig:
    """ESS on a mismatch CUSUM (k 1, ARL0 1e7) about its score's level 0 (the calibration
    lines'), the score's AR model AR(0) with sigma 1."""
    return MonitorConfig({}, {"ess": POOLED}, {"ess": InControl(0.0, 1.0)},
                         mismatch=Cusum(1.0, cusum_h(1.0, 1e7, two_sided=False), "high"),
                         warmup=warmup, phase1=phase1, health_level=level)


def _ess(drop_at: int | None = None, seed: int = 4) -> np.ndarray:
    """A line whose ESS falls from the calibration lines' level 10 to 9 over its first
    ``RAMP`` products (the filter's health transient), then stays; N(., 1) about it;
    ``DROP`` lower from ``drop_at`` on (a mismatch)."""
    rng = np.random.default_rng(seed)
    i = np.arange(N)
    ess = 10.0 - np.minimum(i, RAMP) / RAMP + rng.standard_normal(N)
    return ess - (DROP * (i >= drop_at) if drop_at is not None else 0.0)


def _excursion() -> np.ndarray:
    """:func:`_ess` with a drop of ``DROP`` for products 1000-1029 only."""
    ess = _ess()
    ess[1000:1030] -= DROP
    return ess


def _run(config: MonitorConfig, ess: np.ndarray) -> tuple[list[Alarm], list[float], Monitor]:
    mon, levels, alarms = Monitor(config), [], []
    for i, v in enumerate(ess):
        alarms += mon.update_values({"ess": float(v)}, i)
        levels.append(mon.means["ess"])
    return alarms, levels, mon


@pytest.mark.parametrize("lam", [0.01, 0.02])
def test_health_level_follows_a_transient_and_still_sees_a_drop(lam: float) -> None:
    """The ESS transient moves the line's score (against the calibration lines' N(10, 1))
    from a mean of 0 to 1 at 1 / 600 per product. Fixed level: the mean reaches the
    CUSUM's k = 1, it random-walks and alarms again and again. Followed level: an EWMA
    lags a ramp of slope ``s`` by ``s (1 - lam) / lam`` (0.17 at lam 0.01, 0.08 at 0.02),
    well below ``k``: no alarm in 2000 products; after the ramp the level settles at 1
    (within 4 of its std ``sqrt(lam / (2 - lam))``). A drop of 3 after the transient
    moves the level by at most ``3 lam`` per product and is seen within 7 products: the
    score is capped at ``Phi^-1(1 - 1 / 10^4)`` = 3.72 by the 5000 reference values, so
    the CUSUM climbs ~1.7 per product to its limit 7.24."""
    ess = _ess()
    fixed, _, _ = _run(_config(None), ess)
    assert len([a for a in fixed if a.index >= RAMP]) > 5
    alarms, levels, _ = _run(_config(lam), ess)
    assert alarms == []
    slope = 1.0 / RAMP
    lag = slope * (RAMP - 1) - levels[RAMP - 1]  # the score's mean at RAMP - 1, less the level
    sd = float(np.sqrt(lam / (2.0 - lam)))
    assert abs(lag - slope * (1.0 - lam) / lam) < 4.0 * sd
    assert abs(levels[-1] - 1.0) < 4.0 * sd
    drop, _, _ = _run(_config(lam), _ess(drop_at=1500))
    assert drop and drop[0].chart == "mismatch" and 1500 <= drop[0].index <= 1506


def test_a_persistent_mismatch_stays_signalled() -> None:
    """ESS 3 lower from product 1000 to the end. A level that kept following would move up
    to 0.03 per product towards the dropped score and, within ~100 products, leave less
    than the CUSUM's ``k`` between them: the alarms would stop. The level pauses from each
    alarm until the chart has been quiet for 1 / 0.01 = 100 products, which a persistent
    mismatch never is: the level stays where it was at the first alarm and the chart
    signals in every 50-product window to the end."""
    alarms, levels, _ = _run(_config(0.01), _ess(drop_at=1000))
    first = min(a.index for a in alarms if a.index >= 1000)
    assert 1000 <= first <= 1006
    assert levels[-1] == levels[first - 1]
    hit = {a.index // 50 for a in alarms if a.index >= 1000}
    assert hit == set(range(1000 // 50, N // 50))


def test_health_level_resumes_after_a_short_excursion() -> None:
    """A drop of 3 for 30 products only: alarmed, then the level is held for the 100
    products after the last alarm (exactly), then follows the line again."""
    alarms, levels, _ = _run(_config(0.01), _excursion())
    last = max(a.index for a in alarms)
    assert 1000 <= min(a.index for a in alarms) and last < 1040
    assert len(set(levels[last - 1:last + 100])) == 1
    assert levels[last + 100] != levels[last + 99]


def test_health_level_starts_from_the_calibration_lines_level() -> None:
    """A line that fits worse than the calibration lines from its first product (a wrong
    model: ESS 3 lower throughout) is signalled in the first products charted: the level
    starts at the calibration lines' and follows only once charting has started."""
    ess = _ess(drop_at=0)
    alarms, levels, _ = _run(_config(0.01), ess)
    assert levels[119] == 0.0
    assert alarms and 120 <= alarms[0].index <= 127  # h / (3 - k) = 3.6 products on average


@pytest.mark.parametrize("split", [900, 1060])
def test_health_level_is_restored_with_the_monitor_state(split: int) -> None:
    """The followed level and its pause are part of the monitor's state and the config's
    JSON: a monitor restored mid-line (before an excursion, or while its level is held
    after it) continues bit for bit."""
    config, ess = _config(0.01), _excursion()
    whole, _, mon = _run(config, ess)
    assert MonitorConfig.from_json(config.to_json()).health_level == 0.01
    first = Monitor(config)
    alarms = [a for i, v in enumerate(ess[:split]) for a in first.update_values({"ess": v}, i)]
    second = Monitor(MonitorConfig.from_json(config.to_json()),
                     json.loads(json.dumps(first.state())))
    alarms += [a for i, v in enumerate(ess[split:], split)
               for a in second.update_values({"ess": float(v)}, i)]
    assert alarms == whole and second.state() == mon.state()


def test_health_level_is_checked() -> None:
    with pytest.raises(ValueError, match="health_level"):
        _config(1.5)
    with pytest.raises(ValueError, match="health_level"):
        _config(0.0)
