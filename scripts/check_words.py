"""Fail on development-process words in the product's text (``make lint``).

README, changelog, docs, src, tests, benchmarks, examples and scripts speak of the product:
dates, versions and commands, never of work periods, who ran what, locks of a development
machine or paths outside the repository. Provenance (commit, machine, load) belongs in
``benchmarks/results/*.json``, which is not checked.

    python scripts/check_words.py [PATH ...]     # exit 1 and list the lines found
"""

from __future__ import annotations

import re
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: what is checked when no path is given
TARGETS = ("README.md", "CHANGELOG.md", "Makefile", "pyproject.toml", "docs", "src", "tests",
           "benchmarks", "examples", "scripts")
SUFFIXES = {".md", ".py", ".toml", ".txt", ".html", ".js", ".css", ".sh", ".cfg", ".ini"}
#: not the product's text: caches and environments anywhere, and the docs build with the
#: reference pages it generates (from src, which is checked)
SKIP_PARTS = {"_build", ".cache", ".venv", ".venv-particles", "__pycache__"}
SKIP = (ROOT / "docs" / "reference" / "commands.md", ROOT / "docs" / "reference" / "api")

#: each pattern with what it stands for; written so that this file does not match itself
PATTERNS: list[tuple[str, re.Pattern[str]]] = [
    ("a numbered work period", re.compile(r"\bsession[ -]?[0-9]", re.IGNORECASE)),
    ("a lock of the development machine",
     re.compile(r"under the loc[k]|heavy\.lock|formtwin-cpu\.lock", re.IGNORECASE)),
    ("who did the work", re.compile(r"\bthe lea[d]\b|\bhelper s[0-9]", re.IGNORECASE)),
    ("a scratch path", re.compile(r"/tmp/[a-z0-9]+/")),
    ("an absolute path of a development machine", re.compile(r"(?<![\w.])/(?:work|root)/")),
    ("a clock time as history",
     re.compile(r"(?<![\dT:])[0-2]\d:[0-5]\d ?(?:-|–) ?[0-2]\d:[0-5]\d(?: ?UTC)?(?![\d:])")),
    # the verb ("issues the final angle's interval", "the issued interval") and a
    # physical branch ("the unloading branch", "a stick branch `mu*5`") are product words
    ("an item of the project's tracker (name the target, version or figure)",
     re.compile(r"\biss[u]es? ?-?[0-9]|\b(?:the|this) iss[u]e\b|\biss[u]e(?:'s|s'| items?\b"
                r"| targets?\b| asks\b)|\(iss[u]e\b", re.IGNORECASE)),
    ("a rewrite of the development history", re.compile(r"\breba[s]", re.IGNORECASE)),
    ("a development line of the code (name the version or the variant)",
     re.compile(r"\b(?:on|from|developed on) (?:the |a )?bran[c]h\b|\bthe bran[c]h's"
                r"|\bbran[c]h `[\w.]+-", re.IGNORECASE)),
    ("a commit hash as history", re.compile(r"\b(?:commit|main) [0-9a-f]{7,40}\b")),
]


def files(targets: Iterable[Path]) -> Iterator[Path]:
    """The text files under ``targets`` (files or folders) that are checked."""
    for target in targets:
        base = target if target.is_dir() else target.parent
        for path in [target] if target.is_file() else sorted(target.rglob("*")):
            skipped = any(path.resolve().is_relative_to(s) for s in SKIP)
            if (path.is_file() and (path.suffix in SUFFIXES or path.name == "Makefile")
                    and not SKIP_PARTS.intersection(path.relative_to(base).parts)
                    and not skipped):
                yield path


def findings(path: Path) -> Iterator[str]:
    """``path:line: what: text`` for every line of ``path`` with a development word."""
    text = path.read_text(encoding="utf-8", errors="replace")
    for number, line in enumerate(text.splitlines(), 1):
        for what, pattern in PATTERNS:
            if pattern.search(line):
                yield f"{path}:{number}: {what}: {line.strip()[:120]}"


def main(argv: list[str]) -> int:
    """Check the paths given (default: :data:`TARGETS`); 1 if anything was found."""
    targets = [Path(a) for a in argv] or [ROOT / t for t in TARGETS if (ROOT / t).exists()]
    found = [f for path in files(targets) for f in findings(path)]
    for line in found:
        print(line)
    if found:
        print(f"{len(found)} development-process words; write dates, versions and commands "
              "instead (provenance goes in benchmarks/results/*.json)", file=sys.stderr)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
