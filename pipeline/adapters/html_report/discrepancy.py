"""``report.html`` of a discrepancy run, rendered from ``discrepancy.json`` and
``discrepancy_series.parquet``."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline._threads import single_threaded_blas
from pipeline.adapters.html_report.page import (
    esc,
    figure_png,
    figure_svg,
    fmt,
    new_figure,
    page,
    panel_grid,
    section,
    table,
)
from pipeline.discrepancy.report import (
    effect_markup,
    fmt_percent,
    json_number,
    low_text,
    pass_rule,
)
from pipeline.readouts.run_summary import signal_units

__all__ = ["render_discrepancy_html", "effect_html"]

_SECTIONS = (("series", "Measured, nominal and augmented"), ("gap-chain", "Held-out gap, effect by effect"),
             ("candidates", "Candidates"), ("localisation", "Localisation"),
             ("minor-effects", "Minor effects and look-alikes"))


def effect_html(effect: Mapping[str, Any]) -> str:
    """An effect as HTML: ``gain at controller (factor = 1.204)``.

    Parameters
    ----------
    effect : mapping
        ``name``, ``location``, ``parameters`` (and optionally ``equivalent_locations``).
    """
    return effect_markup(effect, code=lambda s: f"<code>{esc(s)}</code>", plain=esc)


def _header(doc: Mapping[str, Any], manifest: Mapping[str, Any]) -> str:
    data = doc.get("data") if isinstance(doc.get("data"), Mapping) else {}
    facts = [f"run <b>{esc(doc.get('run_id') or manifest.get('run_id'))}</b>"]
    if doc.get("model"):
        kind = ("external simulator outputs" if doc.get("model_source") == "external_simulator"
                else "block diagram")
        facts.append(f"model <code>{esc(doc['model'])}</code> ({kind})")
    if data:
        facts.append(f"{esc(data.get('analysed_samples'))} samples at {fmt(doc.get('dt_s'))} s "
                     f"({esc(data.get('start_utc'))} to {esc(data.get('end_utc'))})")
    chain = [e for e in doc.get("effects") or [] if isinstance(e, Mapping)]
    if chain:
        finding = (f"<b>{len(chain)} effect(s) found</b>, in order: "
                   + "; ".join(effect_html(e) for e in chain) + " — in model_augmented.yaml.")
    elif doc.get("verdict") == "inconclusive":
        finding = "<b>Inconclusive</b>: look-alike candidates fit about equally well."
    elif rejected := [c for c in doc.get("rejected") or [] if isinstance(c, Mapping)]:
        finding = ("<b>No significant effect</b>: the candidate that fits best, "
                   + "; ".join(effect_html(c) for c in rejected) + ", fails on held-out "
                   "data; the nominal model stays.")
    elif doc.get("minor_effects"):
        finding = ("<b>No significant effect</b>: what the tests detect closes too little "
                   "of the gap to matter (see Minor effects); the nominal model stays.")
    else:
        finding = "<b>No effect accepted</b>: the nominal model stays."
    equivalent = [c for c in doc.get("equivalent_effects") or [] if isinstance(c, Mapping)]
    if equivalent:
        finding += ("<br>Equivalent explanations (the simplest is named): "
                    + "; ".join(effect_html(c) for c in equivalent))
    finding += "".join(f'<br><span class="note"><b>Note:</b> {esc(n)}</span>'
                       for n in doc.get("notes") or [] if isinstance(n, str))
    nav = " ".join(f'<a href="#{k}">{esc(t)}</a>' for k, t in _SECTIONS)
    return (f"<h1>Discrepancy: {esc(doc.get('verdict'))} — {esc(doc.get('job'))}</h1>\n"
            f"<p class=\"meta\">{' · '.join(facts)}</p>\n<p id=\"finding\">{finding}</p>\n"
            f"<nav>{nav}</nav>")


def _rolling_rms(x: np.ndarray, n: int) -> np.ndarray:
    """RMS over a centred window of ``n`` samples (NaN-aware)."""
    ok = np.isfinite(x)
    k = np.ones(n)
    num = np.convolve(np.where(ok, x * x, 0.0), k, mode="same")
    cnt = np.convolve(ok.astype(float), k, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(num / np.where(cnt > n // 2, cnt, np.nan))


def _shade(ax, h: np.ndarray, part: np.ndarray) -> None:
    if (part == "holdout").any():
        ax.axvspan(h[part == "holdout"][0], h[-1], color="#fff3c4", lw=0)
    if (part == "warmup").any():
        ax.axvspan(h[0], h[part == "warmup"][-1], color="#eeeeee", lw=0)


def _axes_text(ax, ylabel: str, xlabel: str) -> None:
    ax.set_ylabel(ylabel, fontsize=7)
    ax.set_xlabel(xlabel, fontsize=7)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=3,
              frameon=False, borderaxespad=0.1)
    ax.grid(True, lw=0.3, alpha=0.5)


def _series(doc: Mapping[str, Any], series: pl.DataFrame | None, units: dict[str, str]) -> str:
    if series is None:
        return "<p>No discrepancy_series.parquet in this run.</p>"
    outputs = series["output"].unique(maintain_order=True).to_list()
    fig = new_figure(12.0, 3 * 2.35 * len(outputs) + 0.2)
    axes = panel_grid(fig, 3 * len(outputs), 1, panel_w=10.6, panel_h=1.6, left=0.95,
                      bottom=0.45, right=0.45, top=0.3)
    hours = "time (h) from the first analysed sample; grey: warm-up, yellow: held out"
    for k, o in enumerate(outputs):
        df = series.filter(pl.col("output") == o).sort("time_s")
        h = df["time_s"].to_numpy() / 3600.0
        part = df["part"].to_numpy()
        unit = units.get(o) or "output unit"
        whole, zoom, res = (axes[3 * k + m][0] for m in range(3))
        cols = {c: df[c].cast(pl.Float64).to_numpy() for c in
                ("measured", "nominal", "augmented", "residual_before", "residual_after")}
        for ax in (whole, res):
            _shade(ax, h, part)
        held = np.flatnonzero(part == "holdout")
        a = int(held[0]) if held.size else 0
        b = min(h.size, a + max(300, h.size // 20))
        for ax, sl in ((whole, slice(None)), (zoom, slice(a, b))):
            ax.plot(h[sl], cols["measured"][sl], color="#555555", lw=0.6, label="measured")
            ax.plot(h[sl], cols["nominal"][sl], color="#1f77b4", lw=0.9, label="nominal model")
            ax.plot(h[sl], cols["augmented"][sl], color="#d62728", lw=0.9,
                    label="augmented model")
        n = max(5, h.size // 100)
        res.plot(h, _rolling_rms(cols["residual_before"], n), color="#1f77b4", lw=0.9,
                 label="measured − nominal")
        res.plot(h, _rolling_rms(cols["residual_after"], n), color="#d62728", lw=0.9,
                 label="measured − augmented")
        _axes_text(whole, f"{o} ({unit})", hours)
        _axes_text(zoom, f"{o} ({unit})", "time (h), zoom on the start of the held-out part")
        _axes_text(res, f"rolling RMS of the residual ({unit})",
                   f"{hours}; window {n} samples")
    return ("<figure>" + figure_png(fig, alt="measured, nominal and augmented outputs") +
            "<figcaption>Deviation variables (the operating point removed). Per output: the "
            "whole record, a zoom on the held-out part, and the residual's rolling RMS "
            "before (nominal) and after (augmented). The held-out last part judged every "
            "candidate; the fit part was used to fit it.</figcaption></figure>")


def _gap_chain(doc: Mapping[str, Any], units: dict[str, str]) -> str:
    gap = doc.get("gap") if isinstance(doc.get("gap"), Mapping) else {}
    chain = [e for e in doc.get("effects") or [] if isinstance(e, Mapping)]
    labels = ["nominal"] + [f"+ {e.get('name')} at {e.get('location')}" for e in chain]
    values = [json_number(gap.get("holdout_rms_before"))] + \
        [json_number(e.get("gap_after")) for e in chain]
    rows = [[esc(k), effect_html(e), fmt(e.get("gap_before")), fmt(e.get("gap_after")),
             fmt_percent(e.get("gap_reduction"))] for k, e in enumerate(chain, 1)]
    per_out = [[esc(o), fmt(g.get("holdout_rms_before")), fmt(g.get("holdout_rms_after")),
                fmt_percent(g.get("reduction")), esc(units.get(o) or "–")]
               for o, g in (gap.get("per_output") or {}).items() if isinstance(g, Mapping)]
    fig = new_figure(1.6 + 1.5 * len(labels), 2.6)
    ax = fig.add_axes((1.0 / (1.6 + 1.5 * len(labels)), 0.3, 1 - 1.3 / (1.6 + 1.5 * len(labels)),
                       0.6))
    ax.bar(range(len(values)), values, color=["#1f77b4"] + ["#d62728"] * len(chain), width=0.6)
    ax.set_xticks(range(len(labels)), labels, fontsize=7)
    outs = [o for o in (gap.get("per_output") or {})]
    unit = units.get(outs[0]) if len(outs) == 1 and units.get(outs[0]) else \
        (gap.get("units") or "output units")
    ax.set_ylabel(f"held-out RMS gap ({unit})", fontsize=7)
    ax.tick_params(labelsize=7)
    ax.set_title("held-out RMS gap after each accepted effect", fontsize=8)
    check = doc.get("augmented_model_check") if isinstance(doc.get("augmented_model_check"),
                                                           Mapping) else {}
    chk = [[esc(o), fmt(v), fmt((check.get("holdout_rms_resimulated") or {}).get(o))]
           for o, v in (check.get("holdout_rms_reported") or {}).items()]
    return ("<figure>" + figure_svg(fig, "gap-chain") + "</figure>"
            + (table(["step", "effect", "held-out gap before", "after", "reduction"], rows,
                     table_id="chain-table", numeric=(2, 3, 4)) if rows else
               "<p>No effect was accepted: the gap stays the nominal model's.</p>")
            + table(["output", "held-out RMS before", "after", "reduction", "unit"], per_out
                    + [["<b>overall</b>", fmt(gap.get("holdout_rms_before")),
                        fmt(gap.get("holdout_rms_after")), fmt_percent(gap.get("reduction")), ""]],
                    table_id="gap-table", numeric=(1, 2, 3))
            + (table(["output", "held-out RMS reported", "model_augmented.yaml re-simulated"],
                     chk, table_id="model-check", numeric=(1, 2)) if chk else ""))


def _candidates(doc: Mapping[str, Any]) -> str:
    cands = [c for c in doc.get("candidates") or [] if isinstance(c, Mapping)]
    if not cands:
        return "<p>No candidate was fitted.</p>"
    rows = []
    for k, c in enumerate(cands, 1):
        params = c.get("parameters") or {}
        rows.append([
            esc(k), f"<code>{esc(c.get('name'))}</code>", f"<code>{esc(c.get('location'))}</code>",
            esc(", ".join(f"{p} = {v if isinstance(v, str) else fmt(v)}" for p, v in params.items())),
            esc(", ".join(map(str, c.get("equivalent_locations") or [])) or "–"),
            esc(c.get("n_parameters")), fmt(c.get("delta_bic")), fmt(c.get("criterion")),
            fmt(c.get("screening_score")), fmt(c.get("holdout_z"), 3), fmt(c.get("holdout_gap")),
            esc(", ".join(f"{o}: {fmt(v)}" for o, v in (c.get("holdout_rms") or {}).items())),
            fmt_percent(c.get("gap_reduction")), low_text(c),
            fmt(c.get("holdout_rms_p"), 2),
            fmt_percent(c.get("closed_loop_prediction_error_reduction")),
            "yes" if c.get("passed") is True else "no", esc(c.get("passed_by") or "–")])
    rule = pass_rule(doc)
    return ((f"<p>{esc(rule)}</p>" if rule else "")
            + table(["#", "effect", "location", "parameters", "equivalent locations",
                     "parameters (n)", "ΔBIC", "criterion", "screening score", "held-out z",
                     "held-out gap", "held-out RMS", "gap_reduction",
                     "largest output gap_reduction, 95 % lower bound", "RMS p",
                     "closed-loop prediction-error reduction", "passed", "passed_by"], rows,
                    table_id="candidates-table",
                    numeric=(0, 5, 6, 7, 8, 9, 10, 12, 13, 14, 15)))


def _signals_table(o: str, loc: Mapping[str, Any]) -> str:
    rows = []
    for name, sig in (loc.get("signals") or {}).items():
        if not isinstance(sig, Mapping):
            continue
        band = sig.get("band_of_largest_discrepancy_hz")
        rows.append([
            f"<b>{esc(name)}</b>", "yes" if sig.get("significant") else "no",
            fmt(sig.get("partial_r2"), 3), fmt(sig.get("p_value"), 3), fmt(sig.get("statistic")),
            fmt(sig.get("peak_lag_s")), fmt(sig.get("first_significant_lag_s")),
            esc(sig.get("significant_lags")),
            f"{fmt(sig.get('discrepancy_step_final'), 3)} ± {fmt(sig.get('discrepancy_step_final_std'), 2)}",
            "–" if not band else f"{fmt(band[0], 3)}–{fmt(band[1], 3)}"])
    return table(["signal", "significant", "partial R²", "p", "statistic", "peak lag (s)",
                  "first significant lag (s)", "significant lags", "discrepancy step final",
                  "largest model–data difference (Hz)"], rows,
                 table_id=f"localisation-{o}", numeric=(2, 3, 4, 5, 6, 7))


def _localisation(doc: Mapping[str, Any]) -> str:
    locs = doc.get("localization") if isinstance(doc.get("localization"), Mapping) else {}
    if not locs:
        return "<p>No localisation in this run.</p>"
    out = []
    for o, loc in locs.items():
        if not isinstance(loc, Mapping):
            continue
        by = loc.get("explained_by") or []
        out.append(f"<h3>{esc(o)}</h3><p>Residual RMS {fmt(loc.get('residual_rms'))} "
                   f"({fmt_percent(loc.get('relative_residual'))} of the measured std), explained by "
                   f"<b>{esc(', '.join(map(str, by)) or 'no input')}</b>.</p>")
        out.append(_signals_table(o, loc))
        for name, sig in (loc.get("signals") or {}).items():
            bands = sig.get("frequency_bands") if isinstance(sig, Mapping) else None
            if bands:
                out.append(table([f"{esc(name)}: band (Hz)", "data gain", "model gain",
                                  "relative difference"],
                                 [[f"{fmt(b.get('f_lo_hz'), 3)}–{fmt(b.get('f_hi_hz'), 3)}",
                                   fmt(b.get("data_gain")), fmt(b.get("model_gain")),
                                   fmt_percent(b.get("relative_difference"))] for b in bands],
                                 numeric=(1, 2, 3)))
        tw = loc.get("time_windows") or {}
        if tw.get("mean_change_points_s") or tw.get("level_change_points_s"):
            out.append(f"<p>Change points (s): mean {esc(tw.get('mean_change_points_s'))}, "
                       f"level {esc(tw.get('level_change_points_s'))}.</p>")
        orr = loc.get("operating_range")
        if isinstance(orr, Mapping) and orr.get("bins"):
            out.append(f"<p>Residual by load signal <b>{esc(orr.get('load_signal'))}</b> (RMS "
                       f"spread over bins {fmt(orr.get('rms_spread'), 3)}):</p>" + table(
                ["load from", "to", "samples", "residual mean", "residual RMS"],
                [[fmt(b.get("load_lo")), fmt(b.get("load_hi")), esc(b.get("n")),
                  fmt(b.get("mean"), 3), fmt(b.get("rms"), 3)] for b in orr["bins"]],
                numeric=(0, 1, 2, 3, 4)))
        ranked = [x for x in loc.get("locations") or [] if isinstance(x, Mapping)][:10]
        if ranked:
            out.append("<p>Screening ranking of effect locations for this output:</p>" + table(
                ["effect", "location", "equivalent", "score"],
                [[f"<code>{esc(x.get('name'))}</code>", esc(x.get("location")),
                  esc(", ".join(map(str, x.get("equivalent_locations") or []))),
                  fmt(x.get("score"))] for x in ranked], numeric=(3,)))
    return "\n".join(out)


def _minor(doc: Mapping[str, Any]) -> str:
    minor = [e for e in doc.get("minor_effects") or [] if isinstance(e, Mapping)]
    looks = [e for e in doc.get("lookalikes") or [] if isinstance(e, Mapping)]
    out = []
    if minor:
        out.append(table(["effect", "gap_reduction", "ΔBIC", "held-out z"],
                         [[effect_html(e), fmt_percent(e.get("gap_reduction")), fmt(e.get("delta_bic")),
                           fmt(e.get("holdout_z"), 3)] for e in minor],
                         table_id="minor-table", numeric=(1, 2, 3)))
    else:
        out.append("<p>No minor effects: nothing statistically significant was too small to "
                   "count.</p>")
    if looks:
        out.append("<p>Look-alikes (too close to tell apart on this record):</p>" + table(
            ["effect", "ΔBIC", "held-out gap"],
            [[effect_html(e), fmt(e.get("delta_bic")), fmt(e.get("holdout_gap"))] for e in looks],
            table_id="lookalike-table", numeric=(1, 2)))
    return "\n".join(out)


@single_threaded_blas
def render_discrepancy_html(run_dir: Path, *, manifest: Mapping[str, Any] | None = None) -> str:
    """The discrepancy run's report as one self-contained HTML document.

    Parameters
    ----------
    run_dir : Path
        The run directory (``discrepancy.json`` required), or the store's temporary
        directory while it is written.
    manifest : mapping, optional
        ``job``, ``run_id``, ``config`` when ``manifest.json`` does not exist yet;
        default: read ``run_dir/manifest.json`` if present.
    """
    run_dir = Path(run_dir)
    doc = json.loads((run_dir / "discrepancy.json").read_text(encoding="utf-8"))
    if manifest is None and (run_dir / "manifest.json").is_file():
        manifest = json.loads((run_dir / "manifest.json").read_text(encoding="utf-8"))
    manifest = dict(manifest or {})
    path = run_dir / "discrepancy_series.parquet"
    series = pl.read_parquet(path) if path.is_file() else None
    data = doc.get("data") if isinstance(doc.get("data"), Mapping) else {}
    units = signal_units(manifest.get("config"), data.get("quality"))
    body = {"series": lambda: _series(doc, series, units),
            "gap-chain": lambda: _gap_chain(doc, units),
            "candidates": lambda: _candidates(doc),
            "localisation": lambda: _localisation(doc),
            "minor-effects": lambda: _minor(doc)}
    parts = [_header(doc, manifest)] + [section(k, t, body[k]) for k, t in _SECTIONS]
    parts.append("<footer><p class=\"meta\">Rendered from discrepancy.json and "
                 "discrepancy_series.parquet; rebuild: <code>python -m "
                 "pipeline.adapters.html_report RUN_DIR</code>.</p></footer>")
    return page(f"plantdyn discrepancy {doc.get('job')} {doc.get('run_id')}", "\n".join(parts))
