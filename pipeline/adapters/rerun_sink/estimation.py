"""The recording of an estimation run: step responses as an outputs × inputs grid with
±2σ bands, signals and residuals one view per signal, trends."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

from pipeline.adapters.rerun_sink.common import (
    ALL_COLOUR,
    BAND_EDGE_COLOUR,
    BAND_FILL_COLOUR,
    MASKED_COLOUR,
    RESIDUAL_COLOUR,
    ROLE_COLOURS,
    TIMELINES,
    TREND_COLUMNS,
    WINDOW_COLOURS,
    check_out_name,
    durations,
    float_values,
    legend,
    make_blueprint,
    path_part,
    read_parquet,
    send_series,
    units_of,
    with_fixed_ids,
    with_unit,
    write_recording,
    x_range,
)
from pipeline.adapters.series_reader import (
    KeyInfo,
    Reduced,
    Spec,
    reduce_series,
    scan_keys,
)
from pipeline.errors import ConfigError, DataQualityError

#: Points of a pair's band fill: a triangle wave between the ±2σ bounds, about one pixel
#: apart in a maximised 1920-pixel view, so the band reads as a filled area.
BAND_POINTS = 2001
#: Step panels show their legend when the grid has at most this many rows; a taller grid
#: shows it in its first panel only (every panel uses the same names and colours).
LEGEND_ROWS = 3
BAND_NAME = "±2σ (all data)"
_TRENDS_NOTE = ("# Trends\n\nEarlier runs of this job are drawn on the **run_time** timeline: pick "
                "`run_time` in the timeline menu of the time panel (the bar at the bottom). Each "
                "panel is one output ← input pair; its gain (or rate) per run.\n")


@dataclass(frozen=True)
class StepPlot:
    """How one pair's step response is framed: x up to ``end_s`` (the last lag), y over
    ``y_lo``..``y_hi`` (0 and every drawn value, padded), legend in ``corner`` (the
    right-hand corner away from where the response settles)."""

    end_s: float
    y_lo: float
    y_hi: float
    corner: str


@dataclass(frozen=True)
class Layout:
    """What the default blueprint arranges (read from the stored files)."""

    ident: str
    units: dict[str, str]
    outputs: list[str]
    inputs: list[str]
    steps: dict[tuple[str, str], StepPlot]
    signals: list[tuple[str, str]]
    residual_outputs: list[str]
    trend_metrics: dict[tuple[str, str], list[str]]
    start: np.datetime64 | None  # elapsed 0 of signals and residuals (UTC)
    trend_span: tuple[float, float] | None = None  # first and last run, s since the epoch

    def since(self) -> str:
        """`` (0 s = 2026-03-01 06:00:00 UTC)``: what elapsed 0 is in the time tabs."""
        if self.start is None:
            return ""
        return f" (0 s = {np.datetime_as_string(self.start, unit='s').replace('T', ' ')} UTC)"


def _pairs(checks: dict[str, Any] | None, steps: pl.DataFrame | None) -> list[tuple[str, str]]:
    """Output–input pairs: in checks.json's order when it lists them, else as stored."""
    stored: list[tuple[str, str]] = []
    if steps is not None:
        stored = [tuple(r) for r in steps.select("output", "input").unique(maintain_order=True).rows()]
    listed = []
    if checks is not None and isinstance(checks.get("pairs"), list):
        listed = [(p["output"], p["input"]) for p in checks["pairs"]
                  if isinstance(p, dict) and "output" in p and "input" in p]
    return list(dict.fromkeys([*listed, *stored]))


