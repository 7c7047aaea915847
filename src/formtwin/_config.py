"""Settings dataclasses as TOML sections and command-line flags (one declaration each).

A settings class is a frozen dataclass whose fields carry their help text in
``field(metadata={"help": ...})`` (optional extra flags in ``metadata["flags"]``). From it:

* :func:`add_arguments` generates one ``--name-with-dashes`` flag per field (booleans get
  ``--x/--no-x``, tuples of floats are comma-separated, ``None`` defaults stay optional);
  only flags given on the command line appear in the parsed namespace;
* :func:`from_mapping` builds the dataclass from a mapping (a TOML table), refusing unknown
  keys with a message naming them and the known ones;
* :func:`resolve` layers defaults < TOML section < flags.

>>> import argparse
>>> from dataclasses import dataclass, field
>>> @dataclass(frozen=True)
... class Demo:
...     n: int = field(default=3, metadata={"help": "how many"})
...     fast: bool = field(default=False, metadata={"help": "go fast"})
>>> p = argparse.ArgumentParser()
>>> add_arguments(p, Demo)
>>> resolve(Demo, p.parse_args(["--n", "5", "--fast"]))
Demo(n=5, fast=True)
"""

from __future__ import annotations

import argparse
import dataclasses
import tomllib
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def _floats(text: str) -> tuple[float, ...]:
    """A comma-separated list of numbers as a tuple of floats."""
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated numbers") \
            from exc


def _names(text: str) -> tuple[str, ...]:
    """A comma-separated list of names as a tuple of strings (empty text: none)."""
    return tuple(v.strip() for v in text.split(",") if v.strip())


def _kind(hint: Any) -> Any:
    """The flag type of a field's type hint: int, float, str, bool, tuple (of floats) or
    :func:`_names` (a tuple of strings)."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    base = typing.get_origin(hint) or hint
    if base in (typing.Union, getattr(__import__("types"), "UnionType", None)) and args:
        return _kind(args[0])
    if base is tuple:
        return _names if str in typing.get_args(hint) else tuple
    if hint in (int, float, str, bool):
        return hint
    return str


def add_arguments(parser: argparse.ArgumentParser | Any, cls: type[Any],
                  exclude: tuple[str, ...] = ()) -> None:
    """Add one flag per field of dataclass ``cls`` (except ``exclude``) to ``parser``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in exclude or not f.init:
            continue
        flags = [f"--{f.name.replace('_', '-')}", *f.metadata.get("flags", ())]
        kind = _kind(hints[f.name])
        default = f.default if f.default is not dataclasses.MISSING else None
        text = f"{f.metadata.get('help', f.name)} (default: {default!r})".replace("%", "%%")
        if kind is bool:
            parser.add_argument(*flags, dest=f.name, action=argparse.BooleanOptionalAction,
                                default=argparse.SUPPRESS, help=text)
        else:
            parser.add_argument(*flags, dest=f.name, default=argparse.SUPPRESS, help=text,
                                type=_floats if kind is tuple else kind)


def given(args: argparse.Namespace, cls: type[Any]) -> dict[str, Any]:
    """The fields of ``cls`` given on the command line (see :func:`add_arguments`)."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
            if hasattr(args, f.name)}


def from_mapping(cls: type[T], values: Mapping[str, Any], where: str = "settings") -> T:
    """``cls(**values)`` with lists as tuples; ``ValueError`` naming unknown keys."""
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ValueError(f"{where}: unknown setting(s) {', '.join(unknown)}; known: "
                         f"{', '.join(names)}")
    clean = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    return cls(**clean)


def read_section(path: str | Path | None, section: str) -> dict[str, Any]:
    """The table ``[section]`` of TOML file ``path`` (empty without a file or section)."""
    if path is None:
        return {}
    p = Path(path)
    if not p.exists():
        raise ValueError(f"--config {p}: no such file")
    with open(p, "rb") as fh:
        try:
            data = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{p}: not valid TOML: {exc}") from exc
    table = data.get(section, {})
    if not isinstance(table, dict):
        raise ValueError(f"{p}: [{section}] must be a table, got {type(table).__name__}")
    return dict(table)


def resolve(cls: type[T], args: argparse.Namespace, config_file: str | Path | None = None,
            section: str = "", base: Mapping[str, Any] | None = None) -> T:
    """Defaults, then ``base``, then ``[section]`` of ``config_file``, then given flags."""
    values = dict(base or {})
    values.update(read_section(config_file, section) if section else {})
    values.update(given(args, cls))
    where = f"{config_file} [{section}]" if config_file and section else "settings"
    return from_mapping(cls, values, where)
