"""The generated reference pages of the documentation (docs/_ext/reference_pages.py): every
command of the parser has its section with its own help, and every public module its page."""

from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path
from types import ModuleType

from formtwin.cli import COMMANDS, build_parser

REPO = Path(__file__).resolve().parent.parent


def _pages() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "reference_pages", REPO / "docs" / "_ext" / "reference_pages.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _all_progs(parser: argparse.ArgumentParser) -> list[str]:
    """``prog`` of the parser and of every sub-command below it."""
    out = [parser.prog]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                out += _all_progs(sub)
    return out


def test_every_command_has_its_section_and_help(tmp_path: Path) -> None:
    page = tmp_path / "commands.md"
    _pages().write_cli_page(page)
    text = page.read_text(encoding="utf-8")
    headings = re.findall(r"^#{2,4} `([^`]+)`$", text, flags=re.MULTILINE)
    progs = _all_progs(build_parser())
    assert headings == progs
    # one top-level command per module of formtwin.cli's COMMANDS
    assert len([h for h in headings if h.count(" ") == 1]) == len(COMMANDS)
    for prog in progs:
        assert f"usage: {prog} " in text, prog


def test_api_pages_one_per_public_module(tmp_path: Path) -> None:
    pages = _pages()
    pages.write_api_pages(tmp_path)
    names = sorted(p.stem for p in tmp_path.glob("formtwin*.md"))
    assert "formtwin.tracker" in names and "formtwin.metamodel" in names
    assert not [n for n in names if n.startswith(pages.SKIP_PREFIXES)]
    index = (tmp_path / "index.md").read_text(encoding="utf-8")
    for name in names:
        assert f"\n{name}\n" in index
        assert f".. automodule:: {name}\n" in (tmp_path / f"{name}.md").read_text()