def _check_trends(trends: pl.DataFrame) -> pl.DataFrame:
    missing = [c for c in TREND_COLUMNS if c not in trends.columns]
    if missing:
        raise ConfigError(f"trends: missing columns {missing}; pass ResultStore.trend(job) "
                          f"(columns {list(TREND_COLUMNS)})")
    created = trends["created_utc"]
    if created.dtype == pl.String:
        trends = trends.with_columns(pl.col("created_utc").str.to_datetime(time_zone="UTC"))
    elif not isinstance(created.dtype, pl.Datetime):
        raise ConfigError(f"trends: created_utc must be a UTC Datetime or ISO string, got {created.dtype}")
    trends = trends.filter(pl.col("output").is_not_null() & pl.col("input").is_not_null()
                           & pl.col("value").is_not_null())
    n_dup = trends.height - trends.select("output", "input", "metric", "created_utc").unique().height
    if n_dup:
        raise DataQualityError(f"trends: {n_dup} duplicate (output, input, metric, created_utc) row(s); "
                               "pass one window's rows, e.g. ResultStore.trend(job, window='all')")
    return trends


def _step_plot(pair: pl.DataFrame) -> StepPlot | None:
    """Frame of one pair's stored rows (every window), None when nothing is finite."""
    step = float_values(pair["step"])
    alls = pair.filter(pl.col("window") == "all").sort("lag")
    std = float_values(alls["step_std"])
    drawn = np.concatenate([step, float_values(alls["step"]) + 2 * std, float_values(alls["step"]) - 2 * std])
    drawn = drawn[np.isfinite(drawn)]
    times = float_values(pair["time_s"])
    times = times[np.isfinite(times)]
    if drawn.size == 0 or times.size == 0:
        return None
    lo, hi = min(0.0, float(drawn.min())), max(0.0, float(drawn.max()))
    pad = 0.06 * (hi - lo) if hi > lo else 1.0
    finite = pair.sort("lag").filter(pl.col("step").is_finite())
    settled = finite.filter(pl.col("window") == "all")
    settled = settled if settled.height else finite
    final = float(settled["step"][-1]) if settled.height else 0.0
    corner = "RightBottom" if final >= (lo + hi) / 2 else "RightTop"
    return StepPlot(end_s=float(times.max()), y_lo=lo - pad, y_hi=hi + pad, corner=corner)


def _layout(ident: str, units: dict[str, str], checks: dict[str, Any] | None, steps: pl.DataFrame | None,
            signals: Sequence[KeyInfo], resid: Sequence[KeyInfo], trends: pl.DataFrame | None,
            start: np.datetime64 | None) -> Layout:
    pairs = _pairs(checks, steps)
    plots: dict[tuple[str, str], StepPlot] = {}
    if steps is not None:
        for o, i in pairs:
            plot = _step_plot(steps.filter((pl.col("output") == o) & (pl.col("input") == i)))
            if plot is not None:
                plots[(o, i)] = plot
    trend_metrics: dict[tuple[str, str], list[str]] = {}
    trend_span = None
    if trends is not None:
        for o, i, metric in trends.select("output", "input", "metric").unique(maintain_order=True).rows():
            trend_metrics.setdefault((o, i), []).append(metric)
        created = trends["created_utc"].dt.epoch("us").cast(pl.Float64) / 1e6
        trend_span = (float(created.min()), float(created.max()))
    return Layout(
        ident=ident, units=units,
        outputs=list(dict.fromkeys(o for o, _ in pairs)), inputs=list(dict.fromkeys(i for _, i in pairs)),
        steps=plots,
        signals=[(str(k.key[0]), str(k.key[1])) for k in signals],
        residual_outputs=[str(k.key[0]) for k in resid],
        trend_metrics=trend_metrics, start=start, trend_span=trend_span)


def _blueprint(layout: Layout) -> rrb.Blueprint:
    """Tabs *Step responses* (outputs × inputs grid), *Signals* (raw | conditioned, one
    row per signal), *Residuals* (one view per output) and *Trends*; opens on the
    ``elapsed`` timeline, where the first three tabs all have data."""
    def fixed(item: Any, key: str) -> Any:
        return with_fixed_ids(item, layout.ident, key)

    tabs = [_step_tab(layout, fixed)]
    if layout.signals:
        tabs.append(_signals_tab(layout, fixed))
    if layout.residual_outputs:
        tabs.append(_residuals_tab(layout, fixed))
    if layout.trend_metrics:
        tabs.append(_trends_tab(layout, fixed))
    return make_blueprint(fixed(rrb.Tabs(*tabs, name="plantdyn"), "tabs"), TIMELINES["elapsed"])


