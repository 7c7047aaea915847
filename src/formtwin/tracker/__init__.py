"""The online tracker, by job:

* :mod:`~formtwin.tracker.config`: :class:`TrackerConfig`, the one set of settings;
* :mod:`~formtwin.tracker.ssm`: :class:`BendingSSM`, the augmented state-space model
  (evolution, jitter, measurement, deviation; ``simulate`` draws a production run);
* :mod:`~formtwin.tracker.core`: :class:`Tracker`, one filter step per product;
* :mod:`~formtwin.tracker.fit`: the absolute goodness of fit and health of an estimate;
* :mod:`~formtwin.tracker.fusion`: sensor values besides the curve, fused late and in any
  order (:meth:`Tracker.fuse`);
* :mod:`~formtwin.tracker.recorded`: :func:`track_recorded`, a recorded run with its
  sensor values, each fused when the line knew it;
* :mod:`~formtwin.tracker.state`: the state as bytes or checkpoint file, bit for bit;
* :mod:`~formtwin.tracker.build`: :func:`build_tracker`, the one assembly path.
"""

from formtwin.estimates import HEALTH, Estimate, Estimates, Fit
from formtwin.tracker.build import build_measurement, build_tracker
from formtwin.tracker.config import COMPARE, LIKELIHOODS, TrackerConfig
from formtwin.tracker.core import Tracker
from formtwin.tracker.fit import FitRule
from formtwin.tracker.fusion import FusionError, Posterior
from formtwin.tracker.recorded import Recorded, track_recorded
from formtwin.tracker.ssm import CHUNK, BendingSSM
from formtwin.tracker.state import TrackerState
from formtwin.tracker.validate import validate_controls, validate_curve

__all__ = ["BendingSSM", "CHUNK", "COMPARE", "HEALTH", "LIKELIHOODS", "Estimate", "Estimates",
           "Fit", "FitRule", "FusionError", "Posterior", "Recorded", "Tracker",
           "TrackerConfig", "TrackerState", "build_measurement", "build_tracker",
           "track_recorded", "validate_controls", "validate_curve"]
