"""Physically implausible but well-formed strokes, rejected before the tracker.

A dead sensor sends perfectly valid JSON: 101 zeros, or a curve flat at the value where the
amplifier saturates. The tracker would step on it (an all-zero curve even gets a *better*
log-likelihood than real ones when the model's curves are small at the window's edges), so
the service refuses such strokes first, each with its own reason
(:data:`formtwin.service.messages.REASONS`):

``no_stroke``
    peak force below ``min_peak_N``: no part was bent, or the sensor is unplugged;
``clipped_sensor``
    at least ``clip_samples`` consecutive samples equal (to ``clip_rel_tol`` of the peak)
    to the curve's maximum: a clipped or saturated sensor, or a flat curve;
``peak_outside_window``
    the time of the peak force outside ``peak_window_s`` (or at the first or last sample,
    unless the model's own curves peak there: on a stroke axis the force often peaks at
    the end of the stroke): the trigger or the time base is wrong.

Limits from the spec's ranges (:meth:`Plausibility.from_model`): the model's curves at the
``2^d`` corners of the input box and 1000 points inside it (seeded), each distorted by the
four extreme constant deviations ``g`` (force and speed scaling at their bounds), give the
smallest peak ``P_min`` and the range of peak times. Then ``min_peak_N = 0.5 P_min`` and the
window is that range widened by 5 samples on each side. For the bundled demonstrator
(physics metamodel): ``P_min`` about 50 N and peaks between -45 and 0 ms. Each limit can be
overridden (``formtwin serve --min-peak``, ``--clip-samples``, ``--peak-window``).

>>> import numpy as np
>>> lim = Plausibility(min_peak_N=20.0, clip_samples=3, peak_window_s=(-0.05, 0.0),
...                    time=np.linspace(-0.08, 0.02, 101))
>>> c = 100.0 * np.exp(-((lim.time + 0.01) / 0.01) ** 2)
>>> lim.check(c) is None, lim.check(0 * c).reason, lim.check(np.minimum(c, 30.0)).reason
(True, 'no_stroke', 'clipped_sensor')
>>> lim.check(np.roll(c, 25)).reason
'peak_outside_window'
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from formtwin.deviation import DeviationModel
from formtwin.measurement import ProcessModel
from formtwin.service.messages import MessageError, Stroke

FloatArray = NDArray[np.float64]

#: ``min_peak_N`` as a share of the smallest peak the model gives over the spec's ranges
PEAK_FLOOR_SHARE = 0.5
#: samples added on each side of the model's range of peak times
WINDOW_MARGIN_SAMPLES = 5
#: consecutive samples at the maximum that make a clipped curve. Curves of the bundled DOE
#: (7048, the whole box) and of physics production runs (10 000), sampled every 1 ms and clipped
#: at 80 % of their peak keep >= 4 samples at the clip level (at 5, 1 in 1000 passed); unclipped,
#: each has one sample at its maximum. The rule assumes a sensor resolution finer than
#: ``clip_rel_tol`` of the peak: rounded to 1 N, production-run curves keep up to 3 equal samples
#: at their peak, but flat-topped ones from the box's edges up to 25, so a coarsely quantised
#: sensor needs its own ``--clip-samples`` (or a larger ``clip_rel_tol``).
CLIP_SAMPLES = 4


@dataclass(frozen=True)
class Plausibility:
    """Limits of a plausible stroke (see module doc); ``check`` applies them.

    Attributes
    ----------
    min_peak_N : lowest accepted peak force, N.
    clip_samples : that many consecutive samples at the maximum make a clipped curve.
    peak_window_s : (lo, hi) accepted times of the peak force, s.
    time : (n_t,) the spec's time grid, s.
    clip_rel_tol : samples within this share of the peak count as equal to it.
    expected_peak_N : (lo, hi) range of the model's peak forces over the spec's ranges, N
        (for messages; ``None`` when the limits were given by hand).
    edge_peaks : (first, last): a peak at the first / last sample is plausible (the model's
        curves peak there).
    axis_unit, axis_scale : the curve axis' unit for messages and its factor to the
        internal one (the spec's ``[curve] unit``; ms for the demonstrator).
    """

    min_peak_N: float
    clip_samples: int
    peak_window_s: tuple[float, float]
    time: FloatArray = field(repr=False)
    clip_rel_tol: float = 1e-6
    expected_peak_N: tuple[float, float] | None = None
    edge_peaks: tuple[bool, bool] = (False, False)
    axis_unit: str = "ms"
    axis_scale: float = 1e-3

    def __post_init__(self) -> None:
        if self.clip_samples < 2:
            raise ValueError(f"clip_samples = {self.clip_samples}, expected >= 2")
        lo, hi = self.peak_window_s
        if not lo < hi:
            raise ValueError(f"peak window ({lo * 1e3:g}, {hi * 1e3:g}) ms is empty")

    @classmethod
    def from_model(cls, model: ProcessModel, min_peak_N: float | None = None,
                   clip_samples: int = CLIP_SAMPLES,
                   peak_window_ms: tuple[float, float] | None = None,
                   seed: int = 0) -> Plausibility:
        """Limits derived from the spec's ranges through ``model`` (overrides win)."""
        spec = model.spec
        lo, hi = spec.inputs.lo, spec.inputs.hi
        d = lo.size
        corners = np.array(list(itertools.product((0.0, 1.0), repeat=d))) if d <= 12 else \
            np.empty((0, d))
        inside = np.random.default_rng(seed).random((1000, d))
        X = lo + (hi - lo) * np.vstack([corners, inside])
        curves = model.predict_curves(X)
        curves = curves[np.all(np.isfinite(curves), axis=1)]
        g = DeviationModel.from_spec(spec)
        dev, k = spec.deviation.group, g.knots.size
        peaks, times = [], []
        # every corner of the chosen kinds, each held constant over its knots
        ends = [(dev.lo[j * k], dev.hi[j * k]) for j in range(len(g.kinds))]
        for corner in itertools.product(*ends):
            td = np.concatenate([np.full(k, c) for c in corner]) if corner else np.zeros(0)
            z = g.apply(curves, np.tile(td, (len(curves), 1)))
            peaks.append(z.max(axis=1))
            times.append(spec.time[np.argmax(z, axis=1)])
        p, t = np.concatenate(peaks), np.concatenate(times)
        dt = float(spec.time[1] - spec.time[0])
        window = (float(t.min()) - WINDOW_MARGIN_SAMPLES * dt,
                  float(t.max()) + WINDOW_MARGIN_SAMPLES * dt)
        if peak_window_ms is not None:  # in the spec's curve unit (ms for the demonstrator)
            window = (peak_window_ms[0] * spec.axis_scale, peak_window_ms[1] * spec.axis_scale)
        return cls(min_peak_N=PEAK_FLOOR_SHARE * float(p.min()) if min_peak_N is None
                   else float(min_peak_N), clip_samples=int(clip_samples),
                   peak_window_s=window, time=np.asarray(spec.time, dtype=np.float64),
                   expected_peak_N=(float(p.min()), float(p.max())),
                   edge_peaks=(bool(t.min() <= spec.time[0]), bool(t.max() >= spec.time[-1])),
                   axis_unit=spec.axis_unit, axis_scale=spec.axis_scale)

    def check(self, force: FloatArray, part_id: str | None = None) -> MessageError | None:
        """The rejection of curve ``force`` (n_t,) N, or None if it is plausible."""
        f = np.asarray(force, dtype=np.float64)
        i = int(np.argmax(f))
        top = float(f[i])
        if top < self.min_peak_N:
            return MessageError("no_stroke", f"peak force {top:.4g} N < {self.min_peak_N:.4g} "
                                "N (no stroke or sensor unplugged)", part_id)
        at_top = np.abs(f - top) <= self.clip_rel_tol * abs(top)
        n_top = int(np.count_nonzero(at_top))  # a run is no longer than the count
        run = _longest_run(at_top) if n_top >= self.clip_samples else n_top
        if run >= self.clip_samples:
            return MessageError("clipped_sensor", f"{run} consecutive samples at the maximum "
                                f"{top:.6g} N (>= {self.clip_samples}: clipped or saturated "
                                "sensor)", part_id)
        t = float(self.time[i])
        lo, hi = self.peak_window_s
        edge = (i == 0 and not self.edge_peaks[0]) or (i == f.size - 1 and not self.edge_peaks[1])
        if not lo <= t <= hi or edge:
            u, sc = self.axis_unit, self.axis_scale
            return MessageError("peak_outside_window", f"peak force at {t / sc:.4g} {u}, "
                                f"outside {lo / sc:.4g} .. {hi / sc:.4g} {u}"
                                + (" (at the curve's edge)" if edge else ""), part_id)
        return None

    def __call__(self, stroke: Stroke) -> None:
        """Raise the :class:`MessageError` of an implausible stroke (processor hook)."""
        err = self.check(stroke.force_N, stroke.part_id)
        if err is not None:
            raise err

    def describe(self) -> str:
        """One line for the service's start-up output."""
        lo, hi = self.peak_window_s
        u, sc = self.axis_unit, self.axis_scale
        return (f"plausibility: peak >= {self.min_peak_N:.4g} N, < {self.clip_samples} "
                f"samples at the maximum, peak time in {lo / sc:.4g} .. {hi / sc:.4g} {u}")


def _longest_run(mask: NDArray[np.bool_]) -> int:
    """Length of the longest run of True in a 1-D mask."""
    if not mask.any():
        return 0
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int((ends - starts).max())


__all__ = ["CLIP_SAMPLES", "PEAK_FLOOR_SHARE", "WINDOW_MARGIN_SAMPLES", "Plausibility"]
