"""Process definition: variables, bounds and statistics, loaded from TOML.

A process spec names the hidden process state ``x`` (paper eq. 4-5, with its statistics
``theta_s = (mu, sigma, rho)``), the constant machine parameters ``theta``, the deviation
parameters ``theta_d`` of ``z = g(z~, theta_d)`` and the time grid of the stage-1 force curve.

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
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: unit as written in a spec -> (internal unit, factor to multiply by)
UNITS: dict[str, tuple[str, float]] = {
    "MPa": ("MPa", 1.0),
    "GPa": ("MPa", 1e3),
    "mm": ("mm", 1.0),
    "um": ("mm", 1e-3),
    "N": ("N", 1.0),
    "kN": ("N", 1e3),
    "N/mm": ("N/mm", 1.0),
    "kN/mm": ("N/mm", 1e3),
    "s": ("s", 1.0),
    "ms": ("s", 1e-3),
    "%": ("-", 1e-2),
    "-": ("-", 1.0),
    "log10(1/s)": ("log10(1/s)", 1.0),
}

DEMONSTRATOR = "demonstrator"


class SpecError(ValueError):
    """A process spec is malformed; the message names the file, the field and the value."""


@dataclass(frozen=True)
class Variable:
    """One named scalar of the process, bounds in internal units.

    ``mu_min, mu_max, sigma, rho`` are set for state variables only (NaN otherwise).
    """

    name: str
    label: str
    unit: str
    internal_unit: str
    scale: float
    lo: float
    hi: float
    mu_min: float = math.nan
    mu_max: float = math.nan
    sigma: float = math.nan
    rho: float = math.nan
    note: str = ""

    @property
    def width(self) -> float:
        """``hi - lo`` in internal units."""
        return self.hi - self.lo


@dataclass(frozen=True)
class Group:
    """An ordered set of variables with a name -> column map.

    ``group["name"]`` is the :class:`Variable`, ``group.index["name"]`` its column.
    """

    variables: tuple[Variable, ...]
    index: Mapping[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "index", {v.name: i for i, v in enumerate(self.variables)})

    def __getitem__(self, name: str) -> Variable:
        try:
            return self.variables[self.index[name]]
        except KeyError:
            raise KeyError(f"no variable {name!r}; known: {', '.join(self.names)}") from None

    def __iter__(self) -> Iterator[Variable]:
        return iter(self.variables)

    def __len__(self) -> int:
        return len(self.variables)

    def __add__(self, other: Group) -> Group:
        return Group(self.variables + other.variables)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the variables, in order."""
        return tuple(v.name for v in self.variables)

    def _col(self, attr: str) -> FloatArray:
        return np.array([getattr(v, attr) for v in self.variables], dtype=np.float64)

    @property
    def lo(self) -> FloatArray:
        """Lower bounds, shape ``(d,)``."""
        return self._col("lo")

    @property
    def hi(self) -> FloatArray:
        """Upper bounds, shape ``(d,)``."""
        return self._col("hi")

    @property
    def mu_min(self) -> FloatArray:
        """(d,) lower bounds of the statistics mu, internal units."""
        return self._col("mu_min")

    @property
    def mu_max(self) -> FloatArray:
        """(d,) upper bounds of the statistics mu, internal units."""
        return self._col("mu_max")

    @property
    def mu_mid(self) -> FloatArray:
        """``(mu_min + mu_max) / 2``: the mean assumed when mu is unknown (series 4, 6)."""
        return 0.5 * (self.mu_min + self.mu_max)

    @property
    def sigma(self) -> FloatArray:
        """(d,) standard deviations of the state variables, internal units."""
        return self._col("sigma")

    @property
    def rho(self) -> FloatArray:
        """(d,) autocorrelations of the state variables (eq. 4-5)."""
        return self._col("rho")


