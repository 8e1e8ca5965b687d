"""The drop folder of a nightly job, as files on disk: is a file complete, when does its
data start, and how many files may be processed side by side.

Decisions (docs/guide/nightly.md, "Nightly over a backlog"):

* **Complete files only.**  A file is taken when its size and modification time have not
  changed for ``nightly.settle_s`` seconds (default 60; ``$PLANTDYN_SETTLE_S`` overrides
  the job's value), judged from the modification time — an exporter appending to a file
  moves it forward with every write — and checked again after the file is hashed (a file
  that changed meanwhile is still being written).  With ``nightly.marker: .done`` a file
  is taken only once ``<file>.done`` exists instead (the exporter writes the marker when
  it has closed the file).  A file that is not complete is skipped with a line and taken
  on a later night.
* **Data-time order.**  Files are processed by the data's first timestamp: for MCAP the
  first message's log time from the summary at the end of the file (no message is
  decoded); for CSV the earliest time of the first chunk the job's own reader parses
  (up to :data:`~pipeline.adapters.ingest.options.CHUNK_CELLS` cells, i.e. the whole of a
  small export; a long export sorted by tag gives its first tag's first time, which is
  the export's start).  When a file cannot be read so (a truncated MCAP without summary,
  an unreadable head) its modification time stands in, and the row says so.
* **Bounded concurrency.**  ``nightly.max_parallel``, else
  ``max(1, min(cores, floor(0.5 · available memory / per-file memory)))`` with the
  per-file memory ``256 MiB + 2 × the largest file's size``.  Basis: ingesting and
  gridding a month at 1 Hz × 20 tags (a 2.6 GB CSV) peaks at 1.83 GiB, 0.7× its size
  (``bench_ingest``); 2× leaves room for the estimate and the results, whose writing is
  bounded separately (issue 33, build 3).  A small export costs ≈ 3 MiB above the
  ≈ 300 MiB of the process itself (``bench_nightly``), so for them the cores bound first.
  The cores are those this process may use (``os.sched_getaffinity``); the memory is
  ``MemAvailable`` of ``/proc/meminfo``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time
from pathlib import Path

from pipeline.errors import ConfigError

__all__ = ["SETTLE_ENV", "FileState", "data_start_s", "default_max_parallel", "file_state",
           "per_file_memory_bytes", "settle_s"]

#: Environment variable overriding ``nightly.settle_s`` (seconds; tests use 0).
SETTLE_ENV = "PLANTDYN_SETTLE_S"

_MIB = 1 << 20

#: The first bytes of an MCAP file (the ingest's test of a file without the suffix).
MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclasses.dataclass(frozen=True)
class FileState:
    """A drop-folder file as seen once: ``ready`` (complete), ``writing`` (changed within
    the settle time, or no marker yet) or ``vanished`` (gone since the folder was listed).

    Attributes
    ----------
    state : str
        ``"ready"``, ``"writing"`` or ``"vanished"``.
    size : int
        Bytes (0 when vanished).
    mtime_ns : int
        Modification time, ns since the epoch (0 when vanished).
    reason : str
        In words, for the status line ("modified 3 s ago, settle_s 60").
    """

    state: str
    size: int
    mtime_ns: int
    reason: str = ""


def settle_s(configured: float) -> float:
    """The settle time in s: ``$PLANTDYN_SETTLE_S`` when set, else ``configured``.

    Parameters
    ----------
    configured : float
        The job's ``nightly.settle_s``.
    """
    text = os.environ.get(SETTLE_ENV, "").strip()
    if not text:
        return float(configured)
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(f"{SETTLE_ENV}={text!r} is not a number; give the settle time in "
                          "seconds, e.g. 60 (or set nightly.settle_s in the job YAML)") from None
    if not (math.isfinite(value) and value >= 0):
        raise ConfigError(f"{SETTLE_ENV}={text!r} must be a number of seconds >= 0, e.g. 60")
    return value


def file_state(path: str | os.PathLike[str], *, settle: float, marker: str | None = None,
               now_s: float | None = None) -> FileState:
    """Whether ``path`` is complete (module notes).

    Parameters
    ----------
    path : path
        The file.
    settle : float
        Seconds its modification time must lie in the past (ignored with ``marker``).
    marker : str, optional
        Suffix of the marker file (``".done"``): ready only once ``path + marker`` exists.
    now_s : float, optional
        The current time, Unix s (default: now).
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return FileState("vanished", 0, 0, "deleted or moved since the folder was listed")
    if marker is not None:
        if not os.path.exists(os.fspath(path) + marker):
            return FileState("writing", st.st_size, st.st_mtime_ns,
                             f"no marker {Path(path).name}{marker} yet")
        return FileState("ready", st.st_size, st.st_mtime_ns)
    age = (time.time() if now_s is None else now_s) - st.st_mtime_ns / 1e9
    if age < settle:
        return FileState("writing", st.st_size, st.st_mtime_ns,
                         f"modified {max(age, 0.0):.0f} s ago, nightly.settle_s is {settle:g}")
    return FileState("ready", st.st_size, st.st_mtime_ns)


