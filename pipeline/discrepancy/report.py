"""The one text rendering of a discrepancy run: ``report.md``, the Prefect artifact and the
Rerun summary panel are all :func:`summary_markdown` of the ``discrepancy.json`` document
(pure: a mapping in, Markdown out; missing keys are left out, never guessed)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["candidate_records", "effect_text", "fmt_number", "json_number", "md_cell",
           "pass_rule", "summary_markdown"]


def json_number(value: Any) -> float:
    """A JSON number as float; None and the strings 'nan'/'inf'/'-inf' (how
    ``DiscrepancyResult.to_dict`` writes non-finite values) as NaN / ±inf.

    Parameters
    ----------
    value : object
        A value read from ``discrepancy.json``.
    """
    if value is None or isinstance(value, bool):
        return float("nan")
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def fmt_number(value: Any, digits: int = 4) -> str:
    """``value`` to ``digits`` significant figures, ``–`` when missing or NaN.

    Parameters
    ----------
    value : object
        A JSON number (as :func:`json_number` reads it).
    digits : int
        Significant figures.
    """
    x = json_number(value)
    return "–" if math.isnan(x) else f"{x:.{digits}g}"


def fmt_percent(value: Any) -> str:
    """A share as a percentage with one decimal, ``–`` when missing or NaN (a
    candidate's lower bound is computed only when it passed the held-out tests).

    Parameters
    ----------
    value : object
        A JSON number (as :func:`json_number` reads it).
    """
    x = json_number(value)
    return "–" if math.isnan(x) else f"{100 * x:.1f} %"


def low_text(candidate: Mapping[str, Any]) -> str:
    """A candidate's ``gap_reduction_low`` with the output it is measured on, e.g.
    ``12.3 % (cw_flow)``; ``–`` when not computed.

    Parameters
    ----------
    candidate : mapping
        One of ``discrepancy.json``'s candidates.
    """
    text, on = fmt_percent(candidate.get("gap_reduction_low")), candidate.get(
        "gap_reduction_low_output")
    return f"{text} ({on})" if on and text != "–" else text


def md_cell(value: Any) -> str:
    """``value`` as text for a Markdown table cell (pipes escaped, one line).

    Parameters
    ----------
    value : object
        Any value.
    """
    return str(value).replace("|", "\\|").replace("\n", " ")


def effect_parts(effect: Mapping[str, Any]) -> tuple[str, str, list[tuple[str, str]], list[str]]:
    """An effect's text pieces, for every renderer (Markdown here, HTML in the report):
    name, location, ``(parameter, formatted value)`` pairs and equivalent locations.

    Parameters
    ----------
    effect : mapping
        ``name``, ``location`` and ``parameters`` (and optionally
        ``equivalent_locations``), as in ``discrepancy.json``.
    """
    params = effect.get("parameters") or {}
    # by name, as discrepancy.json stores them (sorted keys): a page rendered before the
    # document is written and one rendered from the stored file read the same
    pairs = ([(str(k), v if isinstance(v, str) else fmt_number(v))
              for k, v in sorted(params.items())] if isinstance(params, Mapping) else [])
    return (str(effect.get("name")), str(effect.get("location")), pairs,
            [str(e) for e in effect.get("equivalent_locations") or []])


def effect_text(effect: Mapping[str, Any]) -> str:
    """An effect as Markdown: ``\\`gain\\` at \\`controller\\` (factor = 1.2)``.

    Parameters
    ----------
    effect : mapping
        ``name``, ``location`` and ``parameters`` (and optionally
        ``equivalent_locations``), as in ``discrepancy.json``.
    """
    return effect_markup(effect, code=lambda s: f"`{md_cell(s)}`", plain=str)


def effect_markup(effect: Mapping[str, Any], *, code: Callable[[str], str],
                  plain: Callable[[str], str]) -> str:
    """An effect in one markup (the one sentence shape of report.md and report.html).

    Parameters
    ----------
    effect : mapping
        As for :func:`effect_text`.
    code : callable
        Marks up a name or location as code (escaping it).
    plain : callable
        Escapes plain text.
    """
    name, location, params, eq = effect_parts(effect)
    text = f"{code(name)} at {code(location)}"
    if params:
        text += " (" + ", ".join(f"{plain(k)} = {plain(v)}" for k, v in params) + ")"
    if eq:
        text += f"; equivalent locations: {plain(', '.join(eq))}"
    return text


def _header(doc: Mapping[str, Any]) -> list[str]:
    lines = [f"# Discrepancy: {doc.get('verdict')}", ""]
    who = [f"Run `{doc['job']}/{doc['run_id']}`" if doc.get("job") and doc.get("run_id")
           else "Run"]
    if doc.get("model"):
        kind = ("external simulator outputs" if doc.get("model_source") == "external_simulator"
                else "block diagram")
        who.append(f"model `{doc['model']}` ({kind})")
    data = doc.get("data") if isinstance(doc.get("data"), Mapping) else {}
    if data:
        who.append(f"{data.get('analysed_samples')} samples at {fmt_number(doc.get('dt_s'))} s "
                   f"({data.get('start_utc')} to {data.get('end_utc')})")
    lines += [", ".join(who) + ".", ""]
    effect = doc.get("effect")
    chain = [e for e in doc.get("effects") or [] if isinstance(e, Mapping)]
    if len(chain) > 1:
        lines.append(f"**{len(chain)} effects found**, in order: "
                     + "; ".join(effect_text(e) for e in chain)
                     + " — all added to `model_augmented.yaml`.")
    elif isinstance(effect, Mapping):
        lines.append(f"**Effect found:** {effect_text(effect)} — added to `model_augmented.yaml`.")
    elif doc.get("verdict") == "inconclusive":
        lines.append("**Inconclusive:** look-alike candidates fit about equally well:")
    elif rejected := [c for c in doc.get("rejected") or [] if isinstance(c, Mapping)]:
        lines.append("**No significant effect**: the candidate that fits the fit part best, "
                     + "; ".join(effect_text(c) for c in rejected) + ", fails on held-out "
                     "data — what the fit part shows is not a stable plant effect; the "
                     "nominal model stays.")
    elif doc.get("minor_effects"):
        lines.append("**No significant effect**: what the tests detect closes too little of "
                     "the gap to matter (see *Minor effects*); the nominal model stays.")
    else:
        lines.append("**No effect accepted**: the nominal model stays.")
    equivalent = [c for c in doc.get("equivalent_effects") or [] if isinstance(c, Mapping)]
    if equivalent:
        lines += ["", "Equivalent explanations (the data cannot tell them apart; the "
                  "simplest is named): " + "; ".join(effect_text(c) for c in equivalent) + "."]
    diverged = [e for e in doc.get("diverged") or [] if isinstance(e, Mapping)]
    if diverged:
        lines += ["", "Dropped because its simulation diverges (it destabilises a loop): "
                  + "; ".join(effect_text(e) for e in diverged) + "."]
    notes = [n for n in doc.get("notes") or [] if isinstance(n, str)]
    if notes:
        lines += [""] + [f"> **Note:** {md_cell(n)}" for n in notes]
    looks = [c for c in doc.get("lookalikes") or [] if isinstance(c, Mapping)]
    if looks:
        if isinstance(effect, Mapping):
            lines.append("Look-alike candidates (too close to tell apart on this record):")
        lines += [f"- {effect_text(c)} (ΔBIC {fmt_number(c.get('delta_bic'), 3)})" for c in looks]
    return lines


def _gap(doc: Mapping[str, Any]) -> list[str]:
    gap = doc.get("gap") if isinstance(doc.get("gap"), Mapping) else {}
    lines = ["", "## Held-out gap", "", "| output | RMS before | RMS after | reduction |",
             "|---|---|---|---|"]
    per_output = gap.get("per_output") if isinstance(gap.get("per_output"), Mapping) else {}
    for name, g in per_output.items():
        if isinstance(g, Mapping):
            lines.append(f"| {md_cell(name)} | {fmt_number(g.get('holdout_rms_before'))} | "
                         f"{fmt_number(g.get('holdout_rms_after'))} "
                         f"| {100 * json_number(g.get('reduction')):.1f} % |")
    lines.append(f"| **overall** | {fmt_number(gap.get('holdout_rms_before'))} | "
                 f"{fmt_number(gap.get('holdout_rms_after'))} "
                 f"| {100 * json_number(gap.get('reduction')):.1f} % |")
    if gap.get("units"):
        lines += ["", f"Units: {gap['units']}."]
    fit, hold, n, dt = (doc.get("fit_samples"), doc.get("holdout_samples"),
                        doc.get("n_samples"), json_number(doc.get("dt_s")))
    if fit and hold and n and not math.isnan(dt):
        lines += ["", f"Warm-up 0–{fit[0] * dt:g} s, fit {fit[0] * dt:g}–{hold[0] * dt:g} s, "
                      f"hold-out {hold[0] * dt:g}–{(n - 1) * dt:g} s."]
    return lines


def _effects(doc: Mapping[str, Any]) -> list[str]:
    chain = [e for e in doc.get("effects") or [] if isinstance(e, Mapping)]
    minor = [e for e in doc.get("minor_effects") or [] if isinstance(e, Mapping)]
    lines = []
    if len(chain) > 1:
        lines += ["", "## Effects, step by step", "",
                  "Each effect was found on the model augmented by the ones before it, held "
                  "to the same tests.", "",
                  "| step | effect | held-out gap before | after | reduction |",
                  "|---|---|---|---|---|"]
        lines += [f"| {k} | {effect_text(e)} | {fmt_number(e.get('gap_before'))} | "
                  f"{fmt_number(e.get('gap_after'))} | "
                  f"{100 * json_number(e.get('gap_reduction')):.1f} % |"
                  for k, e in enumerate(chain, 1)]
    if minor:
        cfg = doc.get("config") if isinstance(doc.get("config"), Mapping) else {}
        lines += ["", "## Minor effects", "",
                  "Statistically significant, but each closes less than "
                  f"{100 * json_number(cfg.get('min_gap_reduction')):.0f} % of every "
                  "output's held-out gap of the nominal model (with the accepted sensor "
                  "corrections taken off; at the 95 % lower bound when tried): not a "
                  "finding.  The gap reduction listed is of the model each was tried "
                  "on (the augmented model when the chain holds effects; for one dropped "
                  "from the final chain, the chain without it).", ""]
        lines += [f"- {effect_text(e)}: gap reduction "
                  f"{100 * json_number(e.get('gap_reduction')):.1f} %, ΔBIC "
                  f"{fmt_number(e.get('delta_bic'))}, held-out z {fmt_number(e.get('holdout_z'), 3)}"
                  for e in minor]
    return lines


def pass_rule(doc: Mapping[str, Any]) -> str:
    """The held-out tests a candidate passes and the practical bar a finding clears, with
    the run's thresholds, in one sentence (report.md and report.html); ``""`` without
    the run's ``config``.

    Parameters
    ----------
    doc : mapping
        The run's ``discrepancy.json`` document.
    """
    cfg = doc.get("config") if isinstance(doc.get("config"), Mapping) else {}
    if not cfg:
        return ""
    return (f"Passed: ΔBIC ≥ {fmt_number(cfg.get('bic_margin'))}, held-out z ≥ "
            f"{fmt_number(cfg.get('holdout_z_min'))} and a held-out gap below the nominal "
            f"{fmt_number((doc.get('gap') or {}).get('holdout_rms_before'))} (whitened), "
            "or a held-out RMS reduction beyond the noise model's disturbance at p ≤ "
            f"{fmt_number(cfg.get('holdout_rms_alpha'))} (held-out RMS); a finding must "
            f"also close ≥ {100 * json_number(cfg.get('min_gap_reduction')):.0f} % of "
            "some output's held-out gap (one whose nominal error is at least that share "
            "of its held-out std) or of the pooled gap, at the 95 % lower bound of its "
            "share." + (
                " With the loop(s) opened, a candidate must also narrow the held-out "
                "one-step prediction error of the loop closed again and driven by the "
                "setpoints and loads alone (closed-loop check)."
                if doc.get("opened_loops") else ""))


def candidate_records(doc: Mapping[str, Any], limit: int = 8, *,
                      effect: Callable[[Mapping[str, Any]], str] | None = None
                      ) -> list[dict[str, str]]:
    """The best ``limit`` candidates as rows of text (report.md's table and the Prefect
    candidates artifact print these).

    Parameters
    ----------
    doc : mapping
        The run's ``discrepancy.json`` document.
    limit : int
        Rows kept, best first.
    effect : callable (candidate) -> str, optional
        Writes the effect's cell; default plain text (:func:`effect_markup` without
        markup), report.md passes :func:`effect_text`.
    """
    effect = effect or (lambda c: effect_markup(c, code=str, plain=str))
    return [{"effect": effect(c), "delta_bic": fmt_number(c.get("delta_bic")),
             "holdout_z": fmt_number(c.get("holdout_z"), 3),
             "holdout_gap": fmt_number(c.get("holdout_gap")),
             "gap_reduction": fmt_percent(c.get("gap_reduction")),
             "gap_reduction_low": low_text(c),
             "holdout_rms_p": fmt_number(c.get("holdout_rms_p"), 2),
             "passed": str(c.get("passed_by")) if c.get("passed") is True else (
                 "no (closed loop)"
                 if json_number(c.get("closed_loop_prediction_error_reduction")) <= 0
                 else "no")}
            for c in doc.get("candidates") or [] if isinstance(c, Mapping)][:limit]


def _candidates(doc: Mapping[str, Any]) -> list[str]:
    rows = candidate_records(doc, effect=effect_text)  # effect_text escapes its own cell
    if not rows:
        return []
    rule = pass_rule(doc)
    lines = ["", "## Candidates (best first)", ""] + ([rule, ""] if rule else [])
    lines += ["| # | effect | ΔBIC | held-out z | held-out gap | gap reduction | "
              "largest output gap reduction, 95 % lower bound | RMS p | passed |",
              "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {k} | {r['effect']} | "
              + " | ".join(md_cell(v) for key, v in r.items() if key != "effect") + " |"
              for k, r in enumerate(rows, 1)]
    return lines


def _localisation(doc: Mapping[str, Any]) -> list[str]:
    locs = doc.get("localization") if isinstance(doc.get("localization"), Mapping) else {}
    lines = ["", "## Localisation", ""] if locs else []
    for o, loc in locs.items():
        if not isinstance(loc, Mapping):
            continue
        lines.append(f"**{md_cell(o)}**: residual RMS {fmt_number(loc.get('residual_rms'))} "
                     f"({100 * json_number(loc.get('relative_residual')):.1f} % of the measured "
                     f"std), explained by {loc.get('explained_by') or 'no input'}.")
        for sname, sig in (loc.get("signals") or {}).items():
            if not sig.get("significant"):
                continue
            text = (f"- `{sname}`: partial R² {json_number(sig.get('partial_r2')):.3f}, "
                    f"p = {json_number(sig.get('p_value')):.3g}, peak lag {fmt_number(sig.get('peak_lag_s'))} s")
            band = sig.get("band_of_largest_discrepancy_hz")
            if band:
                text += (f", largest model-vs-data difference in {json_number(band[0]):.3g}–"
                         f"{json_number(band[1]):.3g} Hz")
            lines.append(text)
        tw = loc.get("time_windows") or {}
        if tw.get("mean_change_points_s") or tw.get("level_change_points_s"):
            lines.append(f"- change points (s): mean {tw.get('mean_change_points_s')}, "
                         f"level {tw.get('level_change_points_s')}")
        orr = loc.get("operating_range")
        if orr:
            lines.append(f"- by {orr['load_signal']}: residual RMS spread over bins "
                         f"{fmt_number(orr.get('rms_spread'))}")
        lines.append("")
    return lines


def summary_markdown(doc: Mapping[str, Any]) -> str:
    """A discrepancy run in a page: verdict and effect, the held-out gap and the split,
    the best candidates, the localisation.

    Parameters
    ----------
    doc : mapping
        The run's ``discrepancy.json`` document (``DiscrepancyResult.to_dict()`` plus the
        workflow's ``job``, ``run_id``, ``model``, ``model_source``, ``data``); keys that
        are absent are left out of the page.
    """
    lines = _header(doc) + _gap(doc) + _effects(doc) + _candidates(doc) + _localisation(doc)
    lines += ["", "Files: `discrepancy.json` (everything above, machine-readable), "
              "`model_augmented.yaml`, `discrepancy_series.parquet` (measured, nominal, "
              "augmented, residuals), `recording.rrd` (open with `rerun`)."]
    return "\n".join(lines) + "\n"
