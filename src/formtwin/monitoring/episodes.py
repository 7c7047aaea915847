"""Alarm episodes: one alarm per chart and variable from its first signal until the chart
has been quiet, as alarm management has it (ANSI/ISA-18.2, EEMUA 191), instead of one per
signalling product.

A chart restarts after each signal (:mod:`~formtwin.monitoring.charts`), so a change that
persists makes it signal again and again (a force-sensor fault: 600 signals per 1000
products). An :class:`Episode` of a chart on a variable is

* **raised** by the chart's first signal;
* **active** while the chart keeps signalling: each signal updates its last signalling
  product, its number of signals and its largest ``|statistic| / limit``; an update is
  *reported* at most once per clear-after products (:class:`Change` ``updated``, else
  ``signal``: stored, not published);
* **cleared** (returned to normal) once the chart has been quiet for its clear-after number
  of products; a later signal raises a new episode.

Acknowledgement is an operator's act, stored with the episode by the service
(:mod:`formtwin.service.alarms`), not part of this state: it does not change when an
episode clears. An acknowledged episode that has cleared is closed.

**Clear-after** (:func:`clear_after`): between two signals of a restarted chart under a
change that persists lies one run length of the chart under that change. An episode clears
after the 99.9 % quantile of that run length for a persistent shift of the size the chart
is designed for: a CUSUM's ``2 k`` (``k`` is half the shift it is tuned to, Montgomery
ch. 9.1.3: 1 residual sigma for the states, the lasting residual shift of a 2-sigma step;
2 for the mismatch charts); the GLR the states' CUSUM's ``2 k`` (the same lasting shift);
an EWMA the shift at which its mean sits on its asymptotic limit, ``L sqrt(lam / (2 -
lam))`` (1.77 for ``lam`` 0.2 at an ARL0 of 1e7: it is given little of the false-alarm
budget and sees large shifts; at 1 sigma it signals every 200 products on average).
With the default design these are about 70 (CUSUM), 60 (GLR), 50 (EWMA) and 20 (mismatch)
products before widening (wider limits, longer gaps).
Why 99.9 %: a change of that size lasting 1000 products gives 30-100 gaps, so it stays one
episode with a probability of about 90-97 %; a smaller shift has longer gaps and may come
back as several episodes. Simulated on ``runs`` streams of independent N(shift, 1) scores
with the chart's own limits (widened ones included), seed fixed: the same store gets the
same values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.monitoring.charts import Alarm, Cusum, Ewma, ewma_limit
from formtwin.monitoring.glr import Glr, glr_advance
from formtwin.monitoring.monitor import Monitor

#: the quantile of the run length under a persistent shift after which an episode clears
QUANTILE = 0.999


@dataclass
class Episode:
    """One alarm episode of a chart on a variable.

    Attributes
    ----------
    variable, chart : what signals (:class:`~formtwin.monitoring.charts.Alarm`).
    side : the side of its first signal.
    first, last : the product (the caller's numbering: a product index, a store's seq) of
        its first and of its last signal.
    signals : signals so far.
    ratio : the largest ``|statistic| / limit`` of its signals; ``statistic``, ``limit``:
        that signal's.
    cleared : the product at which it cleared (``None``: active).
    quiet : products since its last signal.
    unreported : products since its last report (raised or updated).
    """

    variable: str
    chart: str
    side: str
    first: int
    last: int
    signals: int
    ratio: float
    statistic: float
    limit: float
    cleared: int | None = None
    quiet: int = 0
    unreported: int = 0

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe values (non-finite numbers as ``None``)."""
        return {k: None if isinstance(v, float) and not math.isfinite(v) else v
                for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Episode:
        """Inverse of :meth:`to_dict`."""
        nums = {k: math.nan if d[k] is None else float(d[k])
                for k in ("ratio", "statistic", "limit")}
        return cls(str(d["variable"]), str(d["chart"]), str(d["side"]), int(d["first"]),
                   int(d["last"]), int(d["signals"]), **nums,
                   cleared=None if d.get("cleared") is None else int(d["cleared"]),
                   quiet=int(d["quiet"]), unreported=int(d["unreported"]))


@dataclass(frozen=True)
class Change:
    """What one product did to an episode: ``kind`` raised, signal (a signal, not
    reported), updated (a signal, reported) or cleared; ``episode``: its state after it."""

    kind: str
    episode: Episode

    @property
    def reported(self) -> bool:
        """Whether the change is published (all but a plain ``signal``)."""
        return self.kind != "signal"


class Episodes:
    """The open episodes of a monitor's charts (pure: no storage).

    Parameters
    ----------
    clear_after : quiet products after which an episode clears, by ``"variable/chart"``
        (:func:`clear_after`) or by chart name; charts without one: the largest value.
    state : a state from :meth:`state` to continue from.

    Examples
    --------
    >>> eps = Episodes({"thickness/cusum": 3})
    >>> sig = [Alarm("thickness", "cusum", 0, 6.0, 5.0, "high")]
    >>> [[c.kind for c in eps.update(i, sig if i in (1, 2, 5, 9) else [])] for i in range(10)]
    [[], ['raised'], ['signal'], [], [], ['updated'], [], [], ['cleared'], ['raised']]
    """

    def __init__(self, clear_after: Mapping[str, int],
                 state: Mapping[str, Any] | None = None) -> None:
        if not clear_after or min(clear_after.values()) < 1:
            raise ValueError(f"clear_after {dict(clear_after)}: expected values >= 1")
        self.clear_after = dict(clear_after)
        self._default = max(self.clear_after.values())
        #: the active episodes by (variable, chart), oldest first
        self.open: dict[tuple[str, str], Episode] = {}
        if state is not None:
            for d in state["open"]:
                ep = Episode.from_dict(d)
                self.open[(ep.variable, ep.chart)] = ep

    def after(self, variable: str, chart: str) -> int:
        """Quiet products after which an episode of ``chart`` on ``variable`` clears."""
        got = self.clear_after.get(f"{variable}/{chart}", self.clear_after.get(chart))
        return self._default if got is None else got

    def update(self, product: int, signals: Sequence[Alarm]) -> list[Change]:
        """One charted product and its signals; the changes of episodes it made (cleared
        ones first, then by signal)."""
        worst: dict[tuple[str, str], Alarm] = {}
        for a in signals:
            key = (a.variable, a.chart)
            if key not in worst or _ratio(a) > _ratio(worst[key]):
                worst[key] = a
        changes = []
        for key, ep in list(self.open.items()):
            if key in worst:
                continue
            ep.quiet += 1
            ep.unreported += 1
            if ep.quiet >= self.after(*key):
                ep.cleared = product
                del self.open[key]
                changes.append(Change("cleared", replace(ep)))
        for key, a in worst.items():
            if key not in self.open:
                self.open[key] = Episode(a.variable, a.chart, a.side, product, product, 1,
                                         _ratio(a), a.statistic, a.limit)
                changes.append(Change("raised", replace(self.open[key])))
                continue
            ep = self.open[key]
            ep.last, ep.signals, ep.quiet = product, ep.signals + 1, 0
            ep.unreported += 1
            if _ratio(a) > ep.ratio:
                ep.ratio, ep.statistic, ep.limit = _ratio(a), a.statistic, a.limit
            kind = "signal"
            if ep.unreported >= self.after(*key):
                ep.unreported, kind = 0, "updated"
            changes.append(Change(kind, replace(ep)))
        return changes

    def state(self) -> dict[str, Any]:
        """JSON-safe state: the open episodes."""
        return {"open": [ep.to_dict() for ep in self.open.values()]}


def _ratio(a: Alarm) -> float:
    """``|statistic| / limit`` of a signal (NaN -> 0)."""
    r = abs(a.statistic) / a.limit if a.limit else math.nan
    return r if math.isfinite(r) else 0.0


def clear_after(monitor: Monitor, quantile: float = QUANTILE, runs: int = 4000,
                horizon: int = 5000, seed: int = 0) -> dict[str, int]:
    """Quiet products after which an episode of each of ``monitor``'s charts clears, by
    ``"variable/chart"``: the ``quantile`` of its run length for a persistent shift of its
    design size (module doc), simulated on ``runs`` streams (at most ``horizon``)."""
    c = monitor.config
    state_shift = 2.0 * c.cusum.k
    charts: dict[str, tuple[Ewma | Cusum | Glr, float]] = {}
    for n, (ewma, cusum, _) in monitor.charts.items():
        charts[f"{n}/ewma"] = (ewma, ewma.L * math.sqrt(ewma.lam / (2.0 - ewma.lam)))
        if n in monitor.with_cusum:
            charts[f"{n}/cusum"] = (cusum, state_shift)
    charts.update({f"{n}/glr": (g, state_shift) for n, g in monitor.glr_charts.items()})
    charts.update({f"{n}/mismatch": (m, 2.0 * m.k) for n, m in monitor.mismatch.items()})
    out = {}
    for key, (chart, shift) in charts.items():
        rl = run_lengths(chart, shift, runs, horizon, seed)
        out[key] = max(1, int(np.quantile(rl, quantile, method="higher")))
    return out


def run_lengths(chart: Ewma | Cusum | Glr, shift: float, runs: int, horizon: int,
                seed: int = 0) -> NDArray[np.int64]:
    """Run lengths (runs,) of ``chart`` from its start on independent N(``shift``, 1)
    scores (``horizon + 1``: no signal within ``horizon``); the charts' recursions of
    :mod:`~formtwin.monitoring.charts` and :mod:`~formtwin.monitoring.glr`, vectorised."""
    rng = np.random.default_rng(seed)
    out = np.full(runs, horizon + 1, dtype=np.int64)
    left = np.arange(runs)
    a, b = np.zeros(runs), np.zeros(runs)
    sums = np.zeros((runs, chart.window)) if isinstance(chart, Glr) else np.zeros((runs, 0))
    for t in range(1, horizon + 1):
        z = rng.standard_normal(left.size) + shift
        if isinstance(chart, Ewma):
            a = chart.lam * z + (1.0 - chart.lam) * a
            hit = np.abs(a) > ewma_limit(t, chart.lam, chart.L)
        elif isinstance(chart, Cusum):
            if chart.sides != "low":
                a = np.maximum(0.0, z - chart.k + a)
            if chart.sides != "high":
                b = np.maximum(0.0, -z - chart.k + b)
            hit = (a > chart.h) | (b > chart.h)
        else:
            if chart.clip is not None:
                z = np.clip(z, -chart.clip, chart.clip)
            sig, d2 = chart._s, chart._d2  # type: ignore[attr-defined]
            hit = glr_advance(sums, sig, d2, z, min(t, chart.window)) > chart.h
        out[left[hit]] = t
        keep = ~hit
        left, a, b, sums = left[keep], a[keep], b[keep], sums[keep]
        if not left.size:
            break
    return out


__all__ = ["QUANTILE", "Change", "Episode", "Episodes", "clear_after", "run_lengths"]