def _step_tab(layout: Layout, fixed: Any) -> Any:
    """Rows = outputs, columns = inputs; a pair without a stored response is an empty
    cell that says so, so the matrix stays aligned."""
    units, views = layout.units, []
    legend_everywhere = len(layout.outputs) <= LEGEND_ROWS
    legend_shown = False
    for o in layout.outputs:
        for i in layout.inputs:
            plot = layout.steps.get((o, i))
            name = f"{with_unit(o, units)} ← {with_unit(i, units)}"
            origin = f"/step/{path_part(o)}/{path_part(i)}"
            if plot is None:
                views.append(fixed(rrb.TimeSeriesView(origin=origin, name=f"{name} (not estimated)",
                                                      plot_legend=legend(None),
                                                      **x_range([TIMELINES["elapsed"]])), f"step/{o}/{i}"))
                continue
            show = legend_everywhere or not legend_shown
            legend_shown = True
            views.append(fixed(rrb.TimeSeriesView(
                origin=origin, name=name, plot_legend=legend(plot.corner if show else None),
                axis_y=rrb.ScalarAxis(range=(plot.y_lo, plot.y_hi)),
                **x_range([TIMELINES["elapsed"]], 0.0, plot.end_s * 1.02)), f"step/{o}/{i}"))
    return fixed(rrb.Grid(*views, grid_columns=max(1, len(layout.inputs)), name="Step responses"), "steps")


def _signals_tab(layout: Layout, fixed: Any) -> Any:
    """One row per signal, its own y axis: raw (with the masked samples) | conditioned."""
    views = []
    timelines = [TIMELINES["elapsed"], TIMELINES["signals"]]
    for name, role in layout.signals:
        part = path_part(name)
        label = f"{with_unit(name, layout.units)} ({role})"
        views.append(fixed(rrb.TimeSeriesView(
            origin="/signals", contents=[f"/signals/raw/{part}", f"/signals/masked/{part}"],
            name=f"{label}: raw, × masked", plot_legend=legend(None), **x_range(timelines)),
            f"signals/raw/{name}"))
        views.append(fixed(rrb.TimeSeriesView(
            origin=f"/signals/conditioned/{part}", name=f"{label}: conditioned",
            plot_legend=legend(None), **x_range(timelines)), f"signals/conditioned/{name}"))
    return fixed(rrb.Grid(*views, grid_columns=2, name=f"Signals{layout.since()}"), "signals")


def _residuals_tab(layout: Layout, fixed: Any) -> Any:
    timelines = [TIMELINES["elapsed"], TIMELINES["signals"]]
    views = [fixed(rrb.TimeSeriesView(origin=f"/residuals/{path_part(o)}",
                                      name=f"{with_unit(o, layout.units)}: residual of the all-data estimate",
                                      plot_legend=legend(None), **x_range(timelines)), f"residuals/{o}")
             for o in layout.residual_outputs]
    return fixed(rrb.Vertical(*views, name=f"Residuals{layout.since()}"), "residuals")


