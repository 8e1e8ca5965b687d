"""What the estimation job's stages hand each other: recording, prepared data, summary, report."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.identification.sampling import sample_period_s
from pipeline.readouts.run_summary import RunSummary



@dataclass(frozen=True)
class Recording:
    """Signals of a job on one uniform grid, with quality masks.

    ``values``/``good`` columns follow ``names`` (inputs first, then outputs).
    """

    names: tuple[str, ...]
    roles: tuple[str, ...]
    tags: tuple[str, ...]
    time: np.ndarray  # datetime64[us] UTC, (N,)
    grid_dt_s: float  # the grid period; the estimation period T is Prepared.dt_s
    values: np.ndarray  # (N, k), NaN where masked
    good: np.ndarray  # (N, k) bool
    files: tuple[str, ...]
    quality: dict  # per signal: counts of masked samples by reason + ingest stats
    ingest: dict  # ingest report summary


@dataclass(frozen=True)
class Prepared:
    """The record at the estimation sample period, conditioned."""

    recording: Recording
    decimation: int  # the sample period T is decimation x the grid period (decided once)
    sampling: dict  # how T was chosen: alpha_T choice or the configured value (JSON-ready)
    time: np.ndarray  # (N,) datetime64[us]
    raw: np.ndarray  # (N, k) resampled, not conditioned (NaN where bad)
    x: np.ndarray  # (N, n_x) conditioned inputs (NaN where bad)
    y: np.ndarray  # (N, n_y) conditioned outputs (NaN where bad)
    good: np.ndarray  # (N, k) bool
    conditioning: dict
    integrating: tuple[bool, ...]
    r: np.ndarray | None = None  # (N, n_r) conditioned instruments (NaN where bad)

    @property
    def dt_s(self) -> float:
        """The estimation sample period ``T`` (s): ``decimation`` grid periods."""
        return sample_period_s(self.decimation, self.recording.grid_dt_s)

    @property
    def inputs(self) -> list[str]:
        return [n for n, r in zip(self.recording.names, self.recording.roles) if r == "input"]

    @property
    def outputs(self) -> list[str]:
        return [n for n, r in zip(self.recording.names, self.recording.roles) if r == "output"]

    @property
    def instruments(self) -> list[str]:
        return [n for n, r in zip(self.recording.names, self.recording.roles)
                if r == "instrument"]

    @property
    def good_xy(self) -> np.ndarray:
        """Quality of the inputs and outputs (the estimator's mask)."""
        return self.good[:, : len(self.inputs) + len(self.outputs)]


@dataclass(frozen=True)
class LongTable:
    """A long result table (``signals.parquet``, ``residuals.parquet``: a row per signal
    and sample) made chunk by chunk from the arrays it describes, so the whole table
    never exists in memory at once; iterating it yields the chunks in order.

    Attributes
    ----------
    rows : int
        Rows of the whole table (an upper bound when rows are filtered per chunk).
    make : callable (int) -> iterator of polars.DataFrame
        Yields the chunks of at most the given number of rows.
    chunk_rows : int
        Rows per chunk when iterated.
    """

    rows: int
    make: Callable[[int], Iterator[pl.DataFrame]]
    chunk_rows: int = 1 << 20

    def __iter__(self) -> Iterator[pl.DataFrame]:
        return iter(self.make(self.chunk_rows))



@dataclass(frozen=True)
class Summary:
    """Everything a run writes, as tables and its summary (no I/O yet): checks.json,
    report.md and the status are the :class:`~pipeline.readouts.run_summary.RunSummary`'s."""

    step_responses: pl.DataFrame
    signals: LongTable
    residuals: LongTable
    metrics: list
    report: RunSummary

    @property
    def checks(self) -> dict:
        """The run's checks.json document."""
        return dict(self.report.checks)

    @property
    def status(self) -> str:
        """The run's status."""
        return self.report.status

    @property
    def report_md(self) -> str:
        """The run's report.md."""
        return self.report.to_markdown()


@dataclass(frozen=True)
class RunReport:
    """What a run produced (printable)."""

    job: str
    run_id: str
    run_dir: Path
    status: str
    dt_s: float
    n_p: dict
    n_d: int
    verdicts: dict
    files: tuple[str, ...]
    recording: Path | None
    summary: RunSummary = field(repr=False)
    """What report.md says, rendered here for the terminal (the same numbers)."""
    timings_s: dict = field(default_factory=dict)

    def __str__(self) -> str:
        lines = [f"run {self.job}/{self.run_id}: {self.status}", f"  results: {self.run_dir}"]
        lines += [f"  {line}" for line in self.summary.to_text()]
        if self.recording:
            lines.append(f"  Rerun recording: {self.recording}  (open: rerun {self.recording})")
        if self.timings_s:
            lines.append("  " + stage_times(self.timings_s))
        return "\n".join(lines)


def stage_times(timings_s: dict) -> str:
    """``stage times: ingest 1.2 s, …, store 3.4 s (tables …, commit …); stages 9.9 s``:
    the top-level stages in order, the store's parts (``store/<part>``) in brackets.

    Parameters
    ----------
    timings_s : dict of str to float
        Seconds per stage (:attr:`RunReport.timings_s`).
    """
    top = {k: v for k, v in timings_s.items() if "/" not in k}
    parts = {k.split("/", 1)[1]: v for k, v in timings_s.items() if k.startswith("store/")}
    text = ", ".join(f"{k} {v:.1f} s" for k, v in top.items())
    if parts:
        text += " (" + ", ".join(f"{k} {v:.1f} s" for k, v in parts.items()) + ")"
    return f"stage times: {text}; stages {sum(top.values()):.1f} s"


@dataclass(frozen=True)
class WindowFailure:
    """A disjoint window that could not be estimated (recorded, not fatal)."""

    window: tuple[int, int]
    error: str
