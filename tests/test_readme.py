"""The README: short, with its figures, the two commands, and results rows that are exactly
what scripts/readme_results.py makes of benchmarks/results/*.json."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from types import ModuleType

import pytest
from repo_scripts import load_script

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"


def _script() -> ModuleType:
    return load_script("readme_results")


def test_readme_rows_are_generated_from_the_results_files() -> None:
    """A results file changed without `python scripts/readme_results.py --write` fails."""
    script = _script()
    assert script.block(README.read_text(encoding="utf-8")) == script.rows()


def test_a_changed_results_file_changes_the_rows(tmp_path: Path) -> None:
    """The rows follow the JSON: a new tracker figure and date show up in the tracker row."""
    script = _script()
    results = tmp_path / "results"
    shutil.copytree(REPO / "benchmarks" / "results", results)
    path = results / "bench_filter.json"
    data = json.loads(path.read_text())
    data["figures"]["step_cpu_ms_n500"] = 123.4
    data["date"] = "2031-01-02T03:04:05+00:00"
    path.write_text(json.dumps(data))
    before, after = script.rows(), script.rows(results)
    changed = [row for row in after if row not in before]
    assert len(changed) == 1 and changed[0].startswith("| tracker |")
    assert "123.4 ms CPU" in changed[0] and "| 2031-01-02 |" in changed[0]
    stale = script.rewrite(README.read_text(encoding="utf-8"), before)
    assert script.block(stale) != after


def test_every_row_has_date_model_and_command() -> None:
    rows = _script().rows()[2:]
    assert 1 <= len(rows) <= 9
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert len(cells) == 5, row
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", cells[2]), row
        assert re.fullmatch(r"bending-\d+\.\d+", cells[3]), row
        assert cells[4].startswith("`python "), row


def test_model_version_is_required() -> None:
    with pytest.raises(ValueError, match="model version"):
        _script().model_version({"figures": {}, "model": None})


def test_readme_is_short_with_its_commands_and_figures() -> None:
    text = README.read_text(encoding="utf-8")
    assert len(text.encode("utf-8")) <= 10_000
    assert "make demo" in text and "make test" in text
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert "docs/figures/physics_bending.png" in images
    for image in images:
        assert (REPO / image).is_file(), image
    for link in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if not link.startswith("http"):
            assert (REPO / link).exists(), link