def _trends_tab(layout: Layout, fixed: Any) -> Any:
    """The pairs' gain (or rate; every metric when neither is stored) over runs, in the
    step grid's arrangement, below a note on the timeline they need."""
    pairs = list(layout.trend_metrics)
    outputs = [o for o in layout.outputs if any(p[0] == o for p in pairs)] or list(dict.fromkeys(p[0] for p in pairs))
    inputs = [i for i in layout.inputs if any(p[1] == i for p in pairs)] or list(dict.fromkeys(p[1] for p in pairs))
    first, last = layout.trend_span or (0.0, 0.0)
    pad = 0.05 * (last - first) if last > first else 86400.0  # points off the plot's edges
    views = []
    for o in outputs:
        for i in inputs:
            metrics = layout.trend_metrics.get((o, i), [])
            shown = [m for m in metrics if m in ("gain", "rate")] or metrics
            base = f"/trends/{path_part(o)}/{path_part(i)}"
            views.append(fixed(rrb.TimeSeriesView(
                origin=base, contents=[f"{base}/{path_part(m)}" for m in shown] or [base],
                name=f"{o} ← {i}: {', '.join(shown) or 'no trend'} per run", plot_legend=legend("RightBottom"),
                **x_range([TIMELINES["trends"]], first - pad, last + pad)), f"trends/{o}/{i}"))
    note = fixed(rrb.TextDocumentView(origin="/trends/readme", name="How to see the trends"), "trends/readme")
    grid = fixed(rrb.Grid(*views, grid_columns=max(1, len(inputs))), "trends/grid")
    return fixed(rrb.Vertical(note, grid, row_shares=[1, 6], name="Trends"), "trends")


def render_run(run_dir: Path, *, trends: pl.DataFrame | None = None, out_name: str = "recording.rrd",
               ident: str | None = None, config: Mapping[str, Any] | None = None) -> Path:
    """Render the stored files of ``run_dir`` into ``run_dir/out_name``.

    Parameters
    ----------
    run_dir : Path
        A run directory (or the store's temporary directory before the rename).
    trends : polars.DataFrame, optional
        Catalog trend rows of earlier runs (columns ``created_utc``, ``output``, ``input``,
        ``metric``, ``value``; one window, as ``ResultStore.trend(job)`` returns), drawn on
        a ``run_time`` timeline.  Rows with a null value (labels such as verdicts) are skipped.
    out_name : str
        File name of the recording inside ``run_dir``.  It is written to a temporary name
        and renamed, so a failed render leaves no partial file.
    ident : str, optional
        ``"<job>/<run_id>"``; the recording id derives from it.  Default: from
        ``manifest.json``, else the folder name.  Pass it when rendering in the store's
        temporary directory (whose name is random and which has no manifest yet).
    config : mapping, optional
        The resolved job config (units of the signals, ``signals.<group>.<name>.unit``,
        label the views).  Default: ``manifest.json``'s ``config``; pass it when rendering
        before the manifest exists.

    Returns
    -------
    Path
        The written recording.

    Raises
    ------
    ConfigError
        ``out_name`` is not a plain file name, or ``trends`` lacks columns.
    DataQualityError
        ``trends`` holds several rows per output, input, metric and run.
    """
    run_dir = Path(run_dir)
    check_out_name(out_name)
    manifest_path = run_dir / "manifest.json"
    manifest = json.loads(manifest_path.read_text(encoding="utf-8")) if manifest_path.is_file() else None
    if ident is None and isinstance(manifest, dict):
        ident = f"{manifest.get('job')}/{manifest.get('run_id')}"
    ident = ident or run_dir.name
    if config is None and isinstance(manifest, dict):
        config = manifest.get("config")
    checks_path = run_dir / "checks.json"
    checks = json.loads(checks_path.read_text(encoding="utf-8")) if checks_path.is_file() else None
    steps = read_parquet(run_dir, "step_responses.parquet")
    sig_path, res_path = run_dir / "signals.parquet", run_dir / "residuals.parquet"
    signals = scan_keys(sig_path, ["signal", "role"]) if sig_path.is_file() else []
    resid = scan_keys(res_path, ["output"], where=_ALL_WINDOW, where_columns=["window"]) \
        if res_path.is_file() else []
    trends = _check_trends(trends) if trends is not None and trends.height else None
    firsts = [k.first for k in [*signals, *resid] if k.rows]
    start = min(firsts) if firsts else None
    layout = _layout(ident, units_of(config), checks, steps, signals, resid, trends, start)

    def send(rec: rr.RecordingStream) -> None:
        if signals:
            reduce_series(sig_path, ["signal", "role"], _SIGNAL_SPECS, columns=["raw", "conditioned", "good"],
                          infos=signals, on_key=lambda info, series: _send_signal(rec, info, series, start))
        if steps is not None:
            _send_steps(rec, steps, [(o, i) for o in layout.outputs for i in layout.inputs])
        if resid:
            reduce_series(res_path, ["output"], _RESIDUAL_SPECS, columns=["residual", "window"],
                          where=_ALL_WINDOW, infos=resid,
                          on_key=lambda info, series: _send_residual(rec, info, series, start))
        if trends is not None:
            _send_trends(rec, trends)

    return write_recording(run_dir / out_name, ident, _blueprint(layout), send)


