"""What every recording shares: ids, timelines, colours, bulk series, writing the file."""

from __future__ import annotations

import contextlib
import os
import secrets
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

from pipeline.errors import ConfigError


APPLICATION_ID = "plantdyn"
#: Timeline names: sample time of the signals, lag after the step, creation time of runs,
#: seconds since the first sample of a discrepancy record.
TIMELINES = {"signals": "time", "step": "lag_s", "trends": "run_time", "discrepancy": "time_s"}
# Fixed namespace: recording ids are uuid5(namespace, "<job>/<run_id>"), stable across
# processes and machines (uuid5 of a URL-namespace name, as the first version did).
_NAMESPACE = uuid.NAMESPACE_URL
WINDOW_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                   (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127)]
ALL_COLOUR = (240, 240, 240)
BAND_COLOUR = (150, 150, 150)
MASKED_COLOUR = (220, 0, 0)
TREND_COLUMNS = ("created_utc", "output", "input", "metric", "value")


def recording_id_for(ident: str) -> str:
    """The recording id of run ``"<job>/<run_id>"`` (a uuid5, deterministic).

    Parameters
    ----------
    ident : str
        Run identity, normally ``"<job>/<run_id>"``; the same text always gives the same
        id.
    """
    return str(uuid.uuid5(_NAMESPACE, f"plantdyn:{ident}"))


def path_part(name: str) -> str:
    """``name`` as one entity-path part.

    Parameters
    ----------
    name : str
        A signal, pair or output name.
    """
    # Escaping (not replacing) keeps distinct names distinct: 'flow rate' vs 'flow_rate'.
    return rr.escape_entity_path_part(str(name))


def full_range(timeline: str) -> dict[str, Any]:
    """Both the visible data range and the x-axis view range span all data (design.md:
    without an explicit range the view shows ±30 s around the time cursor).

    Parameters
    ----------
    timeline : str
        The view's timeline (:data:`TIMELINES`).
    """
    inf = rrb.TimeRangeBoundary.infinite()
    return {"time_ranges": [rrb.VisibleTimeRange(timeline, start=inf, end=inf)],
            "axis_x": rrb.TimeAxis(view_range=rr.TimeRange(start=inf, end=inf))}


def with_fixed_ids(item: Any, ident: str, key: str) -> Any:
    """Give a blueprint view/container an id derived from the run and its place, instead
    of the random uuid4 the SDK picks, so the same run gets the same blueprint.

    Parameters
    ----------
    item : blueprint view or container
        Gets the id.
    ident : str
        The run (``job/run_id``).
    key : str
        The item's place in the blueprint.
    """
    item.id = uuid.uuid5(_NAMESPACE, f"plantdyn:{ident}:blueprint:{key}")
    return item


def send_series(rec: rr.RecordingStream, path: str, index: rr.TimeColumn, values: np.ndarray,
                *, name: str, colour: tuple[int, int, int] | None = None,
                width: float = 1.5) -> None:
    """Log one series in bulk (``send_columns``: ~30× faster than a log call per row).

    Parameters
    ----------
    rec : rerun.RecordingStream
        The recording.
    path : str
        Entity path.
    index : rerun.TimeColumn
        The samples' times on the series' timeline.
    values : ndarray (N,)
        The values (NaN: a gap).
    name : str
        Legend name.
    colour : (int, int, int), optional
        RGB; None lets the viewer choose.
    width : float
        Line width.
    """
    style = rr.SeriesLines(names=name, widths=width,
                           **({"colors": [colour]} if colour is not None else {}))
    rec.log(path, style, static=True, strict=True)
    rec.send_columns(path, indexes=[index], columns=rr.Scalars.columns(scalars=values), strict=True)


def float_values(series: pl.Series) -> np.ndarray:
    """Float64 values with nulls as NaN (a gap in the plot).

    Parameters
    ----------
    series : polars.Series
        Numeric column.
    """
    return series.cast(pl.Float64).fill_null(np.nan).to_numpy()


def read_parquet(run_dir: Path, name: str) -> pl.DataFrame | None:
    """A run directory's parquet file, or None when it is absent.

    Parameters
    ----------
    run_dir : Path
        The run directory.
    name : str
        File name.
    """
    path = run_dir / name
    return pl.read_parquet(path) if path.is_file() else None


def check_out_name(out_name: str) -> None:
    """Refuse an output name that is not a plain file name.

    Parameters
    ----------
    out_name : str
        The recording's file name inside the run directory.
    """
    if not out_name or Path(out_name).name != out_name or out_name.startswith("."):
        raise ConfigError(f"out_name {out_name!r} must be a plain file name such as 'recording.rrd'")


def write_recording(out: Path, ident: str, blueprint: rrb.Blueprint,
                     send: Callable[[rr.RecordingStream], None]) -> Path:
    """Write a recording with id ``recording_id_for(ident)`` to a temporary name next to
    ``out``, call ``send(rec)`` to log the data, finalise and rename to ``out``.  Any
    failure removes the temporary file and leaves ``out`` as it was.

    Parameters
    ----------
    out : Path
        The recording file.
    ident : str
        The run (``job/run_id``): recording id and name.
    blueprint : rerun.blueprint.Blueprint
        The default layout saved with it.
    send : callable (rec) -> None
        Logs the data.
    """
    tmp = out.parent / f".{out.name}.{secrets.token_hex(4)}.part"
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id_for(ident), send_properties=False)
    try:
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        rec.save(tmp, default_blueprint=blueprint)
        rec.send_recording_name(ident)  # shown in the viewer; deterministic, unlike a start time
        send(rec)
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
