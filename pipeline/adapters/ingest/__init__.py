"""Ingestion: historian CSV (long / wide) and MCAP → one canonical table.

Every reader ends in the same *canonical table* (a polars DataFrame), sorted by
``signal`` then ``time``, one row per (signal, time):

========  ========================  =================================================
column    dtype                     meaning
========  ========================  =================================================
time      Datetime(us, "UTC")       sample instant, UTC
signal    Categorical               the historian tag (or MCAP topic / tag field)
value     Float64                   the number; null where ``quality == "bad"``
quality   Enum(good, suspect, bad)  ``"good"``, ``"suspect"`` or ``"bad"``
state     String                    null for good samples; otherwise the text state
                                    ("Bad Input", "I/O Timeout", "#N/A", ...) or the
                                    raw quality flag ("B", "64", "Questionable")
========  ========================  =================================================

and an :class:`IngestReport` that says what was found, what was masked and why
(per-signal counts), so ``checks.json`` can report data quality.

The modules, in the order data flows through them:

* :mod:`.options` — reader options (``source.csv`` / ``source.mcap``) and chunk sizes;
* :mod:`.csv_reader` — historian CSV, long (``tag,timestamp,value[,status]``) and wide
  (time column plus a value and optionally a quality column per tag, one or several
  header rows), read in streaming chunks; :mod:`.mcap_reader` — MCAP with JSON,
  protobuf or ROS 2 (CDR) channels, decoded in batches per channel;
* :mod:`.values`, :mod:`.timestamps`, :mod:`.quality` — value text, timestamps (local time
  → UTC, DST by order of appearance) and quality flags, shared by both readers;
* :mod:`.sink` — each chunk masked and sorted on arrival; :mod:`.canonical` — the schema
  and the one merge of all chunks (duplicates: the later wins);
* :mod:`.report` — the per-signal counts; :mod:`.read` — the entry points.
"""

from __future__ import annotations

from pipeline.adapters.ingest.canonical import CANONICAL_SCHEMA, QUALITY_DTYPE, empty_canonical_table
from pipeline.adapters.ingest.options import CsvOptions, McapOptions
from pipeline.adapters.ingest.quality import quality_of_flag
from pipeline.adapters.ingest.read import read_recording, read_recordings
from pipeline.adapters.ingest.report import IngestReport, SignalIngestStats

__all__ = [
    "CANONICAL_SCHEMA",
    "QUALITY_DTYPE",
    "CsvOptions",
    "IngestReport",
    "McapOptions",
    "SignalIngestStats",
    "empty_canonical_table",
    "quality_of_flag",
    "read_recording",
    "read_recordings",
]
