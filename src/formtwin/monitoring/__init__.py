"""Monitoring of the estimates: EWMA and CUSUM control charts on the estimated state and the
predicted angles, a model-mismatch chart on the filter's health, and alarms.

Layer: above the tracker (it consumes :class:`~formtwin.estimates.Estimate`), below the
study, the service and the command line. See ``docs/explanation/monitoring.md``.

* :mod:`~formtwin.monitoring.charts`: the charts and their run-length design;
* :mod:`~formtwin.monitoring.glr`: the GLR chart for a level change of an AR quantity;
* :mod:`~formtwin.monitoring.incontrol`: in-control AR models and health references;
* :mod:`~formtwin.monitoring.monitor`: :class:`Monitor`, :class:`Alarm`;
  :mod:`~formtwin.monitoring.config`: :class:`MonitorConfig`;
  :mod:`~formtwin.monitoring.bank`: the monitor's per-product pass over arrays (Numba);
* :mod:`~formtwin.monitoring.episodes`: alarm episodes (one per chart and variable from its
  first signal until the chart is quiet) and their clear-after;
* :mod:`~formtwin.monitoring.calibrate`: a monitor from a simulated in-control run;
* :mod:`~formtwin.monitoring.scenarios`: production runs with known changes;
* :mod:`~formtwin.monitoring.bound`: what the curves allow any chart to see of a step (the
  linear-Gaussian approximation: Kalman filter, Willsky-Jones GLR).
"""

from formtwin.monitoring.charts import Cusum, Ewma
from formtwin.monitoring.incontrol import InControl, Reference
from formtwin.monitoring.monitor import Alarm, Monitor, MonitorConfig

__all__ = ["Alarm", "Cusum", "Ewma", "InControl", "Monitor", "MonitorConfig", "Reference"]
