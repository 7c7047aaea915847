"""Process definition: variables, bounds and statistics, loaded from TOML.

A process spec names the hidden process state ``x`` (paper eq. 4-5, with its statistics
``theta_s = (mu, sigma, rho)``), the constant machine parameters ``theta``, the deviation
parameters ``theta_d`` of ``z = g(z~, theta_d)``, the press settings ``u`` the line sets per
product (control inputs: known, never estimated) and the time grid of the stage-1 force
curve. The model of a run takes ``(x, theta, u)`` (:attr:`ProcessSpec.run_inputs`); the
tracker estimates ``(x, theta, theta_d)`` (:attr:`ProcessSpec.augmented`).

Internal unit system
--------------------
Everything inside formtwin is in **mm, N, s and MPa** (N/mm^2); dimensionless values are
fractions (a deviation of 20 % is 0.2). Spec files are written in the units of the paper's
Table 1 (um, kN/mm, %, ms, ...) and converted on load; :data:`UNITS` lists the units a spec
may use and their factor to the internal unit. ``Variable.unit`` keeps the file's unit for
display, ``Variable.internal_unit`` names the internal one.

Table 1 of the paper lost a cell in its row ``log(eps0_dot)``; the bundled demonstrator
reads it as min 1.5, max 2.9, mu_min 2.0, mu_max 2.4, sigma 0.05, rho 0.8 (see
``specs/demonstrator.toml``).

>>> spec = load_spec()
>>> spec.state.index["yield_stress"], spec.params.index["press_stiffness"]
(0, 2)
>>> float(spec.state["thickness"].lo)  # 295 um, in mm
0.295
>>> spec.inputs.names[-1], spec.n_inputs, spec.deviation.names[4]
('press_stiffness', 10, 'speed_scaling_1')
>>> spec.controls.names, float(spec.controls["stage2_depth"].nominal), spec.n_run_inputs
(('stage2_depth',), 0.0, 11)
>>> spec.run_columns(spec.inputs.lo, u=0.05).shape
(1, 11)
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

import numpy as np

from formtwin.spec.model import (
    DEFAULT_OUTPUTS,
    DEMONSTRATOR,
    DEVIATION_KINDS,
    UNITS,
    Deviation,
    FloatArray,
    Group,
    Output,
    ProcessSpec,
    SpecError,
    Variable,
)
from formtwin.spec.reader import KEYS, Reader
from formtwin.spec.sensors import Sensor, parse_sensors

__all__ = ["DEFAULT_OUTPUTS", "DEMONSTRATOR", "DEVIATION_KINDS", "KEYS", "UNITS", "Deviation",
           "FloatArray", "Group", "Output", "ProcessSpec", "Sensor", "SpecError", "Variable",
           "load_spec", "parse_spec"]

#: internal unit of the curve axis -> the axis it measures
AXES = {"s": "time", "mm": "stroke"}


def load_spec(path: str | Path | None = None) -> ProcessSpec:
    """Load and validate a process spec; ``None`` loads the bundled demonstrator."""
    if path is None:
        ref = resources.files("formtwin") / "specs" / f"{DEMONSTRATOR}.toml"
        return parse_spec(ref.read_text(encoding="utf-8"), source=f"{DEMONSTRATOR}.toml")
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise SpecError(f"{p}: cannot read spec file ({exc.strerror})") from exc
    return parse_spec(text, source=str(p))


def parse_spec(text: str, source: str = "<string>") -> ProcessSpec:
    """Parse and validate the TOML text of a spec; errors name ``source``."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{source}: not valid TOML ({exc})") from exc
    r = Reader(source)
    r.keys(doc, "", set(KEYS["<top>"]))
    process = r.table(doc, "process")
    r.keys(process, "process", set(KEYS["process"]))
    curve = r.table(doc, "curve")
    r.keys(curve, "curve", set(KEYS["curve"]))
    t_unit, t_scale = r.unit(curve, "curve")
    if t_unit not in AXES:
        raise SpecError(f"{source}: curve.unit = {curve['unit']!r}, expected a time unit "
                        "(s, ms) or a stroke unit (mm, um)")
    noise_sd = r.number(curve, "curve", "noise_sd") if "noise_sd" in curve else 0.0
    if not noise_sd >= 0:
        raise SpecError(f"{source}: curve.noise_sd = {noise_sd!r}, expected a force std >= 0 N")
    t0 = r.number(curve, "curve", "t_start") * t_scale
    t1 = r.number(curve, "curve", "t_end") * t_scale
    n = r.integer(curve, "curve", "n_samples")
    if not t0 < t1:
        raise SpecError(f"{source}: curve.t_start = {t0 / t_scale} must be below t_end")
    if n < 3:
        raise SpecError(f"{source}: curve.n_samples = {n}, expected at least 3")
    if r.text(curve, "curve", "force_unit") != "N":
        raise SpecError(f"{source}: curve.force_unit = {curve['force_unit']!r}, expected 'N'")
    state = Group(tuple(r.variable(t, f"state[{i}]", True) for i, t in
                        enumerate(r.array(doc, "state"))))
    params = Group(tuple(r.variable(t, f"parameter[{i}]", False) for i, t in
                         enumerate(r.array(doc, "parameter"))))
    controls = Group(tuple(r.variable(t, f"control[{i}]", False, is_control=True) for i, t in
                           enumerate(r.array(doc, "control"))) if "control" in doc else ())
    deviation = r.deviation(r.table(doc, "deviation"), t0, t1)
    outputs = tuple(r.output(t, f"output[{i}]") for i, t in
                    enumerate(r.array(doc, "output"))) if "output" in doc else DEFAULT_OUTPUTS
    seen: set[str] = set()
    for name in (*(state + params + controls + deviation.group).names,
                 *(o.name for o in outputs)):
        if name in seen:
            raise SpecError(f"{source}: variable name {name!r} is used twice")
        seen.add(name)
    return ProcessSpec(
        name=r.text(process, "process", "name"),
        description=str(process.get("description", "")),
        state=state,
        params=params,
        deviation=deviation,
        time=np.linspace(t0, t1, n),
        source=source,
        text=text,
        controls=controls,
        sensors=parse_sensors(doc.get("sensor"), state, source,
                              tuple(o.name for o in outputs)),
        outputs=outputs,
        axis=AXES[t_unit],
        axis_unit=str(curve["unit"]),
        axis_scale=t_scale,
        noise_sd=noise_sd,
    )
