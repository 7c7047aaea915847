"""The line's sensors besides the stage-1 force curve: ``[[sensor]]`` entries of a spec.

A sensor measures one scalar of a product: a state variable (a strip-thickness gauge:
``measures = "thickness"``) or a model output (a camera after stage 2: ``measures =
"angle_stage2"``, the final angle), with Gaussian noise of standard deviation ``noise`` in
the sensor's ``unit``, and a ``delay`` in products: the value of product ``k`` is known
after the curve of product ``k + delay`` (0: with the product's own curve). Which sensors a
run uses is a tracker setting (:attr:`formtwin.tracker.TrackerConfig.sensors`).

The model outputs a sensor may name are :func:`output_names`; :func:`output_column` maps a
name to its column in the model's output (angle) array, the one place that knows the
layout.

>>> from formtwin.spec import load_spec
>>> spec = load_spec()
>>> [(s.name, s.measures, s.delay) for s in spec.sensors]
[('gauge', 'thickness', 0), ('camera', 'angle_stage2', 1)]
>>> spec.sensor("gauge").noise, spec.sensor("camera").noise  # mm (0.5 um), deg
(0.0005, 0.2)
>>> output_column(spec, "angle_stage2")
1
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from formtwin.spec.model import UNITS, Group, SpecError
from formtwin.spec.reader import KEYS

if TYPE_CHECKING:
    from formtwin.spec.model import ProcessSpec

#: the model outputs of a run, in the column order of its angle array (degrees)
OUTPUTS = ("angle_stage1", "angle_stage2")

#: units a sensor of a model output (an angle) may be written in -> factor to degrees
ANGLE_UNITS = {"deg": 1.0}


@dataclass(frozen=True)
class Sensor:
    """One ``[[sensor]]`` entry, in internal units.

    Attributes
    ----------
    name : identifier used by the tracker settings and :meth:`Tracker.fuse`.
    measures : a state variable's name or a model output's name (:func:`output_names`).
    kind : ``"state"`` or ``"output"``.
    noise : standard deviation of the Gaussian noise, internal units (the state
        variable's, degrees for an angle), ``>= 0``.
    delay : products after which the value is known (``>= 0``).
    unit : the unit ``noise`` was written in (for display).
    label, note : free text.
    """

    name: str
    measures: str
    kind: str
    noise: float
    delay: int
    unit: str
    label: str = ""
    note: str = ""


def output_names(spec: ProcessSpec | None = None) -> tuple[str, ...]:
    """Names of the scalar model outputs of ``spec`` (the columns of the model's angle
    array): ``spec.output_names``; without a spec the demonstrator's."""
    return OUTPUTS if spec is None else spec.output_names


def final_output(spec: ProcessSpec | None = None) -> str:
    """The output a camera's values calibrate and teach the discrepancy of: the spec's last
    (the demonstrator's final angle ``angle_stage2``)."""
    return output_names(spec)[-1]


def output_column(spec: ProcessSpec | None, name: str) -> int:
    """Column of output ``name`` in the model's output (angle) array; ``KeyError``
    naming the known outputs."""
    names = output_names(spec)
    if name not in names:
        raise KeyError(f"no model output {name!r}; known: {', '.join(names)}")
    return names.index(name)


def parse_sensors(entries: Any, state: Group, source: str,
                  outputs: tuple[str, ...] = OUTPUTS) -> tuple[Sensor, ...]:
    """The ``[[sensor]]`` entries (a list of tables, or None) checked against the state
    variables ``state`` and the model outputs ``outputs`` (the spec's ``[[output]]``
    names); :class:`SpecError` naming the file, entry, field and value."""
    if entries is None:
        return ()
    if not isinstance(entries, list):
        raise SpecError(f"{source}: sensor = {entries!r}, expected [[sensor]] tables")
    out: list[Sensor] = []
    for i, t in enumerate(entries):
        out.append(_sensor(t, f"sensor[{i}]", state, source, outputs))
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SpecError(f"{source}: sensor name(s) {dup} used twice")
    return tuple(out)


def _fail(source: str, where: str, key: str, value: Any, expected: str) -> SpecError:
    return SpecError(f"{source}: {where}.{key} = {value!r}, expected {expected}")


def _sensor(t: Any, where: str, state: Group, source: str,
            outputs: tuple[str, ...] = OUTPUTS) -> Sensor:
    if not isinstance(t, Mapping):
        raise SpecError(f"{source}: {where} = {t!r}, expected a table")
    allowed = set(KEYS["sensor"])
    for key in t:
        if key not in allowed:
            raise _fail(source, where, key, t[key], f"one of the keys {sorted(allowed)}")
    for key in ("name", "measures", "unit", "noise", "delay"):
        if key not in t:
            raise SpecError(f"{source}: {where}.{key} is missing")
    name = t["name"]
    if not isinstance(name, str) or not name.isidentifier():
        raise _fail(source, where, "name", name, "a Python identifier (letters, digits, _)")
    where = f"{where} {name!r}"
    measures, unit, noise, delay = t["measures"], t["unit"], t["noise"], t["delay"]
    if not isinstance(measures, str) or (measures not in state.names and measures not in
                                         outputs):
        raise _fail(source, where, "measures", measures, "a state variable ("
                    f"{', '.join(state.names)}) or a model output ({', '.join(outputs)})")
    kind = "state" if measures in state.names else "output"
    if kind == "state":
        internal = state[measures].internal_unit
        if unit not in UNITS or UNITS[unit][0] != internal:
            ok = sorted(u for u, (i, _) in UNITS.items() if i == internal)
            raise _fail(source, where, "unit", unit, f"a unit of {measures} ({', '.join(ok)})")
        scale = UNITS[unit][1]
    else:
        if unit not in ANGLE_UNITS:
            raise _fail(source, where, "unit", unit, f"one of {sorted(ANGLE_UNITS)}")
        scale = ANGLE_UNITS[unit]
    if isinstance(noise, bool) or not isinstance(noise, int | float) or not (
            math.isfinite(noise) and noise >= 0):
        raise _fail(source, where, "noise", noise, "a finite standard deviation >= 0")
    if isinstance(delay, bool) or not isinstance(delay, int) or delay < 0:
        raise _fail(source, where, "delay", delay, "a whole number of products >= 0")
    return Sensor(name=name, measures=measures, kind=kind, noise=float(noise) * scale,
                  delay=delay, unit=unit, label=str(t.get("label", name)),
                  note=str(t.get("note", "")))


def line_sensors(spec: ProcessSpec) -> tuple[Sensor, ...]:
    """The sensors of ``spec``'s line: its ``[[sensor]]`` entries; a spec without any that
    has the bundled demonstrator's name and variables (e.g. the spec stored in a metamodel
    file made before sensors entered the spec) takes the bundled demonstrator's."""
    if spec.sensors:
        return spec.sensors
    from formtwin.spec.model import DEMONSTRATOR
    if spec.name != DEMONSTRATOR:
        return ()
    names, sensors = _bundled()
    return sensors if names == spec.augmented.names else ()


@functools.lru_cache(maxsize=1)
def _bundled() -> tuple[tuple[str, ...], tuple[Sensor, ...]]:
    """The bundled demonstrator's augmented names and sensors (parsed once)."""
    from formtwin.spec import load_spec
    bundled = load_spec()
    return bundled.augmented.names, bundled.sensors


def sensor_by_name(sensors: Sequence[Sensor], name: str) -> Sensor:
    """The sensor called ``name``; ``KeyError`` naming the known ones."""
    for s in sensors:
        if s.name == name:
            return s
    raise KeyError(f"no sensor {name!r}; the spec has: "
                   f"{', '.join(s.name for s in sensors) or 'none'}")


#: how far (in the sensor's noise sd) a state variable's value may lie outside the spec's
#: bounds of it and still be fused
RANGE_MARGIN = 5.0


def value_refusal(spec: ProcessSpec, sensor: Sensor, value: Any, offset: Any = 0.0
                  ) -> str | None:
    """Why ``sensor``'s ``value`` (with a known ``offset``) cannot be fused whatever the
    particles (None: it can): not a finite number, or a state variable's value outside the
    spec's bounds of it by more than :data:`RANGE_MARGIN` noise sd (a glitch or a unit
    mixed up: the model covers no such product, and the particles would be pulled to the
    box's edge).

    >>> from formtwin.spec import load_spec
    >>> spec = load_spec()
    >>> value_refusal(spec, spec.sensor("gauge"), 0.3) is None
    True
    >>> value_refusal(spec, spec.sensor("gauge"), 300.0)  # um, not mm
    "value 300 mm: outside thickness's range in the spec, [0.295, 0.305] mm"
    """
    for name, v in (("value", value), ("offset", offset)):
        if isinstance(v, bool) or not isinstance(v, int | float | np.number) \
                or not math.isfinite(float(v)):
            return f"{name} = {v!r}, expected a finite number"
    if sensor.kind == "state":
        var = spec.state[sensor.measures]
        margin = RANGE_MARGIN * sensor.noise
        if not var.lo - margin <= float(value) <= var.hi + margin:
            return (f"value {float(value):g} {var.internal_unit}: outside {var.name}'s range "
                    f"in the spec, [{var.lo:g}, {var.hi:g}] {var.internal_unit}")
    return None


__all__ = ["ANGLE_UNITS", "OUTPUTS", "RANGE_MARGIN", "Sensor", "final_output", "line_sensors",
           "output_column", "output_names", "parse_sensors", "sensor_by_name", "value_refusal"]
