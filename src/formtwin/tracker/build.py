"""The one assembly path: a tracker from a process model and a :class:`TrackerConfig`.

The study, the service, the command line and the examples build their trackers here, so
the measurement model (``K_MC`` from ``config.n_mc`` Monte-Carlo curves about ``config.mu``,
likelihood ``config.nu``) is made the same way everywhere.
"""

from __future__ import annotations

import numpy as np

from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.tracker.config import TrackerConfig
from formtwin.tracker.core import Tracker


def build_measurement(model: ProcessModel, config: TrackerConfig,
                      rng: np.random.Generator | None = None) -> MeasurementModel:
    """The measurement model of eq. 12 for ``config``: ``K_MC`` from ``config.n_mc`` curves
    of ``model`` with the state about ``config.mu`` (mid-range when ``None``).

    ``rng`` defaults to ``numpy.random.default_rng(config.seed)``.
    """
    rng = np.random.default_rng(config.seed) if rng is None else rng
    mu = None if config.mu is None else np.asarray(config.mu, dtype=np.float64)
    return MeasurementModel.from_monte_carlo(model, mu=mu, n=config.n_mc, rng=rng,
                                             nu=config.nu)


def build_tracker(model: ProcessModel, config: TrackerConfig | None = None,
                  measurement: MeasurementModel | None = None) -> Tracker:
    """A fresh tracker on ``model`` with ``config`` (default :class:`TrackerConfig()`).

    ``measurement`` defaults to :func:`build_measurement` of ``model`` and ``config``; a
    given one must have been made for the same ``model`` (its ``nu`` wins over the
    config's).
    """
    config = TrackerConfig() if config is None else config
    if measurement is None:
        measurement = build_measurement(model, config)
    return Tracker(model, measurement, config)