_ALL_WINDOW = pl.col("window") == "all"
#: What is drawn per signal: raw, conditioned (a masked sample is not part of the
#: conditioned signal the estimator used: a gap) and the masked samples as markers.
_SIGNAL_SPECS = {
    "raw": Spec(pl.col("raw")),
    "conditioned": Spec(pl.when(pl.col("good")).then(pl.col("conditioned"))),
    "masked": Spec(pl.col("raw"), flag=~pl.col("good") & pl.col("raw").is_not_null()),
}
_RESIDUAL_SPECS = {"residual": Spec(pl.col("residual"))}


def _time_indexes(stamps: np.ndarray, start: np.datetime64 | None) -> list[rr.TimeColumn]:
    """The points on ``elapsed`` (since ``start``) and on ``time`` (UTC)."""
    stamps = np.asarray(stamps, dtype="datetime64[ns]")
    return [rr.TimeColumn(TIMELINES["elapsed"], duration=(stamps - start).astype("timedelta64[ns]")),
            rr.TimeColumn(TIMELINES["signals"], timestamp=stamps)]


def _line(rec: rr.RecordingStream, path: str, series: Reduced, start: np.datetime64 | None, *, name: str,
          colour: tuple[int, int, int] | None) -> None:
    """One line: every sample, or the min/max envelope drawn with the viewer's min/max
    aggregation (so zooming out keeps the band)."""
    if series.envelope:
        name = f"{name}, min/max envelope"
    send_series(rec, path, _time_indexes(series.time, start), series.value, name=name, colour=colour,
                width=1.0, aggregation="MinMax" if series.envelope else None)


def _send_signal(rec: rr.RecordingStream, info: KeyInfo, series: Mapping[str, Reduced],
                 start: np.datetime64 | None) -> None:
    name, role = str(info.key[0]), str(info.key[1])
    colour = ROLE_COLOURS.get(role)
    _line(rec, f"signals/raw/{path_part(name)}", series["raw"], start, name=f"{name} ({role})", colour=colour)
    _line(rec, f"signals/conditioned/{path_part(name)}", series["conditioned"], start,
          name=f"{name} ({role}) conditioned", colour=colour)
    masked = series["masked"]
    if masked.time.size:
        path = f"signals/masked/{path_part(name)}"
        label = f"{name} masked" + (", first per bucket" if masked.envelope else "")
        rec.log(path, rr.SeriesPoints(names=label, colors=[MASKED_COLOUR],
                                      markers="cross", marker_sizes=6.0), static=True, strict=True)
        rec.send_columns(path, indexes=_time_indexes(masked.time, start),
                         columns=rr.Scalars.columns(scalars=masked.value), strict=True)


def _send_residual(rec: rr.RecordingStream, info: KeyInfo, series: Mapping[str, Reduced],
                   start: np.datetime64 | None) -> None:
    output = str(info.key[0])
    _line(rec, f"residuals/{path_part(output)}", series["residual"], start, name=f"residual {output}",
          colour=RESIDUAL_COLOUR)


