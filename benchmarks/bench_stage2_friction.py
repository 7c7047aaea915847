"""Which tool's stage-2 friction moves the final angle, in the beam model and in CalculiX.

At the centre of Table 1 the tool-flap friction of one stage-2 tool (the die, the stage-2
punch, or, in the beam only, the blank holder; CalculiX clamps the sheet there) is set to
the bounds of Table 1 (0.01 and 0.3) while every other contact keeps the centre value (0.15),
stage 1 included; ``stage1`` varies stage 1's friction with stage 2's held. Per-tool
friction is not a model input: the script wraps the beam model's ``solve`` (beam) and
edits the CalculiX deck (the die and the stage-2 punch get their own ``*SURFACE
INTERACTION``, set by ``*CHANGE FRICTION`` from step 2 on).

Figures (deg, final angle at 0.3 minus at 0.01): ``beam_<tool>``, ``fe_<tool>``; with
``--fe`` also the loaded chord angle at the stage-2 bottom dead centre (``*_bdc``).
Beam runs take ~0.2 s each; ``--fe`` adds 5 two-stage ccx runs on 2 CPE8R through the
thickness (~25 s CPU each; run it under the heavy lock).

Run: ``python benchmarks/bench_stage2_friction.py [--fe] [--beam KEY=VALUE,...]``.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from bench_physics_fe import beam_overrides  # noqa: E402

import formtwin.physics.bending.model as bending  # noqa: E402
from formtwin._bench import write_result  # noqa: E402
from formtwin.physics.bending import BendingModel  # noqa: E402

LO, MID, HI = 0.01, 0.15, 0.3
STAGE2: dict[str, float] = {}  # stage-2 friction per tool name, set around a run
_solve = bending.solve


def _solve_per_tool(sheet, material, tools, targets, disc, **kw):  # type: ignore[no-untyped-def]
    """The model's ``solve`` with stage 2's (21 targets) friction set per tool by STAGE2."""
    if targets.size == 21 and tools is not None and STAGE2:
        mu = np.array(kw["mu"], dtype=np.float64)
        for name, value in STAGE2.items():
            mu[tools.names.index(name)] = value
        kw["mu"] = mu
    return _solve(sheet, material, tools, targets, disc, **kw)


def chord_deg(pos: np.ndarray, s: np.ndarray, length: float = 0.5) -> float:
    """Bend angle (deg, downward +) of the chord of the last ``length`` mm: points ``pos
    (n, 2)`` ordered along the sheet, ``s (n,)`` their reference arc positions."""
    j = int(np.searchsorted(s, s[-1] - length - 1e-9))
    d = pos[-1] - pos[j]
    return math.degrees(math.atan2(-d[1], d[0]))


def beam_effects(model: BendingModel) -> dict[str, float]:
    """Final angle at 0.3 minus 0.01 per stage-2 tool, and for stage 1's friction alone."""
    bending.solve = _solve_per_tool
    x0 = model.centre()
    ix = model.spec.run_inputs.index["friction_tool_flap"]
    out: dict[str, float] = {}

    def final(mu_all: float, stage2: dict[str, float]) -> float:
        STAGE2.clear()
        STAGE2.update(stage2)
        x = x0.copy()
        x[ix] = mu_all
        return float(model.run(x).angles[1])

    try:
        out["beam_centre"] = final(MID, {})
        for tool in ("die", "punch", "holder"):
            out[f"beam_{tool}"] = final(MID, {tool: HI}) - final(MID, {tool: LO})
        held = {"die": MID, "holder": MID, "punch": MID}
        out["beam_stage1"] = final(HI, held) - final(LO, held)
        out["beam_all"] = final(HI, {}) - final(LO, {})
    finally:
        STAGE2.clear()
        bending.solve = _solve
    return out


