"""Model health in the service: say it, once per episode, when the model does not explain
the curves.

Every estimate carries its absolute goodness of fit (``health``: ok / degraded / no_fit,
:mod:`formtwin.tracker.fit`). A single ``no_fit`` product can be a bad stroke; a run of
them means that the model does not explain this press. :class:`ModelHealth` keeps the
health of the last ``m`` accepted products and, when at least ``k`` of them are
``no_fit`` (:class:`HealthRule`, defaults ``k = 5`` of ``m = 10``), asks whether the
model could explain those curves at all (the ``explain`` check: the best fit over the
model's whole box, :mod:`formtwin.tracker.explain`, on the last up to 3 unexplained
curves, until their majority is decided: 30-200 ms a curve for the bundled metamodel, the
one product of the service that takes that long). If it can, the *filter* is behind (its
start-up, a process change, a cloud stuck in a wrong mode): nothing is raised, the entry
says ``explained``, the count starts afresh.
If it cannot, a *model mismatch episode* opens:

* one ``model_mismatch`` message (schema ``formtwin.error/1``) on the errors topic, in
  words: what the measurement model expects, what was seen, the likely causes;
* the episode in the store's ``health_episodes`` table (with the message);
* every estimate of the episode is still stored and published, marked
  ``flags.model_mismatch = true`` and ``model_health.state = "model_mismatch"``, so that no
  consumer can take it for a good one; the live page shows a banner.

The episode closes (one ``model_fit_restored`` message) after ``m`` products in a row
without ``no_fit``. Why 5 of 10: a model of another press fails on every product and is
reported at the 5th; on matched data ``no_fit`` products are rare, and their runs (the
filter's start-up) are explained by the model (``benchmarks/bench_health.py``); 5 failures
within 10 products need more than bad luck (under the model, ``P(no_fit) <= 10^-3`` per
product).

Like the charts of :mod:`formtwin.service.alarms`, the state goes into the estimate message
before the commit (``model_health``: state, failures in the window, the window itself, the
event of this product), and an opening or closing goes into the episodes table
(:meth:`ModelHealth.write`), both in the transaction of the product. A restart takes the
window from the last stored estimate.

>>> r = HealthRule(k=2, m=3)
>>> w = HealthWindow(r)
>>> [w.push(h) for h in ("ok", "no_fit", "ok", "no_fit", "ok", "ok", "ok")]
[None, None, None, 'opened', None, None, 'closed']
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaincinv

from formtwin.service.messages import ERROR_SCHEMA
from formtwin.service.store import Store

log = logging.getLogger(__name__)


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of chi-square with ``dof`` degrees of freedom: SciPy's own
    ``chi2.ppf`` (``2 gammaincinv(dof / 2, p)``) without importing ``scipy.stats`` (about
    1.3 s CPU at the service's start)."""
    return float(2.0 * gammaincinv(dof / 2, p))

FloatArray = NDArray[np.float64]

#: notices the service publishes on the errors topic about the model (not rejections)
NOTICES: dict[str, str] = {
    "model_mismatch": "the model does not explain the curves (k of the last m products "
                      "beyond the measurement model's 99.9 % quantile); estimates marked",
    "model_fit_restored": "the model explains the curves again (m products in a row)",
}

LIKELY_CAUSES = (
    "a metamodel of another press, tool or process than this one (check --metamodel)",
    "a faulty, unplugged or recalibrated force sensor, or one noisier than the likelihood "
    "assumes (serve --sensor-noise, its std in N)",
    "force in other units than N, or a time window other than the spec's",
)

_DDL = """
CREATE TABLE IF NOT EXISTS health_episodes (
    id INTEGER PRIMARY KEY,
    opened_seq INTEGER NOT NULL UNIQUE,
    opened_part TEXT NOT NULL,
    opened_at REAL NOT NULL,
    closed_seq INTEGER,
    closed_at REAL,
    message TEXT NOT NULL
);
"""