def _send_steps(rec: rr.RecordingStream, steps: pl.DataFrame, pairs: Sequence[tuple[str, str]]) -> None:
    """Per pair ``band/{fill,upper,lower}`` then ``window/<w>``: the viewer draws a view's
    series in entity-path order, so the band lies under every line and the windows (thin)
    over the all-data estimate (thick)."""
    windows = sorted(steps["window"].unique().to_list(),
                     key=lambda w: (w != "all", int(w[1:]) if w[1:].isdigit() else -1, w))
    for output, inp in pairs:
        base = f"step/{path_part(output)}/{path_part(inp)}"
        pair = steps.filter((pl.col("output") == output) & (pl.col("input") == inp))
        for k, window in enumerate(windows):
            df = pair.filter(pl.col("window") == window).sort("lag")
            if df.height == 0:
                continue
            index = rr.TimeColumn(TIMELINES["elapsed"], duration=durations(df["time_s"].to_numpy()))
            step = float_values(df["step"])
            if window == "all":
                std = float_values(df["step_std"])
                _send_band(rec, base, df["time_s"].to_numpy(), step - 2 * std, step + 2 * std)
                send_series(rec, f"{base}/window/all", index, step, name="all data", colour=ALL_COLOUR, width=2.5)
            else:
                colour = WINDOW_COLOURS[(k - ("all" in windows)) % len(WINDOW_COLOURS)]
                send_series(rec, f"{base}/window/{path_part(window)}", index, step, name=f"window {window}",
                            colour=colour, width=1.0)


def _send_band(rec: rr.RecordingStream, base: str, time_s: np.ndarray, lower: np.ndarray,
               upper: np.ndarray) -> None:
    """``band/upper`` and ``band/lower`` (step ± 2·step_std at the lags) and ``band/fill``:
    Rerun 0.41 has no filled area, so a triangle wave of :data:`BAND_POINTS` points
    between the bounds (linear between lags, as the lines are drawn) fills it."""
    index = rr.TimeColumn(TIMELINES["elapsed"], duration=durations(time_s))
    ok = np.isfinite(time_s) & np.isfinite(lower) & np.isfinite(upper)
    if ok.any():
        t, lo, hi = time_s[ok], lower[ok], upper[ok]
        fill_t = np.linspace(t[0], t[-1], BAND_POINTS if t[-1] > t[0] else 2)
        fill = np.where(np.arange(fill_t.size) % 2 == 0, np.interp(fill_t, t, lo), np.interp(fill_t, t, hi))
        send_series(rec, f"{base}/band/fill", rr.TimeColumn(TIMELINES["elapsed"], duration=durations(fill_t)),
                    fill, name=BAND_NAME, colour=BAND_FILL_COLOUR, width=1.5, aggregation="Off")
    send_series(rec, f"{base}/band/lower", index, lower, name=BAND_NAME, colour=BAND_EDGE_COLOUR, width=1.0)
    send_series(rec, f"{base}/band/upper", index, upper, name=BAND_NAME, colour=BAND_EDGE_COLOUR, width=1.0)


def _send_trends(rec: rr.RecordingStream, trends: pl.DataFrame) -> None:
    rec.log("trends/readme", rr.TextDocument(_TRENDS_NOTE, media_type=rr.MediaType.MARKDOWN), static=True,
            strict=True)
    for (output, inp, metric), df in trends.sort("created_utc").group_by(
            ["output", "input", "metric"], maintain_order=True):
        path = f"trends/{path_part(output)}/{path_part(inp)}/{path_part(metric)}"
        rec.log(path, rr.SeriesPoints(names=metric, marker_sizes=6.0), static=True, strict=True)
        rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINES["trends"], timestamp=df["created_utc"].to_numpy())],
                         columns=rr.Scalars.columns(scalars=float_values(df["value"])), strict=True)
