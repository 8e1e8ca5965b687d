"""Reader options (``source.csv`` / ``source.mcap`` in the job YAML) and chunk sizes."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, Literal

from pipeline.errors import ConfigError


ON_TRUNCATED = ("error", "warn")


LAYOUTS = ("auto", "long", "wide", "mcap")


Layout = Literal["auto", "long", "wide", "mcap"]


#: MCAP messages per channel decoded at a time (the payloads of one batch per channel
#: are held, not the file's).
CHUNK_MESSAGES = 200_000


#: Cells (rows x fields) a CSV reader parses at a time — a million rows of a 4-column
#: long export (module note in ingest_csv): the text of a chunk is freed once its rows
#: are compact, so memory follows the parsed data, not the text.
CHUNK_CELLS = 4_000_000


@dataclass(frozen=True)
class CsvOptions:
    """Overrides for historian-CSV detection; every ``None`` means "detect".

    Parameters
    ----------
    separator : str or None
        Field separator (``","``, ``";"``, ``"\\t"``, ``"|"``). Detected from the first
        lines: the candidate with the largest consistent count per line.
    decimal : {".", ","} or None
        Decimal mark. Detected as ``","`` when the separator is not a comma and numbers
        like ``12,5`` appear.
    encoding : str or None
        A Python codec name. Detected from the byte-order mark (UTF-8, UTF-16 LE/BE);
        without one the file must be valid UTF-8.
    skip_lines : int
        Lines to skip before the header (export banners).
    tag_column, time_column, value_column, quality_column : str or None
        Long layout: header names of the tag, time, value and quality/status columns.
        Detected from common names (tag/name/pointname/TagName, time/timestamp/datetime,
        value/PV, status/quality). ``quality_column=""`` says there is none.
    header_rows : int or None
        Wide layout: number of header rows before the first data row. Detected as the
        rows before the first one whose time cell parses as a timestamp.
    tag_row : int
        Wide layout: the header row (0-based) that names the tags.
    unit_row, description_row : int or None
        Wide layout: header rows holding engineering units / descriptions. Detected as
        the last (units) and second-to-last (descriptions) header rows when there are
        enough of them and the cell is not the tag name again.
    time_format : str or None
        A strptime format (polars/chrono syntax, e.g. ``"%m-%d-%Y %H:%M:%S"``), or
        ``"epoch_s"`` for Unix seconds. Detected from a list of common formats.
    quality_map : mapping of str to {"good", "suspect", "bad"} or None
        Extra quality flags (matched case-insensitively, stripped) that take precedence
        over the built-in ones.
    """

    separator: str | None = None
    decimal: str | None = None
    encoding: str | None = None
    skip_lines: int = 0
    tag_column: str | None = None
    time_column: str | None = None
    value_column: str | None = None
    quality_column: str | None = None
    header_rows: int | None = None
    tag_row: int = 0
    unit_row: int | None = None
    description_row: int | None = None
    time_format: str | None = None
    quality_map: Mapping[str, str] | None = None


@dataclass(frozen=True)
class McapOptions:
    """How samples are found in MCAP messages.

    Parameters
    ----------
    topics : sequence of str or None
        Topics to read; ``None`` reads every topic with a supported encoding.
    time_field : str or None
        Dotted path of the sample time in a message (``"t"``, ``"header.stamp"``).
        Numbers are Unix time in ``time_unit``; strings are ISO 8601 (naive ones are in
        the ``timezone`` given to :func:`read_recording`); objects with ``sec`` /
        ``nanosec`` (ROS 2) or ``seconds`` / ``nanos`` (protobuf Timestamp) are read as
        such. When the field is absent (or ``None``) the message ``log_time`` is used.
    value_field : str
        Dotted path of the value (``"value"``; ``"data"`` for ``std_msgs/Float64``).
    quality_field : str or None
        Dotted path of a quality flag (``"good"``/``"bad"``/``"suspect"``, ``G``/``B``,
        or an OPC numeric quality); absent means good.
    tag_field : str or None
        Field naming the tag. ``None``: the tag is the topic without ``topic_prefix``.
        Inside ``samples_field`` records the default ``"tag"`` is used when present.
    samples_field : str
        Field holding a list of sample records (``{"samples": [{"tag", "t", "value"},
        ...]}``); used when present in a JSON message.
    time_unit : {"s", "ms", "us", "ns"}
        Unit of numeric times.
    topic_prefix : str
        Stripped from topics to form tags (``"/FIC-101.PV"`` → ``"FIC-101.PV"``).
    validate_crcs : bool
        Check chunk CRCs while reading (catches corrupt chunks; costs ~5 %).
    """

    topics: Sequence[str] | None = None
    time_field: str | None = "t"
    value_field: str = "value"
    quality_field: str | None = "quality"
    tag_field: str | None = None
    samples_field: str = "samples"
    time_unit: Literal["s", "ms", "us", "ns"] = "s"
    topic_prefix: str = "/"
    validate_crcs: bool = True


def coerce_options(value: Any, cls: type, name: str) -> Any:
    """Accept an options dataclass, a mapping of its fields, or None.

    Parameters
    ----------
    value : cls, mapping or None
        The options as given; None gives the defaults.
    cls : type
        :class:`CsvOptions` or :class:`McapOptions`.
    name : str
        The argument's name for the error message (``csv`` / ``mcap``).
    """
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise ConfigError(
                f"{name} options: unknown key(s) {unknown}; allowed keys are {sorted(known)}"
            )
        return cls(**value)
    raise ConfigError(
        f"{name} options must be a {cls.__name__} or a mapping, got {type(value).__name__}"
    )
