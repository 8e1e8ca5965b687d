"""``plantdyn runs JOB``: a job's runs from the catalog — changed pairs first, the runs,
the metric trend — and the trend figure (:mod:`pipeline.adapters.trend_plot`).

The catalog is opened read-only and never created.  The figure is the one file this
command writes: ``<storage>/<job>/trend.png`` by default (beside the job's runs,
replaced atomically), or ``--plot FILE``; it is drawn once the job has two runs with a
gain or rate.  Where it may go is checked before anything is printed, by the one rule of
:func:`pipeline.adapters.safe_write.safe_target`: ``--plot`` replaces an existing regular
file only with ``--force``, and never a FIFO, device node, folder or link, a file inside a
run directory or the catalog (exit 2).  On a read-only archive the listing still prints
and a note says where the default figure could not go.
"""

from __future__ import annotations

import sys
from pathlib import Path

import polars as pl

DEFAULT_METRICS = ["gain", "rate", "dead_time_s", "static_gain", "holdout_rms_before",
                   "holdout_rms_after", "reduction"]
"""Metrics the trend table shows unless ``--metric`` is given."""


def changed_table(trend: pl.DataFrame) -> pl.DataFrame:
    """Pairs flagged ``changed`` against their baseline, newest run first.

    Parameters
    ----------
    trend : polars.DataFrame
        :meth:`ResultStore.trend` of the job.
    """
    mon = trend.filter(pl.col("metric") == "monitor")
    hit = mon.filter(pl.col("label") == "changed").select(
        "run_id", "created_utc", pl.concat_str("output", pl.lit("<-"), "input").alias("pair"),
        "output", "input")
    if hit.height == 0:
        return hit.drop("output", "input")
    wide = trend.filter(pl.col("metric").is_in(["gain_z", "dead_time_z", "step_max_z"])) \
        .pivot(on="metric", index=["run_id", "output", "input"], values="value")
    base = trend.filter(pl.col("metric") == "monitor_baseline").select(
        "run_id", "output", "input", pl.col("label").alias("baseline"))
    out = hit.join(base, on=["run_id", "output", "input"], how="left") \
        .join(wide, on=["run_id", "output", "input"], how="left")
    cols = ["run_id", "created_utc", "pair", "baseline"] + \
        [c for c in ("gain_z", "dead_time_z", "step_max_z") if c in out.columns]
    return out.select(cols).sort("created_utc", descending=True)


def runs_table(runs: pl.DataFrame, trend: pl.DataFrame) -> pl.DataFrame:
    """The runs with the pairs each flagged ``changed`` (column ``changed``), runs with a
    change first, each group oldest first.

    Parameters
    ----------
    runs : polars.DataFrame
        :meth:`ResultStore.list_runs` of the job.
    trend : polars.DataFrame
        :meth:`ResultStore.trend` of the job.
    """
    hit = trend.filter((pl.col("metric") == "monitor") & (pl.col("label") == "changed")) \
        .group_by("run_id", maintain_order=True).agg(
            pl.concat_str("output", pl.lit("<-"), "input").str.join(", ").alias("changed"))
    out = runs.join(hit, on="run_id", how="left").with_columns(
        pl.col("changed").fill_null(""))
    out = out.with_columns((pl.col("changed") == "").alias("_quiet")) \
        .sort(["_quiet", "created_utc", "run_id"]).drop("_quiet")
    return out.select([c for c in ("run_id", "status", "changed", "created_utc", "n_inputs",
                                   "path") if c in out.columns])


def show_runs(store, job: str, *, metrics: list[str] | None = None,
              plot: str | None = None, draw: bool = True, force: bool = False) -> int:
    """Print a job's runs (changed pairs first) and write the trend figure; returns the
    exit code.

    Parameters
    ----------
    store : ResultStore
        The results root, opened read-only.
    job : str
        Job name.
    metrics : list of str, optional
        Metrics of the trend table (default :data:`DEFAULT_METRICS`).
    plot : str, optional
        Where to write the figure (default ``<storage>/<job>/trend.png``).
    draw : bool
        Write the figure at all (``--no-plot``: False).
    force : bool
        Replace an existing ``plot`` file (``--force``; the default figure, the store's
        own file, is always replaced).

    Raises
    ------
    ConfigError, StorageError
        ``--plot`` names a place the figure may not go
        (:func:`pipeline.adapters.safe_write.safe_target`); checked before anything is
        printed.
    """
    runs = store.list_runs(job)
    if runs.height == 0:
        print(f"no runs of job {job!r} under {store.root}")
        return 0
    target = _plot_target(store, job, plot, force) if draw else None
    trend = store.trend(job)
    with pl.Config(tbl_rows=200, tbl_cols=20, fmt_str_lengths=60, tbl_width_chars=200):
        changed = changed_table(trend)
        n_mon = trend.filter(pl.col("metric") == "monitor")["run_id"].n_unique()
        if changed.height:
            print(f"CHANGED vs baseline: {changed.height} pair-run(s) in {n_mon} monitored "
                  "run(s), newest first")
            print(changed)
        elif n_mon:
            print(f"no pair changed against its baseline in {n_mon} monitored run(s)")
        print(runs_table(runs, trend))
        if trend.height:
            keep = [c for c in ("run_id", "created_utc", "output", "input", "metric", "value")
                    if c in trend.columns]
            print(trend.filter(pl.col("metric").is_in(metrics or DEFAULT_METRICS))
                  .select(keep))
    if draw:
        _write_plot(job, trend, target)
    return 0


def _plot_target(store, job: str, plot: str | None, force: bool) -> Path | str:
    """Where the figure goes, by the one rule (``safe_target``); for the default figure
    in a folder that is not writable (a read-only archive), the reason it cannot go."""
    from pipeline.adapters.safe_write import safe_target
    from pipeline.errors import StorageError

    if plot is not None:
        return safe_target(plot, force=force, option="--plot")
    try:  # the store's own figure: always replaced, but never a non-regular file
        return safe_target(store.root / job / "trend.png", force=True, option="the figure",
                           fix="move it away, or give --plot FILE (or --no-plot)")
    except StorageError:
        return f"{store.root / job / 'trend.png'} (the folder is not writable)"


def _write_plot(job: str, trend: pl.DataFrame, path: Path | str) -> None:
    """Write the trend figure and print its path (a note on stderr when it cannot be)."""
    from pipeline.adapters.trend_plot import pair_trends, write_trend_png

    trends = pair_trends(trend)
    if not trends or max(len(t.run_ids) for t in trends) < 2:
        print("trend plot: needs two runs with a gain or rate", file=sys.stderr)
        return
    if isinstance(path, str):
        print(f"trend plot: not written to {path}; give --plot FILE to write it elsewhere",
              file=sys.stderr)
        return
    what = "/".join(sorted({t.metric for t in trends}))
    title = f"{job}: {what} per run" + \
        (" with the unchanged band (baseline ± threshold·σ)"
         if any(t.monitor[k] for t in trends for k in range(len(t.monitor))) else "")
    try:
        write_trend_png(trends, path, title=title)
    except OSError as exc:
        print(f"trend plot: not written to {path} ({exc.strerror or exc}); give --plot FILE "
              "to write it elsewhere", file=sys.stderr)
        return
    print(f"trend plot: {path}")
