"""Control charts on a stream of estimates: an EWMA chart per quantity, a CUSUM and a GLR
chart for a level change (:mod:`~formtwin.monitoring.glr`) on those configured, and a
model-mismatch chart on the filter's health; alarms: :class:`~formtwin.monitoring.charts.Alarm`.

Quantities: the posterior means of the state variables (``spec.state.names``) and the
predicted outputs (``spec.output_names``: the demonstrator's ``angle_stage1``,
``angle_stage2``), each standardised by its in-control
AR model (:class:`~formtwin.monitoring.incontrol.InControl`) into a residual ``z`` that is
N(0, 1) and independent in control. Health: the log-evidence increment ``loglik`` and the
ESS of each step, as normal scores against their simulated in-control distribution
(:class:`~formtwin.monitoring.incontrol.Reference`), each on a one-sided CUSUM that signals
a worse fit only.

Life of a monitor: the first ``warmup`` products are not charted (the filter is still
converging from its prior); the next ``phase1`` products estimate the in-control mean of
every quantity whose mean is not set (Phase I, Montgomery ch. 7.1: the angles' level
depends on the machine parameters, known only once the line runs); charting starts after
that. With ``health_per_line`` the health statistics' references are the line's own
Phase-I values, frozen at its end (the filter's health depends on the line: with the
deviation estimated its ESS does on ``theta_d``). A chart that signals restarts from zero.

The charts' states are arrays over the quantities, and a charted product is one pass over
them (:mod:`~formtwin.monitoring.bank`: the scalar charts' float operations, so the same
alarms and the same state bit for bit). The state is a JSON-safe dict
(:meth:`Monitor.state`); ``Monitor(config, state)`` continues exactly where the saved one
stopped.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Collection, Mapping
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtri

from formtwin.estimates import Estimate
from formtwin.monitoring import bank
from formtwin.monitoring.bank import NEVER, QUANTITY_CHARTS, FloatArray, padded, split
from formtwin.monitoring.charts import Alarm
from formtwin.monitoring.config import ANGLES, HEALTH, MonitorConfig, observe

#: a side's code in :func:`~formtwin.monitoring.bank.chart_step`'s outputs -> its name
_SIDES = {1: "high", -1: "low"}


class Monitor:
    """EWMA, CUSUM, GLR and mismatch charts over a stream of estimates.

    Parameters
    ----------
    config : what to watch.
    state : a state from :meth:`state` to continue from; ``None``: a fresh start.

    Examples
    --------
    >>> from formtwin.monitoring.charts import Cusum
    >>> from formtwin.monitoring.incontrol import InControl
    >>> ic = {"thickness": InControl(mean=0.3, sigma=0.001)}
    >>> mon = Monitor(MonitorConfig(ic, warmup=0, phase1=0, cusum=Cusum(k=0.5, h=4.0)))
    >>> [a.chart for v in (0.3, 0.3, 0.305) for a in mon.update_values({"thickness": v})]
    ['ewma', 'cusum']
    """

    def __init__(self, config: MonitorConfig, state: Mapping[str, Any] | None = None) -> None:
        self.config = c = config
        self.n = 0  # products seen
        #: the chart statistics and limits of the last charted product, by quantity and
        #: chart (``{"thickness": {"ewma": (Z, limit), "cusum": (C, h)}, "ess":
        #: {"mismatch": (C, h)}}``, sigma units); empty before charting starts
        self.last: dict[str, dict[str, tuple[float, float]]] = {}
        #: every AR model by name: the quantities' and the health scores'
        self.models = {**c.quantities, **c.health_models}
        if len(self.models) != len(c.quantities) + len(c.health_models):
            raise ValueError(f"health models {sorted(set(c.quantities) & set(c.health_models))}"
                             " are named as charted quantities: expected other names")
        self.phase1_sums = {n: 0.0 for n, q in self.models.items() if q.mean is None}
        #: the quantities with a CUSUM chart
        self.with_cusum = {n for n in c.quantities if c.cusum_on is None or n in c.cusum_on}
        #: products seen (:attr:`n`) at each health statistic's last mismatch alarm
        self.alarmed_at: dict[str, int] = {}
        w = c.widen
        #: each quantity's charts with its limits (the design's times its ``widen``)
        self.charts = {n: (replace(c.ewma, L=c.ewma.L * w.get(n, {}).get("ewma", 1.0)),
                           replace(c.cusum, h=c.cusum.h * w.get(n, {}).get("cusum", 1.0)),
                           None if c.shewhart is None
                           else c.shewhart * w.get(n, {}).get("shewhart", 1.0))
                       for n in c.quantities}
        self.glr_charts = {n: replace(g, h=g.h * w.get(n, {}).get("glr", 1.0))
                           for n, g in c.glr.items()}
        self.mismatch = {n: replace(c.mismatch, h=c.mismatch.h * w.get(n, {}).get(
            "mismatch", 1.0)) for n in c.health}
        #: the health statistics' Phase-I values on this line (``health_per_line``)
        self.phase1_health: dict[str, list[float]] = {n: [] for n in c.health}
        #: the references in force: the config's pooled ones, or this line's after Phase I
        self.references = dict(c.health)
        self._arrays()
        if state is not None:
            self._load(state)

    def _arrays(self) -> None:
        """The charts' constants and fresh states as arrays (:mod:`~formtwin.monitoring.
        bank`): models ``j`` (quantities, then health models), quantities ``q``, health
        statistics ``r``; the states are views of two buffers (:meth:`save`)."""
        c, models = self.config, list(self.models.values())
        quantities, health, names = list(c.quantities), list(c.health), list(self.models)
        nm, nq, nh = len(models), len(quantities), len(health)
        g = [self.glr_charts.get(n) for n in quantities]
        self._order = np.array([q.order for q in models], dtype=np.int64)
        self._phi, _ = padded([q.phi for q in models])
        self._sigma = np.array([q.sigma for q in models], dtype=np.float64)
        self._quant, self._qlen = padded([q.quantiles for q in models])
        self._zmax = np.array([q._zmax for q in models], dtype=np.float64)  # type: ignore[attr-defined]
        self._elam = np.array([self.charts[n][0].lam for n in quantities], dtype=np.float64)
        self._elim, self._elen = padded([tuple(bank.ewma_limits(e.lam, e.L))
                                         for e, _, _ in self.charts.values()])
        self._has_c = np.array([n in self.with_cusum for n in quantities], dtype=np.bool_)
        self._ck = np.array([self.charts[n][1].k for n in quantities], dtype=np.float64)
        self._ch = np.array([self.charts[n][1].h for n in quantities], dtype=np.float64)
        self._shew = np.array([math.nan if s is None else s for _, _, s in self.charts.values()],
                              dtype=np.float64)
        self._has_g = np.array([x is not None for x in g], dtype=np.bool_)
        self._gs, _ = padded([() if x is None else tuple(x._s) for x in g])  # type: ignore[attr-defined]
        self._gd2, _ = padded([() if x is None else tuple(x._d2) for x in g])  # type: ignore[attr-defined]
        self._gwin = np.array([1 if x is None else x.window for x in g], dtype=np.int64)
        self._gh = np.array([math.nan if x is None else x.h for x in g], dtype=np.float64)
        self._gclip = np.array([math.nan if x is None or x.clip is None else x.clip for x in g],
                               dtype=np.float64)
        #: each quantity's charts (columns of the kernel's outputs), in the report's order
        self._columns = [(0, *((1,) if x is not None else ()),
                          *((2,) if n in self.with_cusum else ()),
                          *((3,) if n in self.with_cusum and s is not None else ()))
                         for n, x, (_, _, s) in zip(quantities, g, self.charts.values(),
                                                    strict=True)]
        self._hmodel = np.array([names.index(n) if n in c.health_models else -1
                                 for n in health], dtype=np.int64)
        self._hk = np.array([self.mismatch[n].k for n in health], dtype=np.float64)
        self._hh = np.array([self.mismatch[n].h for n in health], dtype=np.float64)
        self._ref_of_model = np.array([health.index(n) for n in c.health_models], dtype=np.int64)
        #: the values' names in the kernels' order: the quantities, then the health statistics
        self._inputs = (*quantities, *health)
        self._work = (np.empty(nh), np.empty(nm), np.empty(nm, np.bool_), np.empty(nm),
                      np.empty(nm), np.empty(nm, np.bool_))  # u, y, use, f, direct, need
        self._out = (np.empty((nq, 4)), np.empty((nq, 4)), np.empty((nq, 4), dtype=np.int64),
                     np.empty(nh), np.empty(nh, dtype=np.int64), np.empty(nh, dtype=np.bool_))
        #: the states' shapes: floats (means, histories, EWMA, CUSUM high and low, GLR
        #: sums, mismatch high and low), ints (has mean, history length, EWMA i, GLR
        #: length and i, alarmed at)
        self._shapes: tuple[list[tuple[int, ...]], ...] = (
            [(nm,), (nm, self._phi.shape[1]), (nq,), (nq,), (nq,), self._gs.shape, (nh,), (nh,)],
            [(nm,), (nm,), (nq,), (nq,), (nq,), (nh,)])
        self._views(np.zeros(sum(math.prod(x) for x in self._shapes[0])),
                    np.zeros(sum(math.prod(x) for x in self._shapes[1]), dtype=np.int64))
        self._mean[:] = [math.nan if q.mean is None else q.mean for q in models]
        self._has_mean[:] = [q.mean is not None for q in models]
        self._hist[:] = math.nan
        self._alarmed[:] = NEVER
        self._reference_arrays()

    def _views(self, floats: FloatArray, ints: NDArray[np.int64]) -> None:
        """The charts' states as views of the buffers ``floats`` and ``ints``."""
        self._buffers = (floats, ints)
        (self._mean, self._hist, self._ez, self._chi, self._clo, self._gsums, self._hhi,
         self._hlo) = split(floats, self._shapes[0])
        (self._has_mean, self._hlen, self._ei, self._glen, self._gi,
         self._alarmed) = split(ints, self._shapes[1])

    def _reference_arrays(self) -> None:
        """The references in force as arrays (again after Phase I with ``health_per_line``)."""
        refs = [self.references[n] for n in self.config.health]
        self._rsample, self._rlen = padded([r.sample for r in refs])
        self._rbad = np.array([r.bad == "low" for r in refs], dtype=np.bool_)

    def save(self) -> tuple[Any, ...]:
        """What :meth:`restore` needs to bring the monitor back to now (two buffer copies
        and the small containers)."""
        return (self.n, self.last, dict(self.phase1_sums), dict(self.alarmed_at),
                {n: list(v) for n, v in self.phase1_health.items()}, self.references,
                (self._rsample, self._rlen, self._rbad),
                tuple(b.copy() for b in self._buffers))

    def restore(self, saved: tuple[Any, ...]) -> None:
        """Back to the moment of :meth:`save`."""
        (self.n, self.last, self.phase1_sums, self.alarmed_at, self.phase1_health,
         self.references, (self._rsample, self._rlen, self._rbad), buffers) = saved
        for mine, theirs in zip(self._buffers, buffers, strict=True):
            mine[:] = theirs

    def copy(self) -> Monitor:
        """An independent copy: its own states and its own work arrays, so that a copy
        may chart in another thread."""
        out = copy.copy(self)
        saved = self.save()
        out._views(*saved[-1])
        out.restore(saved)
        out._work, out._out = copy.deepcopy(self._work), copy.deepcopy(self._out)
        return out

    @property
    def means(self) -> dict[str, float | None]:
        """The in-control means in force by AR model (None: not yet set by Phase I)."""
        return {n: float(m) if h else None for n, m, h in zip(
            self.models, self._mean.tolist(), self._has_mean.tolist(), strict=True)}

    @property
    def history(self) -> dict[str, list[float]]:
        """Each AR model's last ``order`` values, oldest first."""
        return {n: self._hist[j, :k].tolist()
                for j, (n, k) in enumerate(zip(self.models, self._hlen.tolist(), strict=True))}

    @property
    def charting(self) -> bool:
        """Whether the charts are running (warm-up and Phase I over)."""
        return self.n >= self.config.warmup + self.config.phase1

    def update(self, estimate: Estimate) -> tuple[Alarm, ...]:
        """Chart one estimate; the alarms it raises (usually none)."""
        return self.update_values(observe(estimate), estimate.index)

    def update_values(self, values: Mapping[str, float], index: int | None = None
                      ) -> tuple[Alarm, ...]:
        """Chart one product given its monitored values by name (see :func:`observe`);
        ``index`` defaults to the number of products seen before."""
        c = self.config
        idx = self.n if index is None else int(index)
        missing = [n for n in (*c.quantities, *c.health) if n not in values]
        if missing:
            raise ValueError(f"values lack {missing}; expected {list(c.quantities)} and "
                             f"{list(c.health)}")
        self.n += 1
        if self.n <= c.warmup:
            return ()
        if self.n <= c.warmup + c.phase1:
            self._phase1(values)
            return ()
        return self._chart(values, idx)

    def _phase1(self, values: Mapping[str, float]) -> None:
        """A Phase-I product: its values summed for the means to estimate, remembered."""
        c = self.config
        per_line = c.health_per_line
        if per_line:  # this line's health references: its Phase-I values, raw
            for n, vals in self.phase1_health.items():
                v = float(values[n])
                if math.isfinite(v):
                    vals.append(v)
        else:  # health: normal scores
            values = {**values, **{n: ref.normal_score(float(values[n]))
                                   for n, ref in self.references.items()}}
        for n in self.phase1_sums:
            self.phase1_sums[n] += float(values[n])
        if self.n == c.warmup + c.phase1:
            names = list(self.models)
            for n, total in self.phase1_sums.items():
                j = names.index(n)
                self._mean[j], self._has_mean[j] = total / c.phase1, True
            if per_line:
                self._line_references()
        self._remember(values, skip=c.health if per_line else ())

    def _chart(self, values: Mapping[str, float], idx: int) -> tuple[Alarm, ...]:
        """A charted product: the kernels' pass, then its alarms and :attr:`last`."""
        c, nq = self.config, len(self.config.quantities)
        v = np.array([values[n] for n in self._inputs], dtype=np.float64)
        u, y, use, f, direct, need = self._work
        bank.reference_probabilities(v, nq, self._rsample, self._rlen, self._rbad, u)
        scores = ndtri(u)  # the health statistics' normal scores
        bank.residual_probabilities(v, scores, self._ref_of_model, self._hist, self._hlen,
                                    self._order, self._phi, self._mean, self._has_mean,
                                    self._sigma, self._quant, self._qlen, self._zmax, y, use,
                                    f, direct, need)
        lam = c.health_level
        stat, lim, side, h_stat, h_side, h_charted = self._out
        bank.chart_step(ndtri(f), direct, need, use, scores, y, self._hist, self._hlen,
                        self._order, self._mean, self._has_mean,
                        self._elam, self._ez, self._ei, self._elim, self._elen,
                        self._has_c, self._ck, self._ch, c.cusum.sides != "low",
                        c.cusum.sides != "high", self._chi, self._clo, self._shew,
                        self._has_g, self._gs, self._gd2, self._gwin, self._gh, self._gclip,
                        self._gsums, self._glen, self._gi,
                        self._hmodel, self._hk, self._hh, self._hhi, self._hlo, self._alarmed,
                        self.n, 0.0 if lam is None else lam,
                        0 if lam is None else round(1.0 / lam),
                        stat, lim, side, h_stat, h_side, h_charted)
        return self._report(idx, use[:nq].tolist(), stat.tolist(), lim.tolist(),
                            side.tolist(), h_stat.tolist(), h_side.tolist(),
                            h_charted.tolist())

    def _report(self, idx: int, scored: list[bool], stat: list[list[float]],
                lim: list[list[float]], side: list[list[int]], h_stat: list[float],
                h_side: list[int], h_charted: list[bool]) -> tuple[Alarm, ...]:
        """The alarms of a charted product and :attr:`last`, from the kernel's outputs."""
        alarms: list[Alarm] = []
        self.last = last = {}  # type: ignore[var-annotated]
        for q, n in enumerate(self.config.quantities):
            if not scored[q]:
                continue
            d = last[n] = {}
            for k in self._columns[q]:
                chart, s = QUANTITY_CHARTS[k], stat[q][k]
                d[chart] = (s, lim[q][k])
                if side[q][k]:
                    alarms.append(Alarm(n, chart, idx, s, lim[q][k], _SIDES[side[q][k]]))
        for r, n in enumerate(self.config.health):
            if not h_charted[r]:
                continue
            last[n] = {"mismatch": (h_stat[r], float(self._hh[r]))}
            if h_side[r]:
                alarms.append(Alarm(n, "mismatch", idx, h_stat[r], float(self._hh[r]), "high"))
                self.alarmed_at[n] = self.n
        return tuple(alarms)

    def _line_references(self) -> None:
        """Freeze this line's health references from its Phase-I values (the pooled one
        where there are fewer than 20)."""
        self.references = {n: ref.of_line(self.phase1_health[n])
                           for n, ref in self.config.health.items()}
        self._reference_arrays()

    def _remember(self, values: Mapping[str, float], skip: Collection[str] = ()) -> None:
        """Add each AR model's value to its history (those in ``skip`` not)."""
        for j, (n, q) in enumerate(self.models.items()):
            y = float(values[n])
            if n in skip or not q.order or not math.isfinite(y):
                continue
            k = int(self._hlen[j])
            if k < q.order:
                self._hist[j, k] = y
                self._hlen[j] = k + 1
            else:
                self._hist[j, :q.order] = [*self._hist[j, 1:q.order].tolist(), y]

    # ------------------------------------------------------------------ persistence
    def state(self) -> dict[str, Any]:
        """JSON-safe state (products seen, Phase-I sums and means, AR history, charts, the
        health statistics' Phase-I values and last mismatch alarms)."""
        c, quantities = self.config, list(self.config.quantities)
        glr = {n: [self._gsums[q, :k].tolist(), i] for q, (n, k, i) in enumerate(zip(
            quantities, self._glen.tolist(), self._gi.tolist(), strict=True)) if n in c.glr}
        return {"n": self.n, "means": self.means, "phase1_sums": dict(self.phase1_sums),
                "history": self.history,
                "ewma": {n: [z, i] for n, z, i in zip(quantities, self._ez.tolist(),
                                                      self._ei.tolist(), strict=True)},
                "cusum": {n: [a, b] for n, a, b in zip(quantities, self._chi.tolist(),
                                                       self._clo.tolist(), strict=True)
                          if n in self.with_cusum},
                "health": {n: [a, b] for n, a, b in zip(c.health, self._hhi.tolist(),
                                                        self._hlo.tolist(), strict=True)},
                "glr": {n: glr[n] for n in c.glr},
                "phase1_health": {n: list(v) for n, v in self.phase1_health.items()},
                "alarmed_at": dict(self.alarmed_at)}

    def _load(self, st: Mapping[str, Any]) -> None:
        names, health = set(self.models), set(self.config.health)
        if (set(st["history"]) != names or set(st["health"]) != health
                or set(st["cusum"]) != self.with_cusum):
            raise ValueError(f"monitor state watches {sorted(st['history'])} and "
                             f"{sorted(st['health'])}, the config {sorted(names)} and "
                             f"{sorted(health)}")
        glr = st.get("glr", {})
        if set(glr) - set(self.config.glr):
            raise ValueError(f"monitor state has GLR charts {sorted(glr)}, the config "
                             f"{sorted(self.config.glr)}")
        self.n = int(st["n"])
        models, quantities = list(self.models), list(self.config.quantities)
        for n, v in st["means"].items():
            j = models.index(n)
            self._mean[j], self._has_mean[j] = (math.nan, False) if v is None else (float(v), True)
        self.phase1_sums = {n: float(v) for n, v in st["phase1_sums"].items()}
        for n, h in st["history"].items():
            j = models.index(n)
            self._hist[j, :len(h)], self._hlen[j] = [float(v) for v in h], len(h)
        for n, (z, i) in st["ewma"].items():
            q = quantities.index(n)
            self._ez[q], self._ei[q] = float(z), int(i)
        for n, (a, b) in st["cusum"].items():
            q = quantities.index(n)
            self._chi[q], self._clo[q] = float(a), float(b)
        for r, n in enumerate(self.config.health):
            self._hhi[r], self._hlo[r] = (float(v) for v in st["health"][n])
        for n, (v, i) in glr.items():
            q = quantities.index(n)
            self._gsums[q, :len(v)], self._glen[q], self._gi[q] = v, len(v), int(i)
        self.phase1_health.update({n: [float(v) for v in vals] for n, vals in
                                   st.get("phase1_health", {}).items() if n in health})
        self.alarmed_at = {n: int(v) for n, v in st.get("alarmed_at", {}).items() if n in health}
        for r, n in enumerate(self.config.health):
            self._alarmed[r] = self.alarmed_at.get(n, NEVER)
        if self.config.health_per_line and self.charting:
            self._line_references()


__all__ = ["ANGLES", "HEALTH", "Alarm", "Monitor", "MonitorConfig", "observe"]
