"""Typed reading of a spec's TOML tables: every error names the file, the field and the value."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from formtwin.spec.model import (
    DEVIATION_KINDS,
    UNITS,
    Deviation,
    Group,
    Output,
    SpecError,
    Variable,
)

_BASE = {"name", "label", "unit", "min", "max", "note"}
_STATS = {"mu_min", "mu_max", "sigma", "rho"}

#: every key a spec may use, by table (``"<top>"``: the top-level tables); the reader
#: refuses any other, and docs/reference/spec.md lists exactly these (a test compares them)
KEYS: dict[str, frozenset[str]] = {
    "<top>": frozenset({"process", "curve", "state", "parameter", "control", "deviation",
                        "output", "sensor"}),
    "process": frozenset({"name", "description"}),
    "curve": frozenset({"unit", "t_start", "t_end", "n_samples", "force_unit", "noise_sd"}),
    "state": frozenset(_BASE | _STATS),
    "parameter": frozenset(_BASE),
    "control": frozenset(_BASE | {"nominal"}),
    "output": frozenset({"name", "label", "unit", "uses_controls", "note"}),
    "sensor": frozenset({"name", "label", "measures", "unit", "noise", "delay", "note"}),
    "deviation": frozenset({"kinds", "knots", "unit"} | {f"{k}_{e}" for k in DEVIATION_KINDS
                                                         for e in ("min", "max")}),
}


class Reader:
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

    def variable(self, t: Mapping[str, Any], where: str, is_state: bool,
                 is_control: bool = False) -> Variable:
        self.keys(t, where, set(KEYS["state" if is_state else "control" if is_control
                                     else "parameter"]))
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
        if is_control:
            nominal = self.number(t, where, "nominal")
            if not lo <= nominal <= hi:
                raise self.fail(where, "nominal", nominal, f"min = {lo} <= nominal <= max = {hi}")
            values = {"nominal": nominal * scale}
        label = str(t.get("label", name))
        return Variable(name=name, label=label, unit=t["unit"], internal_unit=internal,
                        scale=scale, lo=lo * scale, hi=hi * scale,
                        note=str(t.get("note", "")), **values)

    def flag(self, table: Mapping[str, Any], where: str, key: str, default: bool) -> bool:
        """An optional boolean ``key`` (``default`` when absent)."""
        value = table.get(key, default)
        if not isinstance(value, bool):
            raise self.fail(where, key, value, "true or false")
        return value

    def output(self, t: Mapping[str, Any], where: str) -> Output:
        """One ``[[output]]`` entry: name, label, unit (free text), uses_controls, note."""
        self.keys(t, where, set(KEYS["output"]))
        name = self.text(t, where, "name")
        if not name.isidentifier():
            raise self.fail(where, "name", name, "a Python identifier (letters, digits, _)")
        where = f"{where} {name!r}"
        return Output(name=name, label=str(t.get("label", name)), unit=self.text(t, where, "unit"),
                      uses_controls=self.flag(t, where, "uses_controls", True),
                      note=str(t.get("note", "")))

    def deviation(self, t: Mapping[str, Any], t0: float, t1: float) -> Deviation:
        kinds_value = t.get("kinds", list(DEVIATION_KINDS))
        if not isinstance(kinds_value, list) or any(
                k not in DEVIATION_KINDS for k in kinds_value) or len(set(kinds_value)) != len(
                    kinds_value):
            raise self.fail("deviation", "kinds", kinds_value,
                            f"a list of distinct kinds from {list(DEVIATION_KINDS)} (or [])")
        kinds = tuple(k for k in DEVIATION_KINDS if k in kinds_value)
        if not kinds:
            self.keys(t, "deviation", {"kinds"})
            return Deviation(group=Group(()), knots=np.linspace(t0, t1, 2), kinds=())
        self.keys(t, "deviation", {"knots", "unit", "kinds"} | {f"{k}_{e}" for k in kinds
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
        return Deviation(group=Group(tuple(variables)), knots=np.linspace(t0, t1, n),
                         kinds=kinds)