@dataclass(frozen=True)
class HealthRule:
    """When the service reports a model mismatch.

    Attributes
    ----------
    k : ``no_fit`` products among the last ``m`` that open an episode.
    m : window, products; an episode closes after ``m`` products in a row without
        ``no_fit``.
    """

    k: int = 5
    m: int = 10

    def __post_init__(self) -> None:
        if not 1 <= self.k <= self.m:
            raise ValueError(f"expected 1 <= k ({self.k}) <= m ({self.m})")


@dataclass
class HealthWindow:
    """The last ``m`` health values and the episode state (pure, no storage)."""

    rule: HealthRule = field(default_factory=HealthRule)
    failing: deque[bool] = field(default_factory=deque)
    mismatch: bool = False
    streak_ok: int = 0

    def push(self, health: str) -> str | None:
        """Add a product's health; return ``"opened"``, ``"closed"`` or None."""
        bad = health == "no_fit"
        self.failing.append(bad)
        while len(self.failing) > self.rule.m:
            self.failing.popleft()
        self.streak_ok = 0 if bad else self.streak_ok + 1
        if not self.mismatch and sum(self.failing) >= self.rule.k:
            self.mismatch = True
            return "opened"
        if self.mismatch and self.streak_ok >= self.rule.m:
            self.mismatch = False
            return "closed"
        return None

    def veto(self) -> None:
        """Cancel an opening (the model explains the curves): start counting afresh."""
        self.mismatch = False
        self.failing.clear()

    def copy(self) -> HealthWindow:
        """An independent copy (to undo a push)."""
        return HealthWindow(self.rule, deque(self.failing), self.mismatch, self.streak_ok)

    def to_dict(self) -> dict[str, Any]:
        """The window as JSON-ready values (stored with every estimate)."""
        return {"recent": [int(b) for b in self.failing], "streak": self.streak_ok,
                "mismatch": self.mismatch}

    @classmethod
    def from_dict(cls, rule: HealthRule, d: dict[str, Any]) -> HealthWindow:
        """Inverse of :meth:`to_dict`."""
        return cls(rule, deque(bool(b) for b in d.get("recent", [])), bool(d.get("mismatch")),
                   int(d.get("streak", 0)))


def _describe(recent: list[dict[str, Any]], rule: HealthRule,
              expected_peak: tuple[float, float] | None,
              best: list[float] | None = None) -> dict[str, Any]:
    """The ``model_mismatch`` notice's words and figures from the window's estimates."""
    fits = [m.get("fit") or {} for m in recent]
    bad = [f for f, m in zip(fits, recent, strict=True) if m.get("health") == "no_fit"]
    dof = int(next((f["dof"] for f in fits if f.get("dof")), 0))
    d2 = [float(f["distance2"]) if f.get("distance2") is not None else float("inf")
          for f in bad]
    ess = [float(m["ess"]) for m in recent if m.get("ess") is not None]
    seen_d2 = float(np.median(d2)) if d2 else float("nan")
    q999 = chi2_quantile(0.999, dof) if dof else float("nan")
    peaks = [float(m["peak_force_N"]) for m in recent if m.get("peak_force_N") is not None]
    expected = (f"a curve within the measurement model's spread: squared Mahalanobis "
                f"distance about {dof} (chi-square with {dof} degrees of freedom), "
                f"below {q999:.0f} for 99.9 % of products")
    seen = (f"{len(bad)} of the last {len(recent)} products beyond it, median distance "
            f"{seen_d2:.4g}; ESS {min(ess) if ess else float('nan'):.3g} to "
            f"{max(ess) if ess else float('nan'):.3g}")
    if expected_peak is not None:
        expected += (f"; peak force {expected_peak[0]:.0f} - {expected_peak[1]:.0f} N "
                     "over the spec's ranges")
    if peaks:
        seen += f"; peak force {min(peaks):.0f} - {max(peaks):.0f} N"
    if best:
        seen += (f"; even the best state and parameters over the spec's ranges leave a "
                 f"distance of {min(best):.4g} or more")
    detail = (f"the model does not explain the force curves: expected {expected}; seen "
              f"{seen}. Estimates are still stored and published, marked "
              f"flags.model_mismatch = true, until {rule.m} products in a row fit again. "
              f"Likely causes: {'; '.join(LIKELY_CAUSES)}.")
    return {"detail": detail, "expected": expected, "seen": seen,
            "likely_causes": list(LIKELY_CAUSES), "rule": {"k": rule.k, "m": rule.m},
            "median_distance2": seen_d2 if np.isfinite(seen_d2) else None, "dof": dof}