@dataclass(frozen=True)
class Deviation:
    """Layout of ``theta_d``: force scaling then speed scaling at ``knots`` knots (s)."""

    group: Group
    knots: FloatArray

    @property
    def n_knots(self) -> int:
        """Number of deviation knots (the dimension of theta_d)."""
        return int(self.knots.size)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the deviation parameters theta_d."""
        return self.group.names


@dataclass(frozen=True)
class ProcessSpec:
    """A process: state ``x``, parameters ``theta``, deviation ``theta_d`` and time grid.

    ``inputs`` (state then parameters) are the model inputs, ``augmented`` (inputs then
    deviation) the particle filter's state. ``time`` is the force-curve grid in s.
    ``text`` is the TOML the spec was parsed from, so that files can carry their spec.
    """

    name: str
    description: str
    state: Group
    params: Group
    deviation: Deviation
    time: FloatArray
    source: str
    text: str = field(default="", repr=False, compare=False)

    @property
    def inputs(self) -> Group:
        """State then parameters: the 10 inputs of the process model."""
        return self.state + self.params

    @property
    def augmented(self) -> Group:
        """State, parameters, deviation: the particle filter's augmented state."""
        return self.inputs + self.deviation.group

    @property
    def n_inputs(self) -> int:
        """Number of model inputs ``[x, theta]`` (10 for Table 1)."""
        return len(self.state) + len(self.params)

    @property
    def n_t(self) -> int:
        """Samples per force curve on the time grid."""
        return int(self.time.size)

    @property
    def dt(self) -> float:
        """Time step of the uniform curve grid, s."""
        return float(self.time[1] - self.time[0])


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
    r = _Reader(source)
    r.keys(doc, "", {"process", "curve", "state", "parameter", "deviation"})
    process = r.table(doc, "process")
    curve = r.table(doc, "curve")
    r.keys(curve, "curve", {"unit", "t_start", "t_end", "n_samples", "force_unit"})
    t_unit, t_scale = r.unit(curve, "curve")
    if t_unit != "s":
        raise SpecError(f"{source}: curve.unit = {curve['unit']!r}, expected a time unit (s, ms)")
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
    deviation = r.deviation(r.table(doc, "deviation"), t0, t1)
    seen: set[str] = set()
    for v in (state + params + deviation.group):
        if v.name in seen:
            raise SpecError(f"{source}: variable name {v.name!r} is used twice")
        seen.add(v.name)
    return ProcessSpec(
        name=r.text(process, "process", "name"),
        description=str(process.get("description", "")),
        state=state,
        params=params,
        deviation=deviation,
        time=np.linspace(t0, t1, n),
        source=source,
        text=text,
    )


