"""What ingestion found: per-signal counts (:class:`IngestReport`) and reader metadata."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from pipeline.errors import IngestError


@dataclass(frozen=True)
class SignalIngestStats:
    """What happened to one signal during ingestion (counts are samples/rows).

    Attributes
    ----------
    signal : str
        The tag.
    rows : int
        Rows read for this tag, before dropping empty cells and duplicates.
    good, suspect, bad : int
        Samples of each quality in the canonical table.
    bad_by_state : dict of str to int
        Bad samples by state (text state or raw flag), e.g. ``{"Bad Input": 3}``.
    suspect_by_state : dict of str to int
        Suspect samples by raw flag.
    duplicates_removed : int
        Rows dropped because a later row had the same tag and time (the last is kept).
    out_of_order : int
        Rows whose time was earlier than the previous row of the same tag in the file
        (sorted into place).
    dst_ambiguous_resolved : int
        Naive local timestamps inside a repeated (autumn) hour, resolved by order of
        appearance.
    empty_dropped : int
        Rows with an empty value cell and no bad flag (no sample at that time).
    unit, description : str or None
        From the header rows of a wide export, when present.
    """

    signal: str
    rows: int
    good: int
    suspect: int
    bad: int
    bad_by_state: dict[str, int] = field(default_factory=dict)
    suspect_by_state: dict[str, int] = field(default_factory=dict)
    duplicates_removed: int = 0
    out_of_order: int = 0
    dst_ambiguous_resolved: int = 0
    empty_dropped: int = 0
    unit: str | None = None
    description: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class IngestReport:
    """What ingestion found: layout, encoding, formats, per-signal counts, warnings.

    Attributes
    ----------
    paths : tuple of str
        Files read, in order (later files win duplicate samples).
    layout : str
        ``"long"``, ``"wide"``, ``"mcap"`` (or several joined by ``"+"``).
    encoding : str
        Text encoding (CSV) or message encodings (MCAP), ``"+"``-joined when several.
    separator, decimal : str or None
        CSV field separator and decimal mark.
    time_format : str or None
        The timestamp format used (strptime syntax, ``"epoch_s"`` or ``"mcap"``).
    timezone : str
        Zone of naive timestamps.
    header_rows : int
        Header rows of a CSV (0 for headerless long files and MCAP).
    signals : tuple of SignalIngestStats
        One entry per signal, sorted by name.
    warnings : tuple of str
        Decoding warnings (unknown quality flags, skipped channels, truncation, DST
        resolution without a visible clock roll-back, ...).
    truncated : bool
        An MCAP file was cut short and only its readable part was used.
    """

    paths: tuple[str, ...]
    layout: str
    encoding: str
    separator: str | None
    decimal: str | None
    time_format: str | None
    timezone: str
    header_rows: int
    signals: tuple[SignalIngestStats, ...]
    warnings: tuple[str, ...] = ()
    truncated: bool = False

    @property
    def signal_names(self) -> tuple[str, ...]:
        """Signal names, sorted."""
        return tuple(s.signal for s in self.signals)

    def signal(self, name: str) -> SignalIngestStats:
        """Statistics of one signal.

        Parameters
        ----------
        name : str
            The signal (tag) name.

        Raises
        ------
        IngestError
            When ``name`` was not ingested.
        """
        for s in self.signals:
            if s.signal == name:
                return s
        raise IngestError(
            f"signal {name!r} is not in the ingest report; it has {list(self.signal_names)}"
        )

    def masked_summary(self) -> dict[str, dict[str, int]]:
        """Per signal, the samples that are not good and why.

        Returns
        -------
        dict
            ``{signal: {"bad:<state>": n, "suspect:<flag>": n, "duplicates_removed": n,
            "empty_dropped": n}}`` with zero counts left out.
        """
        out: dict[str, dict[str, int]] = {}
        for s in self.signals:
            d = {f"bad:{k}": v for k, v in s.bad_by_state.items()}
            d.update({f"suspect:{k}": v for k, v in s.suspect_by_state.items()})
            if s.duplicates_removed:
                d["duplicates_removed"] = s.duplicates_removed
            if s.empty_dropped:
                d["empty_dropped"] = s.empty_dropped
            out[s.signal] = d
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (signals as a list of dicts)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["paths"] = list(self.paths)
        d["warnings"] = list(self.warnings)
        d["signals"] = [s.to_dict() for s in self.signals]
        return d


@dataclass(frozen=True)
class ReaderMeta:
    """What a format reader hands to the canonicaliser besides the pre-table."""

    path: str
    layout: str
    encoding: str
    separator: str | None = None
    decimal: str | None = None
    time_format: str | None = None
    header_rows: int = 0
    dst_resolved: dict[str, int] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    descriptions: dict[str, str] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    truncated: bool = False