def _mcap_start_s(path: Path) -> float | None:
    from mcap.reader import make_reader

    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    stats = summary.statistics if summary is not None else None
    if stats is None or not stats.message_count:
        return None
    return stats.message_start_time / 1e9


def _looks_like_mcap(path: Path) -> bool:
    if path.suffix.lower() == ".mcap":
        return True
    with path.open("rb") as f:
        return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC


class _FirstChunk:
    """A reader sink that keeps the first chunk's earliest time and stops the reader."""

    class Enough(Exception):
        """Raised by the sink once a chunk has been seen."""

    def __init__(self) -> None:
        self.first_s: float | None = None

    def at(self, fraction: float) -> None:
        """Progress (ignored)."""

    def __call__(self, pre) -> None:
        times = pre["time"].drop_nulls()
        if len(times):
            self.first_s = times.min().timestamp()
        raise self.Enough


def data_start_s(path: str | os.PathLike[str], cfg) -> tuple[float, str]:
    """When the data of ``path`` starts, Unix s, and how that was found (``"data"`` or
    ``"mtime"``; module notes).

    Parameters
    ----------
    path : path
        The file.
    cfg : JobConfig
        The job (``source.layout``, ``source.csv``, ``source.timezone``).
    """
    from pipeline.adapters.ingest.csv_reader import read_csv_raw
    from pipeline.adapters.ingest.options import CsvOptions, coerce_options

    p = Path(path)
    first = None
    with contextlib.suppress(Exception):  # any unreadable head: the mtime stands in
        if cfg.source.layout == "mcap" or (cfg.source.layout == "auto" and _looks_like_mcap(p)):
            first = _mcap_start_s(p)
        else:
            sink = _FirstChunk()
            opts = coerce_options(cfg.source.csv.model_dump() if cfg.source.csv else None,
                                  CsvOptions, "csv")
            with contextlib.suppress(_FirstChunk.Enough):
                read_csv_raw(p, layout=cfg.source.layout, options=opts,
                             timezone=cfg.source.timezone, tags=None, sink=sink)
            first = sink.first_s
    if first is not None and math.isfinite(first):
        return float(first), "data"
    return p.stat().st_mtime, "mtime"


def per_file_memory_bytes(largest_file_bytes: int) -> int:
    """Memory budgeted for one file being processed: 256 MiB + 2 × its size.

    Parameters
    ----------
    largest_file_bytes : int
        Size of the largest file to be processed, bytes.
    """
    return 256 * _MIB + 2 * max(int(largest_file_bytes), 0)


def _cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _available_bytes() -> int:
    with contextlib.suppress(OSError, ValueError, StopIteration):
        with open("/proc/meminfo", encoding="ascii") as f:
            line = next(ln for ln in f if ln.startswith("MemAvailable:"))
        return int(line.split()[1]) * 1024
    return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def default_max_parallel(largest_file_bytes: int, *, cores: int | None = None,
                         available_bytes: int | None = None) -> int:
    """``max(1, min(cores, floor(0.5 · available / per-file)))`` (module notes).

    Parameters
    ----------
    largest_file_bytes : int
        Size of the largest file to be processed, bytes.
    cores : int, optional
        Cores this process may use (default: ``os.sched_getaffinity``).
    available_bytes : int, optional
        Memory available, bytes (default: ``MemAvailable`` of ``/proc/meminfo``).
    """
    if cores is None:
        cores = _cores()
    if available_bytes is None:
        available_bytes = _available_bytes()
    by_memory = math.floor(0.5 * available_bytes / per_file_memory_bytes(largest_file_bytes))
    return max(1, min(int(cores), by_memory))