class ModelHealth:
    """The service's model-health state over a store (see module doc).

    Parameters
    ----------
    store : Store
        The service's store (holds the ``health_episodes`` table).
    rule : HealthRule
        When an episode opens and closes.
    expected_peak : (lo, hi) or None
        Peak force range over the spec's ranges, N (for the notice's words).
    explain : callable or None
        ``explain(curve, mean)``: the smallest squared Mahalanobis distance of a curve
        over the model's whole box (:func:`formtwin.tracker.explain.best_distance2`). When
        the rule fires, the last (up to 3) unexplained curves are checked, oldest first,
        until the majority is decided: if the model reaches the 99.9 % quantile on most
        of them, the filter (not the model) is behind,
        and no episode opens (``model_health.explained`` says so); the count starts afresh.
    """

    def __init__(self, store: Store, rule: HealthRule | None = None,
                 expected_peak: tuple[float, float] | None = None,
                 explain: Callable[[FloatArray, FloatArray | None], float] | None = None
                 ) -> None:
        self.rule = HealthRule() if rule is None else rule
        self.expected_peak = expected_peak
        self.explain = explain
        self.store = store
        store.ensure_tables(_DDL)
        self.window = HealthWindow(self.rule)
        self._recent: deque[dict[str, Any]] = deque(maxlen=self.rule.m)
        self._failing: deque[tuple[FloatArray, FloatArray | None]] = deque(maxlen=3)
        self._undo: tuple[Any, ...] | None = None
        self._restore(store)

    def _restore(self, store: Store) -> None:
        """The state of the last stored product."""
        rows = list(store.products(since_seq=max(store.next_seq() - 1 - self.rule.m, 0),
                                   status="accepted"))
        for row in rows:
            msg = row.estimate or {}
            self._remember(msg, row.curve)
            entry = msg.get("model_health")
            if isinstance(entry, dict) and "window" in entry:
                self.window = HealthWindow.from_dict(self.rule, entry["window"])

    @property
    def mismatch(self) -> bool:
        """Whether a model-mismatch episode is open."""
        return self.window.mismatch

    def _remember(self, message: dict[str, Any], curve: FloatArray | None) -> None:
        self._recent.append({k: message.get(k) for k in ("health", "fit", "ess",
                                                         "peak_force_N")})
        if curve is not None and message.get("health") == "no_fit":
            mean = message.get("mean")
            vals = None if not isinstance(mean, dict) else np.array(
                [np.nan if v is None else v for v in mean.values()], dtype=np.float64)
            self._failing.append((np.asarray(curve, dtype=np.float64), vals))

    def observe(self, message: dict[str, Any], curve: FloatArray | None = None
                ) -> dict[str, Any]:
        """The ``model_health`` entry of an estimate message (before its commit);
        ``curve`` (n_t,) N is the product's curve (for the explain check)."""
        self._undo = (self.window.copy(), list(self._recent), list(self._failing))
        event = self.window.push(str(message.get("health", "ok")))
        self._remember(message, curve)
        entry: dict[str, Any] = {}
        if event == "opened" and self.explain is not None and self._failing:
            dof = int((message.get("fit") or {}).get("dof") or len(self._failing[0][0]))
            q = chi2_quantile(0.999, dof)
            best = self._search(q)
            if 2 * sum(b <= q for b in best) > len(self._failing):
                self.window.veto()
                event = None
                entry["explained"] = {
                    "best_distance2": best, "quantile_999": q,
                    "note": "the model explains these curves with other parameters: the "
                            "filter has not found the state yet (start-up, a process "
                            "change); no model mismatch"}
            else:
                entry["best_distance2"] = best
        entry.update({"state": "model_mismatch" if self.window.mismatch else "ok",
                      "failing": int(sum(self.window.failing)),
                      "event": event, "window": self.window.to_dict()})
        if event == "opened":
            entry.update(_describe(list(self._recent), self.rule, self.expected_peak,
                                   entry.get("best_distance2")))
        return entry

    def _search(self, q: float) -> list[float]:
        """The best distances of the unexplained curves, newest last, searched (each
        30-200 ms for the bundled metamodel) only until the majority is decided: those
        at most ``q`` explain them, the others not."""
        assert self.explain is not None
        best: list[float] = []
        n = len(self._failing)
        for c, m in self._failing:
            best.append(float(self.explain(c, m)))
            ok = sum(b <= q for b in best)
            if 2 * ok > n or 2 * (len(best) - ok) >= n:
                break
        return best

    def rollback(self) -> None:
        """Undo the last :meth:`observe` (its product was not committed)."""
        if self._undo is not None:
            self.window, recent, failing = self._undo
            self._recent = deque(recent, maxlen=self.rule.m)
            self._failing = deque(failing, maxlen=3)
            self._undo = None

    def write(self, cur: sqlite3.Cursor, seq: int, part_id: str, entry: dict[str, Any],
              now: float) -> list[dict[str, Any]]:
        """Record the event of product ``seq`` with ``cur`` (inside the product's
        transaction); return its notices for the errors topic (none, or one
        ``model_mismatch`` / ``model_fit_restored``)."""
        if entry.get("event") is None:
            return []
        if entry["event"] == "opened":
            cur.execute("INSERT INTO health_episodes(opened_seq, opened_part, opened_at, "
                        "message) VALUES (?,?,?,?)", (seq, part_id, now, json.dumps(entry)))
        else:
            cur.execute("UPDATE health_episodes SET closed_seq = ?, closed_at = ? WHERE "
                        "closed_seq IS NULL AND opened_seq < ?", (seq, now, seq))
        return [notice(entry, part_id, seq, now)]

    def committed(self) -> None:
        """The product of the last :meth:`observe` is in: forget its undo."""
        self._undo = None

    def episodes(self) -> list[dict[str, Any]]:
        """All episodes, oldest first: ids, opening/closing product and the message."""
        rows = self.store.query("SELECT id, opened_seq, opened_part, opened_at, closed_seq, "
                                "closed_at, message FROM health_episodes ORDER BY id")
        return [{**json.loads(r[6]), "id": r[0], "opened_seq": r[1], "opened_part": r[2],
                 "opened_at": r[3], "closed_seq": r[4], "closed_at": r[5]} for r in rows]

    def state(self) -> dict[str, Any]:
        """The current state for the page: ``state``, and the open episode if any."""
        eps = self.episodes()
        open_ep = eps[-1] if eps and eps[-1]["closed_seq"] is None else None
        return {"state": "model_mismatch" if self.mismatch else "ok",
                "rule": {"k": self.rule.k, "m": self.rule.m}, "episode": open_ep,
                "episodes": len(eps)}


def notice(entry: dict[str, Any], part_id: str, seq: int, now: float) -> dict[str, Any]:
    """The errors-topic message of a health event (schema ``formtwin.error/1``)."""
    if entry["event"] == "opened":
        return {"schema": ERROR_SCHEMA, "reason": "model_mismatch",
                "detail": entry["detail"], "part_id": part_id, "seq": seq,
                "expected": entry["expected"], "seen": entry["seen"],
                "likely_causes": entry["likely_causes"], "received_at": now}
    return {"schema": ERROR_SCHEMA, "reason": "model_fit_restored",
            "detail": NOTICES["model_fit_restored"], "part_id": part_id, "seq": seq,
            "received_at": now}


__all__ = ["LIKELY_CAUSES", "NOTICES", "HealthRule", "HealthWindow", "ModelHealth", "notice"]
