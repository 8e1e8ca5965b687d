"""The recording of a discrepancy run: measured / nominal / augmented, residuals, localisation."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

from pipeline.adapters.rerun_sink.common import (
    TIMELINES,
    WINDOW_COLOURS,
    check_out_name,
    durations,
    float_values,
    full_range,
    legend,
    make_blueprint,
    path_part,
    send_series,
    with_fixed_ids,
    write_recording,
)
from pipeline.discrepancy.report import (
    effect_text,
    fmt_number,
    json_number,
    md_cell,
    summary_markdown,
)
from pipeline.errors import DataQualityError


_DISCREPANCY_FILES = ("discrepancy.json", "discrepancy_series.parquet")
_DISCREPANCY_VALUES = ("measured", "nominal", "augmented", "residual_before", "residual_after", "rolling_rms")
_DISCREPANCY_PARTS = ("warmup", "fit", "holdout")
_SIGNAL_COLOURS = {"measured": (200, 200, 200), "nominal": (31, 119, 180), "augmented": (255, 127, 14)}
_BEFORE_COLOUR, _AFTER_COLOUR = (31, 119, 180), (255, 127, 14)
_ROLLING_COLOUR, _BLOCK_COLOUR = (148, 103, 189), (44, 160, 44)
_MODEL_COLOUR, _DATA_COLOUR = (31, 119, 180), (255, 127, 14)
_PASSED_COLOUR, _FAILED_COLOUR = (44, 160, 44), (214, 39, 40)
_SPLIT_COLOUR = (220, 0, 0)


def render_discrepancy(run_dir: Path, *, out_name: str = "recording.rrd", ident: str | None = None) -> Path:
    """Render a discrepancy run (``discrepancy.json`` + ``discrepancy_series.parquet``)
    into ``run_dir/out_name``.

    Time series are on the ``time_s`` timeline (a duration: seconds since the first
    sample, the parquet's ``time_s``); bar charts and documents are static.  ``<o>`` is
    a measured output, ``<s>`` a measured signal (names escaped with
    ``rr.escape_entity_path_part``):

    * ``discrepancy/summary`` -- markdown: verdict, effect, held-out gap per output, the
      fit/hold-out split, look-alikes, the best candidates;
    * ``discrepancy/<o>/signals/{measured,nominal,augmented}`` -- every stored sample;
    * ``discrepancy/<o>/signals/{fit_start,holdout_start}`` -- the split: a vertical
      line (two points at the same time, from the lowest to the highest value in the
      view; no aggregation);
    * ``discrepancy/<o>/residual/{before,after}`` -- ``residual_before/after``, with the
      same split lines ``discrepancy/<o>/residual/{fit_start,holdout_start}``;
    * ``discrepancy/<o>/rolling_rms`` -- rolling RMS of the residual before (NaN ends
      are gaps);
    * ``discrepancy/<o>/localisation/partial_r2/<s>`` and ``.../neg_log10_p/<s>`` --
      one bar per signal at x = its index in ``localization[o]["signals"]`` (the view
      title names them in x order, ``0 air · 1 fuel``: a bar chart has no labels):
      partial R² of the residual on the signal's lagged bank and -log10 of its
      bootstrap p-value (1.3 = p 0.05);
    * ``discrepancy/<o>/localisation/frequency_bands/<s>/{model_gain,data_gain}`` --
      for model inputs: mean |H| per band, x = log10 f in Hz: each band
      [log10 f_lo, log10 f_hi] holds the model's bar in its left half and the data's in
      its right half;
    * ``discrepancy/<o>/localisation/time_windows/block_rms`` -- block RMS of the
      residual on ``time_s``, a staircase (step-after) with one row at each block start
      (fit start + k·window_s) and a closing row at the end of the last block repeating
      its value; ``.../time_windows/high_rms`` -- points at the centres of the
      high-RMS windows, at their block RMS;
    * ``discrepancy/<o>/localisation/operating_range/rms`` -- residual RMS per load
      bin, each bar spanning 95 % of its bin, centred (x in load-signal units);
    * ``discrepancy/<o>/localisation/report`` -- markdown: the localisation numbers
      (signals, bands, change points, bins, candidate locations);
    * ``discrepancy/candidates/{delta_bic,holdout_z}/{passed,failed}`` -- one bar per
      candidate at x = its rank (1 = best criterion), split by whether it passed both
      acceptance tests; ``discrepancy/candidates/table`` -- markdown ranking.

    Bar charts are stored with the viewer's convention: ``abscissa`` is a bar's left
    edge, so a bar centred on x with width w has abscissa x - w/2.

    The default blueprint has tabs *Summary* (full width, so its tables are never cut
    off), *Measured vs simulated* and *Residual before/after* (one view per output, each
    with its own y axis), *Localisation* (per output its plots beside its numbers; one
    sub-tab per output when there are several) and *Candidates* (bars beside the ranking;
    with several outputs their held-out RMS is a second table).  Views are titled with
    the output and signal names and say which colour is which; legends are hidden (bar
    charts would list raw entity paths, and time-series legends covered the data).  The
    side panels start collapsed; the time panel is on ``time_s`` with the hold-out
    selected, and every TimeSeriesView spans all data.  Series are sent with ``send_columns``; the recording
    id derives from ``ident`` and no log time/tick is recorded.

    Parameters
    ----------
    run_dir : Path
        The discrepancy run directory (or the store's temporary directory).
    out_name : str
        File name inside ``run_dir``; written to a temporary name and renamed.
    ident : str, optional
        ``"<job>/<run_id>"`` for the recording id.  Default: ``job`` and ``run_id`` of
        ``discrepancy.json``, else of ``manifest.json``, else the folder name.

    Returns
    -------
    Path
        The written recording.

    Raises
    ------
    ConfigError
        ``out_name`` is not a plain file name.
    DataQualityError
        ``discrepancy.json`` or ``discrepancy_series.parquet`` is missing, unreadable or
        lacks required keys/columns, or holds values of the wrong kind.
    """
    run_dir = Path(run_dir)
    check_out_name(out_name)
    summary = _read_discrepancy_json(run_dir)
    series = _read_discrepancy_series(run_dir)
    ident = _resolve_ident(run_dir, summary, ident)
    view = _discrepancy_view(summary, series)
    blueprint = _discrepancy_blueprint(ident, view.outputs, view.per_output, view.layout,
                                       bool(view.candidates), view.first)
    return write_recording(run_dir / out_name, ident, blueprint,
                           lambda rec: _send_discrepancy(rec, ident, view))


#: What the viewer adds to the run's summary page (report.md's text).
_VIEWER_NOTE = ("\nIn this viewer: the split is marked by red vertical lines in the plots; all "
                "candidates are on the tab *Candidates*.\n")


@dataclass(frozen=True)
class _DiscrepancyView:
    """What a discrepancy recording shows, read from ``discrepancy.json`` and the series."""

    summary: Mapping[str, Any]
    localization: Mapping[str, Any]
    outputs: list[str]
    per_output: dict[str, pl.DataFrame]
    splits: dict[str, tuple[float, float, float]]
    candidates: list[Mapping[str, Any]]
    layout: dict[str, dict[str, Any]]
    first: tuple[float, float, float]
    fit_start_json: float  # fit start of an output with localisation but no series


def _resolve_ident(run_dir: Path, summary: Mapping[str, Any], ident: str | None) -> str:
    """Recording id ``"<job>/<run_id>"``: `ident`, else from discrepancy.json, manifest.json, the folder."""
    if ident is None:
        ident = _ident_from(summary) or _ident_from(_read_json_or_none(run_dir / "manifest.json"))
    return ident or run_dir.name


def _discrepancy_view(summary: Mapping[str, Any], series: pl.DataFrame) -> _DiscrepancyView:
    """Outputs, per-output series and splits, candidates and localisation layout of a run."""
    localization = summary.get("localization") or {}
    outputs = list(dict.fromkeys([*series["output"].unique(maintain_order=True).to_list(),
                                  *[o for o in localization if isinstance(localization[o], Mapping)]]))
    per_output = {o: df.sort("time_s") for (o,), df in series.group_by(["output"], maintain_order=True)}
    splits = {o: _split_times(df) for o, df in per_output.items()}
    candidates = [c for c in summary.get("candidates") or [] if isinstance(c, Mapping)]
    layout = {o: _localisation_layout(localization.get(o)) for o in outputs}

    first = next(iter(splits.values()))
    # Fit start of an output that has localisation but no series (not written by the job).
    fit_samples = summary.get("fit_samples")
    fit_start_json = (json_number(fit_samples[0]) * json_number(summary.get("dt_s")) if isinstance(fit_samples, list)
                      and fit_samples else first[0])
    if not math.isfinite(fit_start_json):
        fit_start_json = first[0]
    return _DiscrepancyView(summary, localization, outputs, per_output, splits, candidates, layout,
                            first, fit_start_json)


def _send_discrepancy(rec: rr.RecordingStream, ident: str, view: _DiscrepancyView) -> None:
    """Log the summary, series, localisation and candidates of `view` to `rec`."""
    summary, localization, outputs, splits = view.summary, view.localization, view.outputs, view.splits
    rec.log("discrepancy/summary", rr.TextDocument(summary_markdown(summary) + _VIEWER_NOTE,
                                                   media_type=rr.MediaType.MARKDOWN), static=True, strict=True)
    for output, df in view.per_output.items():
        _send_discrepancy_series(rec, output, df, splits[output])
    for output in outputs:
        loc = localization.get(output)
        if isinstance(loc, Mapping):
            _send_localisation(rec, output, loc, splits[output][0] if output in splits else view.fit_start_json)
    if view.candidates:
        _send_candidates(rec, view.candidates)
    rec.log("discrepancy/candidates/table", rr.TextDocument(_candidates_markdown(view.candidates),
                                                            media_type=rr.MediaType.MARKDOWN),
            static=True, strict=True)


def _read_json_or_none(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None
    except (OSError, ValueError):
        return None


def _ident_from(doc: Any) -> str | None:
    if isinstance(doc, Mapping) and doc.get("job") and doc.get("run_id"):
        return f"{doc['job']}/{doc['run_id']}"
    return None


def _read_discrepancy_json(run_dir: Path) -> dict[str, Any]:
    path = run_dir / _DISCREPANCY_FILES[0]
    if not path.is_file():
        raise DataQualityError(f"{path}: missing; render_discrepancy needs a discrepancy run directory "
                               f"with {' and '.join(_DISCREPANCY_FILES)} (re-run the discrepancy job)")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DataQualityError(f"{path}: not readable JSON ({exc}); the file is corrupt, "
                               "re-run the discrepancy job") from None
    if not isinstance(doc, dict):
        raise DataQualityError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    missing = [k for k in ("verdict", "gap", "candidates", "localization") if k not in doc]
    if missing:
        raise DataQualityError(f"{path}: missing keys {missing}; it must hold DiscrepancyResult.to_dict() "
                               "(verdict, effect, candidates, gap, localization, ...)")
    for key, kind in (("gap", dict), ("candidates", list), ("localization", dict)):
        if not isinstance(doc[key], kind):
            raise DataQualityError(f"{path}: {key!r} must be a JSON {'object' if kind is dict else 'array'}, "
                                   f"got {type(doc[key]).__name__}")
    return doc


def _read_discrepancy_series(run_dir: Path) -> pl.DataFrame:
    path = run_dir / _DISCREPANCY_FILES[1]
    if not path.is_file():
        raise DataQualityError(f"{path}: missing; render_discrepancy needs a discrepancy run directory "
                               f"with {' and '.join(_DISCREPANCY_FILES)} (re-run the discrepancy job)")
    try:
        df = pl.read_parquet(path)
    except Exception as exc:  # polars raises several types for a damaged file
        raise DataQualityError(f"{path}: not a readable parquet file ({type(exc).__name__}: {exc}); "
                               "the file is corrupt, re-run the discrepancy job") from None
    required = ("output", "time_s", "part", *_DISCREPANCY_VALUES)
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DataQualityError(f"{path}: missing columns {missing}; expected {list(required)}")
    if df.height == 0:
        raise DataQualityError(f"{path}: has no rows; nothing to draw")
    try:
        df = df.select(pl.col("output").cast(pl.String), pl.col("part").cast(pl.String),
                       *[pl.col(c).cast(pl.Float64, strict=True) for c in ("time_s", *_DISCREPANCY_VALUES)])
    except Exception as exc:  # InvalidOperationError, ComputeError: a text column where numbers belong
        raise DataQualityError(f"{path}: columns have the wrong types ({exc}); output and part must be "
                               f"strings, {['time_s', *_DISCREPANCY_VALUES]} numbers") from None
    for column in ("output", "part", "time_s"):
        n_null = df[column].null_count()
        if n_null:
            raise DataQualityError(f"{path}: column {column!r} has {n_null} null value(s) of {df.height}")
    bad_parts = sorted(set(df["part"].unique().to_list()) - set(_DISCREPANCY_PARTS))
    if bad_parts:
        raise DataQualityError(f"{path}: column 'part' holds {bad_parts}; allowed {list(_DISCREPANCY_PARTS)}")
    if not df["time_s"].is_finite().all():
        raise DataQualityError(f"{path}: column 'time_s' has non-finite values")
    n_dup = df.height - df.select("output", "time_s").unique().height
    if n_dup:
        raise DataQualityError(f"{path}: {n_dup} duplicate (output, time_s) row(s); each sample must appear once")
    return df


def _split_times(df: pl.DataFrame) -> tuple[float, float, float]:
    """(fit start, hold-out start, last sample) in s; a missing part starts at the end."""
    times = df["time_s"].to_numpy()
    parts = df["part"].to_numpy()
    end = float(times[-1])

    def start(part: str) -> float:
        idx = np.flatnonzero(parts == part)
        return float(times[idx[0]]) if idx.size else end

    return start("fit"), start("holdout"), end


def _time_index(seconds: np.ndarray | Sequence[float]) -> rr.TimeColumn:
    return rr.TimeColumn(TIMELINES["discrepancy"], duration=durations(seconds))


def _split_lines(rec: rr.RecordingStream, base: str, values: Sequence[np.ndarray],
                 split: tuple[float, float, float]) -> None:
    """Vertical lines at the fit and hold-out starts spanning the finite range of ``values``."""
    finite = np.concatenate([v[np.isfinite(v)] for v in values])
    if finite.size == 0:
        return
    lo, hi = float(finite.min()), float(finite.max())
    for key, t_s, label in (("fit_start", split[0], "fit starts"), ("holdout_start", split[1], "hold-out starts")):
        if t_s >= split[2]:
            continue
        path = f"{base}/{key}"
        rec.log(path, rr.SeriesLines(names=label, colors=[_SPLIT_COLOUR], widths=1.0,
                                     aggregation_policy="Off"), static=True, strict=True)
        rec.send_columns(path, indexes=[_time_index([t_s, t_s])],
                         columns=rr.Scalars.columns(scalars=np.array([lo, hi])), strict=True)


def _send_discrepancy_series(rec: rr.RecordingStream, output: str, df: pl.DataFrame,
                             split: tuple[float, float, float]) -> None:
    base = f"discrepancy/{path_part(output)}"
    index = _time_index(df["time_s"].to_numpy())
    values = {c: float_values(df[c]) for c in _DISCREPANCY_VALUES}
    for key in ("measured", "nominal", "augmented"):
        send_series(rec, f"{base}/signals/{key}", index, values[key], name=key, colour=_SIGNAL_COLOURS[key])
    _split_lines(rec, f"{base}/signals", [values[k] for k in ("measured", "nominal", "augmented")], split)
    send_series(rec, f"{base}/residual/before", index, values["residual_before"], name="before (measured − nominal)",
            colour=_BEFORE_COLOUR)
    send_series(rec, f"{base}/residual/after", index, values["residual_after"], name="after (measured − augmented)",
            colour=_AFTER_COLOUR)
    _split_lines(rec, f"{base}/residual", [values["residual_before"], values["residual_after"]], split)
    send_series(rec, f"{base}/rolling_rms", index, values["rolling_rms"], name="rolling RMS (before)",
            colour=_ROLLING_COLOUR, width=2.0)


def _bars(rec: rr.RecordingStream, path: str, values: Sequence[float], abscissa: Sequence[float],
          widths: Sequence[float] | float, colour: tuple[int, int, int]) -> None:
    """A static bar chart; bar k spans x from ``abscissa[k]`` to ``abscissa[k] + widths[k]``
    (the viewer puts the abscissa at the bar's left edge, not its centre)."""
    values = np.asarray(values, dtype=np.float64)
    widths = np.broadcast_to(np.asarray(widths, dtype=np.float32), values.shape)
    rec.log(path, rr.BarChart(values, abscissa=np.asarray(abscissa, dtype=np.float64), widths=widths,
                              color=colour), static=True, strict=True)


def _signals_of(loc: Mapping[str, Any] | None) -> dict[str, Mapping[str, Any]]:
    signals = loc.get("signals") if isinstance(loc, Mapping) else None
    return {str(k): v for k, v in signals.items() if isinstance(v, Mapping)} if isinstance(signals, Mapping) else {}


def _bands_of(entry: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    bands = entry.get("frequency_bands")
    return [b for b in bands if isinstance(b, Mapping)] if isinstance(bands, list) else []


def _bins_of(loc: Mapping[str, Any] | None) -> tuple[str | None, list[Mapping[str, Any]]]:
    rng = loc.get("operating_range") if isinstance(loc, Mapping) else None
    if not isinstance(rng, Mapping) or not isinstance(rng.get("bins"), list):
        return None, []
    return rng.get("load_signal"), [b for b in rng["bins"] if isinstance(b, Mapping)]


def _block_rms_of(loc: Mapping[str, Any] | None) -> tuple[float, list[float]]:
    tw = loc.get("time_windows") if isinstance(loc, Mapping) else None
    if not isinstance(tw, Mapping) or not isinstance(tw.get("block_rms"), list):
        return float("nan"), []
    return json_number(tw.get("window_s")), [json_number(v) for v in tw["block_rms"]]


def _localisation_layout(loc: Any) -> dict[str, Any]:
    """What the localisation of one output draws (for the blueprint)."""
    if not isinstance(loc, Mapping):
        return {"signals": [], "bands": [], "blocks": False, "load_signal": None}
    signals = _signals_of(loc)
    window_s, blocks = _block_rms_of(loc)
    load_signal, bins = _bins_of(loc)
    return {"signals": list(signals), "bands": [s for s, e in signals.items() if _bands_of(e)],
            "blocks": bool(blocks) and window_s > 0, "load_signal": load_signal if bins else None}


def _send_localisation(rec: rr.RecordingStream, output: str, loc: Mapping[str, Any], fit_start_s: float) -> None:
    base = f"discrepancy/{path_part(output)}/localisation"
    signals = _signals_of(loc)
    for j, (name, entry) in enumerate(signals.items()):
        colour = WINDOW_COLOURS[j % len(WINDOW_COLOURS)]
        _bars(rec, f"{base}/partial_r2/{path_part(name)}", [json_number(entry.get("partial_r2"))], [j - 0.4], 0.8, colour)
        p = json_number(entry.get("p_value"))
        _bars(rec, f"{base}/neg_log10_p/{path_part(name)}", [-math.log10(p) if p > 0 else float("nan")], [j - 0.4],
              0.8, colour)
        bands = _bands_of(entry)
        if bands:
            lo = np.array([json_number(b.get("f_lo_hz")) for b in bands])
            hi = np.array([json_number(b.get("f_hi_hz")) for b in bands])
            with np.errstate(divide="ignore", invalid="ignore"):
                left, width = np.log10(lo), np.log10(hi) - np.log10(lo)
            for key, shift, colour in (("model_gain", 0.05, _MODEL_COLOUR), ("data_gain", 0.5, _DATA_COLOUR)):
                _bars(rec, f"{base}/frequency_bands/{path_part(name)}/{key}", [json_number(b.get(key)) for b in bands],
                      left + shift * width, 0.45 * width, colour)

    window_s, block_rms = _block_rms_of(loc)
    if block_rms and window_s > 0:
        starts = fit_start_s + window_s * np.arange(len(block_rms) + 1)
        path = f"{base}/time_windows/block_rms"
        rec.log(path, rr.SeriesLines(names=f"block RMS ({window_s:g} s blocks)", colors=[_BLOCK_COLOUR], widths=2.0,
                                     interpolation_mode="StepAfter"), static=True, strict=True)
        rec.send_columns(path, indexes=[_time_index(starts)],
                         columns=rr.Scalars.columns(scalars=np.array([*block_rms, block_rms[-1]])), strict=True)
        high = loc["time_windows"].get("high_rms_windows_s") or []
        ks = [int(round((json_number(w[0]) - fit_start_s) / window_s)) for w in high
              if isinstance(w, list) and len(w) == 2 and math.isfinite(json_number(w[0]))]
        ks = [k for k in ks if 0 <= k < len(block_rms)]
        if ks:
            path = f"{base}/time_windows/high_rms"
            rec.log(path, rr.SeriesPoints(names="high-RMS window", colors=[_SPLIT_COLOUR], markers="diamond",
                                          marker_sizes=6.0), static=True, strict=True)
            rec.send_columns(path, indexes=[_time_index(fit_start_s + window_s * (np.array(ks) + 0.5))],
                             columns=rr.Scalars.columns(scalars=np.array([block_rms[k] for k in ks])), strict=True)

    _, bins = _bins_of(loc)
    if bins:
        lo = np.array([json_number(b.get("load_lo")) for b in bins])
        hi = np.array([json_number(b.get("load_hi")) for b in bins])
        _bars(rec, f"{base}/operating_range/rms", [json_number(b.get("rms")) for b in bins], lo + 0.025 * (hi - lo),
              0.95 * (hi - lo), _BLOCK_COLOUR)
    rec.log(f"{base}/report", rr.TextDocument(_localisation_markdown(output, loc), media_type=rr.MediaType.MARKDOWN),
            static=True, strict=True)


def _send_candidates(rec: rr.RecordingStream, candidates: Sequence[Mapping[str, Any]]) -> None:
    rank = np.arange(1, len(candidates) + 1, dtype=np.float64)
    passed = np.array([c.get("passed") is True for c in candidates])
    for key in ("delta_bic", "holdout_z"):
        values = np.array([json_number(c.get(key)) for c in candidates])
        for group, sel, colour in (("passed", passed, _PASSED_COLOUR), ("failed", ~passed, _FAILED_COLOUR)):
            if sel.any():
                _bars(rec, f"discrepancy/candidates/{key}/{group}", values[sel], rank[sel] - 0.4, 0.8, colour)


# ---------------------------------------------------------------- markdown documents


def _candidates_markdown(candidates: Sequence[Mapping[str, Any]]) -> str:
    """The ranking; with several outputs their held-out RMS goes to a second table (one
    wide table would be cut off at the view's right edge: the viewer does not scroll
    tables sideways)."""
    if not candidates:
        return "# Candidates\n\nNo candidate effect was fitted.\n"
    outs = list(dict.fromkeys(o for c in candidates if isinstance(c.get("holdout_rms"), Mapping)
                              for o in c["holdout_rms"]))
    inline = outs if len(outs) <= 1 else []
    head = ["#", "effect", "criterion (BIC)", "ΔBIC", "held-out z", *[f"held-out RMS {o}" for o in inline], "passed"]
    lines = ["# Candidates", "", "Ranked by the whitened BIC on the fit part (rank = x of the bar charts; "
             "ΔBIC = nominal − candidate, larger is better).", "",
             "| " + " | ".join(map(md_cell, head)) + " |", "|" + "---|" * len(head)]
    rms_rows = []
    for k, c in enumerate(candidates, 1):
        rms = c.get("holdout_rms") if isinstance(c.get("holdout_rms"), Mapping) else {}
        row = [str(k), effect_text(c), fmt_number(c.get("criterion"), 6), fmt_number(c.get("delta_bic"), 5),
               fmt_number(c.get("holdout_z"), 3), *[fmt_number(rms.get(o)) for o in inline],
               "yes" if c.get("passed") is True else "no"]
        lines.append("| " + " | ".join(row) + " |")
        rms_rows.append("| " + " | ".join([f"rank {k}", *[fmt_number(rms.get(o)) for o in outs]]) + " |")
    if not inline and outs:
        lines += ["", "## Held-out RMS per output", "",
                  "| candidate | " + " | ".join(map(md_cell, outs)) + " |", "|" + "---|" * (len(outs) + 1), *rms_rows]
    return "\n".join(lines) + "\n"


def _localisation_markdown(output: str, loc: Mapping[str, Any]) -> str:
    lines = [f"# Localisation: {output}", ""]
    lines.append(f"Residual RMS {fmt_number(loc.get('residual_rms'))}, mean {fmt_number(loc.get('residual_mean'))}, "
                 f"{100 * json_number(loc.get('relative_residual')):.1f} % of the measured std; explained by: "
                 f"{', '.join(map(str, loc.get('explained_by') or [])) or 'no signal (p < 0.05)'}.")
    signals = _signals_of(loc)
    if signals:
        lines += ["", "## Signals (x = bar position)", "",
                  "| x | signal | partial R² | p | significant | peak lag s | first significant lag s |",
                  "|---|---|---|---|---|---|---|"]
        for j, (name, e) in enumerate(signals.items()):
            lines.append(f"| {j} | {md_cell(name)} | {fmt_number(e.get('partial_r2'))} | {fmt_number(e.get('p_value'), 3)} | "
                         f"{'yes' if e.get('significant') is True else 'no'} | {fmt_number(e.get('peak_lag_s'))} | "
                         f"{fmt_number(e.get('first_significant_lag_s'))} |")
        for name, e in signals.items():
            bands = _bands_of(e)
            if bands:
                lines += ["", f"### Frequency bands, {md_cell(name)} → {md_cell(output)}", "",
                          "| band Hz | model gain | data gain | relative difference |", "|---|---|---|---|"]
                lines += [f"| {fmt_number(b.get('f_lo_hz'), 3)}–{fmt_number(b.get('f_hi_hz'), 3)} | {fmt_number(b.get('model_gain'))} | "
                          f"{fmt_number(b.get('data_gain'))} | {fmt_number(b.get('relative_difference'), 3)} |" for b in bands]
    tw = loc.get("time_windows")
    if isinstance(tw, Mapping):
        def spans(key: str) -> str:
            items = tw.get(key) or []
            text = ", ".join(f"{fmt_number(w[0], 6)}–{fmt_number(w[1], 6)}" if isinstance(w, list) else fmt_number(w, 6) for w in items)
            return text or "none"
        lines += ["", "## Time windows", "", f"Blocks of {fmt_number(tw.get('window_s'))} s. High-RMS windows (s): "
                  f"{spans('high_rms_windows_s')}. Mean change points (s): {spans('mean_change_points_s')}. "
                  f"Level change points (s): {spans('level_change_points_s')}."]
    load_signal, bins = _bins_of(loc)
    if bins:
        lines += ["", f"## Operating range (load signal {md_cell(load_signal)})", "",
                  "| bin | n | mean | RMS |", "|---|---|---|---|"]
        lines += [f"| {fmt_number(b.get('load_lo'))} – {fmt_number(b.get('load_hi'))} | {b.get('n')} | {fmt_number(b.get('mean'))} | "
                  f"{fmt_number(b.get('rms'))} |" for b in bins]
    locations = [x for x in loc.get("locations") or [] if isinstance(x, Mapping)]
    if locations:
        lines += ["", "## Candidate locations (screening score)", "", "| effect | location | score |", "|---|---|---|"]
        lines += [f"| {md_cell(x.get('name'))} | {md_cell(x.get('location'))} | {fmt_number(x.get('score'))} |"
                  for x in locations]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- discrepancy blueprint


def _names_by_x(names: Sequence[str]) -> str:
    """``0 air · 1 load``: which signal each bar position is (BarChart has no labels)."""
    return " · ".join(f"{j} {n}" for j, n in enumerate(names))


def _localisation_views(output: str, lay: Mapping[str, Any], has_series: bool, bars_view: Any,
                        series_view: Any, text_view: Any) -> tuple[list[Any], Any | None]:
    """One output's localisation plots and its numbers document (None when it has none)."""
    base = f"/discrepancy/{path_part(output)}/localisation"
    views: list[Any] = []
    if lay["signals"]:
        names = _names_by_x(lay["signals"])
        views.append(bars_view(f"partial_r2/{output}", origin=f"{base}/partial_r2",
                               name=f"{output}: partial R² — {names}"))
        views.append(bars_view(f"neg_log10_p/{output}", origin=f"{base}/neg_log10_p",
                               name=f"{output}: −log10 p (1.3: p = 0.05) — {names}"))
    for s in lay["bands"]:
        views.append(bars_view(f"bands/{output}/{s}", origin=f"{base}/frequency_bands/{path_part(s)}",
                               name=f"{output} ← {s}: |H| model blue, data orange; x: log10 f/Hz"))
    if lay["blocks"] or has_series:
        views.append(series_view(f"time_windows/{output}", origin=f"/discrepancy/{path_part(output)}",
                                 contents=[f"{base}/time_windows/**", f"/discrepancy/{path_part(output)}/rolling_rms"],
                                 name=f"{output}: block RMS (green), rolling RMS (purple), high blocks (red)"))
    if lay["load_signal"] is not None:
        views.append(bars_view(f"operating_range/{output}", origin=f"{base}/operating_range",
                               name=f"{output}: residual RMS per {lay['load_signal']} bin (x: {lay['load_signal']})"))
    report = None
    if lay["signals"] or lay["blocks"] or lay["load_signal"] is not None:
        report = text_view(f"report/{output}", f"{base}/report", f"{output}: localisation numbers")
    return views, report


def _discrepancy_blueprint(ident: str, outputs: Sequence[str], per_output: Mapping[str, pl.DataFrame],
                           layout: Mapping[str, dict[str, Any]], has_candidates: bool,
                           split: tuple[float, float, float]) -> rrb.Blueprint:
    """Tabs *Summary* (full width: its tables are never cut), *Measured vs simulated*,
    *Residual before/after* (one view per output), *Localisation* (per output its plots
    beside its numbers; a tab per output when there are several) and *Candidates*."""
    timeline = TIMELINES["discrepancy"]

    def fixed(item: Any, key: str) -> Any:
        return with_fixed_ids(item, ident, f"discrepancy:{key}")

    def series_view(key: str, **kwargs: Any) -> rrb.TimeSeriesView:
        # The title names every series by colour: a legend would cover the data, which
        # fill these plots from edge to edge.
        return fixed(rrb.TimeSeriesView(**kwargs, plot_legend=legend(None), **full_range(timeline)), key)

    def bars_view(key: str, **kwargs: Any) -> rrb.BarChartView:
        # Bar charts have no series names: their legend would list raw entity paths.
        return fixed(rrb.BarChartView(**kwargs, plot_legend=legend(None)), key)

    def text_view(key: str, origin: str, name: str) -> rrb.TextDocumentView:
        return fixed(rrb.TextDocumentView(origin=origin, name=name), key)

    drawn = [o for o in outputs if o in per_output]
    tabs = [fixed(rrb.Vertical(text_view("summary", "/discrepancy/summary", "Summary"), name="Summary"),
                  "tab:summary")]
    signal_views = [series_view(f"signals/{o}", origin=f"/discrepancy/{path_part(o)}/signals",
                                name=f"{o}: measured (grey), nominal (blue), augmented (orange); "
                                     "red: fit / hold-out start") for o in drawn]
    if signal_views:
        tabs.append(fixed(rrb.Vertical(*signal_views, name="Measured vs simulated"), "tab:signals"))
    residual_views = [series_view(f"residual/{o}", origin=f"/discrepancy/{path_part(o)}",
                                  contents=[f"/discrepancy/{path_part(o)}/residual/**",
                                            f"/discrepancy/{path_part(o)}/rolling_rms"],
                                  name=f"{o}: residual before (blue) / after (orange), rolling RMS (purple); "
                                       "red: fit / hold-out start") for o in drawn]
    if residual_views:
        tabs.append(fixed(rrb.Vertical(*residual_views, name="Residual before/after"), "tab:residual"))
    per_output_tabs = []
    for o in outputs:
        views, report = _localisation_views(o, layout[o], o in per_output, bars_view, series_view, text_view)
        if not views and report is None:
            continue
        plots = fixed(rrb.Grid(*views, grid_columns=2 if len(views) > 2 else 1), f"localisation_plots/{o}")
        parts = [p for p in (plots if views else None, report) if p is not None]
        per_output_tabs.append(fixed(rrb.Horizontal(*parts, column_shares=[3, 2] if len(parts) == 2 else None,
                                                    name=f"Localisation: {o}" if len(outputs) > 1 else "Localisation"),
                                     f"tab:localisation/{o}"))
    if len(per_output_tabs) == 1:
        tabs.append(per_output_tabs[0])
    elif per_output_tabs:
        tabs.append(fixed(rrb.Tabs(*per_output_tabs, name="Localisation"), "tab:localisation"))
    tabs.append(_candidates_tab(has_candidates, fixed, bars_view, text_view))
    fit_s, hold_s, end_s = split
    ns = durations([hold_s, end_s]).astype(np.int64)
    holdout = rr.encodings.AbsoluteTimeRange(int(ns[0]), int(ns[1])) if hold_s < end_s else None
    return make_blueprint(fixed(rrb.Tabs(*tabs, name="plantdyn discrepancy"), "tabs"), timeline,
                          time_selection=holdout)


def _candidates_tab(has_candidates: bool, fixed: Any, bars_view: Any, text_view: Any) -> Any:
    """The criteria as bars (x: rank) beside the ranking table."""
    table = text_view("candidates", "/discrepancy/candidates/table", "Candidate ranking")
    if not has_candidates:
        return fixed(rrb.Horizontal(table, name="Candidates"), "tab:candidates")
    bars = [bars_view("delta_bic", origin="/discrepancy/candidates/delta_bic",
                      name="ΔBIC per candidate (x: rank; green passed, red failed)"),
            bars_view("holdout_z", origin="/discrepancy/candidates/holdout_z",
                      name="held-out z per candidate (x: rank; green passed, red failed)")]
    return fixed(rrb.Horizontal(fixed(rrb.Vertical(*bars), "candidates_column"), table, column_shares=[2, 3],
                                name="Candidates"), "tab:candidates")
