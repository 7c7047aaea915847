"""scripts/uv_sources.py: the package sources pip is configured with, as uv's flags (the
Makefile builds the virtual environment with uv, which reads no pip configuration)."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path
from types import ModuleType

from repo_scripts import load_script

REPO = Path(__file__).resolve().parent.parent


def _script() -> ModuleType:
    return load_script("uv_sources")


def test_precedence_and_lists() -> None:
    """A PIP_* variable beats [install], which beats [global]; list values become one flag
    per item; extra indexes take pip's best-version strategy."""
    listing = "\n".join([
        "global.index-url='https://global.example/simple'",
        "install.index-url='https://install.example/simple'",
        ":env:.find-links='/wheels/a /wheels/b'",
        "global.find-links='/wheels/ignored'",
        "global.extra-index-url='file:///mirror/simple'",
        "global.constraint='/etc/pins.txt'",
        "global.timeout='60'",  # not a source: no flag
    ])
    flags = _script().uv_flags(listing)
    assert flags == ["--index-url", "https://install.example/simple",
                     "--extra-index-url", "file:///mirror/simple",
                     "--find-links", "/wheels/a", "--find-links", "/wheels/b",
                     "--constraints", "/etc/pins.txt",
                     "--index-strategy", "unsafe-best-match"]


def test_no_index_and_empty() -> None:
    """``no-index`` set true gives ``--no-index``; no configuration gives no flag."""
    mod = _script()
    assert mod.uv_flags(":env:.no-index='true'\n") == ["--no-index"]
    assert mod.uv_flags(":env:.no-index='0'\n") == []
    assert mod.uv_flags("") == []


def test_this_pip(tmp_path: Path) -> None:
    """End to end through this environment's pip: a config file and a PIP_* variable."""
    conf = tmp_path / "pip.conf"
    conf.write_text("[global]\nindex-url = https://file.example/simple\n"
                    "[install]\nfind-links = /a/wheels\n", encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env.update(PIP_CONFIG_FILE=str(conf), PIP_EXTRA_INDEX_URL="https://env.example/simple")
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "uv_sources.py")],
                         env=env, capture_output=True, text=True, check=True).stdout
    flags = shlex.split(out)
    pairs = set(zip(flags[::2], flags[1::2], strict=False))
    assert ("--index-url", "https://file.example/simple") in pairs
    assert ("--find-links", "/a/wheels") in pairs
    assert ("--extra-index-url", "https://env.example/simple") in pairs
