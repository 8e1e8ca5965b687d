"""What every recording shares: ids, timelines, colours, view ranges and legends, units,
bulk series, writing the file."""

from __future__ import annotations

import contextlib
import os
import secrets
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb

from pipeline.errors import ConfigError


APPLICATION_ID = "plantdyn"
#: Timeline names.  ``elapsed`` (a duration, the timeline a recording opens on) carries
#: every estimation series: seconds after the step for step responses, seconds since the
#: first stored sample for signals and residuals.  ``time`` is the same samples' UTC clock
#: time, ``run_time`` the creation time of earlier runs (trends), ``time_s`` the seconds
#: since the first sample of a discrepancy record.  A Rerun 0.41 time-series view plots
#: against the time panel's active timeline only (there is no per-view timeline), so what
#: a tab shows by default must share the timeline it opens on.
TIMELINES = {"elapsed": "elapsed", "signals": "time", "trends": "run_time", "discrepancy": "time_s"}
# Fixed namespace: recording ids are uuid5(namespace, "<job>/<run_id>"), stable across
# processes and machines (uuid5 of a URL-namespace name, as the first version did).
_NAMESPACE = uuid.NAMESPACE_URL
WINDOW_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                   (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127)]
ALL_COLOUR = (240, 240, 240)
#: The ±2σ band: a dense fill (drawn first, under every line) and its edges.
BAND_FILL_COLOUR = (64, 96, 96)
BAND_EDGE_COLOUR = (120, 170, 170)
MASKED_COLOUR = (220, 0, 0)
#: Signals by role (raw and conditioned alike) and residuals.
ROLE_COLOURS = {"input": (86, 180, 233), "output": (230, 159, 0), "instrument": (0, 158, 115)}
RESIDUAL_COLOUR = (204, 121, 167)
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
    """TimeSeriesView arguments: all data on ``timeline``, x axis over the whole timeline
    (design.md: without an explicit range the view shows ±30 s around the time cursor).

    Parameters
    ----------
    timeline : str
        The view's timeline (:data:`TIMELINES`).
    """
    return x_range([timeline])


def x_range(timelines: Sequence[str], start_s: float | None = None, end_s: float | None = None) -> dict[str, Any]:
    """TimeSeriesView arguments: all data on each of ``timelines``; the x axis spans
    ``start_s``..``end_s`` (a duration timeline's seconds) or, when they are None, the
    whole active timeline.

    An explicit span keeps a short series (a step response with N_p = 3) from being a
    sliver at the left of a timeline that also holds hours of signals.  It is one range
    for every timeline (Rerun 0.41 keeps a single x range per view), so only views whose
    data live on one timeline get one.

    Parameters
    ----------
    timelines : sequence of str
        The timelines the view's data are on.
    start_s, end_s : float, optional
        The x span in seconds on a duration timeline.
    """
    inf = rrb.TimeRangeBoundary.infinite()
    if start_s is None or end_s is None:
        start, end = inf, inf
    else:
        start = rrb.TimeRangeBoundary.absolute(seconds=float(start_s))
        end = rrb.TimeRangeBoundary.absolute(seconds=float(end_s))
    return {"time_ranges": [rrb.VisibleTimeRange(t, start=inf, end=inf) for t in timelines],
            "axis_x": rrb.TimeAxis(view_range=rr.TimeRange(start=start, end=end))}


def legend(corner: str | None) -> rrb.PlotLegend:
    """A plot legend in ``corner`` (``"RightTop"``, ``"RightBottom"``, ...), or hidden.

    Parameters
    ----------
    corner : str or None
        Corner of the plot; None hides the legend.
    """
    return rrb.PlotLegend(corner, visible=corner is not None)


def with_unit(name: str, units: Mapping[str, str]) -> str:
    """``name [unit]`` when the job gives ``name`` a unit, else ``name``.

    Parameters
    ----------
    name : str
        A signal name.
    units : mapping of str to str
        Units by signal name (``signals.<group>.<name>.unit`` of the job config).
    """
    unit = units.get(name)
    return f"{name} [{unit}]" if unit else str(name)


