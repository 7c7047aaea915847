"""The study report: Markdown and HTML from one list of blocks, plus CSV/JSON of the numbers."""

from __future__ import annotations

import html
import json
import platform
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

import formtwin
from formtwin.spec import DEMONSTRATOR, ProcessSpec
from formtwin.study.figures import component_labels, plot_nrmse, plot_timeseries
from formtwin.study.honest import honest_summary, honest_table, plot_honest
from formtwin.study.metrics import summarise
from formtwin.study.pseudodata import data_digest
from formtwin.study.run import StudyResult
from formtwin.study.sensor_report import sensor_blocks
from formtwin.study.series import SERIES

Block = tuple[str, ...] | tuple[str, list[str], list[list[str]]]

#: the paper's series-1 normalised RMSE of the angles after stage 1 and stage 2
PAPER_SERIES1_ANGLES = (0.11, 0.24)


def _fmt(v: float) -> str:
    return "–" if not np.isfinite(v) else f"{v:.2f}"


def _groups(spec: ProcessSpec) -> dict[str, slice]:
    n_x, n_in, n_aug = len(spec.state), len(spec.inputs), len(spec.augmented)
    return {"state x": slice(0, n_x), "parameters theta": slice(n_x, n_in),
            "deviation theta_d": slice(n_in, n_aug),
            "angles": slice(n_aug, n_aug + spec.n_outputs)}


def comparison(spec: ProcessSpec, overall: np.ndarray, series: tuple[int, ...]) -> list[str]:
    """Sentences comparing our Fig. 4 with the paper's findings."""
    g = _groups(spec)
    score = {s: float(np.nanmean(np.r_[overall[s - 1, g["state x"]], overall[s - 1, g["angles"]]]))
             for s in series}
    order = sorted(score, key=score.__getitem__)
    out = ["Mean normalised RMSE over the state variables and the angles, per series: " +
           ", ".join(f"series {s}: {score[s]:.2f}" for s in order) + " (best first)."]
    if 1 in score:
        a1, a2 = overall[0, g["angles"]]
        out.append(f"Series 1 (perfect model): angle after stage 1 {a1:.2f}, after stage 2 "
                   f"{a2:.2f}; the paper reports {PAPER_SERIES1_ANGLES[0]} and "
                   f"{PAPER_SERIES1_ANGLES[1]}.")
        easy = [spec.inputs.names[i] for i in np.argsort(overall[0, : len(spec.inputs)])[:4]]
        out.append("Best observed in series 1: " + ", ".join(easy) + " (the paper: punch end "
                   "distance and the constant parameters best; material parameters and "
                   "thickness hardest).")
    checks = []
    if {1, 2} <= set(score):
        checks.append(("series 2 (unmodelled deviation) is worse than series 1",
                       score[2] > score[1]))
    if {2, 3} <= set(score):
        checks.append(("estimating theta_d (series 3) recovers much of what series 2 lost",
                       score[3] < score[2]))
    if {1, 4} <= set(score):
        checks.append(("a wrong mu (series 4) is worse than known statistics (series 1)",
                       score[4] > score[1]))
    if {1, 5} <= set(score):
        checks.append(("physics-model data (series 5) is harder than metamodel data (series 1)",
                       score[5] > score[1]))
    if {1, 6} <= set(score):
        checks.append(("series 6 is clearly worse than series 1", score[6] > score[1]))
    for a, b in ((4, 7), (6, 8)):  # not the paper's: learned mu against assumed mid-range
        if {a, b} <= set(score):
            out.append(f"Learned mu (series {b}) against mid-range mu (series {a}): "
                       f"{score[b]:.2f} vs {score[a]:.2f} (see docs/notes/learned-mu.md).")
    for text, holds in checks:
        out.append(f"Paper: {text} — here: {'agrees' if holds else 'DOES NOT agree'}.")
    return out


