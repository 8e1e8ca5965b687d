"""The estimation report's figures (matplotlib, no pyplot): the step-response matrix, the
frequency responses, the residual correlations, the held-out fit, the order search trace
and the masked samples.  Every panel of a matrix has the same size and its own units."""

from __future__ import annotations

from typing import Any

import numpy as np
import polars as pl
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import LogLocator, MaxNLocator, NullLocator

from pipeline.adapters.html_report.page import (
    WINDOW_COLOURS,
    figure_png,
    figure_svg,
    new_figure,
    panel_grid,
    ratio_unit,
)
from pipeline.adapters.html_report.stored import StoredRun, step_arrays, window_labels
from pipeline.adapters.series_reader import Spec, reduce_series
from pipeline.readouts.envelope import bucket_ids, bucket_width, envelope_points
from pipeline.readouts.frequency import frequency_response_from_step

__all__ = [
    "correlation_figures",
    "fit_figure",
    "frequency_matrix",
    "masked_figure",
    "search_trace_figure",
    "step_matrix",
]

_BAND = "#9ecae1"
FIGURE_POINTS = 4000
"""Points per line (or markers per row) of a long time-series figure: a 12-inch PNG is
about 1200 pixels wide, so longer series are drawn as min/max envelopes
(:mod:`pipeline.readouts.envelope`)."""
_SMALL = 7


def _style(ax, *, title: str | None = None, xlabel: str, ylabel: str) -> None:
    if title:
        ax.set_title(title, fontsize=8)
    ax.set_xlabel(xlabel, fontsize=_SMALL)
    ax.set_ylabel(ylabel, fontsize=_SMALL)
    ax.tick_params(labelsize=_SMALL)
    ax.yaxis.get_offset_text().set_fontsize(_SMALL)
    ax.grid(True, lw=0.3, alpha=0.5)
    # few ticks: matplotlib's tick objects are most of the drawing time
    for axis in (ax.xaxis, ax.yaxis):
        if axis.get_scale() == "log":
            axis.set_major_locator(LogLocator(numticks=4))
            axis.set_minor_locator(NullLocator())
        else:
            axis.set_major_locator(MaxNLocator(nbins=4))


def _pair_label(o: str, u: str) -> str:
    return f"{o} ← {u}"


_TF = "#c0392b"


def _exported_step(pair: dict, step: np.ndarray, std: np.ndarray, dt_s: float):
    """The step response of the transfer function ``plantdyn export`` writes for the pair,
    at the lags (None where the export leaves it out,
    :func:`pipeline.readouts.lti_fit.reported_model`)."""
    from pipeline.readouts.lti_fit import reported_model, sampled_step

    key = "rate" if pair.get("integrating") else "gain"
    fit = reported_model(step, dt_s=dt_s, step_std=std, integrating=key == "rate",
                         value=pair.get(key), std=pair.get(f"{key}_std"),
                         stored=pair.get("transfer_function"))
    if isinstance(fit, str):
        return None
    return sampled_step(fit.num, fit.den, delay_s=fit.delay_s, dt_s=dt_s,
                        n_lags=step.size)


