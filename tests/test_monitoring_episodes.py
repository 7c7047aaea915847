"""Alarm episodes (formtwin.monitoring.episodes): one per chart and variable from its first
signal until the chart has been quiet for its clear-after products; the clear-after from
the chart's run length under a persistent shift of its design size."""

from __future__ import annotations

import numpy as np
import pytest

from formtwin.monitoring.charts import (
    Alarm,
    Cusum,
    CusumState,
    Ewma,
    EwmaState,
    cusum_arl_two_sided,
    cusum_h,
)
from formtwin.monitoring.episodes import Episodes, clear_after, run_lengths
from formtwin.monitoring.glr import Glr, GlrState, level_signature
from formtwin.monitoring.incontrol import InControl
from formtwin.monitoring.monitor import Monitor, MonitorConfig


def _signal(i: int, chart: str = "cusum", stat: float = 6.0) -> Alarm:
    return Alarm("thickness", chart, i, stat, 5.0, "high")


def test_a_persistent_step_is_one_episode() -> None:
    """A 3-sigma step of an independent quantity from product 300 to the end: the charts
    signal again and again (they restart), and each chart has exactly one episode, raised
    at its first signal, counting every signal, never cleared."""
    cfg = MonitorConfig({"thickness": InControl(mean=0.0, sigma=1.0)}, warmup=0, phase1=0,
                        ewma=Ewma(0.2, 3.5), cusum=Cusum(0.5, cusum_h(0.5, 1e5)))
    mon = Monitor(cfg)
    eps = Episodes(clear_after(mon))
    y = np.random.default_rng(1).standard_normal(1300)
    y[300:] += 3.0
    signals, changes = [], []
    for i, v in enumerate(y):
        got = mon.update_values({"thickness": float(v)}, i)
        signals += got
        changes += eps.update(i, got)
    assert not [a for a in signals if a.index < 300]  # in control: quiet here
    for chart in ("ewma", "cusum"):
        mine = [a.index for a in signals if a.chart == chart]
        assert len(mine) > 100  # restarted after each signal: 1000 products, ~10 % signal
        raised = [c for c in changes if c.kind == "raised" and c.episode.chart == chart]
        assert [c.episode.first for c in raised] == [mine[0]]
        ep = eps.open[("thickness", chart)]
        assert (ep.first, ep.last, ep.signals, ep.cleared) == (mine[0], mine[-1], len(mine),
                                                               None)
        assert not [c for c in changes if c.kind == "cleared"]
        # reports: the raise, then at most one update per clear-after products
        reports = [c for c in changes if c.reported and c.episode.chart == chart]
        assert 2 <= len(reports) <= 1 + 1000 // eps.after("thickness", chart)


def test_excursion_quiet_excursion_is_two_episodes() -> None:
    eps = Episodes({"thickness/cusum": 20})
    events = {i: eps.update(i, [_signal(i)] if i in (*range(100, 105), 300, 301, 302)
                            else []) for i in range(400)}
    kinds = {i: [c.kind for c in ch] for i, ch in events.items() if ch}
    assert kinds == {100: ["raised"], 101: ["signal"], 102: ["signal"], 103: ["signal"],
                     104: ["signal"], 124: ["cleared"], 300: ["raised"], 301: ["signal"],
                     302: ["signal"], 322: ["cleared"]}
    first, second = events[124][0].episode, events[322][0].episode
    assert (first.first, first.last, first.signals, first.cleared) == (100, 104, 5, 124)
    assert (second.first, second.last, second.signals, second.cleared) == (300, 302, 3, 322)
    # one quiet product fewer: the second excursion continues the first
    eps = Episodes({"thickness/cusum": 197})
    for i in range(303):
        eps.update(i, [_signal(i)] if i in (*range(100, 105), 300, 301, 302) else [])
    ep = eps.open[("thickness", "cusum")]
    assert (ep.first, ep.last, ep.signals) == (100, 302, 8)


def test_episode_keeps_the_largest_ratio_and_state_round_trips() -> None:
    eps = Episodes({"thickness/cusum": 5, "model_mismatch": 1})
    eps.update(0, [_signal(0, stat=6.0)])
    eps.update(1, [_signal(1, stat=9.0), _signal(1, chart="ewma", stat=-7.5)])
    eps.update(2, [_signal(2, stat=7.0)])
    ep = eps.open[("thickness", "cusum")]
    assert (ep.ratio, ep.statistic, ep.limit) == (1.8, 9.0, 5.0)
    assert eps.open[("thickness", "ewma")].ratio == 1.5  # |statistic| / limit, low side
    assert eps.after("thickness", "ewma") == 5  # no own value: the largest
    assert eps.after("model_health", "model_mismatch") == 1  # by chart name
    again = Episodes(eps.clear_after, eps.state())
    for i in range(3, 12):
        sig = [_signal(i)] if i == 6 else []
        assert [(c.kind, c.episode) for c in eps.update(i, sig)] == \
            [(c.kind, c.episode) for c in again.update(i, sig)]
    assert eps.state() == again.state() and not eps.open


def test_run_lengths_are_the_charts_own() -> None:
    """The vectorised run lengths equal the charts' own updates on the same scores."""
    sig = level_signature((0.8,))
    charts = [(Ewma(0.2, 2.8), EwmaState()), (Cusum(0.5, 4.0), CusumState()),
              (Cusum(1.0, 3.0, sides="high"), CusumState()),
              (Glr(sig, h=6.0, window=30, clip=3.0), GlrState())]
    for chart, start in charts:
        got = run_lengths(chart, 0.7, runs=200, horizon=400, seed=5)
        rng = np.random.default_rng(5)
        want, st, alive = np.full(200, 401), [start] * 200, list(range(200))
        for t in range(1, 401):
            z = rng.standard_normal(len(alive)) + 0.7
            left = []
            for j, r in enumerate(alive):
                st[r], s = chart.update(st[r], float(z[j]))  # type: ignore[arg-type]
                if s.side:
                    want[r] = t
                else:
                    left.append(r)
            alive = left
            if not alive:
                break
        np.testing.assert_array_equal(got, want)


def test_clear_after_is_the_run_length_quantile_of_the_design_shift() -> None:
    """A CUSUM's run length under its design shift 2 k has the mean of Siegmund's ARL; the
    clear-after is its 99.9 % quantile, beyond the mean, and a wider limit (widen)
    lengthens it."""
    mon = Monitor(MonitorConfig({"x": InControl(0.0, 1.0)}, cusum=Cusum(0.5, 10.0)))
    got = clear_after(mon)
    assert set(got) == {"x/ewma", "x/cusum"}
    rl = run_lengths(Cusum(0.5, 10.0), 1.0, 4000, 5000)
    assert got["x/cusum"] == int(np.quantile(rl, 0.999, method="higher"))
    assert rl.mean() == pytest.approx(cusum_arl_two_sided(0.5, 10.0, 1.0), rel=0.05)
    assert got["x/cusum"] > 2 * rl.mean()
    wide = Monitor(MonitorConfig({"x": InControl(0.0, 1.0)}, cusum=Cusum(0.5, 10.0),
                                 widen={"x": {"cusum": 1.5}}))
    assert clear_after(wide)["x/cusum"] > got["x/cusum"]
    with pytest.raises(ValueError, match="clear_after"):
        Episodes({"x/cusum": 0})