class _Reader:
    """Typed field access that raises :class:`SpecError` naming file, field and value."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, key: str, value: Any, expected: str) -> SpecError:
        field_name = f"{where}.{key}" if where else key
        return SpecError(f"{self.source}: {field_name} = {value!r}, expected {expected}")

    def keys(self, table: Mapping[str, Any], where: str, allowed: set[str]) -> None:
        for key in table:
            if key not in allowed:
                raise self.fail(where, key, table[key], f"one of the keys {sorted(allowed)}")

    def get(self, table: Mapping[str, Any], where: str, key: str) -> Any:
        if key not in table:
            raise SpecError(f"{self.source}: {where}.{key} is missing")
        return table[key]

    def table(self, doc: Mapping[str, Any], key: str) -> Mapping[str, Any]:
        value = self.get(doc, "<top>", key) if key in doc else None
        if not isinstance(value, dict):
            raise SpecError(f"{self.source}: section [{key}] is missing or not a table")
        return value

    def array(self, doc: Mapping[str, Any], key: str) -> list[Mapping[str, Any]]:
        value = doc.get(key)
        if not isinstance(value, list) or not value:
            raise SpecError(f"{self.source}: no [[{key}]] entries (expected at least one)")
        return value

    def number(self, table: Mapping[str, Any], where: str, key: str) -> float:
        value = self.get(table, where, key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(where, key, value, "a number")
        if not math.isfinite(value):
            raise self.fail(where, key, value, "a finite number")
        return float(value)

    def integer(self, table: Mapping[str, Any], where: str, key: str) -> int:
        value = self.get(table, where, key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(where, key, value, "an integer")
        return value

    def text(self, table: Mapping[str, Any], where: str, key: str) -> str:
        value = self.get(table, where, key)
        if not isinstance(value, str) or not value.strip():
            raise self.fail(where, key, value, "a non-empty string")
        return value

    def unit(self, table: Mapping[str, Any], where: str) -> tuple[str, float]:
        unit = self.text(table, where, "unit")
        if unit not in UNITS:
            raise self.fail(where, "unit", unit, f"one of {sorted(UNITS)}")
        return UNITS[unit]

    def variable(self, t: Mapping[str, Any], where: str, is_state: bool) -> Variable:
        base = {"name", "label", "unit", "min", "max", "note"}
        stats = {"mu_min", "mu_max", "sigma", "rho"}
        self.keys(t, where, base | stats if is_state else base)
        name = self.text(t, where, "name")
        if not name.isidentifier():
            raise self.fail(where, "name", name, "a Python identifier (letters, digits, _)")
        where = f"{where} {name!r}"
        internal, scale = self.unit(t, where)
        lo, hi = self.number(t, where, "min"), self.number(t, where, "max")
        if not lo < hi:
            raise self.fail(where, "max", hi, f"a value above min = {lo}")
        values: dict[str, float] = {}
        if is_state:
            mu_min, mu_max = self.number(t, where, "mu_min"), self.number(t, where, "mu_max")
            sigma, rho = self.number(t, where, "sigma"), self.number(t, where, "rho")
            if not lo <= mu_min <= mu_max <= hi:
                raise self.fail(where, "mu_min", (mu_min, mu_max),
                                f"min = {lo} <= mu_min <= mu_max <= max = {hi}")
            if not sigma > 0:
                raise self.fail(where, "sigma", sigma, "sigma > 0")
            if not 0 <= rho <= 1:
                raise self.fail(where, "rho", rho, "0 <= rho <= 1")
            values = {"mu_min": mu_min * scale, "mu_max": mu_max * scale,
                      "sigma": sigma * scale, "rho": rho}
        label = str(t.get("label", name))
        return Variable(name=name, label=label, unit=t["unit"], internal_unit=internal,
                        scale=scale, lo=lo * scale, hi=hi * scale,
                        note=str(t.get("note", "")), **values)

    def deviation(self, t: Mapping[str, Any], t0: float, t1: float) -> Deviation:
        kinds = ("force_scaling", "speed_scaling")
        self.keys(t, "deviation", {"knots", "unit"} | {f"{k}_{e}" for k in kinds
                                                      for e in ("min", "max")})
        n = self.integer(t, "deviation", "knots")
        if n < 2:
            raise self.fail("deviation", "knots", n, "at least 2")
        internal, scale = self.unit(t, "deviation")
        if internal != "-":
            raise self.fail("deviation", "unit", t["unit"], "a dimensionless unit ('%' or '-')")
        variables = []
        for kind in kinds:
            lo = self.number(t, "deviation", f"{kind}_min")
            hi = self.number(t, "deviation", f"{kind}_max")
            if not lo < hi:
                raise self.fail("deviation", f"{kind}_max", hi, f"a value above {lo}")
            if lo * scale <= -1.0:
                raise self.fail("deviation", f"{kind}_min", lo, "a scaling above -100 %")
            variables += [Variable(name=f"{kind}_{k + 1}", label=f"{kind.replace('_', ' ')} "
                                   f"knot {k + 1}", unit=t["unit"], internal_unit="-",
                                   scale=scale, lo=lo * scale, hi=hi * scale)
                          for k in range(n)]
        return Deviation(group=Group(tuple(variables)), knots=np.linspace(t0, t1, n))
