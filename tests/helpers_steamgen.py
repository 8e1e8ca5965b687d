"""The steam-generator record (DaISy 98-003) as historian exports, for round-trip tests.

``steamgen.dat`` (shared data, read-only): 9,600 rows every 3 s (8 h), 9 whitespace
columns: time, fuel, air, reference level, load disturbance, drum pressure, excess O2,
drum level, steam flow.

The record is placed at local 2023-11-05 00:30 America/Chicago, so the repeated hour
(01:00-02:00 local: CDT then CST) lies inside it, and written as

* a PI-style long CSV with exception reporting, jittered timestamps and digital states
  (:func:`steamgen_to_long_csv`);
* a JSON MCAP (:func:`steamgen_to_mcap`).

Used by ``tests/adapters/test_ingest_csv.py`` / ``tests/adapters/test_ingest_mcap.py`` and available to
other tests (e.g. comparing step responses estimated from the round-tripped data).
"""

from __future__ import annotations

import datetime as _dt
import zoneinfo
from pathlib import Path

import numpy as np
import pytest

from pipeline.adapters.historian_writer import WrittenRecording, write_json_mcap, write_long_csv

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STEAMGEN_FILE = SHARED_DATA / "steamgen.dat"

#: Column name → historian tag, in file order (columns 2..9).
STEAMGEN_TAGS: dict[str, str] = {
    "fuel": "SG.FUEL_FLOW",
    "air": "SG.AIR_FLOW",
    "ref_level": "SG.LEVEL_REF",
    "load": "SG.LOAD_DIST",
    "drum_pressure": "SG.DRUM_PRESS",
    "o2": "SG.EXCESS_O2",
    "drum_level": "SG.DRUM_LEVEL",
    "steam_flow": "SG.STEAM_FLOW",
}
STEAMGEN_DT_S = 3.0
STEAMGEN_ZONE = "America/Chicago"
STEAMGEN_START_LOCAL = _dt.datetime(2023, 11, 5, 0, 30, 0)

#: Digital states injected into the CSV: tag → [(sample index, state text)]. Index 1200
#: (06:30 UTC = 01:30 CDT) is in the first pass of the repeated hour, 2400 (07:30 UTC =
#: 01:30 CST) in the second; 4000-4002 is a three-sample outage.
STEAMGEN_STATES: dict[str, list[tuple[int, str]]] = {
    "SG.FUEL_FLOW": [(500, "Bad Input")],
    "SG.DRUM_PRESS": [
        (1200, "I/O Timeout"),
        (4000, "Shutdown"),
        (4001, "Shutdown"),
        (4002, "Shutdown"),
    ],
    "SG.EXCESS_O2": [(2400, "No Data")],
    "SG.STEAM_FLOW": [(7000, "#N/A")],
}


def require_steamgen() -> Path:
    """Path of steamgen.dat, or skip the test when the shared data folder is absent."""
    if not STEAMGEN_FILE.exists():
        pytest.skip(
            f"shared data not present: {STEAMGEN_FILE} (clone with ../shared beside the repo)"
        )
    return STEAMGEN_FILE


def steamgen_start_utc() -> np.datetime64:
    """The first sample instant, UTC (local 00:30 CDT = 05:30 UTC)."""
    local = STEAMGEN_START_LOCAL.replace(tzinfo=zoneinfo.ZoneInfo(STEAMGEN_ZONE))
    utc = local.astimezone(_dt.UTC).replace(tzinfo=None)
    return np.datetime64(utc, "us")


def load_steamgen() -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Regular record: times (datetime64[us] UTC, shape (9600,)) and tag → values.

    Returns
    -------
    times_utc : numpy.ndarray of datetime64[us]
    values : dict of str to numpy.ndarray, each shape (9600,)
        Keyed by the tags of :data:`STEAMGEN_TAGS`, in column order.
    """
    data = np.loadtxt(require_steamgen())
    if data.shape[1] != 9:
        raise ValueError(f"steamgen.dat: expected 9 columns, got {data.shape[1]}")
    offsets_us = np.round(data[:, 0] * 1e6).astype(np.int64)
    times = steamgen_start_utc() + offsets_us.astype("timedelta64[us]")
    values = {tag: data[:, j + 1].copy() for j, tag in enumerate(STEAMGEN_TAGS.values())}
    return times, values


def steamgen_to_long_csv(
    path: Path,
    *,
    seed: int = 20231105,
    states: dict[str, list[tuple[int, str]]] | None = None,
    **kwargs: object,
) -> WrittenRecording:
    """Write steamgen as a PI-style long CSV in local Chicago time.

    Exception reporting with the writer's default deadband (a quarter of each tag's
    median absolute change), timestamp jitter up to 0.3 s, the states of
    :data:`STEAMGEN_STATES` (unless ``states`` is given). ``kwargs`` go to
    :func:`~pipeline.adapters.historian_writer.write_long_csv`.
    """
    times, values = load_steamgen()
    return write_long_csv(
        path,
        times,
        values,
        timezone=STEAMGEN_ZONE,
        irregular=np.random.default_rng(seed),
        states=STEAMGEN_STATES if states is None else states,
        **kwargs,  # type: ignore[arg-type]
    )


def steamgen_to_mcap(
    path: Path, *, samples_per_message: int = 50, **kwargs: object
) -> WrittenRecording:
    """Write steamgen as a JSON MCAP (one topic per tag, regular samples, no states)."""
    times, values = load_steamgen()
    return write_json_mcap(
        path, times, values, samples_per_message=samples_per_message, **kwargs  # type: ignore[arg-type]
    )
