"""Independent CalculiX check of the pinch rule (``bench_physics_fe --independent N``).

Bending-2.4's pinch rule (``Discretisation.pinch_reach``) was set on the 25 points that
``bench_physics_fe.py`` scores it on. This check takes points it never saw: Latin-hypercube
rows of the bundled physics DOE (all eleven run inputs vary, not only the four main ones),
``n - n // 3`` with punch end distance in ``[310, 340)`` um (where the rule acts) and
``n // 3`` in ``[340, 410]`` um (control), stratified: each group's range is cut into as
many equal punch-end-distance intervals as it has points, and a seeded generator draws one
LHS row from each. At each point both beam models (2.4 and 2.3 = ``pinch_reach=0``) run
against a stage-1-only CalculiX run on the fine mesh (peak, plateau, angle 1) and a
two-stage run on the coarse final-angle mesh (final angle), both cached like the other FE
runs. Figures per group and model: the largest relative peak and plateau errors, the largest
and mean angle-1 and final-angle differences (beam minus FE, deg).
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: punch end distance bounds of the groups (mm, internal units): pinch [310, 340) um,
#: control [340, 410] um
PINCH = (0.310, 0.340)
CONTROL = (0.340, 0.410)


def independent_points(inputs: np.ndarray, names: tuple[str, ...], n_corners: int, n: int,
                       seed: int) -> list[dict[str, Any]]:
    """The check's points: ``n - n // 3`` pinch and ``n // 3`` control rows of a DOE, one
    per equal-width stratum of punch end distance.

    ``inputs (n_runs, d)`` the DOE's run inputs (internal units) in the order ``names``;
    rows before ``n_corners`` (the full factorial) are skipped. Returns dicts with ``name``
    (``"lhs<row>"``), ``row``, ``group`` (``"pinch"`` or ``"control"``), ``pe_um`` and ``x``
    (a copy of the row), by group (pinch first), then punch end distance.

    >>> X = np.column_stack([np.linspace(0.30, 0.42, 13), np.zeros(13)])
    >>> [(p["row"], p["group"]) for p in independent_points(X, ("punch_end_distance", "u"),
    ...                                                      2, 3, seed=1)]
    [(2, 'pinch'), (3, 'pinch'), (8, 'control')]
    >>> independent_points(X, ("punch_end_distance", "u"), 2, 4, seed=1)
    Traceback (most recent call last):
    ...
    ValueError: pinch: no LHS row with punch end distance in [310.0, 320.0] um
    """
    if n < 1:
        raise ValueError(f"--independent needs at least 1 point, got {n}")
    pe = inputs[:, names.index("punch_end_distance")]
    rows = np.arange(inputs.shape[0])
    lhs = rows >= n_corners
    tol = 1e-12
    groups = (("pinch", n - n // 3, PINCH), ("control", n // 3, CONTROL))
    rng = np.random.default_rng(seed)
    out = []
    for group, k, (lo, hi) in groups:
        edges = np.linspace(lo, hi, k + 1)
        for j in range(k):  # one row per stratum of equal punch-end-distance width
            top = pe <= edges[j + 1] + tol if j == k - 1 and group == "control" \
                else pe < edges[j + 1]
            pool = rows[lhs & (pe >= edges[j] - tol) & top]
            if pool.size == 0:
                raise ValueError(f"{group}: no LHS row with punch end distance in "
                                 f"[{1e3 * edges[j]:.1f}, {1e3 * edges[j + 1]:.1f}] um")
            r = int(rng.choice(pool))
            out.append({"name": f"lhs{r}", "row": r, "group": group,
                        "pe_um": float(1e3 * pe[r]), "x": inputs[r].copy()})
    return out


def parse_seeds(text: str) -> list[int]:
    """``--independent-seed`` as a list of distinct seeds (``"2026,2027"``).

    >>> parse_seeds("2026, 2027")
    [2026, 2027]
    >>> parse_seeds("2026,x")
    Traceback (most recent call last):
    ...
    ValueError: --independent-seed: 'x' is not an integer (give seeds as 2026,2027)
    >>> parse_seeds("7,7")
    Traceback (most recent call last):
    ...
    ValueError: --independent-seed: seed 7 given twice
    """
    seeds = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        try:
            seed = int(part)
        except ValueError:
            raise ValueError(f"--independent-seed: {part!r} is not an integer (give seeds as "
                             "2026,2027)") from None
        if seed in seeds:
            raise ValueError(f"--independent-seed: seed {seed} given twice")
        seeds.append(seed)
    if not seeds:
        raise ValueError("--independent-seed: no seed given")
    return seeds


def summarise(points: dict[str, dict[str, Any]], models: tuple[str, ...]
              ) -> dict[str, dict[str, Any]]:
    """Errors of each beam model against CalculiX, per group and over all points.

    ``points[name]`` holds ``group``, ``fe1`` (stage-1 FE figures), ``fe2`` (two-stage FE
    figures) and ``beam[model]`` (beam figures or None); figures as
    ``bench_physics_fe.figures_of``. Returns ``{group: {model: figures}}`` with groups
    ``pinch``, ``control``, ``all``.

    >>> fe = {"ok": True, "peak": 100.0, "plateau": 50.0, "angle1": 40.0, "angle2": 70.0}
    >>> b = {"peak": 104.0, "plateau": 49.0, "angle1": 40.5, "angle2": 69.0}
    >>> s = summarise({"a": {"group": "pinch", "fe1": fe, "fe2": fe, "beam": {"2.4": b}}},
    ...               ("2.4",))
    >>> round(s["pinch"]["2.4"]["peak_rel_err_max"], 9), s["all"]["2.4"]["angle2_err_mean_deg"]
    (0.04, -1.0)
    >>> s["control"]["2.4"]["points"]
    0
    """
    out: dict[str, dict[str, Any]] = {}
    for group in ("pinch", "control", "all"):
        out[group] = {}
        for model in models:
            sel = [p for p in points.values() if group in ("all", p["group"])
                   and p["beam"].get(model)]
            s1 = [p for p in sel if p["fe1"].get("ok")]
            s2 = [p for p in sel if p["fe2"].get("ok")]
            fig: dict[str, Any] = {"points": len(sel), "fe_failed": len(sel) - len(s1),
                                   "fe_failed_final": len(sel) - len(s2)}

            def err(runs: list[dict[str, Any]], q: str, fe: str, rel: bool,
                    model: str = model) -> np.ndarray:
                b = np.array([p["beam"][model][q] for p in runs])
                f = np.array([p[fe][q] for p in runs])
                return b / f - 1 if rel else b - f

            if s1:
                fig["peak_rel_err_max"] = float(np.max(np.abs(err(s1, "peak", "fe1", True))))
                fig["peak_rel_err_mean"] = float(np.mean(err(s1, "peak", "fe1", True)))
                fig["plateau_rel_err_max"] = float(np.max(np.abs(
                    err(s1, "plateau", "fe1", True))))
                d1 = err(s1, "angle1", "fe1", False)
                fig["angle1_err_max_deg"] = float(np.max(np.abs(d1)))
                fig["angle1_err_mean_deg"] = float(np.mean(d1))
            if s2:
                d2 = err(s2, "angle2", "fe2", False)
                fig["angle2_err_max_deg"] = float(np.max(np.abs(d2)))
                fig["angle2_err_mean_deg"] = float(np.mean(d2))
                fig["angle2_err_rms_deg"] = float(np.sqrt(np.mean(d2 ** 2)))
            out[group][model] = fig
    return out


def table(points: dict[str, dict[str, Any]], models: tuple[str, ...]) -> str:
    """Markdown table of the independent points: FE and each beam model's figures."""
    head = ("| point | pe (um) | peak FE | " + " | ".join(f"peak {m}" for m in models)
            + " | angle 1 FE | " + " | ".join(f"a1 {m}" for m in models)
            + " | final FE | " + " | ".join(f"final {m}" for m in models) + " |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, p in points.items():
        f1, f2 = p["fe1"], p["fe2"]

        def val(rec: dict[str, Any] | None, q: str, fmt: str) -> str:
            return format(rec[q], fmt) if rec and rec.get("ok", True) and q in rec else "-"

        lines.append(
            f"| {name} ({p['group']}) | {p['pe_um']:.1f} | {val(f1, 'peak', '.1f')} | "
            + " | ".join(val(p["beam"].get(m), "peak", ".1f") for m in models)
            + f" | {val(f1, 'angle1', '.2f')} | "
            + " | ".join(val(p["beam"].get(m), "angle1", ".2f") for m in models)
            + f" | {val(f2, 'angle2', '.2f')} | "
            + " | ".join(val(p["beam"].get(m), "angle2", ".2f") for m in models) + " |")
    return "\n".join(lines)
