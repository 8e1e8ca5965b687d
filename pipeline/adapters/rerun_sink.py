"""The Rerun sink: renders a run directory into ``recording.rrd`` (the only importer of
``rerun``).

It reads the stored files (``signals.parquet``, ``step_responses.parquet``,
``residuals.parquet``, ``checks.json``), never in-memory results, so a figure can be
rebuilt from a run without refitting: ``render_run(run_dir)``.

Layout (entity paths):

* ``signals/raw/<signal>``, ``signals/conditioned/<signal>`` on the ``time`` timeline;
  masked samples as points on ``signals/masked/<signal>`` (gaps stay gaps in the lines);
* ``step/<output>/<input>/<window>`` on the ``lag_s`` timeline (seconds after the step),
  with ``step/<output>/<input>/all_upper`` and ``all_lower`` (±2σ band of the estimate
  over all data); every disjoint window overlaid in the same view;
* ``residuals/<output>`` on ``time``;
* ``trends/<output>/<input>/<metric>`` on ``run_time`` when nightly trends are given.

Series are sent in bulk with ``send_columns`` (≈30× faster than per-row ``log``), which
also injects no ``log_time``/``log_tick``; the recording id derives from job and run id
and no recording properties (start time) are sent, so the same run renders to the same
data.  A default blueprint opens tabs *Step responses* (one view per pair), *Signals*,
*Residuals* and *Trends*; every TimeSeriesView is given the full time range explicitly
(without it the viewer shows only ±30 s around the cursor).
"""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

__all__ = ["render_run", "APPLICATION_ID"]

APPLICATION_ID = "plantdyn"
_WINDOW_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                   (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127)]


def _full_range(timeline: str) -> dict:
    """Both the data range and the x-axis view range span everything (design.md: else
    the view shows +-30 s around the time cursor)."""
    inf = rrb.TimeRangeBoundary.infinite()
    full = rrb.VisibleTimeRange(timeline, start=inf, end=inf)
    return {"time_ranges": [full],
            "axis_x": rrb.TimeAxis(view_range=rr.TimeRange(start=inf, end=inf))}


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "_-." else "_" for c in str(name))


def _series(rec: rr.RecordingStream, path: str, index: rr.TimeColumn, values: np.ndarray,
            *, name: str, colour=None, width: float = 1.5) -> None:
    style = rr.SeriesLines(names=name, widths=width,
                           **({"colors": [colour]} if colour is not None else {}))
    rec.log(path, style, static=True)
    rec.send_columns(path, indexes=[index], columns=rr.Scalars.columns(scalars=values))


def _blueprint(pairs: list[tuple[str, str]], outputs: list[str], has_trends: bool):
    step_views = [rrb.TimeSeriesView(origin=f"/step/{_safe(o)}/{_safe(i)}",
                                     name=f"{o} ← {i}", **_full_range("lag_s"))
                  for o, i in pairs]
    tabs = [
        rrb.Grid(*step_views, name="Step responses"),
        rrb.Vertical(
            rrb.TimeSeriesView(origin="/signals/raw", name="Raw signals", **_full_range("time")),
            rrb.TimeSeriesView(origin="/signals/conditioned", name="Conditioned signals",
                               **_full_range("time")),
            name="Signals"),
        rrb.Vertical(*[rrb.TimeSeriesView(origin=f"/residuals/{_safe(o)}", name=f"residual {o}",
                                          **_full_range("time")) for o in outputs],
                     name="Residuals"),
    ]
    if has_trends:
        tabs.append(rrb.Grid(*[rrb.TimeSeriesView(origin=f"/trends/{_safe(o)}/{_safe(i)}",
                                                  name=f"trend {o} ← {i}",
                                                  **_full_range("run_time"))
                               for o, i in pairs], name="Trends"))
    # The step responses are what people open the file for: start on their timeline
    # (the Signals/Residuals tabs switch to `time` from the time panel).
    return rrb.Blueprint(rrb.Tabs(*tabs), rrb.TimePanel(timeline="lag_s", play_state="paused"),
                         collapse_panels=False)


