"""The trend of a job's pairs across runs as a figure (``plantdyn runs JOB``): per pair
the gain (rate for an integrating output) of every run with its ±σ, and for monitored
runs the band within which the run counts as unchanged against its baseline
(baseline ± ``monitor.threshold_sigma`` × the combined σ, from the catalog's
``monitor_low`` / ``monitor_high``); changed runs are marked.

Everything is read from the catalog (:meth:`ResultStore.trend`), so the figure can be
redrawn for any results root without the run folders.  matplotlib is imported here
only (no pyplot: no global state, no GUI backend); the PNG is written atomically.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.adapters.store.files import atomic_write_bytes

__all__ = ["PairTrend", "pair_trends", "draw_trends", "write_trend_png"]


@dataclass(frozen=True)
class PairTrend:
    """One pair's gain (or rate) over the runs of a job — what the figure draws.

    Attributes
    ----------
    output, input : str
        Signal names.
    metric : str
        ``"gain"`` or ``"rate"``.
    run_ids : tuple of str
        Runs in catalog order (oldest first) that have the metric.
    value, std : ndarray (n_runs,)
        The metric and its σ per run.
    low, high : ndarray (n_runs,)
        The unchanged band of each monitored run (NaN where the run is not monitored).
    monitor : tuple of str
        Per run ``changed`` / ``unchanged`` / ``baseline``, or ``""`` when not monitored.
    baseline : tuple of str
        Per run the baseline's run id, or ``""``.
    """

    output: str
    input: str
    metric: str
    run_ids: tuple[str, ...]
    value: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray
    monitor: tuple[str, ...]
    baseline: tuple[str, ...]

    @property
    def pair(self) -> str:
        """``"output<-input"``."""
        return f"{self.output}<-{self.input}"

    def outside(self) -> np.ndarray:
        """Runs whose value lies outside their band (bool per run; False unmonitored)."""
        with np.errstate(invalid="ignore"):
            return (self.value < self.low) | (self.value > self.high)


def pair_trends(trend: pl.DataFrame) -> list[PairTrend]:
    """Per pair the gain (or rate) trend with the monitoring band, from a catalog trend.

    Parameters
    ----------
    trend : polars.DataFrame
        :meth:`ResultStore.trend` of the job (window ``all``): columns ``run_id``,
        ``output``, ``input``, ``metric``, ``value``, ``label``.
    """
    out = []
    if trend.height == 0:
        return out
    runs = trend.select("run_id").unique(maintain_order=True)["run_id"].to_list()
    for (o, u), rows in trend.group_by(["output", "input"], maintain_order=True):
        metric = "gain" if rows.filter(pl.col("metric") == "gain").height else "rate"
        if not rows.filter(pl.col("metric") == metric).height:
            continue

        def col(name: str, what: str = "value", rows=rows) -> dict:
            sel = rows.filter(pl.col("metric") == name)
            return dict(zip(sel["run_id"].to_list(), sel[what].to_list()))

        val, std = col(metric), col(f"{metric}_std")
        low, high = col("monitor_low"), col("monitor_high")
        mon, base = col("monitor", "label"), col("monitor_baseline", "label")
        ids = [r for r in runs if val.get(r) is not None]

        def arr(d: dict) -> np.ndarray:
            return np.array([np.nan if d.get(r) is None else d[r] for r in ids], float)

        out.append(PairTrend(o, u, metric, tuple(ids), arr(val), arr(std), arr(low),
                             arr(high), tuple(mon.get(r) or "" for r in ids),
                             tuple(base.get(r) or "" for r in ids)))
    return out


def draw_trends(trends: list[PairTrend], *, title: str):
    """A matplotlib figure: one panel per pair (module notes).

    Parameters
    ----------
    trends : list of PairTrend
        From :func:`pair_trends`.
    title : str
        The figure's title.
    """
    from matplotlib.figure import Figure

    n = max(1, len(trends))
    ncols = 1 if n <= 3 else min(4, math.ceil(math.sqrt(n)))
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(8.5 * ncols, 2.6 * nrows + 0.6), dpi=100, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, t in zip(axes, trends):
        x = np.arange(len(t.run_ids))
        if np.isfinite(t.low).any():
            ax.fill_between(x, t.low, t.high, step="mid", color="tab:green", alpha=0.18,
                            label="unchanged band (baseline ± threshold·σ)", linewidth=0)
            ax.plot(x, (t.low + t.high) / 2, drawstyle="steps-mid", color="tab:green",
                    linewidth=0.8, label="baseline")
        ax.errorbar(x, t.value, yerr=t.std, fmt="o", color="tab:blue", markersize=4,
                    capsize=2, label=f"{t.metric} ± σ")
        changed = np.array([m == "changed" for m in t.monitor])
        if changed.any():
            ax.plot(x[changed], t.value[changed], "X", color="tab:red", markersize=10,
                    label="changed")
        base = np.array([m == "baseline" or r in t.baseline
                         for m, r in zip(t.monitor, t.run_ids)])
        if base.any():
            ax.plot(x[base], t.value[base], "*", color="black", markersize=11,
                    label="baseline run")
        step = max(1, len(x) // 12)
        ax.set_xticks(x[::step], [r[-14:] for r in t.run_ids[::step]], rotation=30,
                      ha="right", fontsize=7)
        ax.set_title(t.pair, fontsize=10)
        ax.set_ylabel(t.metric)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    for ax in axes[len(trends):]:
        ax.set_visible(False)
    fig.suptitle(title, fontsize=11)
    return fig


def write_trend_png(trends: list[PairTrend], path: Path, *, title: str) -> Path:
    """Draw the trends and write the PNG atomically (a temp file renamed into place).

    Parameters
    ----------
    trends : list of PairTrend
        From :func:`pair_trends`.
    path : Path
        The PNG file; its folder must exist.
    title : str
        The figure's title.
    """
    fig = draw_trends(trends, title=title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)