def step_matrix(run: StoredRun, units: dict[str, str]) -> str:
    """Rows = outputs, columns = inputs: the all-data step response with its ±2σ band
    (σ = ``step_std``), every disjoint window as a thin line; inline SVG.

    Parameters
    ----------
    run : StoredRun
        The run (``step_responses.parquet`` required).
    units : dict of str to str
        Unit per signal name.
    """
    steps = run.steps
    windows = window_labels(steps)
    n_y, n_x = len(run.outputs), len(run.inputs)
    pw, ph, left, bottom, right, top = 2.45, 1.55, 0.85, 0.5, 0.2, 0.32
    width = n_x * (left + pw + right)
    per_row = max(2, int(width / 1.25))  # legend entries per row: a narrow matrix wraps
    head = 0.15 + 0.2 * -(-(len(windows) + 1) // per_row)
    fig = new_figure(width, head + n_y * (top + ph + bottom))
    axes = panel_grid(fig, n_y, n_x, panel_w=pw, panel_h=ph, left=left, bottom=bottom,
                      right=right, top=top, head=head)
    groups = {k: g for k, g in steps.group_by(["output", "input", "window"])}
    for i, o in enumerate(run.outputs):
        for j, u in enumerate(run.inputs):
            ax = axes[i][j]
            for k, w in enumerate(windows):
                df = groups.get((o, u, w))
                if df is None or df.height == 0:
                    continue
                df = df.sort("lag")
                t, s = df["time_s"].to_numpy(), df["step"].cast(pl.Float64).to_numpy()
                few = df.height <= 20  # a short response is drawn with its points
                if w == "all":
                    sd = df["step_std"].cast(pl.Float64).to_numpy()
                    ax.fill_between(t, s - 2 * sd, s + 2 * sd, color=_BAND, lw=0, zorder=1)
                    ax.plot(t, s, color="black", lw=1.7, zorder=3, marker="o" if few else None,
                            ms=3)
                    tf = _exported_step(run.pair(o, u), s, sd, float(df["dt_s"][0]))
                    if tf is not None:
                        ax.plot(t, tf, color=_TF, lw=1.1, ls="--", zorder=4)
                    ax.set_xlim(0, float(df["n_p"][0]) * float(df["dt_s"][0]))
                else:
                    ax.plot(t, s, color=WINDOW_COLOURS[(k - 1) % len(WINDOW_COLOURS)], lw=0.8,
                            zorder=2, marker="." if few else None, ms=2)
            ax.axhline(0.0, color="#888888", lw=0.5, zorder=0)
            _style(ax, title=_pair_label(o, u), xlabel="time after the step (s)",
                   ylabel=f"step ({ratio_unit(units.get(o, ''), units.get(u, ''))})")
    handles = [Line2D([], [], color="black", lw=1.7), Patch(color=_BAND),
               Line2D([], [], color=_TF, lw=1.1, ls="--")]
    labels = ["all data", "±2σ (all data)", "exported transfer function"]
    for k, w in enumerate(windows[1:]):
        handles.append(Line2D([], [], color=WINDOW_COLOURS[k % len(WINDOW_COLOURS)], lw=0.8))
        labels.append(f"window {w}")
    fig.legend(handles, labels, loc="upper left", ncol=per_row, fontsize=7, frameon=False,
               bbox_to_anchor=(0.0, 1.0), columnspacing=1.0, handlelength=1.6)
    return figure_svg(fig, "step-matrix")


def frequency_matrix(run: StoredRun, units: dict[str, str]) -> str:
    """Magnitude and phase of every pair's all-data step response (its increments' DTFT,
    :func:`pipeline.readouts.frequency.frequency_response_from_step`); rows = outputs (magnitude
    above phase), columns = inputs; inline SVG.

    Parameters
    ----------
    run : StoredRun
        The run.
    units : dict of str to str
        Unit per signal name.
    """
    dh = step_arrays(run, "all")
    dt = float(run.steps["dt_s"][0])
    outs_cfg = ((run.config.get("signals") or {}).get("outputs") or {})
    P = dh.shape[2]
    omega = np.geomspace(np.pi / (dt * P * 4), np.pi / dt, 200)
    n_y, n_x = len(run.outputs), len(run.inputs)
    pw, ph, left, bottom, right, top = 2.45, 1.05, 0.85, 0.45, 0.2, 0.3
    fig = new_figure(n_x * (left + pw + right), 2 * n_y * (top + ph + bottom))
    axes = panel_grid(fig, 2 * n_y, n_x, panel_w=pw, panel_h=ph, left=left, bottom=bottom,
                      right=right, top=top)
    for i, o in enumerate(run.outputs):
        integ = bool((outs_cfg.get(o) or {}).get("integrating"))
        for j, u in enumerate(run.inputs):
            n = int(run.pair(o, u).get("n_p") or P)
            fr = frequency_response_from_step(dh[i, j, :n], dt_s=dt, omega=omega,
                                              tail="hold" if integ else "zero")
            mag, ph_deg = fr.magnitude, np.degrees(fr.phase_rad)
            am, ap = axes[2 * i][j], axes[2 * i + 1][j]
            am.loglog(omega, np.where(mag > 0, mag, np.nan), color="black", lw=1.2)
            ap.semilogx(omega, ph_deg, color="#1f77b4", lw=1.2)
            _style(am, title=_pair_label(o, u), xlabel="ω (rad/s)",
                   ylabel=f"|G| ({ratio_unit(units.get(o, ''), units.get(u, ''))})")
            _style(ap, xlabel="ω (rad/s)", ylabel="phase (°)")
    return figure_svg(fig, "frequency-matrix")


def correlation_figures(run: StoredRun, corr: dict[str, Any]) -> tuple[str, str]:
    """(autocorrelation per output, input–residual cross-correlation matrix), inline SVG,
    each with its 99 % significance band.

    Parameters
    ----------
    run : StoredRun
        The run.
    corr : dict
        :func:`pipeline.adapters.html_report.stored.residual_correlations`.
    """
    dt = float(run.steps["dt_s"][0]) if run.steps is not None else 1.0
    n_y, n_x = len(run.outputs), len(run.inputs)
    pw, ph, left, bottom, right, top = 2.45, 1.3, 0.85, 0.5, 0.2, 0.32
    fig = new_figure(n_y * (left + pw + right), top + ph + bottom)
    axes = panel_grid(fig, 1, n_y, panel_w=pw, panel_h=ph, left=left, bottom=bottom,
                      right=right, top=top)[0]
    for k, o in enumerate(run.outputs):
        c = corr["outputs"][o]
        rho = np.asarray(c["autocorrelation"], dtype=float)
        ax = axes[k]
        ax.bar(np.arange(1, rho.size + 1), rho, width=0.6, color="#1f77b4")
        for s in (1, -1):
            ax.axhline(s * c["band_99"], color="#c62828", lw=0.8, ls="--")
        p = c.get("p_value")
        _style(ax, title=f"{o}: Ljung–Box p = {p:.2g}" if p is not None else o,
               xlabel="lag (samples)", ylabel="autocorrelation (–)")
    acf = figure_svg(fig, "acf")
    fig = new_figure(n_x * (left + pw + right), n_y * (top + ph + bottom))
    axes = panel_grid(fig, n_y, n_x, panel_w=pw, panel_h=ph, left=left, bottom=bottom,
                      right=right, top=top)
    for i, o in enumerate(run.outputs):
        for j, u in enumerate(run.inputs):
            xc = corr["pairs"][(o, u)]
            lags = np.asarray(xc["lags"], dtype=float) * dt
            ax = axes[i][j]
            ax.axvspan(lags.min(), 0, color="#eeeeee", lw=0)
            ax.plot(lags, xc["r"], color="black", lw=0.8)
            for s in (1, -1):
                ax.axhline(s * xc["band"], color="#c62828", lw=0.8, ls="--")
            _style(ax, title=_pair_label(o, u), xlabel="lag of the input (s)",
                   ylabel="cross-correlation (–)")
    return acf, figure_svg(fig, "xcorr")


def fit_figure(run: StoredRun, fit: dict[str, Any], units: dict[str, str]) -> str:
    """Measured vs simulated output on the held-out stretch, one panel per output; PNG.

    Parameters
    ----------
    run : StoredRun
        The run.
    fit : dict
        :func:`pipeline.adapters.html_report.stored.held_out_fit`.
    units : dict of str to str
        Unit per signal name.
    """
    n_y = len(run.outputs)
    fig = new_figure(12.0, 2.3 * n_y + 0.3)
    axes = panel_grid(fig, n_y, 1, panel_w=10.6, panel_h=1.5, left=0.95, bottom=0.5,
                      right=0.45, top=0.3)
    times = fit["time"]
    hours = (times - times[0]).dt.total_seconds().to_numpy() / 3600.0 if len(times) else \
        np.zeros(0)
    start = f"{times[0]:%Y-%m-%d %H:%M:%S}" if len(times) else ""
    width = bucket_width(float(hours[-1] - hours[0]) if hours.size else 0.0, hours.size, FIGURE_POINTS)
    buckets = bucket_ids(hours, float(hours[0]), width) if width is not None else np.arange(hours.size)
    for i, o in enumerate(run.outputs):
        r = fit["outputs"][o]
        ax = axes[i][0]
        ax.plot(*_drawn(hours, buckets, r["measured"]), color="#888888", lw=0.6, label="measured")
        if "held_out" in r:
            ax.plot(*_drawn(hours, buckets, r["held_out"]), color="#d62728", lw=0.9,
                    label=f"simulated, model of the other windows (fit {r['fit_held_out']:.1f} %)")
        if "all" in r:
            ax.plot(*_drawn(hours, buckets, r["all"]), color="#1f77b4", lw=0.7, ls="--",
                    label=f"simulated, all-data estimate, in-sample (fit {r['fit_all']:.1f} %)")
        what = "Δ" if r["differenced"] else ""
        ax.set_title(o, fontsize=8, loc="left")
        _style(ax, xlabel=f"time since {start} UTC (h)",
               ylabel=f"{what}{o} ({units.get(o) or 'output unit'})")
        ax.legend(fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=3,
                  frameon=False, borderaxespad=0.1)
    return figure_png(fig, alt="measured vs simulated outputs on the held-out window")


def _drawn(x: np.ndarray, buckets: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` to plot: every sample, or the min/max envelope per bucket (a PNG a
    thousand pixels wide shows no more; the statistics use every sample)."""
    env = envelope_points(buckets, np.asarray(y, dtype=float))
    return x[env.index], env.value


def search_trace_figure(run: StoredRun) -> str:
    """The N_p search (tail range over its band per pair and candidate; flat when ≤ 1)
    per output, and the N_d doubling (window-agreement p per pair); inline SVG.

    Parameters
    ----------
    run : StoredRun
        The run (``checks.json`` ``search``).
    """
    search = run.checks.get("search") or {}
    n_y = len(run.outputs)
    pw, ph, left, bottom, right, top = 2.6, 1.6, 0.8, 0.5, 0.2, 0.32
    fig = new_figure((n_y + 1) * (left + pw + right), top + ph + bottom + 0.5)
    axes = panel_grid(fig, 1, n_y + 1, panel_w=pw, panel_h=ph, left=left, bottom=bottom,
                      right=right, top=top, head=0.5)[0]
    chosen = search.get("n_p") or {}
    for i, o in enumerate(run.outputs):
        ax = axes[i]
        for j, u in enumerate(run.inputs):
            pts = sorted((t["n_p"], p["tail_range"] / p["band"] if p.get("band") else np.nan,
                          bool(p.get("flat")))
                         for t in search.get("order_trace") or [] for p in t.get("pairs") or []
                         if p.get("output") == o and p.get("input") == u)
            if not pts:
                continue
            colour = WINDOW_COLOURS[j % len(WINDOW_COLOURS)]
            n, r, flat = map(np.asarray, zip(*pts))
            ax.plot(n, r, color=colour, lw=0.8, label=u)
            ax.scatter(n[flat], r[flat], color=colour, s=10, zorder=3)
            ax.scatter(n[~flat], r[~flat], facecolors="none", edgecolors=colour, s=10, zorder=3)
            if f"{o}<-{u}" in chosen:
                ax.axvline(chosen[f"{o}<-{u}"], color=colour, lw=0.6, ls=":")
        ax.axhline(1.0, color="#c62828", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_yscale("log")
        _style(ax, title=f"N_p search: {o}", xlabel="N_p candidate (lags)",
               ylabel="tail range / band (–)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, frameon=False)
    ax = axes[-1]
    for trial in search.get("nd_trace") or []:
        if "error" in trial:
            ax.axvline(trial["n_d"], color="#c62828", lw=0.6)
            continue
        if "skipped" in trial:
            ax.axvline(trial["n_d"], color="#9e9e9e", lw=0.6, ls="--")
            continue
        for k, p in enumerate(trial.get("pairs") or []):
            if p.get("p_value") is not None:
                ax.scatter(trial["n_d"], max(p["p_value"], 1e-300), s=8,
                           color=WINDOW_COLOURS[k % len(WINDOW_COLOURS)])
    ax.axhline(0.01, color="#c62828", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    _style(ax, title="N_d doubling: windows agree?", xlabel="N_d (samples per window)",
           ylabel="agreement p per pair (–)")
    fig.text(0.01, 0.98, "filled: flat tail (and nothing significant beyond); dotted: chosen "
             "N_p; dashed: flat when ≤ 1 / α = 0.01; red vertical: a window that could not be "
             "estimated; grey dashed: a length skipped, its windows predicted uninformative",
             fontsize=8, va="top")
    return figure_svg(fig, "search-trace")


def masked_figure(run: StoredRun) -> str | None:
    """Where the masked samples are, one row per signal; PNG (None: nothing masked).

    Parameters
    ----------
    run : StoredRun
        The run (``signals.parquet``).
    """
    marks: dict[str, np.ndarray] = {}

    def keep(info, series) -> None:
        marks[str(info.key[0])] = series["masked"].time

    infos = reduce_series(run.signals, ["signal"], {"masked": Spec(pl.col("good").cast(pl.Float64), flag=~pl.col("good"))},
                          columns=["good"], max_points=FIGURE_POINTS, on_key=keep)
    if not any(m.size for m in marks.values()):
        return None
    names = [str(k.key[0]) for k in infos]
    t0 = min(k.first for k in infos)
    h = 0.9 + 0.28 * len(names)
    fig = new_figure(12.0, h)
    ax = fig.add_axes((0.16, 0.6 / h, 0.8, 0.28 * len(names) / h))
    for k, name in enumerate(names):
        hours = (marks.get(name, np.zeros(0, "datetime64[ns]")) - t0) / np.timedelta64(3600, "s")
        ax.scatter(hours, np.full(hours.size, k), marker="|", s=60, color="#c62828")
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(-0.6, len(names) - 0.4)
    span = float((max(k.last for k in infos) - t0) / np.timedelta64(3600, "s"))
    ax.set_xlim(0, max(span, 1e-9))
    start = np.datetime_as_string(t0, unit="s").replace("T", " ")
    _style(ax, xlabel=f"time since {start} UTC (h)", ylabel="")
    return figure_png(fig, alt="masked samples per signal")
