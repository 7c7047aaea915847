"""Control of the final angle from the estimates.

* :mod:`~formtwin.control.feedforward`: :class:`Feedforward` chooses each product's press
  setting ``u`` after its stage-1 curve, minimising the posterior expected squared error of
  the final angle over the particle cloud, within the actuator's limits and maximum step;
* :mod:`~formtwin.control.runtorun`: :class:`EwmaRunToRun`, today's practice: an EWMA
  run-to-run controller on the measured final angles of earlier products;
* :mod:`~formtwin.control.combined`: :class:`Combined`, feedforward plus feedback: the
  feedforward aimed at the target minus an EWMA of its own prediction error;
* :mod:`~formtwin.control.predictive`: :class:`Predictive`, the feedforward on the
  posterior predictive of the measured final angle, the camera's late noisy values entering
  through a learned discrepancy (a :class:`Corrector`).

Generic numerics: the process enters only as a function ``final_angle(u) -> (N, n_u)``
(the final angle of every particle at each candidate setting), so this package sits beside
the filters, below the tracker. See ``docs/explanation/control.md``.
"""

from formtwin.control.combined import (
    TUNED_FIXED_LAM,
    TUNED_FIXED_RHO,
    TUNED_FIXED_WEIGHT,
    TUNED_LAM,
    TUNED_RHO,
    Combined,
)
from formtwin.control.feedforward import Actuator, Feedforward, Suggestion, weighted_quantile
from formtwin.control.predictive import Corrector, Predictive
from formtwin.control.runtorun import EwmaRunToRun

__all__ = ["TUNED_FIXED_LAM", "TUNED_FIXED_RHO", "TUNED_FIXED_WEIGHT", "TUNED_LAM", "TUNED_RHO",
           "Actuator", "Combined", "Corrector", "EwmaRunToRun", "Feedforward", "Predictive",
           "Suggestion", "weighted_quantile"]
