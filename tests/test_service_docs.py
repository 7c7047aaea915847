"""docs/tutorials/live-line.md, followed literally: fit the metamodel of the bundled physics
DOE, start ``formtwin serve --check 100`` on it, replay a synthetic stream drawn from the same
metamodel; the service must find that its model explains the first 100 products.

Only the broker address changes (a private mosquitto on a free port); the commands run in
a scratch folder where ``src`` links to the repository's, so the paths stay as written. The
fit line runs once per session (conftest's ``tutorial_fit``, in a process whose OpenBLAS
runs another kernel than this CPU's: test_same_twin checks that fit is the bundled twin)."""

from __future__ import annotations

import os
import re
import shlex
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

from service_fixtures import (
    REPO,
    Mosquitto,
    doc_commands,
    log_has,
    mosquitto,  # noqa: F401 - fixture
    wait_for,
)

DOC = REPO / "docs" / "tutorials" / "live-line.md"
MARK = "<!-- the block below is run by tests/test_service_docs.py -->"



def run_line(line: str, broker: str, cwd: Path) -> list[str]:
    """The argv of a documented ``formtwin ...`` line, run with this interpreter."""
    argv = shlex.split(line.replace("mqtt://127.0.0.1:1883", broker))
    assert argv[0] == "formtwin", line
    return [sys.executable, "-c", "import sys; from formtwin.cli import main; "
            "sys.exit(main())", *argv[1:]]


def test_docs_quick_start_check_passes(mosquitto: Mosquitto,  # noqa: F811
                                       tutorial_fit: dict[str, Any]) -> None:
    fit, serve, replay = doc_commands(DOC, MARK)
    assert "--check 100" in serve and "--synthetic" in replay
    # the fit line ran as written in the fixture's folder (shared with test_same_twin, which
    # checks that fit under another BLAS kernel); the block goes on there
    assert fit.startswith("formtwin metamodel fit ") and "--out out/mm.npz" in fit
    assert tutorial_fit["returncode"] == 0, tutorial_fit["stderr"][-3000:]
    assert "stored the statistics of 5-fold held-out residuals" in tutorial_fit["stdout"]
    folder: Path = tutorial_fit["folder"]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    log = folder / "serve.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen(run_line(serve, mosquitto.url, folder), cwd=folder,
                                env=env, stdout=fh, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: log_has(log, "connected and subscribed") or proc.poll() is not None,
                 300, lambda: log.read_text()[-2000:])
        assert proc.poll() is None, log.read_text()[-3000:]
        rep = subprocess.run(run_line(replay, mosquitto.url, folder), cwd=folder, env=env,
                             capture_output=True, text=True, timeout=600)
        assert rep.returncode == 0, rep.stderr[-3000:]
        assert "drawing 400 products from the metamodel out/mm.npz" in rep.stdout
        code = proc.wait(300)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert code == 0, text[-3000:]
    assert "check passed: the model explains the first 100 products" in text
    db = sqlite3.connect(folder / "out" / "check.sqlite")
    rows = db.execute("SELECT json_extract(estimate, '$.health'), json_extract(estimate, "
                      "'$.flags.model_mismatch'), json_extract(estimate, '$.fit.distance2') "
                      "FROM products WHERE status = 'accepted' ORDER BY seq LIMIT 100"
                      ).fetchall()
    db.close()
    assert len(rows) == 100
    assert all(m == 0 for _, m, _ in rows)  # never marked
    health = [h for h, _, _ in rows]
    assert health.count("no_fit") <= 5, health  # a healthy fit, product by product
    assert sorted(d for _, _, d in rows)[50] < 101  # median distance below its dof
    assert re.search(r"plausibility: peak >= [0-9.]+ N", text)
