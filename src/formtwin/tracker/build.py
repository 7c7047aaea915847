"""The one assembly path: a tracker from a process model and a :class:`TrackerConfig`.

The study, the service, the command line and the examples build their trackers here, so
the measurement model (``K_MC`` from ``config.n_mc`` Monte-Carlo curves about ``config.mu``,
the residual covariance of a calibrated metamodel when ``config.likelihood`` is
``"calibrated"``, likelihood ``config.nu``) is made the same way everywhere: with one BLAS
thread, as the steps run, so that a tracker's numbers do not depend on how many threads
the environment gives BLAS (a multi-threaded product of the Monte-Carlo curves sums in
another order).
"""

from __future__ import annotations

import logging

import numpy as np

from formtwin._threads import single_blas_thread
from formtwin.measurement import MeasurementModel, ProcessModel
from formtwin.tracker.config import TrackerConfig
from formtwin.tracker.core import Tracker
from formtwin.tracker.discrepancy import residual_covariance

log = logging.getLogger(__name__)


def build_measurement(model: ProcessModel, config: TrackerConfig,
                      rng: np.random.Generator | None = None) -> MeasurementModel:
    """The measurement model for ``config``: ``K_MC`` from ``config.n_mc`` curves of
    ``model`` with the state about ``config.mu`` (mid-range when ``None``), times
    ``config.fraction^2``; plus ``K_res`` when ``config.likelihood == "calibrated"`` (the
    discrepancy likelihood takes the paper's and adds ``K_res`` itself).

    A model without residual statistics (the analytic stand-in, whose error is nil; a
    metamodel file from before the error model) gets ``K_res = 0`` with a warning for a
    metamodel. ``rng`` defaults to ``numpy.random.default_rng(config.seed)``.
    """
    rng = np.random.default_rng(config.seed) if rng is None else rng
    mu = None if config.mu is None else np.asarray(config.mu, dtype=np.float64)
    extra = None
    if config.likelihood == "calibrated":
        extra = residual_covariance(model)
        if extra is None and hasattr(model, "residuals"):
            log.warning("calibrated likelihood: the metamodel has no residual statistics "
                        "(refit it with `formtwin metamodel fit`); using K_res = 0")
    with single_blas_thread():
        return MeasurementModel.from_monte_carlo(model, mu=mu, n=config.n_mc, rng=rng,
                                                 nu=config.nu, fraction=config.fraction,
                                                 sensor_noise=config.sensor_noise,
                                                 extra_cov=extra)


def build_tracker(model: ProcessModel, config: TrackerConfig | None = None,
                  measurement: MeasurementModel | None = None) -> Tracker:
    """A fresh tracker on ``model`` with ``config`` (default :class:`TrackerConfig()`).

    ``measurement`` defaults to :func:`build_measurement` of ``model`` and ``config``; a
    given one must have been made for the same ``model`` (its ``nu`` wins over the
    config's).
    """
    config = TrackerConfig() if config is None else config
    with single_blas_thread():
        if measurement is None:
            measurement = build_measurement(model, config)
        return Tracker(model, measurement, config)
