"""Generated reference pages of the documentation: the ``formtwin`` commands from the
argument parser, and one autodoc page per module of the package.

Pages are rewritten only when their text changes, so an unchanged build stays fast."""

from __future__ import annotations

import argparse
import os
import pkgutil
from pathlib import Path

#: modules left out of the API pages: the command line (documented as commands) and private
#: modules
SKIP_PREFIXES = ("formtwin.cli", "formtwin._")


def _write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` unless it already holds exactly that."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text(encoding="utf-8") != text:
        path.write_text(text, encoding="utf-8")


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    """The (name, parser) of each sub-command of ``parser``, in help order."""
    out: list[tuple[str, argparse.ArgumentParser]] = []
    for action in parser._actions:  # argparse keeps sub-parsers only here
        if isinstance(action, argparse._SubParsersAction):
            out.extend(action.choices.items())
    return out


def _sections(parser: argparse.ArgumentParser, prog: str, level: int) -> list[str]:
    """Markdown for ``prog`` and, one heading level down, each of its sub-commands."""
    lines = [f"{'#' * level} `{prog}`", ""]
    if parser.description:
        lines += [parser.description.strip(), ""]
    lines += ["```text", parser.format_help().rstrip(), "```", ""]
    for name, sub in _subcommands(parser):
        lines += _sections(sub, f"{prog} {name}", min(level + 1, 4))
    return lines


def write_cli_page(path: Path) -> None:
    """Write the reference of every ``formtwin`` command, generated from its parser."""
    from formtwin.cli import build_parser

    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "92"  # argparse wraps help to the terminal's width
    try:
        parser = build_parser()
        body = _sections(parser, "formtwin", 2)
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns
    head = ["# Commands", "",
            "Generated from the argument parser of `formtwin` (`formtwin.cli.build_parser`) "
            "when the documentation is built; `formtwin COMMAND --help` prints the same.", ""]
    _write(path, "\n".join(head + body))


def write_api_pages(folder: Path) -> None:
    """Write one autodoc page per top-level module or package of ``formtwin`` (a package's
    page documents what its ``__init__`` exports) and an index of them."""
    import formtwin

    names = sorted(m.name for m in pkgutil.iter_modules(formtwin.__path__, "formtwin.")
                   if not m.name.startswith(SKIP_PREFIXES))
    names = ["formtwin", *names]
    for name in names:
        _write(folder / f"{name}.md",
               f"# `{name}`\n\n```{{eval-rst}}\n.. automodule:: {name}\n```\n")
    index = ["# API", "",
             "One page per module, generated from the docstrings (numpydoc) when the "
             "documentation is built. The layers and what each package is for are in "
             "[the architecture](../../explanation/architecture.md).", "",
             "```{toctree}", ":maxdepth: 1", "", *names, "```", ""]
    _write(folder / "index.md", "\n".join(index))
    for stale in folder.glob("formtwin*.md"):
        if stale.stem not in names:
            stale.unlink()
