"""The recording of an estimation run: signals, step responses with bands, trends."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

from pipeline.adapters.rerun_sink.common import (
    ALL_COLOUR,
    BAND_COLOUR,
    MASKED_COLOUR,
    TIMELINES,
    TREND_COLUMNS,
    WINDOW_COLOURS,
    check_out_name,
    float_values,
    full_range,
    path_part,
    read_parquet,
    send_series,
    with_fixed_ids,
    write_recording,
)
from pipeline.errors import ConfigError, DataQualityError


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


def _blueprint(ident: str, pairs: Sequence[tuple[str, str]], signals: Sequence[str],
               outputs: Sequence[str], trend_pairs: Sequence[tuple[str, str]]) -> rrb.Blueprint:
    def view(key: str, **kwargs: Any) -> rrb.TimeSeriesView:
        return with_fixed_ids(rrb.TimeSeriesView(**kwargs), ident, key)

    def container(kind: type, key: str, *views: Any, name: str) -> Any:
        return with_fixed_ids(kind(*views, name=name), ident, key)

    tabs = [container(rrb.Grid, "steps", *[
        view(f"step/{o}/{i}", origin=f"/step/{path_part(o)}/{path_part(i)}", name=f"{o} ← {i}",
             **full_range(TIMELINES["step"]))
        for o, i in pairs], name="Step responses")]
    if signals:
        tabs.append(container(rrb.Vertical, "signals",
                              view("signals/raw", origin="/signals", name="Raw signals (masked: ×)",
                                   contents=["/signals/raw/**", "/signals/masked/**"],
                                   **full_range(TIMELINES["signals"])),
                              view("signals/conditioned", origin="/signals/conditioned",
                                   name="Conditioned signals", **full_range(TIMELINES["signals"])),
                              name="Signals"))
    if outputs:
        tabs.append(container(rrb.Vertical, "residuals", *[
            view(f"residuals/{o}", origin=f"/residuals/{path_part(o)}", name=f"residual {o}",
                 **full_range(TIMELINES["signals"]))
            for o in outputs], name="Residuals"))
    if trend_pairs:
        tabs.append(container(rrb.Grid, "trends", *[
            view(f"trends/{o}/{i}", origin=f"/trends/{path_part(o)}/{path_part(i)}", name=f"trend {o} ← {i}",
                 **full_range(TIMELINES["trends"]))
            for o, i in trend_pairs], name="Trends"))
    # The step responses are what people open the file for: start on their timeline.
    return rrb.Blueprint(container(rrb.Tabs, "tabs", *tabs, name="plantdyn"),
                         rrb.TimePanel(timeline=TIMELINES["step"], play_state="paused"),
                         collapse_panels=False)


def render_run(run_dir: Path, *, trends: pl.DataFrame | None = None,
               out_name: str = "recording.rrd", ident: str | None = None) -> Path:
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
    if ident is None and manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        ident = f"{manifest.get('job')}/{manifest.get('run_id')}"
    ident = ident or run_dir.name
    checks_path = run_dir / "checks.json"
    checks = json.loads(checks_path.read_text(encoding="utf-8")) if checks_path.is_file() else None
    steps = read_parquet(run_dir, "step_responses.parquet")
    signals = read_parquet(run_dir, "signals.parquet")
    resid = read_parquet(run_dir, "residuals.parquet")
    if resid is not None:
        resid = resid.filter(pl.col("window") == "all")
    trends = _check_trends(trends) if trends is not None and trends.height else None

    pairs = _pairs(checks, steps)
    signal_names = [] if signals is None else signals["signal"].unique(maintain_order=True).to_list()
    outputs = [] if resid is None else resid["output"].unique(maintain_order=True).to_list()
    trend_pairs = [] if trends is None else [
        tuple(r) for r in trends.select("output", "input").unique(maintain_order=True).rows()]

    def send(rec: rr.RecordingStream) -> None:
        if signals is not None:
            _send_signals(rec, signals)
        if steps is not None:
            _send_steps(rec, steps, pairs)
        if resid is not None:
            for (output,), df in resid.sort("time").group_by(["output"], maintain_order=True):
                send_series(rec, f"residuals/{path_part(output)}",
                        rr.TimeColumn(TIMELINES["signals"], timestamp=df["time"].to_numpy()),
                        float_values(df["residual"]), name=f"residual {output}")
        if trends is not None:
            _send_trends(rec, trends)

    return write_recording(run_dir / out_name, ident,
                            _blueprint(ident, pairs, signal_names, outputs, trend_pairs), send)




def _send_signals(rec: rr.RecordingStream, signals: pl.DataFrame) -> None:
    for (name, role), df in signals.sort("time").group_by(["signal", "role"], maintain_order=True):
        times = df["time"].to_numpy()
        index = rr.TimeColumn(TIMELINES["signals"], timestamp=times)
        send_series(rec, f"signals/raw/{path_part(name)}", index, float_values(df["raw"]), name=f"{name} ({role})")
        # A masked sample is not part of the conditioned signal the estimator used: gap.
        conditioned = np.where(df["good"].to_numpy(), float_values(df["conditioned"]), np.nan)
        send_series(rec, f"signals/conditioned/{path_part(name)}", index, conditioned, name=f"{name} ({role})")
        bad = df.filter(~pl.col("good") & pl.col("raw").is_not_null())
        if bad.height:
            path = f"signals/masked/{path_part(name)}"
            rec.log(path, rr.SeriesPoints(names=f"{name} masked", colors=[MASKED_COLOUR],
                                          markers="cross", marker_sizes=4.0), static=True, strict=True)
            rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINES["signals"], timestamp=bad["time"].to_numpy())],
                             columns=rr.Scalars.columns(scalars=float_values(bad["raw"])), strict=True)


def _send_steps(rec: rr.RecordingStream, steps: pl.DataFrame, pairs: Sequence[tuple[str, str]]) -> None:
    windows = sorted(steps["window"].unique().to_list(),
                     key=lambda w: (w != "all", int(w[1:]) if w[1:].isdigit() else -1, w))
    for output, inp in pairs:
        base = f"step/{path_part(output)}/{path_part(inp)}"
        pair = steps.filter((pl.col("output") == output) & (pl.col("input") == inp))
        for k, window in enumerate(windows):
            df = pair.filter(pl.col("window") == window).sort("lag")
            if df.height == 0:
                continue
            index = rr.TimeColumn(TIMELINES["step"], duration=df["time_s"].to_numpy())
            step = float_values(df["step"])
            if window == "all":
                std = float_values(df["step_std"])
                send_series(rec, f"{base}/all", index, step, name="all data", colour=ALL_COLOUR, width=2.5)
                send_series(rec, f"{base}/all_upper", index, step + 2 * std, name="+2σ",
                        colour=BAND_COLOUR, width=1.0)
                send_series(rec, f"{base}/all_lower", index, step - 2 * std, name="−2σ",
                        colour=BAND_COLOUR, width=1.0)
            else:
                colour = WINDOW_COLOURS[(k - ("all" in windows)) % len(WINDOW_COLOURS)]
                send_series(rec, f"{base}/{path_part(window)}", index, step, name=f"window {window}", colour=colour)


def _send_trends(rec: rr.RecordingStream, trends: pl.DataFrame) -> None:
    for (output, inp, metric), df in trends.sort("created_utc").group_by(
            ["output", "input", "metric"], maintain_order=True):
        path = f"trends/{path_part(output)}/{path_part(inp)}/{path_part(metric)}"
        rec.log(path, rr.SeriesPoints(names=metric, marker_sizes=5.0), static=True, strict=True)
        rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINES["trends"], timestamp=df["created_utc"].to_numpy())],
                         columns=rr.Scalars.columns(scalars=float_values(df["value"])), strict=True)
