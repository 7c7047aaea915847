"""Pseudo-data of the line's sensors: each sensor's reading of every product of a
realisation, the truth plus the sensor's Gaussian noise.

A state sensor reads the realisation's true state variable, an output sensor the data
source's model output (the physics model's final angle for the ``FE`` sources, the
metamodel's for ``MM``), both at the product's own setting. The noise comes from its own
random stream, ``SeedSequence([seed, realisation]).spawn`` (child 0, then one child per
sensor in the spec's order), so the curves and truth of a realisation (drawn from
``SeedSequence([seed, realisation])`` itself) are the same with or without sensors, and a
sensor's readings do not depend on which other sensors a run uses. The standard normals
are scaled by the noise, so readings at two noise levels share their draws.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from formtwin.spec import ProcessSpec, Sensor
from formtwin.spec.sensors import line_sensors, output_column
from formtwin.study.pseudodata import Realisation

FloatArray = NDArray[np.float64]


def sensor_noise(spec: ProcessSpec, seed: int, realisation: int, n: int) -> dict[str, FloatArray]:
    """Standard normal draws (n,) per sensor of ``spec``'s line (by name), from the
    realisation's sensor stream (see the module doc)."""
    sensors = line_sensors(spec)
    parent = np.random.SeedSequence([seed, realisation]).spawn(1)[0]
    return {s.name: np.random.default_rng(child).standard_normal(n)
            for s, child in zip(sensors, parent.spawn(len(sensors)), strict=True)}


def sensor_truth(spec: ProcessSpec, sensor: Sensor, real: Realisation,
                 source: str) -> FloatArray:
    """What ``sensor`` reads without noise (n,), internal units: the true state variable,
    or the data ``source``'s model output (NaN where its run failed)."""
    if sensor.kind == "state":
        out: FloatArray = real.x[:, spec.state.index[sensor.measures]].astype(np.float64)
        return out
    a = real.angles[source][:, output_column(spec, sensor.measures)].astype(np.float64)
    return np.where(real.ok[source], a, np.nan)


def sensor_readings(spec: ProcessSpec, real: Realisation, source: str, seed: int,
                    names: Sequence[str] | None = None,
                    noise: dict[str, float] | None = None) -> dict[str, FloatArray]:
    """Readings (n,) per sensor ``names`` (None: all of the line's) of realisation
    ``real`` with data ``source``: :func:`sensor_truth` plus the sensor's noise
    (``noise`` overrides the spec's sd by name, internal units)."""
    sensors = {s.name: s for s in line_sensors(spec)}
    chosen = list(sensors) if names is None else list(names)
    unknown = [n for n in chosen if n not in sensors]
    if unknown:
        raise ValueError(f"sensors {unknown} unknown; the spec's line has "
                         f"{', '.join(sensors) or 'none'}")
    z = sensor_noise(spec, seed, real.index, real.n)
    sd = {n: sensors[n].noise for n in chosen} | dict(noise or {})
    return {n: sensor_truth(spec, sensors[n], real, source) + sd[n] * z[n] for n in chosen}


__all__ = ["sensor_noise", "sensor_readings", "sensor_truth"]
