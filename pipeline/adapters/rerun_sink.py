"""The Rerun sink: renders a run directory into ``recording.rrd`` (the only importer of
``rerun``).

It reads the stored files (``signals.parquet``, ``step_responses.parquet``,
``residuals.parquet``, ``checks.json``, ``manifest.json``), never in-memory results, so a
figure can be rebuilt from a run without refitting: ``render_run(run_dir)``.  Every file is
optional; what is absent is simply not drawn.

Layout (entity paths; names are escaped with ``rr.escape_entity_path_part``):

* ``signals/raw/<signal>``, ``signals/conditioned/<signal>`` on the ``time`` timeline, one
  row per stored sample; missing values and masked conditioned samples are NaN, which the
  viewer draws as gaps.  Masked samples (``good == False``) that have a raw value are also
  points on ``signals/masked/<signal>`` (red crosses over the raw line);
* ``step/<output>/<input>/<window>`` on the ``lag_s`` timeline (``time_s`` of the stored
  step response, as a duration), with ``step/<output>/<input>/all_upper`` and
  ``all_lower`` (step ± 2·step_std of the estimate over all data); every disjoint window
  overlaid in the same view;
* ``residuals/<output>`` on ``time`` (residuals of the all-data estimate);
* ``trends/<output>/<input>/<metric>`` on ``run_time`` when nightly trends are given.

Series are sent in bulk with ``send_columns`` (≈30× faster than per-row ``log``), which
injects no ``log_time``/``log_tick``; the recording id derives from job and run id and no
wall-clock recording properties are sent, so the same run renders to the same *data*.
The file is not byte-identical between renders: Rerun stamps every chunk and row with a
time-based id (TUID), and the blueprint store gets a random id and a ``log_time``; compare
decoded contents instead (``tests/test_rerun_sink.py`` does).

A default blueprint opens tabs *Step responses* (one view per pair), *Signals*,
*Residuals* and *Trends*, starting on the ``lag_s`` timeline; every TimeSeriesView is
given the full time range explicitly (without it the viewer shows only ±30 s around the
time cursor).  The other tabs need the ``time`` (signals, residuals) or ``run_time``
(trends) timeline, chosen in the time panel.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

from pipeline.errors import ConfigError, DataQualityError

__all__ = ["APPLICATION_ID", "TIMELINES", "recording_id_for", "render_run"]

APPLICATION_ID = "plantdyn"
#: Timeline names: sample time of the signals, lag after the step, creation time of runs.
TIMELINES = {"signals": "time", "step": "lag_s", "trends": "run_time"}
# Fixed namespace: recording ids are uuid5(namespace, "<job>/<run_id>"), stable across
# processes and machines (uuid5 of a URL-namespace name, as the first version did).
_NAMESPACE = uuid.NAMESPACE_URL
_WINDOW_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                   (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127)]
_ALL_COLOUR = (240, 240, 240)
_BAND_COLOUR = (150, 150, 150)
_MASKED_COLOUR = (220, 0, 0)
_TREND_COLUMNS = ("created_utc", "output", "input", "metric", "value")


def recording_id_for(ident: str) -> str:
    """The recording id of run ``"<job>/<run_id>"`` (a uuid5, deterministic)."""
    return str(uuid.uuid5(_NAMESPACE, f"plantdyn:{ident}"))


def _part(name: str) -> str:
    # Escaping (not replacing) keeps distinct names distinct: 'flow rate' vs 'flow_rate'.
    return rr.escape_entity_path_part(str(name))


def _full_range(timeline: str) -> dict[str, Any]:
    """Both the visible data range and the x-axis view range span all data (design.md:
    without an explicit range the view shows ±30 s around the time cursor)."""
    inf = rrb.TimeRangeBoundary.infinite()
    return {"time_ranges": [rrb.VisibleTimeRange(timeline, start=inf, end=inf)],
            "axis_x": rrb.TimeAxis(view_range=rr.TimeRange(start=inf, end=inf))}


def _with_fixed_ids(item: Any, ident: str, key: str) -> Any:
    """Give a blueprint view/container an id derived from the run and its place, instead
    of the random uuid4 the SDK picks, so the same run gets the same blueprint."""
    item.id = uuid.uuid5(_NAMESPACE, f"plantdyn:{ident}:blueprint:{key}")
    return item


def _series(rec: rr.RecordingStream, path: str, index: rr.TimeColumn, values: np.ndarray,
            *, name: str, colour: tuple[int, int, int] | None = None, width: float = 1.5) -> None:
    style = rr.SeriesLines(names=name, widths=width,
                           **({"colors": [colour]} if colour is not None else {}))
    rec.log(path, style, static=True, strict=True)
    rec.send_columns(path, indexes=[index], columns=rr.Scalars.columns(scalars=values), strict=True)


def _floats(series: pl.Series) -> np.ndarray:
    """Float64 values with nulls as NaN (a gap in the plot)."""
    return series.cast(pl.Float64).fill_null(np.nan).to_numpy()


def _read_parquet(run_dir: Path, name: str) -> pl.DataFrame | None:
    path = run_dir / name
    return pl.read_parquet(path) if path.is_file() else None


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
    missing = [c for c in _TREND_COLUMNS if c not in trends.columns]
    if missing:
        raise ConfigError(f"trends: missing columns {missing}; pass ResultStore.trend(job) "
                          f"(columns {list(_TREND_COLUMNS)})")
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
        return _with_fixed_ids(rrb.TimeSeriesView(**kwargs), ident, key)

    def container(kind: type, key: str, *views: Any, name: str) -> Any:
        return _with_fixed_ids(kind(*views, name=name), ident, key)

    tabs = [container(rrb.Grid, "steps", *[
        view(f"step/{o}/{i}", origin=f"/step/{_part(o)}/{_part(i)}", name=f"{o} ← {i}",
             **_full_range(TIMELINES["step"]))
        for o, i in pairs], name="Step responses")]
    if signals:
        tabs.append(container(rrb.Vertical, "signals",
                              view("signals/raw", origin="/signals", name="Raw signals (masked: ×)",
                                   contents=["/signals/raw/**", "/signals/masked/**"],
                                   **_full_range(TIMELINES["signals"])),
                              view("signals/conditioned", origin="/signals/conditioned",
                                   name="Conditioned signals", **_full_range(TIMELINES["signals"])),
                              name="Signals"))
    if outputs:
        tabs.append(container(rrb.Vertical, "residuals", *[
            view(f"residuals/{o}", origin=f"/residuals/{_part(o)}", name=f"residual {o}",
                 **_full_range(TIMELINES["signals"]))
            for o in outputs], name="Residuals"))
    if trend_pairs:
        tabs.append(container(rrb.Grid, "trends", *[
            view(f"trends/{o}/{i}", origin=f"/trends/{_part(o)}/{_part(i)}", name=f"trend {o} ← {i}",
                 **_full_range(TIMELINES["trends"]))
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
    if not out_name or Path(out_name).name != out_name or out_name.startswith("."):
        raise ConfigError(f"out_name {out_name!r} must be a plain file name such as 'recording.rrd'")
    manifest_path = run_dir / "manifest.json"
    if ident is None and manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        ident = f"{manifest.get('job')}/{manifest.get('run_id')}"
    ident = ident or run_dir.name
    checks_path = run_dir / "checks.json"
    checks = json.loads(checks_path.read_text(encoding="utf-8")) if checks_path.is_file() else None
    steps = _read_parquet(run_dir, "step_responses.parquet")
    signals = _read_parquet(run_dir, "signals.parquet")
    resid = _read_parquet(run_dir, "residuals.parquet")
    if resid is not None:
        resid = resid.filter(pl.col("window") == "all")
    trends = _check_trends(trends) if trends is not None and trends.height else None

    pairs = _pairs(checks, steps)
    signal_names = [] if signals is None else signals["signal"].unique(maintain_order=True).to_list()
    outputs = [] if resid is None else resid["output"].unique(maintain_order=True).to_list()
    trend_pairs = [] if trends is None else [
        tuple(r) for r in trends.select("output", "input").unique(maintain_order=True).rows()]

    out = run_dir / out_name
    tmp = run_dir / f".{out_name}.{secrets.token_hex(4)}.part"
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id_for(ident), send_properties=False)
    try:
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        rec.save(tmp, default_blueprint=_blueprint(ident, pairs, signal_names, outputs, trend_pairs))
        rec.send_recording_name(ident)  # shown in the viewer; deterministic, unlike a start time
        if signals is not None:
            _send_signals(rec, signals)
        if steps is not None:
            _send_steps(rec, steps, pairs)
        if resid is not None:
            for (output,), df in resid.sort("time").group_by(["output"], maintain_order=True):
                _series(rec, f"residuals/{_part(output)}",
                        rr.TimeColumn(TIMELINES["signals"], timestamp=df["time"].to_numpy()),
                        _floats(df["residual"]), name=f"residual {output}")
        if trends is not None:
            _send_trends(rec, trends)
        rec.flush()
        rec.disconnect()  # finalises the file (footer with the chunk manifest)
        if not tmp.is_file():
            raise RuntimeError(f"Rerun wrote no file at {tmp}; is logging disabled (RERUN=off)?")
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(Exception):
            rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    return out


def _send_signals(rec: rr.RecordingStream, signals: pl.DataFrame) -> None:
    for (name, role), df in signals.sort("time").group_by(["signal", "role"], maintain_order=True):
        times = df["time"].to_numpy()
        index = rr.TimeColumn(TIMELINES["signals"], timestamp=times)
        _series(rec, f"signals/raw/{_part(name)}", index, _floats(df["raw"]), name=f"{name} ({role})")
        # A masked sample is not part of the conditioned signal the estimator used: gap.
        conditioned = np.where(df["good"].to_numpy(), _floats(df["conditioned"]), np.nan)
        _series(rec, f"signals/conditioned/{_part(name)}", index, conditioned, name=f"{name} ({role})")
        bad = df.filter(~pl.col("good") & pl.col("raw").is_not_null())
        if bad.height:
            path = f"signals/masked/{_part(name)}"
            rec.log(path, rr.SeriesPoints(names=f"{name} masked", colors=[_MASKED_COLOUR],
                                          markers="cross", marker_sizes=4.0), static=True, strict=True)
            rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINES["signals"], timestamp=bad["time"].to_numpy())],
                             columns=rr.Scalars.columns(scalars=_floats(bad["raw"])), strict=True)


def _send_steps(rec: rr.RecordingStream, steps: pl.DataFrame, pairs: Sequence[tuple[str, str]]) -> None:
    windows = sorted(steps["window"].unique().to_list(),
                     key=lambda w: (w != "all", int(w[1:]) if w[1:].isdigit() else -1, w))
    for output, inp in pairs:
        base = f"step/{_part(output)}/{_part(inp)}"
        pair = steps.filter((pl.col("output") == output) & (pl.col("input") == inp))
        for k, window in enumerate(windows):
            df = pair.filter(pl.col("window") == window).sort("lag")
            if df.height == 0:
                continue
            index = rr.TimeColumn(TIMELINES["step"], duration=df["time_s"].to_numpy())
            step = _floats(df["step"])
            if window == "all":
                std = _floats(df["step_std"])
                _series(rec, f"{base}/all", index, step, name="all data", colour=_ALL_COLOUR, width=2.5)
                _series(rec, f"{base}/all_upper", index, step + 2 * std, name="+2σ",
                        colour=_BAND_COLOUR, width=1.0)
                _series(rec, f"{base}/all_lower", index, step - 2 * std, name="−2σ",
                        colour=_BAND_COLOUR, width=1.0)
            else:
                colour = _WINDOW_COLOURS[(k - ("all" in windows)) % len(_WINDOW_COLOURS)]
                _series(rec, f"{base}/{_part(window)}", index, step, name=f"window {window}", colour=colour)


def _send_trends(rec: rr.RecordingStream, trends: pl.DataFrame) -> None:
    for (output, inp, metric), df in trends.sort("created_utc").group_by(
            ["output", "input", "metric"], maintain_order=True):
        path = f"trends/{_part(output)}/{_part(inp)}/{_part(metric)}"
        rec.log(path, rr.SeriesPoints(names=metric, marker_sizes=5.0), static=True, strict=True)
        rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINES["trends"], timestamp=df["created_utc"].to_numpy())],
                         columns=rr.Scalars.columns(scalars=_floats(df["value"])), strict=True)
