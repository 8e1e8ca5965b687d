"""Historian quality flags (PI, OPC, text) → good / suspect / bad."""

from __future__ import annotations

import math
from collections.abc import Mapping

import polars as pl

from pipeline.adapters.ingest.canonical import BAD, GOOD, QUALITY_DTYPE, SUSPECT
from pipeline.adapters.ingest.timestamps import sample_of
from pipeline.errors import ConfigError


GOOD_FLAGS = frozenset(
    {"g", "good", "ok", "valid", "normal", "annotated", "true", "good_local_override"}
)
BAD_FLAGS = frozenset(
    {
        "b", "bad", "invalid", "error", "false", "fail", "failed", "bad input",
        "bad_input", "i/o timeout", "io timeout", "shutdown", "no data", "nodata",
        "comm fail", "comm failure", "scan off", "scan timeout", "calc failed",
        "out of serv", "out of service", "not connected", "configure", "pt created",
        "over range", "under range", "#n/a", "n/a", "na", "nan",
    }
)  # fmt: skip
SUSPECT_FLAGS = frozenset(
    {"s", "suspect", "u", "uncertain", "q", "questionable", "substituted", "subst",
     "manual", "estimated", "stale", "last known value"}
)  # fmt: skip


def quality_of_flag(flag: str | int | float | None) -> str | None:
    """Map one raw quality flag to ``"good"``, ``"suspect"`` or ``"bad"``.

    Parameters
    ----------
    flag : str, int, float or None
        ``G``/``B``/``S``, ``Good``/``Bad``/``Suspect``/``Questionable``/..., PI digital
        states, or an OPC DA numeric quality (``quality & 0xC0``: ``0xC0`` good,
        ``0x40`` uncertain → suspect, ``0x00`` and ``0x80`` bad), also as text
        (``"192"``, ``"0xC0"``). Empty or None means good (no flag given).

    Returns
    -------
    str or None
        The quality, or None when the flag is not recognised.
    """
    if flag is None:
        return GOOD
    if isinstance(flag, bool):
        return GOOD if flag else BAD
    if isinstance(flag, (int, float)):
        if isinstance(flag, float) and not (math.isfinite(flag) and flag.is_integer()):
            return None
        return _opc_quality(int(flag))
    text = str(flag).strip().lower()
    if text == "":
        return GOOD
    if text in GOOD_FLAGS:
        return GOOD
    if text in BAD_FLAGS:
        return BAD
    if text in SUSPECT_FLAGS:
        return SUSPECT
    try:
        number = int(text, 16) if text.startswith("0x") else float(text)
    except ValueError:
        return None
    if isinstance(number, float) and not (math.isfinite(number) and number.is_integer()):
        return None
    return _opc_quality(int(number))


def _opc_quality(code: int) -> str | None:
    # OPC DA quality word: bits 7..6 are the major quality (11 good, 01 uncertain,
    # 00 bad, 10 not used → treat as bad).
    if code < 0 or code > 0xFFFF:
        return None
    major = code & 0xC0
    return {0xC0: GOOD, 0x40: SUSPECT}.get(major, BAD)


def map_flags(
    flags: pl.Series, quality_map: Mapping[str, str] | None
) -> tuple[pl.Series, list[str]]:
    """Vectorised flag → quality: map the (few) distinct flags in Python, then replace.

    Returns the quality series (good where the flag is null) and the unrecognised flags
    (mapped to suspect).

    Parameters
    ----------
    flags : polars.Series of str
        Raw quality flags (PI status text, OPC codes, ``B``/``G``...); null: no flag.
    quality_map : mapping of str -> {"good", "suspect", "bad"} or None
        ``source.csv.quality_map``: the site's own flags, tried before the built-in ones.
    """
    extra = {}
    if quality_map:
        for k, v in quality_map.items():
            if v not in (GOOD, SUSPECT, BAD):
                raise ConfigError(
                    f"quality_map[{k!r}] = {v!r}; allowed values are 'good', 'suspect', 'bad'"
                )
            extra[str(k).strip().lower()] = v
    if flags.dtype == pl.Categorical:
        distinct = [str(f) for f in flags.unique().to_list() if f is not None]
    else:
        if flags.dtype != pl.String:
            flags = flags.cast(pl.String)
        # The distinct flags of a sample usually cover the column; counting equal cells
        # per sampled flag checks that with a comparison each (no hashing of every row).
        sample = sample_of(flags).unique().drop_nulls().to_list()
        covered = sum(int((flags == f).sum()) for f in sample) if len(sample) <= 16 else -1
        if sample and covered + flags.null_count() == len(flags):
            distinct = sample
        else:
            distinct = flags.drop_nulls().unique().to_list()
    mapping: dict[str, str] = {}
    unknown: list[str] = []
    for f in distinct:
        q = extra.get(f.strip().lower()) or quality_of_flag(f)
        if q is None:
            unknown.append(f)
            q = SUSPECT
        mapping[f] = q
    not_good = {f: q for f, q in mapping.items() if q != GOOD}
    quality = pl.repeat(GOOD, len(flags), dtype=QUALITY_DTYPE, eager=True)
    if len(not_good) > 16:
        # Many distinct codes (e.g. OPC numbers): one hashed pass beats a pass per code.
        mapped = flags.cast(pl.String).replace_strict(mapping, default=None,
                                                      return_dtype=QUALITY_DTYPE)
        return mapped.fill_null(GOOD), sorted(unknown)
    for f, q in not_good.items():
        idx = (flags == f).arg_true()
        if len(idx):
            quality = quality.scatter(idx, q)
    return quality, sorted(unknown)
