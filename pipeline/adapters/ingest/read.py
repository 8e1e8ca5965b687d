"""Entry points :func:`read_recording` / :func:`read_recordings`: every file's chunks into one table."""

from __future__ import annotations

import zoneinfo
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import polars as pl

from pipeline.adapters.ingest import csv_reader as ingest_csv
from pipeline.adapters.ingest import mcap_reader as ingest_mcap
from pipeline.adapters.ingest.canonical import assemble
from pipeline.adapters.ingest.options import (
    CsvOptions,
    LAYOUTS,
    Layout,
    McapOptions,
    ON_TRUNCATED,
    coerce_options,
)
from pipeline.adapters.ingest.report import IngestReport, ReaderMeta
from pipeline.adapters.ingest.sink import ChunkSink, build_report
from pipeline.errors import ConfigError, IngestError
from pipeline.progress import Tick, silent


def _validate_common(layout: str, timezone: str, on_truncated: str) -> None:
    if layout not in LAYOUTS:
        raise ConfigError(f"layout={layout!r} is not one of {list(LAYOUTS)}")
    if on_truncated not in ON_TRUNCATED:
        raise ConfigError(f"on_truncated={on_truncated!r} is not one of {list(ON_TRUNCATED)}")
    try:
        zoneinfo.ZoneInfo(timezone)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError) as exc:
        raise ConfigError(
            f"timezone={timezone!r} is not an IANA time zone (e.g. 'UTC', "
            f"'Europe/Berlin', 'America/Chicago', 'Etc/GMT+6'); set source.timezone"
        ) from exc


_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _is_mcap(path: Path) -> bool:
    if path.suffix.lower() == ".mcap":
        return True
    with path.open("rb") as f:
        return f.read(len(_MCAP_MAGIC)) == _MCAP_MAGIC


def read_recording(
    path: str | Path,
    *,
    layout: Layout = "auto",
    timezone: str = "UTC",
    tags: Sequence[str] | None = None,
    csv: CsvOptions | Mapping[str, Any] | None = None,
    mcap: McapOptions | Mapping[str, Any] | None = None,
    on_truncated: Literal["error", "warn"] = "error",
    tick: Tick = silent,
) -> tuple[pl.DataFrame, IngestReport]:
    """Read one historian CSV or MCAP recording into the canonical table.

    Parameters
    ----------
    path : str or Path
        A ``.csv`` (or any text export) or ``.mcap`` file.
    layout : {"auto", "long", "wide", "mcap"}
        ``"auto"`` picks MCAP by extension or magic bytes, else detects long vs wide CSV.
    timezone : str
        IANA zone of naive timestamps (CSV local times, naive ISO strings in MCAP).
        The repeated autumn hour is resolved by order of appearance per tag; a naive
        time inside the skipped spring hour is an error.
    tags : sequence of str or None
        Read only these tags; None reads all. Absent tags are an error.
    csv : CsvOptions or mapping or None
        Overrides of CSV detection.
    mcap : McapOptions or mapping or None
        Where samples are in MCAP messages.
    on_truncated : {"error", "warn"}
        A truncated or corrupt MCAP file raises, or (``"warn"``) yields its readable
        part with a warning in the report.
    tick : callable (done, total), optional
        Called as the file is read, in bytes (:mod:`pipeline.progress`).

    Returns
    -------
    table : polars.DataFrame
        Canonical table (see module docstring), sorted by signal then time.
    report : IngestReport

    Raises
    ------
    IngestError
        Missing/empty file, undecodable text, no time column, unparseable timestamps,
        absent tags, corrupt MCAP.
    ConfigError
        Invalid arguments (layout, zone, options).
    """
    _validate_common(layout, timezone, on_truncated)
    csv_opts: CsvOptions = coerce_options(csv, CsvOptions, "csv")
    mcap_opts: McapOptions = coerce_options(mcap, McapOptions, "mcap")
    return _read_all([_check_path(path)], layout=layout, timezone=timezone, tags=tags, csv=csv_opts,
                     mcap=mcap_opts, on_truncated=on_truncated, tick=tick)


def _check_path(path: str | Path) -> Path:
    p = Path(path)
    if not p.exists():
        raise IngestError(
            f"recording {str(p)!r} does not exist; check source.path in the job YAML "
            f"(relative paths are relative to the YAML file)"
        )
    if not p.is_file():
        raise IngestError(f"recording {str(p)!r} is not a file (a directory?); give a file path")
    if p.stat().st_size == 0:
        raise IngestError(f"recording {str(p)!r} is empty (0 bytes); re-run the export")
    return p


