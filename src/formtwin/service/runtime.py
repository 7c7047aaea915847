"""Assemble a :class:`~formtwin.service.processor.Processor` from a store and settings.

The first start of a store fixes its configuration (model, tracker settings, measurement
model, gate, limits) in the store's ``meta`` table and saves the measurement model beside
the store; every restart must use the same configuration (a mismatch is refused, naming the
field) and loads the same measurement model, so a restarted service continues bit for bit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from formtwin.defaults import load_model
from formtwin.measurement import MeasurementModel
from formtwin.service import cache as _cache
from formtwin.service.gate import OutlierGate
from formtwin.service.health import HealthRule, ModelHealth, chi2_quantile
from formtwin.service.messages import Limits
from formtwin.service.plausibility import CLIP_SAMPLES, Plausibility
from formtwin.service.processor import Processor
from formtwin.service.restore import replay
from formtwin.service.store import Store
from formtwin.tracker import Tracker, TrackerConfig, build_measurement, build_tracker
from formtwin.tracker.explain import best_distance2, default_starts

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ServiceSettings:
    """Everything that determines the stored estimates (fixed at a store's first start).

    Parameters
    ----------
    model : str
        ``"analytic"`` (the closed-form stand-in) or the path of a metamodel file.
    tracker : TrackerConfig
        The tracker's settings (TOML section ``[tracker]``); its ``n_mc``, ``nu`` and
        ``seed`` also make the measurement model.
    gate_k : float
        Outlier gate in robust standard deviations of loglik (0 disables the gate).
    max_bytes, min_force_N, max_force_N : message limits (:class:`Limits`).
    min_peak_N, clip_samples, peak_window_ms : plausibility limits
        (:class:`~formtwin.service.plausibility.Plausibility`); ``None``: derived from the
        spec's ranges through the model.
    health_k, health_m : a model-mismatch episode opens when ``health_k`` of the last
        ``health_m`` products are not explained (:class:`~formtwin.service.health.HealthRule`).
    """

    model: str = "analytic"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    gate_k: float = 0.0
    max_bytes: int = 65536
    min_force_N: float = -50.0
    max_force_N: float = 1.0e4
    min_peak_N: float | None = None
    clip_samples: int = CLIP_SAMPLES
    peak_window_ms: tuple[float, float] | None = None
    health_k: int = 5
    health_m: int = 10

    def to_json(self) -> str:
        """The settings as JSON (stored in the store's ``meta`` table)."""
        d = dataclasses.asdict(self)
        d["tracker"] = self.tracker.to_dict()
        return json.dumps(d, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ServiceSettings:
        """Inverse of :meth:`to_json`; ``ValueError`` for settings of an older format."""
        d: dict[str, Any] = json.loads(text)
        if not isinstance(d.get("tracker"), dict):
            raise ValueError("stored settings predate the nested [tracker] settings; use a "
                             "new --store")
        d["tracker"] = TrackerConfig.from_dict(d["tracker"])
        if d.get("peak_window_ms") is not None:
            d["peak_window_ms"] = tuple(d["peak_window_ms"])
        return cls(**d)

    def limits(self, n_t: int, n_outputs: int = 2) -> Limits:
        """The message limits for curves of ``n_t`` samples and ``n_outputs`` measured
        outputs (the spec's)."""
        return Limits(n_t=n_t, max_bytes=self.max_bytes, min_force_N=self.min_force_N,
                      max_force_N=self.max_force_N, n_outputs=n_outputs)


def _file_digest(path: str) -> str:
    """SHA-256 of a model file (or of the files of a model folder, in name order)."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: no such metamodel file")
    h = hashlib.sha256()
    for f in sorted(p.rglob("*")) if p.is_dir() else [p]:
        if f.is_file():
            h.update(f.relative_to(p).as_posix().encode() if p.is_dir() else b"")
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def check_settings(store: Store, settings: ServiceSettings) -> ServiceSettings:
    """Record ``settings`` in a fresh store, or check them against the stored ones."""
    stored = store.get_meta("settings")
    model_digest = "analytic" if settings.model == "analytic" else _file_digest(settings.model)
    if stored is None:
        store.set_meta("settings", settings.to_json())
        store.set_meta("model_digest", model_digest)
        return settings
    old = ServiceSettings.from_json(stored)
    pairs = [(f.name, getattr(old, f.name), getattr(settings, f.name))
             for f in dataclasses.fields(ServiceSettings) if f.name not in ("model", "tracker")]
    pairs += [(f"tracker.{f.name}", getattr(old.tracker, f.name),
               getattr(settings.tracker, f.name)) for f in dataclasses.fields(TrackerConfig)]
    for name, a, b in pairs:
        if a != b:
            raise ValueError(f"{store.path}: stored setting {name} = {a!r}, now {b!r}; "
                             "a store keeps the settings it was created with (use a new "
                             "--store for new settings)")
    if store.get_meta("model_digest") != model_digest:
        raise ValueError(f"{store.path}: the model {settings.model!r} differs from the one "
                         f"the store was created with (digest {store.get_meta('model_digest')})")
    return old


def explainer(tracker: Tracker) -> Callable[[FloatArray, FloatArray | None], float]:
    """``explain(curve, mean)`` for :class:`ModelHealth`: the best fit of the curve over the
    model's whole box (:func:`formtwin.tracker.explain.best_distance2`), stopping at the
    99.9 % quantile, from the posterior mean, the box centre and 4 Sobol points."""
    q = chi2_quantile(0.999, tracker.measurement.n_t)

    def explain(curve: FloatArray, mean: FloatArray | None) -> float:
        return best_distance2(tracker.ssm, curve, default_starts(tracker.ssm, mean), target=q,
                              scale=tracker.scale or 1.0)

    return explain


def _new_measurement(model: Any, settings: ServiceSettings, model_digest: str | None,
                     mpath: Path, cache: str | Path | None) -> None:
    """Write a new store's measurement model to ``mpath``: the one kept in ``cache`` for
    the same model and tracker settings, else built (and kept there; by one service at a
    time, a second one with the same inputs waits for it)."""
    kept = None if cache is None else _cache.entry(
        cache, "measurement", {"model": model_digest, "tracker": settings.tracker.to_dict()},
        ".npz")
    with _cache.computing(kept):
        _kept_or_built(model, settings, mpath, kept)


def _kept_or_built(model: Any, settings: ServiceSettings, mpath: Path, kept: Path | None
                   ) -> None:
    """Copy the measurement model kept at ``kept`` to ``mpath``, else build it there."""
    if kept is not None and kept.is_file():
        try:
            MeasurementModel.load(kept)  # readable: a file another service finished
            shutil.copyfile(kept, mpath)
            log.info("measurement model from %s", kept)
            return
        except (OSError, ValueError, KeyError):
            pass
    built = build_measurement(model, settings.tracker)
    tmp = built.save(mpath.with_name(mpath.stem + ".tmp.npz"))
    if kept is not None:
        _cache.write_atomic(kept, tmp.read_bytes())
    tmp.replace(mpath)


def measurement_path(store_path: Path) -> Path:
    """Where the measurement model of a store is kept."""
    return store_path.with_name(store_path.name + ".measurement.npz")


def open_processor(store_path: str | Path, settings: ServiceSettings,
                   synchronous: str = "NORMAL", background_checkpoint_s: float = 1.0,
                   checkpoint_every: int = 10, cache: str | Path | None = None
                   ) -> Processor:
    """Open (or create) a store and return a processor with the tracker restored.

    Parameters
    ----------
    store_path : str or Path
        SQLite file of the service.
    settings : ServiceSettings
        Must equal the stored settings on a restart.
    synchronous : str
        SQLite ``synchronous`` (``NORMAL`` or ``FULL``), see :class:`Store`.
    background_checkpoint_s : float
        WAL checkpoint interval of the store's background thread (0: inside commits).
    checkpoint_every : int
        Store the tracker's state (~77 kB at N = 500) with every this many accepted
        products; a restart replays at most ``checkpoint_every - 1`` steps (:func:`replay`).
    cache : str or Path, optional
        Folder where a new store's measurement model is kept by a digest of the model
        and the tracker settings, and found by the next new store with the same ones
        (:mod:`formtwin.service.cache`; None: built every time).
    """
    path = Path(store_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    store = Store(path, synchronous=synchronous,
                  background_checkpoint_s=background_checkpoint_s, exclusive=True)
    try:
        settings = check_settings(store, settings)
        model = load_model(settings.model)
        mpath = measurement_path(path)
        if not mpath.exists():
            _new_measurement(model, settings, store.get_meta("model_digest"), mpath, cache)
        # always the saved file, so the first run and every restart use identical numbers
        measurement = MeasurementModel.load(mpath)
        tracker = build_tracker(model, settings.tracker, measurement)
        if store.checkpoint() is None:  # the tracker's first state: replays start there
            store.execute("INSERT INTO checkpoint(id, seq, data) VALUES (1, 0, ?)",
                          (tracker.state_bytes(),))
        replay(store, tracker)
        gate = OutlierGate(k=settings.gate_k) if settings.gate_k > 0 else None
        plausible = Plausibility.from_model(model, settings.min_peak_N, settings.clip_samples,
                                            settings.peak_window_ms)
        health = ModelHealth(store, HealthRule(settings.health_k, settings.health_m),
                             plausible.expected_peak_N, explainer(tracker))
        limits = settings.limits(model.spec.n_t, model.spec.n_outputs)
        return Processor(store, tracker, limits, gate,
                         health=health, plausible=plausible, checkpoint_every=checkpoint_every)
    except BaseException:
        store.close()
        raise