def write_report(result: StudyResult, spec: ProcessSpec, folder: Path,
                 sources: dict[str, str], calibration: str = "",
                 sensors: dict[str, Any] | None = None, sensor_source: str = "") -> Path:
    """Write ``report.md``, ``report.html``, ``nrmse.csv``, ``results.json`` and figures;
    ``calibration`` says which interval calibration the trackers used
    (:meth:`~formtwin.tracker.intervals.Calibration.describe`), on the first page;
    ``sensors`` the sensor benchmark's figures read from ``sensor_source``
    (:mod:`formtwin.study.sensor_report`; None: the section says how to make them)."""
    folder.mkdir(parents=True, exist_ok=True)
    st = result.settings
    labels = component_labels(spec)
    per_dataset, overall = summarise(result.nrmse)
    plot_nrmse(spec, result.nrmse, st.series, folder / "fig4_nrmse.png")
    figs = []
    for s in (1, 6):
        if s in st.series:
            with np.load(result.run_paths[(s, 0, 0)], allow_pickle=False) as run:
                data = {k: run[k] for k in run.files}
            path = folder / f"fig{4 + (1 if s == 1 else 2)}_series{s}.png"
            plot_timeseries(spec, result.realisations[0], data, s, path,
                            last=min(200, st.n_products))
            figs.append((s, path))
    header = ["component"] + [f"series {s}" for s in st.series]
    table = [[labels[c]] + [_fmt(float(overall[s - 1, c])) for s in st.series]
             for c in range(len(labels))]
    ess = []
    for (s, _, _), p in sorted(result.run_paths.items()):
        with np.load(p, allow_pickle=False) as run:
            h = run["health"] if "health" in run.files else np.zeros(0, np.int8)
            ess.append((s, float(np.nanmean(run["ess"])), int(np.sum(run["collapsed"])),
                        [int(np.sum(h == k)) for k in range(3)]))
    ess_rows = [[str(s), _fmt(float(np.mean([e[1] for e in ess if e[0] == s]))),
                 str(sum(e[2] for e in ess if e[0] == s))]
                + [str(sum(e[3][k] for e in ess if e[0] == s)) for k in range(3)]
                for s in st.series]
    failures = {r.index: int((~r.ok["FE"]).sum()) for r in result.realisations}
    honest = honest_summary(result, spec)
    digest = data_digest(result.realisations)
    plot_honest(honest, folder / "fig_skill_coverage.png")
    blocks: list[Block] = [
        ("h1", "formtwin study: the six simulation series of Havinga et al."
         if spec.name == DEMONSTRATOR else
         f"formtwin study on {spec.name}: the six simulation series"),
        ("p", f"formtwin {formtwin.__version__}, Python {platform.python_version()}, "
              f"{datetime.now(UTC).isoformat(timespec='seconds')}. Run time "
              f"{result.timings['total_s']:.0f} s (pseudo-data "
              f"{result.timings['pseudo_data_s']:.0f} s, "
              f"{int(result.timings['filter_runs_computed'])} filter runs "
              f"{result.timings['filter_runs_s']:.0f} s)."),
        ("p", f"Reported intervals: '{st.tracker.intervals}'"
              + (f", {calibration}." if calibration else ".")),
        ("h2", "Settings"),
        ("table", ["setting", "value"], [[k, str(v)] for k, v in result.settings_dict().items()]
         + [[k, v] for k, v in sources.items()]
         + [[f"pseudo-data digest {src}", d] for src, d in digest.items()]),
        ("table", ["series", "data", "filter model", "statistics"],
         [[str(s.number), s.data_label, "g(MM), estimates theta_d" if s.deviation else "MM",
           "mu known" if s.mu_known else "mu learned, prior U(mu_min, mu_max)"
           if s.learn_mu else "mu = (mu_min + mu_max)/2"]
          for s in SERIES if s.number in st.series]),
        ("h2", "Fig. 4: normalised RMSE"),
        ("p", f"RMSE over the last {st.window} products, normalised by sigma (state), by "
              "(max - min)/sqrt 6 (parameters) and by the std of the real angles; bars are "
              "averages over datasets and repetitions, diamonds per dataset (averaged over "
              "repetitions). For a state variable 1 is the error of always answering the true "
              "mu, for a parameter that of a uniform random guess. With mu unknown (series 4, "
              "6-8) even the prior-only guess scores above 1, so above 1 is not by itself "
              "'no better than guessing': the skill below compares with that guess."),
        ("img", "fig4_nrmse.png", "Fig. 4 analogue"),
        ("table", header, table),
        ("h2", "Skill, coverage, ESS and evidence"),
        ("p", "Skill = 1 - RMSE / RMSE_prior per component, RMSE_prior the error of the "
              "prior-only estimate on the same data (no measurement: the assumed mu for the "
              "state, the middle of the bounds for theta, the prior-mean angle prediction); "
              "above 0 the force curves helped. Coverage: share of the scoring window whose "
              "truth lies in mean +- 1.645 std (0.90 for an honest posterior), the std as the "
              f"tracker reports it (intervals '{st.tracker.intervals}': 'calibrated' adds "
              "floors learned offline on independent physics runs, 'calibrated_fit' those "
              "scaled by the curves' running fit distance in excess of its mean on the "
              "metamodel's own curves; the paper's runs report "
              "the particles' std). Log-evidence: "
              "sum over all products of log p(z_i | z_1..i-1) (higher: the filter's model "
              "explains the data better; compare within a series). Likelihoods: "
              f"'{st.tracker.likelihood}' ({st.n_repetitions} repetitions per dataset)"
              + (f" and the paper's eq. 12 ({st.paper_repetitions} per dataset in series "
                 f"{', '.join(map(str, st.paper_series))}, same data)"
                 if result.paper else "") + "; docs/explanation/likelihood.md explains them."),
        ("img", "fig_skill_coverage.png", "skill and coverage per series"),
        ("table", *honest_table(honest)),
        *(_paper_blocks(result, spec, overall) if spec.name == DEMONSTRATOR else
          _own_blocks(result, spec, overall, sources)),
        *[("img", p.name, f"Fig. {4 + (1 if s == 1 else 2)} analogue: series {s}")
          for s, p in figs],
        ("h2", "Filter health"),
        ("table", ["series", "mean ESS", "collapsed steps", "fit ok", "fit degraded",
                   "no fit"], ess_rows),
        ("p", "Fit: the absolute goodness of fit of every product (formtwin.tracker.fit): "
              "the Mahalanobis distance of the curve from the filter's predictive under the "
              "likelihood's covariance, against chi-square with n_t degrees of freedom; "
              "'no fit' beyond its 99.9 % quantile, 'degraded' beyond 99 % or with ESS "
              "below 1 % of N. Counted over all products of all runs of the series."),
        ("p", "Physics-model failures per realisation (products skipped in series 5 and 6): "
              + ", ".join(f"{k}: {v}" for k, v in failures.items()) + "."),
        *sensor_blocks(sensors, folder, sensor_source),
    ]
    (folder / "report.md").write_text(_markdown(blocks), encoding="utf-8")
    (folder / "report.html").write_text(_html(blocks), encoding="utf-8")
    with open(folder / "nrmse.csv", "w", encoding="utf-8") as f:
        f.write("series,realisation,repetition," + ",".join(labels) + "\n")
        for s in st.series:
            for k in range(st.n_realisations):
                for r in range(st.n_repetitions):
                    vals = ",".join(f"{v:.6g}" for v in result.nrmse[s - 1, k, r])
                    f.write(f"{s},{k},{r},{vals}\n")
    summary: dict[str, Any] = {"settings": result.settings_dict(), "timings": result.timings,
               "sources": sources, "interval_calibration": calibration,
               "components": labels,
               "data_digest": digest,
               "nrmse_overall": {f"series{s}": dict(zip(labels, map(_json_float,
                                                                     overall[s - 1]), strict=True))
                                 for s in st.series},
               "honest": honest}
    (folder / "results.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return folder / "report.html"


def _paper_blocks(result: StudyResult, spec: ProcessSpec, overall: np.ndarray
                  ) -> list[Block]:
    """The demonstrator's comparison with the paper's figures and why ours may differ."""
    st = result.settings
    return [
        ("h2", "Comparison with the paper"),
        *[("p", line) for line in comparison(spec, overall, st.series)],
        ("p", "Spread of the real angles in the scoring window (the angle normaliser), mean "
              "over datasets: " + "; ".join(
                  f"{src} data: stage 1 {a1:.3f} deg, stage 2 {a2:.3f} deg"
                  for src, (a1, a2) in _angle_spread(result).items()) + ". A small spread "
              "makes the normalised angle error large even when the error in degrees is "
              "small: our stage-2 angle hardly varies with the inputs, and the metamodel's "
              "own stage-2 angle error is of the same order as that spread "
              "(docs/explanation/metamodel.md)."),
        ("p", "Why ours may differ: our physics model is a corotational-beam model of an "
              "invented flap geometry, not the paper's MSC.Marc model of the real demonstrator; "
              "the sensitivities of the force curve to each parameter, and therefore what is "
              "observable, differ. Our metamodel, the K_MC-based likelihood (with a residual "
              "term for curves outside the POD span) and the random draws of mu, theta and "
              "theta_d differ too; with 5 datasets the per-dataset spread (diamonds) is large."),
    ]


def _own_blocks(result: StudyResult, spec: ProcessSpec, overall: np.ndarray,
                sources: dict[str, str]) -> list[Block]:
    """For another process than the demonstrator: what the series measured, no paper
    figures (they are the demonstrator's)."""
    g = _groups(spec)
    st = result.settings
    score = {s: float(np.nanmean(np.r_[overall[s - 1, g["state x"]],
                                       overall[s - 1, g["angles"]]])) for s in st.series}
    spread = _angle_spread(result)
    return [
        ("h2", f"Process {spec.name}"),
        ("p", f"{spec.description or spec.name}. Mean normalised RMSE over the state "
              "variables and the outputs, per series: " + ", ".join(
                  f"series {s}: {v:.2f}" for s, v in sorted(score.items(),
                                                           key=lambda kv: kv[1]))
              + " (best first)."),
        ("p", "Physics data of the sources FE and gFE (series 5, 6): "
              f"{sources.get('physics model', '?')}. With an FE dataset the physics values at "
              "the drawn products are an interpolation of the FE runs independent of the "
              "metamodel (formtwin.study.fe_data): series 5 and 6 then measure how the "
              "tracker copes with the metamodel's approximation error, not with the gap "
              "between the FE model and the real press."),
        ("p", "Spread of the real outputs in the scoring window (their normaliser), mean over "
              "datasets: " + "; ".join(
                  f"{src} data: " + ", ".join(f"{o.name} {v:.3g} {o.unit}" for o, v in
                                              zip(spec.outputs, vals, strict=True))
                  for src, vals in spread.items()) + "."),
    ]


def _angle_spread(result: StudyResult) -> dict[str, tuple[float, ...]]:
    """Std of the real angles over the last ``window`` products, per data source (deg)."""
    w = result.settings.window
    out = {}
    for src in ("MM", "FE"):
        spreads = [np.nanstd(np.where(r.ok[src][-w:, None], r.angles[src][-w:], np.nan), axis=0)
                   for r in result.realisations]
        out[src] = tuple(float(v) for v in np.mean(spreads, axis=0))
    return out


def _json_float(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _markdown(blocks: list[Block]) -> str:
    out = []
    for b in blocks:
        kind = b[0]
        if kind == "h1":
            out.append(f"# {b[1]}\n")
        elif kind == "h2":
            out.append(f"## {b[1]}\n")
        elif kind == "p":
            out.append(f"{b[1]}\n")
        elif kind == "img":
            out.append(f"![{b[2]}]({b[1]})\n")
        elif kind == "table":
            head, rows = b[1], b[2]
            out.append("| " + " | ".join(head) + " |")
            out.append("|" + "---|" * len(head))
            out += ["| " + " | ".join(r) + " |" for r in rows]
            out.append("")
    return "\n".join(out)


def _html(blocks: list[Block]) -> str:
    e = html.escape
    body = []
    for b in blocks:
        kind = b[0]
        if kind in ("h1", "h2", "p"):
            body.append(f"<{kind}>{e(str(b[1]))}</{kind}>")
        elif kind == "img":
            body.append(f'<figure><img src="{e(str(b[1]))}" alt="{e(str(b[2]))}">'
                        f"<figcaption>{e(str(b[2]))}</figcaption></figure>")
        elif kind == "table":
            head = "".join(f"<th>{e(h)}</th>" for h in b[1])
            rows = "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>"
                           for r in b[2])
            body.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
    style = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;"
             "padding:2px 8px;text-align:right}img{max-width:100%}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>formtwin study</title>"
            f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n")
