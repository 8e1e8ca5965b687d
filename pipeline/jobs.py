"""Composition: ``run_job(config) -> RunReport``, callable from a REPL.

The estimation job is a readable sequence of stage functions; the Prefect flow in
``flows/estimate.py`` wraps each one in a task (and maps :func:`estimate_window` over
windows), so the flow and a plain call produce the same results.

    load_recording -> prepare -> search_orders -> estimate_window (all + each window)
      -> summarise -> write_run (store + Rerun)

Decisions (also in the README):

* Grid: the recording is put on a uniform grid at the median sample spacing of its
  signals (or ``source.grid_dt_s``); inputs are linearly interpolated, outputs held,
  each up to ``max_gap_s`` (default: the larger of 10 grid periods and 600 s, see
  :data:`DEFAULT_MAX_GAP_S`), beyond which samples are masked.
* Sample period: α_T on the longest stretch where every signal is good; the record is
  then averaged-then-decimated (a decimated sample is bad if any source sample is).
* Conditioning with gaps: masked samples are filled by linear interpolation only to let
  the transform run (mean, detrend, high-pass need a gap-free series), then masked again
  (for ``difference`` the mask is shifted with the difference).  The estimator never sees
  a filled value.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.checks import cross_correlation_check, ljung_box, window_agreement
from pipeline.conditioning import condition
from pipeline.errors import (
    DataQualityError,
    InstrumentError,
    InsufficientDataError,
    PipelineError,
    SingularSystemError,
)
from pipeline.estimate import estimate_step_responses
from pipeline.normal_equations import good_segments
from pipeline.prediction import innovations, residuals
from pipeline.step_result import StepResponseEstimate, lag_times
from pipeline.sampling import choose_sample_period, resample_average_masked
from pipeline.progress import Tick, bar_of, silent
from pipeline.search import SearchResult, search

__all__ = [
    "Recording",
    "Prepared",
    "RunReport",
    "load_recording",
    "prepare",
    "search_orders",
    "estimate_window",
    "summarise",
    "write_run",
    "run_job",
]

Progress = Callable[[str, str], None]

DEFAULT_MAX_GAP_S = 600.0
"""Default longest span bridged on the grid.  Historians record by exception: no record
means "no change beyond the deadband", and a tag is re-recorded at least every
exception-max interval (PI's default ExcMax is 600 s).  Longer gaps are outages: masked."""


STRAY_FRACTION = 0.001
"""An island of the record (samples separated from the rest by more than every signal's
``max_gap_s``) holding fewer than 0.1 % of the samples is a stray — mistyped or clock-reset
timestamps — and is left out and reported (``checks.json`` → ``data_quality.stray_samples``)."""


def _quiet(stage: str, message: str) -> None:  # default progress sink
    pass


# ------------------------------------------------------------------------ dataclasses
@dataclass(frozen=True)
class Recording:
    """Signals of a job on one uniform grid, with quality masks.

    ``values``/``good`` columns follow ``names`` (inputs first, then outputs).
    """

    names: tuple[str, ...]
    roles: tuple[str, ...]
    tags: tuple[str, ...]
    time: np.ndarray  # datetime64[us] UTC, (N,)
    dt_s: float
    values: np.ndarray  # (N, k), NaN where masked
    good: np.ndarray  # (N, k) bool
    files: tuple[str, ...]
    quality: dict  # per signal: counts of masked samples by reason + ingest stats
    ingest: dict  # ingest report summary


@dataclass(frozen=True)
class Prepared:
    """The record at the estimation sample period, conditioned."""

    recording: Recording
    dt_s: float
    decimation: int
    sampling: dict  # alpha_T choice (JSON-ready)
    time: np.ndarray  # (N,) datetime64[us]
    raw: np.ndarray  # (N, k) resampled, not conditioned (NaN where bad)
    x: np.ndarray  # (N, n_x) conditioned inputs (NaN where bad)
    y: np.ndarray  # (N, n_y) conditioned outputs (NaN where bad)
    good: np.ndarray  # (N, k) bool
    conditioning: dict
    integrating: tuple[bool, ...]
    r: np.ndarray | None = None  # (N, n_r) conditioned instruments (NaN where bad)

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
class Summary:
    """Everything a run writes, as tables and documents (no I/O yet)."""

    step_responses: pl.DataFrame
    signals: pl.DataFrame
    residuals: pl.DataFrame
    checks: dict
    metrics: list
    report_md: str
    status: str


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
    timings_s: dict = field(default_factory=dict)

    def __str__(self) -> str:
        lines = [f"run {self.job}/{self.run_id}: {self.status}", f"  results: {self.run_dir}",
                 f"  dt = {self.dt_s:g} s, N_d per window = {self.n_d}"]
        for pair, v in self.verdicts.items():
            lines.append(f"  {pair}: N_p={self.n_p[pair]}, windows {v}")
        if self.recording:
            lines.append(f"  Rerun recording: {self.recording}  (open: rerun {self.recording})")
        return "\n".join(lines)


# -------------------------------------------------------------------------- stages
def load_recording(cfg, files: list[Path] | None = None, tick: Tick = silent) -> Recording:
    """Ingest the job's files and put its signals on one uniform grid (``tick``: bytes
    read, :mod:`pipeline.progress`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    files : list of Path, optional
        Files to read; ``None`` resolves the job's ``source`` (``resolve_sources``).
    tick : callable (done, total)
        Progress of the bytes read.
    """
    from pipeline.adapters.config import resolve_sources
    from pipeline.adapters.grid import to_grid
    from pipeline.adapters.ingest import read_recordings

    files = list(files) if files is not None else resolve_sources(cfg)
    sig = {**{n: ("input", s) for n, s in cfg.signals.inputs.items()},
           **{n: ("output", s) for n, s in cfg.signals.outputs.items()},
           **{n: ("instrument", s) for n, s in cfg.signals.instruments.items()}}
    tags = [s.tag for _, s in sig.values()]
    mcap = cfg.source.mcap.model_dump() if cfg.source.mcap else None
    csv = cfg.source.csv.model_dump() if cfg.source.csv else None
    table, report = read_recordings(files, layout=cfg.source.layout,
                                    timezone=cfg.source.timezone, tags=list(dict.fromkeys(tags)),
                                    mcap=mcap, csv=csv, on_truncated=cfg.source.on_truncated,
                                    tick=tick)
    if cfg.source.time_order == "strict":
        _check_time_order(report)
    grid_dt = cfg.source.grid_dt_s or _median_spacing_s(table)
    spec = {}
    for name, (role, s) in sig.items():
        # inputs are continuous (linear); PVs are exception-reported and setpoints
        # (instruments) are step signals: hold
        interp = s.interpolation or ("linear" if role == "input" else "hold")
        spec[s.tag] = {"interpolation": interp,
                       "max_gap_s": s.max_gap_s or max(10 * grid_dt, DEFAULT_MAX_GAP_S)}
    # breaks longer than every signal's max_gap_s are not gridded (all masked there
    # anyway), and an island of stray samples (a year-9999 timestamp) is left out:
    # memory follows the samples, not the span
    grid = to_grid(table, dt_s=grid_dt, signals=spec,
                   break_gap_s=max(v["max_gap_s"] for v in spec.values()),
                   stray_fraction=STRAY_FRACTION)
    order = [grid.names.index(t) for t in tags]
    values = np.asarray(grid.values)[:, order]
    good = np.asarray(grid.good)[:, order]
    spikes = {}
    if cfg.quality.spikes == "mask":
        from pipeline.spikes import find_spikes

        for k, name in enumerate(sig):
            flag = find_spikes(values[:, k], good[:, k], sigmas=cfg.quality.spike_sigmas)
            if flag.any():
                spikes[name] = {"samples": int(flag.sum()),
                                "first": str(np.asarray(grid.time)[flag][0]) + "Z",
                                "largest": float(np.nanmax(np.abs(values[flag, k])))}
                values[flag, k] = np.nan
                good[flag, k] = False
    quality = {}
    ing = _report_dict(report)
    tag_name = {s.tag: n for n, (_, s) in sig.items()}
    ing["grid"] = {"islands": grid.islands,
                   "stray_samples": [{**d, "signal": tag_name.get(d["signal"], d["signal"]),
                                      "tag": d["signal"]} for d in grid.dropped]}
    per_signal = {row.get("signal"): row for row in ing.get("signals", [])}
    ing["spikes"] = spikes
    for name, (role, s) in sig.items():
        reasons = dict(grid.mask_reasons.get(s.tag, {}))
        if name in spikes:
            reasons["spike"] = spikes[name]["samples"]
        quality[name] = {"tag": s.tag, "role": role,
                         "grid_samples": int(values.shape[0]),
                         "masked": int((~good[:, list(sig).index(name)]).sum()),
                         "masked_by_reason": reasons,
                         "ingest": per_signal.get(s.tag, {})}
        if good[:, list(sig).index(name)].sum() == 0:
            raise DataQualityError(
                f"signal {name!r} (tag {s.tag}): every sample is bad or missing after ingestion "
                f"({reasons}); check the tag's quality in the export or remove the signal"
            )
    return Recording(tuple(sig), tuple(r for r, _ in sig.values()), tuple(tags),
                     np.asarray(grid.time), float(grid_dt), values, good,
                     tuple(str(f) for f in files), quality, ing)


def _check_time_order(report) -> None:
    bad = [(st.signal, st.duplicates_removed, st.out_of_order) for st in report.signals
           if st.duplicates_removed or st.out_of_order]
    if bad:
        detail = "; ".join(f"tag {t}: {d} duplicate and {o} out-of-order timestamp(s)"
                           for t, d, o in bad[:5])
        raise DataQualityError(
            f"source.time_order is 'strict' but the recording has non-monotonic or "
            f"duplicate times: {detail}; fix the export, or set source.time_order: fix to "
            "resolve them (last value wins, rows sorted) and count them in checks.json"
        )


def _report_dict(report) -> dict:
    for attr in ("to_dict", "as_dict"):
        if hasattr(report, attr):
            return getattr(report, attr)()
    return {}


def _median_spacing_s(table: pl.DataFrame) -> float:
    from pipeline.adapters.grid import median_spacing_s

    med = median_spacing_s(table)
    if med is None:
        raise InsufficientDataError(
            "the recording has fewer than two distinct timestamps per signal; it cannot be "
            "put on a grid — export a longer period"
        )
    # Exception-reported timestamps jitter (1.002 s); two significant figures give the
    # period the historian was configured for, and grids of nightly files line up.
    return max(float(f"{med:.2g}"), 0.001)


def _fill(values: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Linear interpolation over masked samples (edges held), column by column."""
    out = values.copy()
    idx = np.arange(values.shape[0])
    for c in range(values.shape[1]):
        g = good[:, c]
        if g.all():
            continue
        out[~g, c] = np.interp(idx[~g], idx[g], values[g, c])
    return out


def longest_common_good(good: np.ndarray) -> tuple[int, int]:
    """The longest stretch ``(start, stop)`` where every signal is good (``(0, 0)`` if none).

    Parameters
    ----------
    good : ndarray of bool (N, k)
        Quality mask, one column per signal.
    """
    segs = good_segments(good.all(axis=1))
    if not segs:
        return (0, 0)
    return max(segs, key=lambda s: s[1] - s[0])


def prepare(cfg, rec: Recording) -> Prepared:
    """Choose T by α_T, average-then-decimate, condition inputs and outputs alike.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``sampling``, ``conditioning``, ``signals``).
    rec : Recording
        The gridded signals from :func:`load_recording`.
    """
    a, b = longest_common_good(rec.good)
    if cfg.sampling.dt_s is not None:
        factor = max(1, int(round(cfg.sampling.dt_s / rec.dt_s)))
        if abs(factor * rec.dt_s - cfg.sampling.dt_s) > 1e-6 * cfg.sampling.dt_s:
            raise DataQualityError(
                f"sampling.dt_s={cfg.sampling.dt_s} is not an integer multiple of the grid "
                f"period {rec.dt_s} s; choose a multiple (e.g. {factor * rec.dt_s:g}) or set "
                "source.grid_dt_s"
            )
        sampling = {"dt_s": factor * rec.dt_s, "decimation": factor, "source": "config"}
    else:
        if b - a < 200:
            raise InsufficientDataError(
                f"the longest stretch where every signal is good has {b - a} samples; the "
                "α_T criterion needs at least 200 — set sampling.dt_s in the job YAML or "
                "supply cleaner data"
            )
        # T is the model's: chosen on the inputs and outputs (instruments only explain
        # the inputs, and follow whatever T the model needs)
        model = [k for k, r in enumerate(rec.roles) if r in ("input", "output")]
        choice = choose_sample_period(
            {rec.names[k]: rec.values[a:b, k] for k in model}, dt_s=rec.dt_s,
            roles={rec.names[k]: rec.roles[k] for k in model},
            target_input=cfg.sampling.target_input, target_output=cfg.sampling.target_output)
        factor = int(choice.decimation)
        sampling = {**choice.to_dict(), "source": "alpha_t"}
    vals, good = resample_average_masked(np.nan_to_num(rec.values), rec.good, factor)
    n = vals.shape[0]
    tgrid = rec.time[: n * factor : factor] if factor > 1 else rec.time[:n]
    dt_s = factor * rec.dt_s
    n_x = sum(r == "input" for r in rec.roles)
    n_y = sum(r == "output" for r in rec.roles)
    filled = _fill(vals, good)
    c = cfg.conditioning
    params: dict[str, Any] = {}
    if c.method == "difference":
        params["kdiff1"] = c.kdiff1
    if c.method == "highpass":
        params["cutoff_period_s"] = c.cutoff_period_s or 50 * dt_s * 10
        params["order"] = c.order
    # instruments are conditioned like the inputs (the same transform on every signal)
    xr = np.concatenate([filled[:, :n_x], filled[:, n_x + n_y:]], axis=1)
    cond = condition(xr, filled[:, n_x:n_x + n_y], method=c.method, dt_s=dt_s, **params)
    g = good
    t = tgrid
    raw = np.where(good, vals, np.nan)
    if c.method == "difference":
        k = c.kdiff1
        g = good[k:] & good[:-k]
        t = tgrid[: g.shape[0]]
        raw = raw[: g.shape[0]]
    xc = np.where(g[:, :n_x], cond.x[:, :n_x], np.nan)
    yc = np.where(g[:, n_x:n_x + n_y], cond.y, np.nan)
    rc = np.where(g[:, n_x + n_y:], cond.x[:, n_x:], np.nan) if cond.x.shape[1] > n_x else None
    integ = tuple(cfg.signals.outputs[o].integrating for o in cfg.signals.outputs)
    return Prepared(rec, float(dt_s), factor, sampling, t, raw, xc, yc, g,
                    {"method": c.method, **params}, integ, rc)


def _instrument_error(cfg, prep: Prepared, exc: InstrumentError) -> DataQualityError:
    """The core's instrument error in terms of the job YAML (names, tags, keys)."""
    tags = cfg.tags()
    if exc.instrument is not None:
        name = prep.instruments[exc.instrument]
        return DataQualityError(
            f"signals.instruments.{name} (tag {tags[name]}) does not move over the record "
            "(constant after conditioning); an instrument must vary to explain the inputs — "
            "remove it from signals.instruments, or run the job on a period where it moves")
    name = prep.inputs[exc.input]
    v = exc.numbers
    return DataQualityError(
        f"signals.instruments ({', '.join(prep.instruments)}) barely move the input {name} "
        f"(tag {tags[name]}): first-stage F = {v.get('F', float('nan')):.3g}, R^2 = "
        f"{v.get('r2', float('nan')):.3g} with {v.get('n_instruments')} instrument lags, "
        "below 10 — an instrument-based estimate would be biased towards the direct one "
        f"and its uncertainty unreliable; list an instrument that moves {name} (its loop's "
        "setpoint, a measured disturbance) under signals.instruments, or remove "
        "signals.instruments (the direct estimate with estimation.feedback: auto then "
        "handles the loop)")


def _named(exc: PipelineError, prep: Prepared) -> PipelineError:
    """The core's index-based singular-system message with the job's signal names."""
    cause = getattr(exc, "cause", None)
    if cause is None:
        return exc
    import re

    from pipeline.solve import describe_singular

    tags = dict(zip(prep.recording.names, prep.recording.tags))
    labels = [f"{n} (tag {tags[n]})" for n in prep.inputs]
    what = re.sub(r"output (\d+)", lambda m: f"output {prep.outputs[int(m.group(1))]!r}",
                  getattr(exc, "what", "the estimate"))
    out = SingularSystemError(f"normal equations of {what} are singular: "
                              f"{describe_singular(*cause, labels=labels)}")
    out.cause, out.what = cause, what
    return out


def search_orders(cfg, prep: Prepared, tick: Tick = silent) -> SearchResult:
    """N_p/N_d trial-and-error search (windows are estimated by the caller; ``tick``:
    the search's steps, :mod:`pipeline.progress`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``search``, ``estimation``).
    prep : Prepared
        The conditioned record from :func:`prepare`.
    tick : callable (done, total)
        Progress of the search's steps.
    """
    s, e = cfg.search, cfg.estimation
    n_p = s.n_p
    if n_p is None and s.settling_time_s is not None:
        n_p = max(1, int(np.ceil(s.settling_time_s / prep.dt_s)))
    n_xy = len(prep.inputs) + len(prep.outputs)
    for k, name in enumerate(prep.instruments):  # constant in the export: say so plainly
        raw = prep.raw[:, n_xy + k]
        raw = raw[np.isfinite(raw)]
        if raw.size and np.ptp(raw) <= 1e-9 * max(float(np.max(np.abs(raw))), 1e-300):
            raise _instrument_error(cfg, prep, InstrumentError("", instrument=k))
    try:
        return search(
            np.nan_to_num(prep.x), np.nan_to_num(prep.y), dt=prep.dt_s,
            integrating=prep.integrating, mask=prep.good_xy, n_p_max=s.n_p_max,
            n_p_min=s.n_p_min, n_p=n_p, n_d_start=s.n_d_start, max_windows=s.max_windows,
            estimate_windows=False, noise=e.noise, n_k=cfg.n_k_matrix(), instruments=prep.r,
            feedback=e.feedback, tick=tick)
    except InstrumentError as exc:
        raise _instrument_error(cfg, prep, exc) from None
    except SingularSystemError as exc:
        raise _named(exc, prep) from None


@dataclass(frozen=True)
class WindowFailure:
    """A disjoint window that could not be estimated (recorded, not fatal)."""

    window: tuple[int, int]
    error: str


def estimate_window(prep: Prepared, window: tuple[int, int] | None, n_p, n_k=0,
                    noise="white", use_instruments: bool = False):
    """Estimate on one window (``None`` = every usable sample) with the search's choices
    (``n_p``, ``n_k``, the noise setting and whether to use the instruments:
    ``SearchResult.n_p, .n_k, .noise, .instruments``).

    A disjoint window whose data cannot be estimated (an input that does not move in it,
    too many masked samples) returns a :class:`WindowFailure` — a bad window is a
    recorded status, never a crash of the job.  Failure of the all-data estimate raises.

    Parameters
    ----------
    prep : Prepared
        The conditioned record from :func:`prepare`.
    window : (int, int) or None
        Sample slice ``(start, stop)`` of ``prep``; ``None`` for every sample.
    n_p : int or int array (n_y, n_x)
        Order per pair (``SearchResult.n_p``).
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair (``SearchResult.n_k``).
    noise : ``"white"``, ``"auto"`` or int
        The estimator's noise setting (``SearchResult.noise``).
    use_instruments : bool
        Estimate with ``prep.r`` as instruments (``SearchResult.instruments``).
    """
    a, b = window if window is not None else (0, prep.x.shape[0])
    try:
        return estimate_step_responses(
            np.nan_to_num(prep.x[a:b]), np.nan_to_num(prep.y[a:b]), n_p=n_p, dt=prep.dt_s,
            integrating=prep.integrating, mask=prep.good_xy[a:b], noise=noise, n_k=n_k,
            instruments=None if (prep.r is None or not use_instruments) else prep.r[a:b])
    except DataQualityError as exc:
        exc = _named(exc, prep)
        if window is None:
            raise exc from None
        return WindowFailure(tuple(window), str(exc))


_ABSOLUTE_TIMES = ("dead_time_s", "settling_time_s", "peak_time_s", "inverse_peak_time_s",
                   "apparent_delay_s")


def _characteristics(est: StepResponseEstimate, i: int, j: int) -> dict:
    """Characteristic quantities of one pair (``{"error": ...}`` when none can be read).

    The gain is the FIR model's own static gain, the final step ``step[n_p - 1]`` with
    its std (the frequency response at zero; one definition everywhere), and the rate
    of an integrating pair is the estimate's ``rate``.
    """
    from pipeline import characteristics as ch

    n = int(est.n_p[i, j])
    try:
        if est.integrating[i]:
            res = ch.integrating_characteristics(est.step[i, j, :n], dt_s=est.dt,
                                                 step_std=est.step_std[i, j, :n],
                                                 rate=float(est.rate[i, j]),
                                                 rate_std=float(est.rate_std[i, j]))
        else:
            res = ch.self_regulating_characteristics(
                est.step[i, j, :n], dt_s=est.dt, step_std=est.step_std[i, j, :n],
                gain=float(est.step[i, j, n - 1]), gain_std=float(est.step_std[i, j, n - 1]))
        out = res.to_dict()
        # characteristics.py puts step[0] at t = 0; our lag times are (l - 1/2) dt
        for key in _ABSOLUTE_TIMES:
            if isinstance(out.get(key), float) and np.isfinite(out[key]):
                out[key] += 0.5 * est.dt
        return out
    except PipelineError as exc:
        return {"error": str(exc)}


def _window_table(sr: SearchResult, window_results: list) -> tuple[list, list]:
    labelled = [(f"w{k}", e) for k, e in enumerate(window_results)]
    status = [{"window": lab, "samples": list(map(int, sr.windows[k])),
               "status": "failed" if isinstance(e, WindowFailure) else "ok",
               **({"error": e.error} if isinstance(e, WindowFailure) else {"n_d": int(e.n_d)})}
              for k, (lab, e) in enumerate(labelled)]
    return status, [(lab, e) for lab, e in labelled if not isinstance(e, WindowFailure)]


def _step_table(ests: list[tuple[str, StepResponseEstimate]], outs, ins) -> pl.DataFrame:
    rows = []
    for label, est in ests:
        P = est.step.shape[2]
        t = lag_times(P, est.dt)
        for i, o in enumerate(outs):
            for j, u in enumerate(ins):
                n = int(est.n_p[i, j])
                rows.append(pl.DataFrame({
                    "window": [label] * n, "output": [o] * n, "input": [u] * n,
                    "lag": np.arange(1, n + 1, dtype=np.int32), "time_s": t[:n],
                    "delta_h": est.delta_h[i, j, :n], "step": est.step[i, j, :n],
                    "step_std": est.step_std[i, j, :n],
                    "n_p": np.full(n, n, dtype=np.int32),
                    "n_d": np.full(n, est.n_d, dtype=np.int32),
                    "dt_s": np.full(n, est.dt)}))
    return pl.concat(rows)


def _pair_metrics(o: str, u: str, pair: dict) -> list[dict]:
    """One row per metric of a pair (unique names: what the catalog trends)."""
    vals = {"gain": pair["gain"], "gain_std": pair["gain_std"], "rate": pair["rate"],
            "rate_std": pair["rate_std"],
            "agreement_statistic": pair["agreement"].get("statistic"),
            "agreement_p_value": pair["agreement"].get("p_value")}
    for k, v in pair["characteristics"].items():
        if k not in vals and isinstance(v, (int, float)) and not isinstance(v, bool):
            vals[k] = v
    return [{"window": "all", "output": o, "input": u, "metric": k, "value": float(v)}
            for k, v in vals.items() if v is not None and np.isfinite(v)]


def summarise(cfg, prep: Prepared, sr: SearchResult, all_est: StepResponseEstimate,
              window_results: list) -> Summary:
    """Tables, checks and the report of a run (pure: no I/O).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    prep : Prepared
        The conditioned record.
    sr : SearchResult
        The order search's outcome.
    all_est : StepResponseEstimate
        The estimate on every usable sample.
    window_results : list of StepResponseEstimate or WindowFailure
        One per ``sr.windows``, in order.
    """
    from pipeline.verdicts import end_jump_z, pair_warnings

    ins, outs = prep.inputs, prep.outputs
    window_status, labelled = _window_table(sr, window_results)
    window_ests = [e for _, e in labelled]
    steps = _step_table([("all", all_est)] + labelled, outs, ins)
    agreement = window_agreement(window_ests) if len(window_ests) >= 2 else \
        [[None] * len(ins) for _ in outs]
    # residuals and one-step prediction errors of the all-data estimate; NaN where any
    # sample they need is masked
    x0, y0 = np.nan_to_num(prep.x), np.nan_to_num(prep.y)
    bad = ~prep.good_xy.all(axis=1)
    P = int(all_est.n_p.max())
    touched = np.convolve(bad.astype(float), np.ones(P + 1))[: bad.size] > 0
    res = residuals(all_est, x0, y0)
    res[touched] = np.nan
    innov = innovations(all_est, x0, y0, good=~touched)
    tags = cfg.tags()
    pairs = []
    metrics = []
    xcorr = {}
    whiteness = {}
    for i, o in enumerate(outs):
        lb = ljung_box(innov[:, i], lags=cfg.checks.ljung_box_lags)
        whiteness[o] = {k: lb[k] for k in ("statistic", "p_value", "lags", "white")}
        whiteness[o]["of"] = "residuals" if all_est.noise_model[i].order == 0 and \
            all_est.noise_model[i].form != "level" else "prediction errors (noise model)"
        nm = all_est.noise_model[i].to_dict()
        for j, u in enumerate(ins):
            n = int(all_est.n_p[i, j])
            a = agreement[i][j]
            agr = a.to_dict() if a is not None else {
                "statistic": None, "p_value": None, "verdict": "insufficient_data",
                "n_windows": len(window_ests)}
            xc = cross_correlation_check(x0[:, j], innov[:, i],
                                         max_lag=cfg.checks.xcorr_max_lag or n)
            xcorr[f"{o}<-{u}"] = {k: xc[k] for k in ("band", "fraction_outside", "max_abs_r",
                                                     "statistic", "p_value", "ok")}
            chars = _characteristics(all_est, i, j)
            fb = sr.feedback[i][j] if sr.feedback else None
            fbd = fb.to_dict() if fb is not None else None
            integ = bool(all_est.integrating[i])
            pair = {"output": o, "input": u, "n_p": n, "n_k": int(all_est.n_k[i, j]),
                    "settled": bool(sr.settled[i, j]), "integrating": integ,
                    "gain": None if integ else float(all_est.step[i, j, n - 1]),
                    "gain_std": None if integ else float(all_est.step_std[i, j, n - 1]),
                    "rate": float(all_est.rate[i, j]) if integ else None,
                    "rate_std": float(all_est.rate_std[i, j]) if integ else None,
                    "method": all_est.method,
                    "agreement": agr, "feedback": fbd, "characteristics": chars}
            pair["warnings"] = pair_warnings(
                inp=u, out=o, tag_in=tags[u], tag_out=tags[o], noise=cfg.estimation.noise,
                noise_model=nm, whiteness_p=lb["p_value"], feedback=fbd,
                feedback_mode=cfg.estimation.feedback, instruments=prep.instruments,
                n_k=pair["n_k"], n_p=n, n_p_min=cfg.search.n_p_min,
                settled=pair["settled"], significant=_significant(pair), dt_s=prep.dt_s,
                end_jump=end_jump_z(*_settling_increments(all_est, i, j)),
                agreement=agr)
            pairs.append(pair)
            metrics += _pair_metrics(o, u, pair)
    d = all_est.diagnostics
    checks = {
        "dt_s": prep.dt_s,
        "sampling": prep.sampling,
        "conditioning": prep.conditioning,
        "estimation": {"method": all_est.method, "noise": cfg.estimation.noise,
                       "feedback": cfg.estimation.feedback,
                       "instruments": {r: tags[r] for r in prep.instruments},
                       **({"first_stage": {ins[k]: v for k, v in
                                           all_est.extra["first_stage"].items()
                                           if k < len(ins)}}
                          if "first_stage" in all_est.extra else {})},
        "noise_model": {o: all_est.noise_model[i].to_dict() for i, o in enumerate(outs)},
        "search": {
            "n_p": {f"{outs[i]}<-{ins[j]}": int(sr.n_p[i, j])
                    for i in range(len(outs)) for j in range(len(ins))},
            "n_k": {f"{outs[i]}<-{ins[j]}": int(all_est.n_k[i, j])
                    for i in range(len(outs)) for j in range(len(ins))},
            "n_d": sr.n_d, "window_samples": sr.window_samples,
            "windows": window_status,
            "bic_order": None if sr.bic_order is None else
            {outs[i]: int(v) for i, v in enumerate(sr.bic_order)},
            "noise_model_at_n_p_max": {outs[i]: m.to_dict()
                                       for i, m in enumerate(sr.noise_model)},
            "order_trace": _named_trace(sr.order_trace, outs, ins),
            "nd_trace": _named_trace(sr.nd_trace, outs, ins),
        },
        "pairs": pairs,
        "residuals": {
            "whiteness": whiteness,
            "input_cross_correlation": xcorr,
        },
        "excitation": {
            "condition_number": d.condition_number,
            "input_rms": {u: float(v) for u, v in zip(ins, d.input_rms)},
            "input_correlation": {ins[a]: {ins[b]: float(d.input_correlation[a, b])
                                           for b in range(len(ins))} for a in range(len(ins))},
            "vif": {u: float(v) for u, v in zip(ins, d.vif)},
            "near_collinear": [{"inputs": [ins[a], ins[b]], "correlation": c}
                               for a, b, c in d.near_collinear],
        },
        "data_quality": {
            "grid_dt_s": prep.recording.dt_s,
            "samples_at_dt": int(prep.good.shape[0]),
            "samples_used_all": int(all_est.n_d),
            "signals": prep.recording.quality,
            "ingest": prep.recording.ingest,
        },
    }
    status = "ok"
    if any(p["agreement"]["verdict"] == "fail" for p in pairs):
        status = "windows_disagree"
    sig = _signals_table(prep)
    rtab = pl.DataFrame({
        "window": ["all"] * (res.shape[0] * len(outs)),
        "time": np.concatenate([prep.time] * len(outs)),
        "output": np.repeat(outs, res.shape[0]),
        "residual": res.T.ravel()}).with_columns(
            pl.col("time").cast(pl.Datetime("us", "UTC"))).filter(
                pl.col("residual").is_not_nan())  # undefined where lags touch a gap
    report = _report_md(cfg, prep, sr, pairs, checks, status)
    return Summary(steps, sig, rtab, checks, metrics, report, status)


def _settling_increments(est: StepResponseEstimate, i: int, j: int):
    """The increments that must die out and their stds: ``delta_h`` for a self-regulating
    pair, ``delta_g`` (the change of slope) for an integrating one — from the step
    covariance, so a level-form pair's precise final slope is compared with the noisy
    transient slopes before it as a difference, not as a value."""
    n = int(est.n_p[i, j])
    D = np.eye(n) - np.eye(n, k=-1)
    T = D @ D if est.integrating[i] else D
    inc = T @ est.step[i, j, :n]
    if est.step_cov is None:
        return inc, (est.delta_h_std[i, j, :n] if not est.integrating[i] else
                     np.full(n, np.inf))
    var = np.einsum("ab,bc,ac->a", T, est.step_cov[i, j, :n, :n], T)
    return inc, np.sqrt(np.clip(var, 0, None))


def _significant(pair: dict) -> bool:
    """The pair's gain (rate) is more than 2 standard deviations from zero."""
    v, s = (pair["rate"], pair["rate_std"]) if pair["integrating"] else \
        (pair["gain"], pair["gain_std"])
    return bool(abs(v) > 2 * s)


def _named_trace(trace: list, outs: list[str], ins: list[str]) -> list:
    out = []
    for t in trace:
        t = dict(t)
        if "pairs" in t:
            t["pairs"] = [{**p, "output": outs[p["output"]], "input": ins[p["input"]]}
                          for p in t["pairs"]]
        out.append(t)
    return out


def _signals_table(prep: Prepared) -> pl.DataFrame:
    rec = prep.recording
    cond = np.concatenate([prep.x, prep.y] + ([prep.r] if prep.r is not None else []), axis=1)
    frames = []
    for k, (name, role) in enumerate(zip(rec.names, rec.roles)):
        frames.append(pl.DataFrame({
            "time": prep.time, "signal": [name] * prep.time.size,
            "role": [role] * prep.time.size,
            "raw": prep.raw[:, k], "conditioned": cond[:, k],
            "good": prep.good[:, k]}).with_columns(
                pl.col("raw").fill_nan(None), pl.col("conditioned").fill_nan(None)))
    return pl.concat(frames).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def _unit(cfg, name: str) -> str:
    s = {**cfg.signals.inputs, **cfg.signals.outputs}.get(name)
    return (s.unit if s is not None and s.unit else "")


def _report_md(cfg, prep: Prepared, sr: SearchResult, pairs: list, checks: dict,
               status: str) -> str:
    est = checks["estimation"]
    method = {"least_squares": "least squares, white-noise assumption (the thesis)",
              "prediction_error": "least squares with a noise model per output "
                                  "(prediction-error method)",
              "instrumental_variables": "instrumental variables ("
                                        + ", ".join(est["instruments"]) + ")"}[est["method"]]
    lines = [f"# plantdyn run: {cfg.job}", "",
             f"Status: **{status}**. Sample period T = {prep.dt_s:g} s "
             f"(decimation {prep.decimation} from the {prep.recording.dt_s:g} s grid, "
             f"{prep.sampling.get('source')}); conditioning: {prep.conditioning['method']}; "
             f"N_d per window = {sr.n_d}, {len(sr.windows)} disjoint windows. "
             f"Estimator: {method}.", "",
             "| output | input | N_p | N_p·T (s) | gain ± σ | rate K ± σ (/s) | windows (p) "
             "| feedback (p) | warnings |",
             "|---|---|---|---|---|---|---|---|---|"]
    for p in pairs:
        uo, ui = _unit(cfg, p["output"]), _unit(cfg, p["input"])
        unit = f" {uo}/{ui}" if uo and ui else ""
        gain = "" if p["gain"] is None else f"{p['gain']:.4g} ± {p['gain_std']:.2g}{unit}"
        rate = "" if p["rate"] is None else f"{p['rate']:.4g} ± {p['rate_std']:.2g}"
        a = p["agreement"]
        agr = a["verdict"] + (f" ({a['p_value']:.2g})" if a.get("p_value") is not None else "")
        fb = p["feedback"]
        fbs = "not tested" if fb is None else \
            (f"**yes** ({fb['p_value']:.2g})" if fb["detected"] else f"no ({fb['p_value']:.2g})")
        codes = ", ".join(w["code"] for w in p["warnings"]) or "none"
        lines.append(f"| {p['output']} | {p['input']} | {p['n_p']} | {p['n_p'] * prep.dt_s:g} "
                     f"| {gain} | {rate} | {agr} | {fbs} | {codes} |")
    lines += ["", "Noise models (per output, chosen from the data):", ""]
    for o, nm in checks["noise_model"].items():
        pole = nm.get("dominant_pole")
        kind = "white" if nm["order"] == 0 else f"AR({nm['order']})" + \
            (f", slowest pole {pole:.3f}" if pole is not None else "")
        lines.append(f"- {o}: {kind}, {nm['form']} form, innovation σ "
                     f"{nm['innovation_std']:.3g}; prediction errors "
                     f"{'white' if checks['residuals']['whiteness'][o]['white'] else 'NOT white'}"
                     f" (Ljung–Box p = {_fmt_p(checks['residuals']['whiteness'][o]['p_value'])})")
    warned = [p for p in pairs if p["warnings"]]
    lines += ["", "## When to distrust a pair", ""]
    if not warned:
        lines.append("No warnings: residuals white under the noise models, no feedback "
                     "without an instrument, N_p inside its bounds, windows agree.")
    for p in warned:
        for w in p["warnings"]:
            lines.append(f"- **{p['output']}<-{p['input']}** ({w['code']}): {w['message']}.")
    masked = {n: q["masked"] for n, q in prep.recording.quality.items() if q["masked"]}
    lines += ["", f"Masked grid samples per signal: {masked or 'none'}."]
    grid = prep.recording.ingest.get("grid", {})
    if len(grid.get("islands", [])) > 1:
        lines.append(f"The record has {len(grid['islands'])} stretches separated by breaks "
                     "longer than every signal's max_gap_s (not gridded).")
    for name, sp in prep.recording.ingest.get("spikes", {}).items():
        lines.append(f"Spikes masked in {name}: {sp['samples']} sample(s) far from their "
                     f"neighbours (largest |value| {sp['largest']:.4g}, first at {sp['first']}); "
                     "quality.spikes: off keeps them.")
    for d in grid.get("stray_samples", []):
        lines.append(f"Stray samples left out: {d['samples']} of {d['signal']} (tag {d['tag']}) "
                     f"between {d['first']} and {d['last']}, far from the rest of the record "
                     "— check the export's timestamps.")
    return "\n".join(lines) + "\n"


def _fmt_p(p) -> str:
    return "n/a" if p is None else f"{p:.2g}"


def write_run(cfg, summary: Summary, *, files: list[str], timings: dict[str, float],
              run_id: str | None = None) -> tuple[str, Path, Path | None]:
    """Write the run directory atomically (store) with its Rerun recording.

    Returns ``(run_id, run_dir, recording_path)``.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``storage_root``, ``job``, ``rerun``).
    summary : Summary
        Tables and documents from :func:`summarise`.
    files : list of str
        Input files, recorded in the run's manifest.
    timings : dict of str to float
        Seconds per stage, recorded with the run.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    """
    from pipeline.adapters.store import ResultStore

    store = ResultStore(cfg.storage_root)
    resolved = cfg.model_dump(mode="json")
    rrd = None
    with store.new_run(cfg.job, run_id=run_id, config=resolved, inputs=files) as run:
        for stage, sec in timings.items():
            run.record_timing(stage, sec)
        run.write_step_responses(summary.step_responses)
        run.write_signals(summary.signals)
        run.write_residuals(summary.residuals)
        run.write_checks(summary.checks)
        run.write_report(summary.report_md)
        run.set_status(summary.status)
        run.add_metrics(summary.metrics)
        if cfg.rerun.enabled:
            from pipeline.adapters.rerun_sink import render_run

            t0 = time.perf_counter()
            trends = store.trend(cfg.job) if store.list_runs(cfg.job).height else None
            render_run(run.path, trends=trends, ident=f"{cfg.job}/{run.run_id}")
            run.record_timing("rerun", time.perf_counter() - t0)
        rid = run.run_id
    run_dir = cfg.storage_root / cfg.job / rid
    if cfg.rerun.enabled:
        rrd = run_dir / "recording.rrd"
    return rid, run_dir, rrd


def run_job(cfg, *, files: list[Path] | None = None, run_id: str | None = None,
            progress: Progress = _quiet) -> RunReport:
    """Run an estimation job end to end (no Prefect): the same stages the flow runs.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    files : list of Path, optional
        Files to read; ``None`` resolves the job's ``source``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message)
        Told when each stage starts and ends; its ``bar`` (if any) shows ingest and search.
    """
    timings: dict[str, float] = {}

    def stage(name, fn, *a, bar: tuple[str, float] | None = None, **k):
        progress(name, "start")
        t0 = time.perf_counter()
        if bar is None:
            out = fn(*a, **k)
        else:
            with bar_of(progress, name, *bar) as tick:
                out = fn(*a, tick=tick, **k)
        timings[name] = time.perf_counter() - t0
        progress(name, f"done in {timings[name]:.2f} s")
        return out

    rec = stage("ingest", load_recording, cfg, files, bar=("MB", 1e-6))
    prep = stage("prepare", prepare, cfg, rec)
    sr = stage("search", search_orders, cfg, prep, bar=("steps", 1.0))
    choice = (sr.n_p, sr.n_k, sr.noise, sr.instruments)
    all_est = stage("estimate_all", estimate_window, prep, None, *choice)
    wins = []
    for k, w in enumerate(sr.windows):
        wins.append(stage(f"estimate_w{k}", estimate_window, prep, tuple(w), *choice))
    summary = stage("summarise", summarise, cfg, prep, sr, all_est, wins)
    return finish_run(cfg, summary, prep, sr, timings, run_id=run_id, progress=progress)


def finish_run(cfg, summary: Summary, prep: Prepared, sr: SearchResult, timings: dict,
               *, run_id: str | None = None, progress: Progress = _quiet) -> RunReport:
    """Write the results and build the :class:`RunReport`.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    summary : Summary
        Tables and documents from :func:`summarise`.
    prep : Prepared
        The conditioned record (files, inputs, outputs, sample period).
    sr : SearchResult
        The order search's outcome (``n_p``, ``n_d``).
    timings : dict
        Seconds per stage; the ``store`` stage is added to it.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message)
        Told before the run directory is written (stage ``"store"``).
    """
    progress("store", "writing run directory")
    t0 = time.perf_counter()
    rid, run_dir, rrd = write_run(cfg, summary, files=list(prep.recording.files),
                                  timings=timings, run_id=run_id)
    timings["store"] = time.perf_counter() - t0
    ins, outs = prep.inputs, prep.outputs
    n_p = {f"{o}<-{u}": int(sr.n_p[i, j]) for i, o in enumerate(outs) for j, u in enumerate(ins)}
    verdicts = {f"{p['output']}<-{p['input']}": p["agreement"]["verdict"]
                for p in summary.checks["pairs"]}
    return RunReport(cfg.job, rid, run_dir, summary.status, prep.dt_s, n_p, sr.n_d, verdicts,
                     prep.recording.files, rrd, timings)
