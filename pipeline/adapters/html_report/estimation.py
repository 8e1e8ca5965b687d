"""``report.html`` of an estimation run, rendered from the stored files."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pipeline._threads import single_threaded_blas
from pipeline.adapters.html_report import figures
from pipeline.adapters.html_report.page import (
    esc,
    fmt,
    grade_badge,
    page,
    ratio_unit,
    section,
    table,
)
from pipeline.adapters.html_report.stored import (
    StoredRun,
    held_out_fit,
    load_run,
    residual_correlations,
)
from pipeline.identification.quality import GRADE_MEANING, GRADE_RULE, relative_gain_array
from pipeline.readouts.run_summary import RunSummary

__all__ = ["render_run_html"]

_SECTIONS = (("step-matrix", "Step responses"), ("gains", "Gains"),
             ("grades", "Quality grades"), ("fit", "Measured vs predicted (held out)"),
             ("residuals", "Residual correlations"), ("frequency", "Frequency responses"),
             ("search", "N_p / N_d search"), ("data-quality", "Data quality"))


def _header(run: StoredRun, summary: RunSummary, banner: str) -> str:
    m = run.manifest
    facts = [f"run <b>{esc(m.get('run_id'))}</b>"]
    if m.get("created_utc"):
        facts.append(f"created {esc(m['created_utc'])}")
    if m.get("status"):
        facts.append(f"status <b>{esc(m['status'])}</b>")
    facts += [esc(f) for f in summary.header_facts()]
    files = [esc(Path(str(f.get("path"))).name)
             + (f" (sha256 {esc(str(f['sha256'])[:12])}…)" if f.get("sha256") else "")
             for f in m.get("inputs") or [] if isinstance(f, Mapping)]
    nav = " ".join(f'<a href="#{k}">{esc(t)}</a>' for k, t in _SECTIONS)
    return (f"<h1>plantdyn run: {esc(m.get('job'))}</h1>\n{banner}\n<p class=\"meta\">"
            + " · ".join(facts) + "</p>\n"
            + (f"<p class=\"meta\">input: {', '.join(files)}</p>\n" if files else "")
            + f"<nav>{nav}</nav>")


def monitor_banner(checks: Mapping[str, Any] | None) -> str:
    """The nightly monitor's verdict as a banner ('' when checks.json has no ``monitor``).

    Parameters
    ----------
    checks : mapping or None
        checks.json; its optional ``monitor`` section holds ``baseline_run``,
        ``threshold_sigma``, ``changed`` (pair names ``"y<-u"``) and ``pairs``.
    """
    mon = (checks or {}).get("monitor")
    if not isinstance(mon, Mapping):
        return ""
    thr = fmt(mon.get("threshold_sigma"), 3)
    base = mon.get("baseline_run")
    changed = mon.get("changed")
    changed = [str(c) for c in changed] if isinstance(changed, (list, tuple)) else []
    if base is None:
        return ('<div id="monitor-banner" class="banner unchanged">Monitor: no baseline run '
                "to compare with yet.</div>")
    if not changed:
        return (f'<div id="monitor-banner" class="banner unchanged">Monitor: no pair moved '
                f"beyond {thr} σ of baseline run {esc(base)}.</div>")
    details = []
    pairs = mon.get("pairs") if isinstance(mon.get("pairs"), Mapping) else {}
    for name in changed:
        d = pairs.get(name)
        if isinstance(d, Mapping):
            kv = ", ".join(f"{esc(k)} {fmt(v, 3) if not isinstance(v, str) else esc(v)}"
                           for k, v in d.items() if not isinstance(v, (Mapping, list)))
            details.append(f"<li><b>{esc(name)}</b>{': ' + kv if kv else ''}</li>")
        else:
            details.append(f"<li><b>{esc(name)}</b></li>")
    return (f'<div id="monitor-banner" class="banner changed"><b>Monitor: {len(changed)} '
            f"pair(s) moved beyond {thr} σ of baseline run {esc(base)}</b>: "
            f"{esc(', '.join(changed))}<ul>{''.join(details)}</ul></div>")


def _step_matrix(run: StoredRun, units: dict[str, str]) -> str:
    if run.steps is None:
        return "<p>No step_responses.parquet in this run.</p>"
    missing = [n for n in run.outputs + run.inputs if not units.get(n)]
    note = (f" No unit is given for {esc(', '.join(missing))} (neither in the job's "
            "signals nor in the export's header)." if missing else "")
    return ("<figure>" + figures.step_matrix(run, units) +
            "<figcaption>Rows are outputs, columns inputs. Black: the estimate on every "
            "usable sample (<code>all</code>) with its ±2σ band (σ = step_std, the "
            "estimator's own; where it is not seen it is narrower than the line); red dashed: "
            "the transfer function <code>plantdyn export</code> writes (absent where the "
            "export leaves the pair out); thin coloured lines: the disjoint windows, each estimated on "
            f"its own. Time is after a unit step of the input.{note}</figcaption></figure>")


def gain_table(run: StoredRun, summary: RunSummary) -> str:
    """The gain matrix (gain ± σ, or rate ± σ for integrating outputs, with the grade)
    and the relative gain array where the matrix is square with finite gains.

    Parameters
    ----------
    run : StoredRun
        The run (its inputs and outputs give the matrix's order).
    summary : RunSummary
        The run's summary (each pair's cell, grade and unit).
    """
    units = summary.units
    head = ["output \\ input"] + [
        f"{esc(u)}<br><span class=\"unit\">[{esc(units.get(u) or 'no unit')}]</span>"
        for u in run.inputs]
    rows, G = [], np.full((len(run.outputs), len(run.inputs)), np.nan)
    for i, o in enumerate(run.outputs):
        row = [f"<b>{esc(o)}</b><br><span class=\"unit\">[{esc(units.get(o) or 'no unit')}]</span>"]
        for j, u in enumerate(run.inputs):
            p = summary.pair(o, u)
            if p is None:
                row.append("–")
                continue
            unit = ratio_unit(units.get(o, ""), units.get(u, ""))
            cell = esc(p.value_plain) or "–"
            if p.integrating:
                cell = f"rate {cell}"
                unit += " per s"
            elif p.value is not None:
                G[i, j] = float(p.value)
            row.append(f"{cell} {grade_badge(p.grade)}<br><span class=\"unit\">{esc(unit)}</span>")
        rows.append(row)
    out = [table(head, rows, table_id="gain-matrix"),
           "<p>Gain = the final value of the all-data step response (the FIR model's static "
           "gain) ± its σ, which includes what the horizon leaves out; a pair still moving "
           "at its horizon has no gain (an extrapolated one, labelled, when its tail "
           "decays); integrating outputs have a rate (slope per unit input step) "
           "instead. The letter is the pair's quality grade (below).</p>"]
    rga = relative_gain_array(G)
    if rga is not None:
        out += ["<h3>Relative gain array</h3>",
                table(["output \\ input"] + [esc(u) for u in run.inputs],
                      [[f"<b>{esc(o)}</b>"] + [fmt(v, 3) for v in rga[i]]
                       for i, o in enumerate(run.outputs)], table_id="rga",
                      numeric=range(1, len(run.inputs) + 1)),
                "<p>Λ = G ∘ (G⁻¹)ᵀ (Bristol). Pair each output with an input whose λ is "
                "near 1; λ &lt; 0 means the loop's gain changes sign when the others close. "
                "The gains' σ are not propagated into Λ.</p>"]
    else:
        n_y, n_x = len(run.outputs), len(run.inputs)
        shape = f"{n_y} output{'s' * (n_y != 1)} × {n_x} input{'s' * (n_x != 1)}"
        why = "not square" if G.shape[0] != G.shape[1] else \
            "not every gain is finite (integrating outputs), or the matrix is singular"
        out.append(f"<p id=\"rga-absent\">No relative gain array: the gain matrix ({shape}) "
                   f"is {why}.</p>")
    return "\n".join(out)


def grade_rule_table() -> str:
    """The grade rule (:data:`pipeline.identification.quality.GRADE_RULE`) as an HTML table with the
    meaning of each letter."""
    rule = table(["criterion", "read from", "A", "B", "C", "D"],
                 [[esc(c) for c in row] for row in GRADE_RULE], table_id="grade-rule")
    meaning = "".join(f"<li>{grade_badge(g)} {esc(t)}</li>" for g, t in GRADE_MEANING.items())
    return ("<h3>The grade rule</h3><p>Each criterion caps the grade; a pair's grade is the "
            "worst cap. A criterion whose value is not in the run is not judged. "
            "(<code>pipeline/identification/quality.py</code>; report.md shows the same grades.)</p>"
            + rule + f"<ul>{meaning}</ul>")


def _grades(summary: RunSummary) -> str:
    rows = []
    for p in summary.pairs:
        crit = p.criteria
        rows.append([
            esc(p.name), grade_badge(p.grade),
            "<br>".join(esc(r) for r in p.reasons) or "all checks pass",
            esc(p.windows_text), fmt(crit["relative_sigma"]["value"], 2),
            fmt(crit["whiteness"]["value"], 2),
            esc({True: "ok", False: "outside band", None: "–"}[crit["cross_correlation"]["value"]]),
            esc(p.feedback_text), fmt(crit["excitation"]["value"], 3)])
    return (table(["pair", "grade", "why not A", "windows (p)", "relative σ", "Ljung–Box p",
                   "input cross-corr.", "feedback (p)", "input VIF"], rows,
                  table_id="grade-table", numeric=(4, 5, 8))
            + grade_rule_table())


def _fit(run: StoredRun, units: dict[str, str]) -> str:
    fit = held_out_fit(run)
    if fit is None:
        return "<p>Needs step_responses.parquet, signals.parquet and checks.json.</p>"
    rows = [[esc(o), fmt(r.get("fit_held_out"), 3), fmt(r.get("fit_all"), 3),
             "differences Δy" if r["differenced"] else "level"]
            for o, r in fit["outputs"].items()]
    return (f"<p id=\"held-out\">Held out: {esc(fit['what'])}. Simulated from the conditioned "
            "inputs in signals.parquet alone (no output feedback), both series with their "
            "held-out mean removed; samples whose lags touch a masked input are left out. "
            "Fit = 100·(1 − ‖y − ŷ‖/‖y − mean(y)‖) (MATLAB <code>compare</code>): 100 % is "
            "perfect, 0 % no better than the mean. Slow unmeasured disturbances (which the "
            "noise model describes but an input-only simulation cannot follow) lower it.</p>"
            + table(["output", "fit %, held out", "fit %, all-data estimate (in-sample)",
                     "compared as"], rows, table_id="fit-table", numeric=(1, 2))
            + "<figure>" + figures.fit_figure(run, fit, units) + "</figure>")


def _residuals(run: StoredRun) -> str:
    corr = residual_correlations(run)
    if corr is None:
        return "<p>Needs residuals.parquet, signals.parquet and checks.json.</p>"
    rows = [[esc(o), esc(c.get("of")), esc(c.get("lags")), fmt(c.get("statistic")),
             fmt(c.get("p_value"), 2), esc({True: "white", False: "NOT white", None: "–"}
                                          [c.get("white")]), esc(c.get("n"))]
            for o, c in corr["outputs"].items()]
    xrows = [[esc(f"{o}<-{u}"), fmt(x["band"], 3), fmt(100 * x["fraction_outside"], 3),
              fmt(x["max_abs_r"], 3), fmt(x["statistic"]), fmt(x["p_value"], 2),
              "ok" if x["ok"] else "<b>outside</b>"] for (o, u), x in corr["pairs"].items()]
    acf, xcorr = figures.correlation_figures(run, corr)
    return ("<p>The prediction errors — the stored residuals of the all-data estimate "
            "through each output's noise model D(q) (checks.json <code>noise_model</code>) — "
            "recomputed from residuals.parquet and signals.parquet exactly as the checks "
            "did. Dashed red: the 99 % band ±2.58/√n of one correlation under "
            "independence.</p>"
            + table(["output", "of", "lags", "Ljung–Box Q", "p", "verdict (p ≥ 0.01)",
                     "samples"], rows, table_id="whiteness-table", numeric=(2, 3, 4, 6))
            + f"<figure>{acf}<figcaption>Autocorrelation of the prediction errors."
              "</figcaption></figure>"
            + table(["pair", "band", "% of lags ≥ 0 outside", "max |r|", "S", "p",
                     "verdict (p ≥ 0.01)"], xrows, table_id="xcorr-table",
                    numeric=(1, 2, 3, 4, 5))
            + f"<figure>{xcorr}<figcaption>Cross-correlation of each input (shifted by the "
              "lag) with the output's prediction errors. Positive lags outside the band: the "
              "model misses part of the input's effect; negative lags (grey): the output "
              "moves the input (feedback).</figcaption></figure>")


def _frequency(run: StoredRun, units: dict[str, str]) -> str:
    if run.steps is None:
        return "<p>No step_responses.parquet in this run.</p>"
    return ("<figure>" + figures.frequency_matrix(run, units) +
            "<figcaption>Frequency response of each all-data step response (the DTFT of its "
            "increments, <code>pipeline/readouts/frequency.py</code>; integrating pairs continue their "
            "last increment), from 1/4 of the slowest lag range up to the Nyquist frequency "
            "π/T.</figcaption></figure>")


def _search(run: StoredRun) -> str:
    s = (run.checks or {}).get("search") or {}
    rows = [[esc(k), esc(v), esc((s.get("n_k") or {}).get(k))] for k, v in (s.get("n_p") or {}).items()]
    wins = [[esc(w.get("window")), esc(w.get("samples")), esc(w.get("status")),
             esc(w.get("n_d", "")), esc(w.get("error", ""))] for w in s.get("windows") or []]
    return ("<p>N_p per pair: the shortest candidate whose tail (last 20 % of lags) stays "
            "within a 2 % band plus 3σ, with nothing significant beyond it; N_d doubled from "
            f"10·N_p until two disjoint windows agree or the data run out: N_d = "
            f"{esc(s.get('n_d'))} samples per window.</p>"
            + "<figure>" + figures.search_trace_figure(run) + "</figure>"
            + table(["pair", "N_p chosen", "n_k"], rows, table_id="search-table", numeric=(1, 2))
            + table(["window", "samples", "status", "N_d used", "error"], wins,
                    table_id="windows-table"))


def _data_quality(run: StoredRun, summary: RunSummary) -> str:
    units = summary.units
    dq = (run.checks or {}).get("data_quality") or {}
    rows = []
    for name, q in (dq.get("signals") or {}).items():
        why = ", ".join(f"{k}: {v}" for k, v in (q.get("masked_by_reason") or {}).items())
        rows.append([esc(name), esc(q.get("role")), esc(q.get("tag")),
                     esc(units.get(name) or "–"), esc(q.get("grid_samples")),
                     esc(q.get("masked")), esc(why or "–")])
    out = [f"<p>Grid period {fmt(dq.get('grid_dt_s'))} s; {esc(dq.get('samples_at_dt'))} "
           f"samples at T; {esc(dq.get('samples_used_all'))} used by the all-data estimate "
           "(every lag of every signal good).</p>",
           table(["signal", "role", "tag", "unit", "grid samples", "masked", "why masked"],
                 rows, table_id="masked-table", numeric=(4, 5))]
    out += [f"<p>{esc(note)}</p>" for note in summary.data_notes()]
    if run.signals is not None:
        fig = figures.masked_figure(run)
        out.append(f"<figure>{fig}<figcaption>Masked samples (red) on the sample-period grid."
                   "</figcaption></figure>" if fig else "<p>No sample is masked.</p>")
    return "\n".join(out)


def _footer(run: StoredRun) -> str:
    files = ", ".join(esc(f.get("name")) for f in run.manifest.get("files") or []
                      if isinstance(f, Mapping))
    return ("<footer><p class=\"meta\">Rendered from the run's stored files"
            + (f" ({files})" if files else "")
            + "; rebuild without refitting: <code>python -m pipeline.adapters.html_report "
              "RUN_DIR</code>.</p></footer>")


@single_threaded_blas
def render_run_html(run_dir: Path, *, manifest: Mapping[str, Any] | None = None) -> str:
    """The estimation run's report as one self-contained HTML document (figures inline).

    Parameters
    ----------
    run_dir : Path
        The run directory, or the store's temporary directory while it is written.
    manifest : mapping, optional
        ``job``, ``run_id``, ``config`` (resolved), ``status``, ``created_utc``, ``inputs``
        when ``manifest.json`` does not exist yet (inside ``store.new_run``); default:
        read ``run_dir/manifest.json``.
    """
    run = load_run(Path(run_dir), manifest)
    summary = RunSummary.from_checks(run.checks or {}, job=str(run.manifest.get("job")),
                                     status=str(run.manifest.get("status")),
                                     config=run.config)
    units = summary.units
    body = {
        "step-matrix": lambda: _step_matrix(run, units),
        "gains": lambda: gain_table(run, summary),
        "grades": lambda: _grades(summary),
        "fit": lambda: _fit(run, units),
        "residuals": lambda: _residuals(run),
        "frequency": lambda: _frequency(run, units),
        "search": lambda: _search(run),
        "data-quality": lambda: _data_quality(run, summary),
    }
    parts = [_header(run, summary, monitor_banner(run.checks))]
    parts += [section(key, title, body[key]) for key, title in _SECTIONS]
    parts.append(_footer(run))
    return page(f"plantdyn {run.manifest.get('job')} {run.manifest.get('run_id')}",
                "\n".join(p for p in parts if p))