def units_of(config: Mapping[str, Any] | None) -> dict[str, str]:
    """Units by signal name from a resolved job config (``signals.<inputs|outputs|
    instruments>.<name>.unit``); empty and ``-`` units are left out.

    Parameters
    ----------
    config : mapping, optional
        The resolved job config, as ``manifest.json`` stores it under ``config``.
    """
    signals = config.get("signals") if isinstance(config, Mapping) else None
    units: dict[str, str] = {}
    if not isinstance(signals, Mapping):
        return units
    for group in ("inputs", "outputs", "instruments"):
        entries = signals.get(group)
        if not isinstance(entries, Mapping):
            continue
        for name, spec in entries.items():
            unit = spec.get("unit") if isinstance(spec, Mapping) else None
            if isinstance(unit, str) and unit.strip() and unit.strip() != "-":
                units[str(name)] = unit.strip()
    return units


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


def send_series(rec: rr.RecordingStream, path: str, index: rr.TimeColumn | Sequence[rr.TimeColumn],
                values: np.ndarray, *, name: str, colour: tuple[int, int, int] | None = None,
                width: float = 1.5, aggregation: str | None = None) -> None:
    """Log one series in bulk (``send_columns``: ~30× faster than a log call per row).

    Parameters
    ----------
    rec : rerun.RecordingStream
        The recording.
    path : str
        Entity path.
    index : rerun.TimeColumn or sequence of them
        The samples' times on the series' timeline(s), one per value.
    values : ndarray (N,)
        The values (NaN: a gap).
    name : str
        Legend name.
    colour : (int, int, int), optional
        RGB; None lets the viewer choose.
    width : float
        Line width.
    aggregation : str, optional
        ``SeriesLines`` aggregation policy (``"Off"`` keeps every point: fills, vertical
        lines); None: the viewer's default.
    """
    style = rr.SeriesLines(names=name, widths=width,
                           **({"colors": [colour]} if colour is not None else {}),
                           **({"aggregation_policy": aggregation} if aggregation is not None else {}))
    rec.log(path, style, static=True, strict=True)
    indexes = [index] if isinstance(index, rr.TimeColumn) else list(index)
    rec.send_columns(path, indexes=indexes, columns=rr.Scalars.columns(scalars=values), strict=True)


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
    except BaseException as exc:
        with contextlib.suppress(Exception):
            rec.disconnect()
        failed = _writer_failure(exc, tmp)  # before the unlink frees the partial file
        tmp.unlink(missing_ok=True)
        if failed is not None:
            raise failed from None
        raise
    return out


#: Below this many free bytes beside a recording whose writer stopped, the disk was full.
_FULL_BELOW_BYTES = 4 << 20


def _writer_failure(exc: BaseException, tmp: Path) -> OSError | None:
    """What a failed Rerun write means for the store: its file writer stops with a bare
    ``RuntimeError("File-writer thread shut down prematurely")`` (the OS error goes to its
    log only), so a nearly empty disk beside the file is read as ``ENOSPC`` and any other
    stop as an ``EIO`` :class:`~pipeline.errors.StorageError`; other errors are not
    changed (None)."""
    import errno

    from pipeline.errors import StorageError

    if not isinstance(exc, RuntimeError) or "writer" not in str(exc).lower():
        return None
    try:
        st = os.statvfs(tmp.parent)
        free = st.f_bavail * st.f_frsize
    except OSError:
        free = None
    if free is not None and free < _FULL_BELOW_BYTES:
        return OSError(errno.ENOSPC, "No space left on device", str(tmp.parent))
    return StorageError(f"storage {tmp.parent}: the Rerun writer stopped ({exc}) while writing "
                        "the recording; check the disk, or set rerun: {enabled: false} in the "
                        "job — nothing was written")


def make_blueprint(root: Any, timeline: str, *, time_selection: Any = None) -> rrb.Blueprint:
    """The saved default blueprint: ``root`` fills the window (blueprint, selection and
    time panels collapsed: one click on the icons at the top right, or the bar at the
    bottom, opens them), the time panel on ``timeline``, paused.

    Parameters
    ----------
    root : blueprint container
        The viewport's root (a Tabs container).
    timeline : str
        The active timeline.
    time_selection : rerun AbsoluteTimeRange, optional
        A selected time range in the time panel.
    """
    panel = rrb.TimePanel(timeline=timeline, play_state="paused", state="collapsed", time_selection=time_selection)
    return rrb.Blueprint(root, rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         panel, collapse_panels=False)


def durations(seconds: np.ndarray | Sequence[float]) -> np.ndarray:
    """Seconds as timedelta64[ns], rounded to the nearest ns (the SDK truncates floats).

    Parameters
    ----------
    seconds : array-like of float
        Durations in seconds.
    """
    return np.rint(np.asarray(seconds, dtype=np.float64) * 1e9).astype(np.int64).astype("timedelta64[ns]")
