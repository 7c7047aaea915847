"""Print the ``uv pip install`` flags for the package sources pip is configured with.

``make`` builds the virtual environment with uv, which reads neither pip's configuration
files nor its ``PIP_*`` variables. A machine that reaches packages only through a mirror,
a wheel folder or a constraints file set up for pip would otherwise install from PyPI (or
fail offline). This script asks the environment's pip (``pip config list``: every file and
variable pip reads, merged as pip merges them) and prints the same sources as uv flags on
one line: index-url, extra-index-url, find-links, constraint, no-index, cert, trusted-host.
For each key pip's order holds: a ``PIP_*`` variable over the ``[install]`` section over
``[global]``.

Usage (what the Makefile runs): ``python scripts/uv_sources.py``.
"""

from __future__ import annotations

import ast
import shlex
import subprocess
import sys

#: pip's key -> (uv's flag, whether the value is a whitespace-separated list)
FLAGS = {
    "index-url": ("--index-url", False),
    "extra-index-url": ("--extra-index-url", True),
    "find-links": ("--find-links", True),
    "constraint": ("--constraints", True),
    "cert": ("--cert", False),
    "trusted-host": ("--allow-insecure-host", True),
}
#: where a key may be set, the first found wins (pip's precedence for ``pip install``)
SECTIONS = (":env:", "install", "global")
TRUE = ("1", "true", "yes", "on")


def parse(listing: str) -> dict[tuple[str, str], str]:
    """``(section, key) -> value`` of ``pip config list``'s lines (``section.key='value'``)."""
    out: dict[tuple[str, str], str] = {}
    for line in listing.splitlines():
        name, sep, value = line.partition("=")
        section, dot, key = name.rpartition(".")
        if sep and dot:
            out[(section, key)] = ast.literal_eval(value)
    return out


def uv_flags(listing: str) -> list[str]:
    """The uv flags (one list element per word) for the configuration ``listing``."""
    config = parse(listing)

    def value(key: str) -> str | None:
        return next((config[(s, key)] for s in SECTIONS if (s, key) in config), None)

    flags: list[str] = []
    if (value("no-index") or "").lower() in TRUE:
        flags.append("--no-index")
    for key, (flag, many) in FLAGS.items():
        got = value(key)
        for item in (got.split() if many else [got]) if got else []:
            flags += [flag, item]
    if "--extra-index-url" in flags:  # pip takes the best version over all indexes; uv
        flags += ["--index-strategy", "unsafe-best-match"]  # by default the first index's
    return flags


def main() -> None:
    """Print the flags of this environment's pip configuration (nothing if it has none)."""
    done = subprocess.run([sys.executable, "-m", "pip", "config", "list"],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        print(f"uv_sources: pip config list failed ({done.stderr.strip()[:200]}); uv uses "
              "its defaults", file=sys.stderr)
    print(shlex.join(uv_flags(done.stdout if done.returncode == 0 else "")))


if __name__ == "__main__":
    main()