def render_run(run_dir: Path, *, trends: pl.DataFrame | None = None,
               out_name: str = "recording.rrd", ident: str | None = None) -> Path:
    """Render the stored files of ``run_dir`` into ``run_dir/out_name``.

    Parameters
    ----------
    run_dir : Path
        A run directory (or the store's temporary directory before the rename).
    trends : polars.DataFrame, optional
        Catalog trend rows (``created_utc``, ``output``, ``input``, ``metric``,
        ``value``) of earlier runs, shown on a ``run_time`` timeline.
    out_name : str
        File name of the recording.
    ident : str, optional
        ``"<job>/<run_id>"``; the recording id derives from it (default: from the
        manifest, else the folder name — pass it when rendering in the store's temporary
        directory, whose name is random).
    """
    run_dir = Path(run_dir)
    manifest_path = run_dir / "manifest.json"
    checks = json.loads((run_dir / "checks.json").read_text())
    if ident is None and manifest_path.is_file():
        m = json.loads(manifest_path.read_text())
        ident = f"{m.get('job')}/{m.get('run_id')}"
    ident = ident or run_dir.name
    steps = pl.read_parquet(run_dir / "step_responses.parquet")
    signals = pl.read_parquet(run_dir / "signals.parquet")
    resid = pl.read_parquet(run_dir / "residuals.parquet")
    pairs = [(p["output"], p["input"]) for p in checks["pairs"]]
    outputs = list(dict.fromkeys(o for o, _ in pairs))
    rec_id = str(uuid.uuid5(uuid.NAMESPACE_URL, f"plantdyn:{ident}"))
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=rec_id, send_properties=False)
    has_trends = trends is not None and trends.height > 0
    out = run_dir / out_name
    rec.save(out, default_blueprint=_blueprint(pairs, outputs, has_trends))

    # signals on the time timeline
    for (name, role), df in signals.sort("time").group_by(["signal", "role"],
                                                          maintain_order=True):
        t = rr.TimeColumn("time", timestamp=df["time"].to_numpy())
        for col in ("raw", "conditioned"):
            v = df[col].cast(pl.Float64).fill_null(np.nan).to_numpy()
            _series(rec, f"signals/{col}/{_safe(name)}", t, v, name=f"{name} ({role})")
        bad = df.filter(~pl.col("good"))
        if bad.height:
            path = f"signals/masked/{_safe(name)}"
            rec.log(path, rr.SeriesPoints(names=f"{name} masked", colors=[(220, 0, 0)],
                                          markers="cross", marker_sizes=4.0), static=True)
            rec.send_columns(path, indexes=[rr.TimeColumn("time", timestamp=bad["time"].to_numpy())],
                             columns=rr.Scalars.columns(
                                 scalars=bad["raw"].cast(pl.Float64).fill_null(0.0).to_numpy()))

    # step responses on a lag_s timeline (duration in seconds)
    windows = sorted(steps["window"].unique().to_list(), key=lambda w: (w != "all", w))
    for o, i in pairs:
        base = f"step/{_safe(o)}/{_safe(i)}"
        for k, w in enumerate(windows):
            df = steps.filter((pl.col("output") == o) & (pl.col("input") == i)
                              & (pl.col("window") == w)).sort("lag")
            if df.height == 0:
                continue
            t = rr.TimeColumn("lag_s", duration=df["time_s"].to_numpy())
            if w == "all":
                h, s = df["step"].to_numpy(), df["step_std"].to_numpy()
                _series(rec, f"{base}/all", t, h, name="all data", colour=(240, 240, 240), width=2.5)
                _series(rec, f"{base}/all_upper", t, h + 2 * s, name="+2σ",
                        colour=(150, 150, 150), width=1.0)
                _series(rec, f"{base}/all_lower", t, h - 2 * s, name="−2σ",
                        colour=(150, 150, 150), width=1.0)
            else:
                _series(rec, f"{base}/{w}", t, df["step"].to_numpy(), name=f"window {w}",
                        colour=_WINDOW_COLOURS[(k - 1) % len(_WINDOW_COLOURS)])

    # residuals of the all-data estimate
    for (o,), df in resid.filter(pl.col("window") == "all").sort("time").group_by(
            ["output"], maintain_order=True):
        _series(rec, f"residuals/{_safe(o)}", rr.TimeColumn("time", timestamp=df["time"].to_numpy()),
                df["residual"].to_numpy(), name=f"residual {o}")

    # nightly trends
    if has_trends:
        tr = trends.filter(pl.col("output").is_not_null() & pl.col("input").is_not_null()
                           & pl.col("value").is_not_null())
        for (o, i, metric), df in tr.sort("created_utc").group_by(
                ["output", "input", "metric"], maintain_order=True):
            ts = df["created_utc"]
            if ts.dtype == pl.String:
                ts = ts.str.to_datetime(time_zone="UTC")
            path = f"trends/{_safe(o)}/{_safe(i)}/{_safe(metric)}"
            rec.log(path, rr.SeriesPoints(names=metric, marker_sizes=5.0), static=True)
            rec.send_columns(path, indexes=[rr.TimeColumn("run_time", timestamp=ts.to_numpy())],
                             columns=rr.Scalars.columns(scalars=df["value"].to_numpy()))
    rec.flush()
    rec.disconnect()
    return out