def _read_all(
    paths: Sequence[Path],
    *,
    layout: str,
    timezone: str,
    tags: Sequence[str] | None,
    csv: CsvOptions,
    mcap: McapOptions,
    on_truncated: str,
    tick: Tick = silent,
) -> tuple[pl.DataFrame, IngestReport]:
    """Every file's chunks into one sink, assembled once (no per-file tables)."""
    tag_list = None if tags is None else list(tags)
    sink = ChunkSink(sizes=[p.stat().st_size for p in paths], tick=tick)
    metas: list[ReaderMeta] = []
    unknown_warning: dict[int, str] = {}
    for i, p in enumerate(paths):
        sink.file = i
        if layout == "mcap" or (layout == "auto" and _is_mcap(p)):
            sink.quality_map = None
            meta = ingest_mcap.read_mcap_raw(
                p, options=mcap, timezone=timezone, tags=tag_list, on_truncated=on_truncated,
                sink=sink,
            )
        else:
            sink.quality_map = csv.quality_map
            meta = ingest_csv.read_csv_raw(
                p, layout=layout, options=csv, timezone=timezone, tags=tag_list, sink=sink
            )
        metas.append(meta)
        sink.at(1.0)
        if i in sink.unknown:
            unknown_warning[i] = (
                f"{meta.path}: unrecognised quality flags {sorted(sink.unknown[i])[:10]} "
                f"treated as suspect; map them with source.csv.quality_map in the job YAML"
            )
    assembled = assemble(sink.chunks)
    sink.chunks.clear()
    dst: dict[str, int] = {}
    units: dict[str, str] = {}
    descriptions: dict[str, str] = {}
    for m in metas:
        for k, v in m.dst_resolved.items():
            dst[k] = dst.get(k, 0) + v
        for k, v in m.units.items():
            units.setdefault(k, v)
        for k, v in m.descriptions.items():
            descriptions.setdefault(k, v)

    def _join(values: Iterable[str | None]) -> str | None:
        uniq = list(dict.fromkeys(v for v in values if v is not None))
        return "+".join(uniq) if uniq else None

    warnings = []
    for i, m in enumerate(metas):
        warnings.extend(m.warnings)
        if i in unknown_warning:
            warnings.append(unknown_warning[i])
    report = build_report(
        assembled.table,
        runs=(assembled.names, assembled.lengths),
        paths=tuple(m.path for m in metas),
        layout=_join(m.layout for m in metas) or "",
        encoding=_join(m.encoding for m in metas) or "",
        separator=_join(m.separator for m in metas),
        decimal=_join(m.decimal for m in metas),
        time_format=_join(m.time_format for m in metas),
        header_rows=max(m.header_rows for m in metas),
        rows=None,
        backward=assembled.backward,
        dups=assembled.dups,
        dropped=sink.dropped,
        dst=dst,
        units=units,
        descriptions=descriptions,
        warnings=warnings,
        truncated=any(m.truncated for m in metas),
        timezone=timezone,
    )
    return assembled.table, report


def read_recordings(
    paths: Sequence[str | Path],
    **kwargs: Any,
) -> tuple[pl.DataFrame, IngestReport]:
    """Read several recordings (same options) and concatenate them.

    Parameters
    ----------
    paths : sequence of str or Path
        Files in order; where two files hold the same (tag, time), the later file wins
        and the row counts as a duplicate removed.
    **kwargs
        Passed to :func:`read_recording` (``layout``, ``timezone``, ``tags``, ``csv``,
        ``mcap``, ``on_truncated``, ``tick``). With ``tags``, each file must hold
        every tag; ``tick`` counts bytes over all files.

    Returns
    -------
    table : polars.DataFrame
        Canonical table over all files.
    report : IngestReport
        Merged: counts summed per signal, final quality counts recomputed.
    """
    paths = list(paths)
    if not paths:
        raise IngestError("read_recordings got no paths; check the glob in source.path")
    layout = kwargs.get("layout", "auto")
    timezone = kwargs.get("timezone", "UTC")
    on_truncated = kwargs.get("on_truncated", "error")
    unknown = sorted(set(kwargs) - {"layout", "timezone", "tags", "csv", "mcap", "on_truncated",
                                    "tick"})
    if unknown:
        raise TypeError(f"read_recordings got unexpected keyword(s) {unknown}")
    _validate_common(layout, timezone, on_truncated)
    return _read_all(
        [_check_path(p) for p in paths],
        layout=layout,
        timezone=timezone,
        tags=kwargs.get("tags"),
        csv=coerce_options(kwargs.get("csv"), CsvOptions, "csv"),
        mcap=coerce_options(kwargs.get("mcap"), McapOptions, "mcap"),
        on_truncated=on_truncated,
        tick=kwargs.get("tick", silent),
    )