def fe_deck(text: str, mu_die: float, mu_punch2: float, times3: np.ndarray) -> str:
    """The two-stage deck with the die (DIE, DIEF2) and the stage-2 punch on their own
    interactions, their friction changed from step 2 on, the mid-line printed at
    ``times3`` (step time of step 3, s)."""
    tp = "*TIME POINTS, NAME=TP3\n" + "\n".join(f"{t:.10g}" for t in times3) + "\n"
    text = re.sub(r"\*TIME POINTS, NAME=TP3\n[^\n*]+\n", tp, text)
    found = re.search(r"\*SURFACE INTERACTION, NAME=SI\n.*?\*FRICTION\n[^\n]+\n", text, re.S)
    if found is None:
        raise RuntimeError("deck without a friction interaction")
    si = found.group(0)
    stick = si.splitlines()[-1].split(",")[1]
    text = text.replace(si, si + si.replace("NAME=SI", "NAME=SID")
                        + si.replace("NAME=SI", "NAME=SIP"))
    for tool, inter, slave in (("DIE", "SID", "SBOT"), ("DIEF2", "SID", "SBOT"),
                               ("PUNCH2", "SIP", "STOP")):
        pair = f"TYPE=NODE TO SURFACE\n{slave}, M{tool}\n"
        text = text.replace(f"*CONTACT PAIR, INTERACTION=SI, {pair}",
                            f"*CONTACT PAIR, INTERACTION={inter}, {pair}")
    step2 = [m.start() for m in re.finditer(r"\*STEP, NLGEOM", text)][1]
    k = text.index("\n", text.index("*STATIC\n", step2) + 8) + 1  # after the increment line
    change = "".join(f"*CHANGE FRICTION, INTERACTION={name}\n*FRICTION\n{mu:.10g},{stick}\n"
                     for name, mu in (("SID", mu_die), ("SIP", mu_punch2)))
    return text[:k] + change + text[k:]


def fe_effects() -> dict[str, float]:
    """CalculiX (2 CPE8R through the thickness, centre): final angle and the loaded angle at
    the stage-2 bottom dead centre, die / stage-2 punch friction at 0.01 and 0.3."""
    from formtwin.physics.calculix import CalculixModel
    from formtwin.physics.calculix.deck import stage2_tools, time_at_height
    from formtwin.physics.calculix.model import run_ccx
    from formtwin.physics.calculix.results import read_dat

    fe = CalculixModel(n_thick=2)
    deck = fe.deck(fe.centre())
    t2 = time_at_height(stage2_tools(fe.geometry, 0.0)[2], fe.geometry)
    times3 = np.array([t2, 2.0 * t2])
    idx = {int(i): k for k, i in enumerate(deck.sheet.node_ids)}
    res: dict[tuple[float, float], tuple[float, float]] = {}
    for mus in ((MID, MID), (LO, MID), (HI, MID), (MID, LO), (MID, HI)):
        with tempfile.TemporaryDirectory(prefix="formtwin-s2f-") as wd:
            tab = read_dat(run_ccx(fe_deck(deck.text, *mus, times3), Path(wd)))
        mid = tab[("displacements", "NMID")]
        ref = deck.sheet.nodes[[idx[int(i)] for i in mid.ids]]
        order = np.argsort(ref[:, 0])
        res[mus] = tuple(chord_deg((ref + mid.values[k, :, :2])[order], ref[order, 0])
                         for k in (-2, -1))  # type: ignore[assignment]
    out = {"fe_centre": res[(MID, MID)][1], "fe_centre_bdc": res[(MID, MID)][0]}
    for tool, lo, hi in (("die", (LO, MID), (HI, MID)), ("punch", (MID, LO), (MID, HI))):
        out[f"fe_{tool}"] = res[hi][1] - res[lo][1]
        out[f"fe_{tool}_bdc"] = res[hi][0] - res[lo][0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fe", action="store_true", help="also the CalculiX runs (5 ccx runs)")
    ap.add_argument("--beam", default="", help="Discretisation overrides KEY=VALUE,...")
    args = ap.parse_args()
    over = beam_overrides(args.beam)
    model = BendingModel(**over)
    figures: dict[str, Any] = {"beam_model": model.version, "beam_overrides": over,
                               "friction_bounds": [LO, MID, HI]}
    figures.update(beam_effects(model))
    if args.fe:
        figures.update(fe_effects())
    name = "stage2_friction" + ("_variant" if over else "")
    write_result(name, figures)


if __name__ == "__main__":
    main()
