"""Composition: ``run_job(config) -> RunReport``, callable from a REPL.

The estimation job is a readable sequence of stage functions; the Prefect flow in
``flows/estimate.py`` wraps each one in a task (and maps :func:`estimate_window` over
windows), so the flow and a plain call produce the same results.

    load_recording -> prepare -> search_orders -> estimate_window (all + each window)
      -> summarise -> [monitor: compare with the baseline run] -> write_run (store + Rerun)

Decisions (also in docs/method.md, "What happens in a run"):

* Grid and a configured sample period: :mod:`pipeline.jobs.recording` (shared by every
  workflow).
* Sample period: α_T on the longest stretch where every signal is good (an integrating
  output's first difference; step-wise signals do not set T; never a T at which the record
  is too short for the N_p search — :mod:`pipeline.identification.sampling`); the record is
  then averaged-then-decimated (a decimated sample is bad if any source sample is).
* Conditioning with gaps: masked samples are filled by linear interpolation only to let
  the transform run (mean, detrend, high-pass need a gap-free series), then masked again
  (for ``difference`` the mask is shifted with the difference).  The estimator never sees
  a filled value.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.estimation.alt_estimates import estimate_correlation_method
from pipeline.identification.conditioning import Conditioning, as_masked_zero, interpolate_gaps
from pipeline.errors import (
    DataQualityError,
    InstrumentError,
    InsufficientDataError,
    PipelineError,
    SingularSystemError,
)
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.jobs.summary import summarise
from pipeline.jobs.job_types import (
    Prepared,
    Recording,
    RunReport,
    Summary,
    WindowFailure,
)
from pipeline.readouts.monitor import monitor_banner
from pipeline.jobs.monitoring import monitor_run
from pipeline.progress import Progress, Tick, quiet, silent
from pipeline.jobs.recording import configured_decimation, load_recording, longest_common_good
from pipeline.identification.sampling import (
    choose_sample_period,
    resample_average_masked,
    sample_period_s,
)
from pipeline.identification.search import SearchResult, search
from pipeline.jobs.stages import StageRunner


__all__ = [
    "Recording",
    "Prepared",
    "RunReport",
    "load_recording",
    "prepare",
    "search_orders",
    "estimate_settings",
    "estimate_window",
    "searched_windows",
    "summarise",
    "write_run",
    "run_job",
    "conditioning_spec",
    "HIGHPASS_PERIODS",
]


HIGHPASS_PERIODS = 500
"""``conditioning.method: highpass`` without ``cutoff_period_s``: the cutoff period is
this many sample periods T, above any horizon the search allows by default
(:data:`pipeline.identification.search.N_P_MAX_CAP` lags at T), so the filter removes
drift without touching the responses it estimates."""


def conditioning_spec(section, dt_s: float) -> Conditioning:
    """The job's ``conditioning`` section as the core's validated spec (the one place its
    defaults are decided).

    Parameters
    ----------
    section : ConditioningConfig
        The job's ``conditioning`` section.
    dt_s : float
        The sample period T (s) the record is conditioned at.
    """
    if section.method == "difference":
        return Conditioning("difference", kdiff1=section.kdiff1)
    if section.method == "highpass":
        return Conditioning("highpass", order=section.order,
                            cutoff_period_s=(section.cutoff_period_s
                                             or HIGHPASS_PERIODS * dt_s))
    return Conditioning(section.method)


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
    factor = configured_decimation(cfg, rec.grid_dt_s)
    if factor is not None:
        sampling = {"dt_s": sample_period_s(factor, rec.grid_dt_s), "decimation": factor, "source": "config"}
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
        # integrating outputs: α_T of the first difference (what eq. 3.15 regresses); the
        # search sees every sample where the model's signals are good, not just [a, b)
        choice = choose_sample_period(
            {rec.names[k]: rec.values[a:b, k] for k in model}, grid_dt_s=rec.grid_dt_s,
            roles={rec.names[k]: rec.roles[k] for k in model},
            integrating={o: s.integrating for o, s in cfg.signals.outputs.items()},
            target_input=cfg.sampling.target_input, target_output=cfg.sampling.target_output,
            n_search_samples=int(rec.good[:, model].all(axis=1).sum()),
            n_p_min=cfg.search.n_p_min)
        factor = int(choice.decimation)
        sampling = {**choice.to_dict(), "source": "alpha_t"}
    vals, good = resample_average_masked(as_masked_zero(rec.values), rec.good, factor)
    n = vals.shape[0]
    tgrid = rec.time[: n * factor : factor] if factor > 1 else rec.time[:n]
    dt_s = sample_period_s(factor, rec.grid_dt_s)
    n_x = sum(r == "input" for r in rec.roles)
    n_y = sum(r == "output" for r in rec.roles)
    filled, _ = interpolate_gaps(vals, good)
    spec = conditioning_spec(cfg.conditioning, dt_s)
    # instruments are conditioned like the inputs (the same transform on every signal)
    xr = np.concatenate([filled[:, :n_x], filled[:, n_x + n_y:]], axis=1)
    cond = spec.apply(xr, filled[:, n_x:n_x + n_y], dt_s=dt_s)
    g = good
    t = tgrid
    raw = np.where(good, vals, np.nan)
    if spec.method == "difference":
        k = spec.kdiff1
        g = good[k:] & good[:-k]
        t = tgrid[: g.shape[0]]
        raw = raw[: g.shape[0]]
    xc = np.where(g[:, :n_x], cond.x[:, :n_x], np.nan)
    yc = np.where(g[:, n_x:n_x + n_y], cond.y, np.nan)
    rc = np.where(g[:, n_x + n_y:], cond.x[:, n_x:], np.nan) if cond.x.shape[1] > n_x else None
    integ = tuple(cfg.signals.outputs[o].integrating for o in cfg.signals.outputs)
    return Prepared(rec, factor, sampling, t, raw, xc, yc, g,
                    {"method": spec.method, **spec.params}, integ, rc)


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

    from pipeline.estimation.solve import describe_singular

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
        sr = search(
            as_masked_zero(prep.x), as_masked_zero(prep.y), dt=prep.dt_s,
            integrating=prep.integrating, mask=prep.good_xy, n_p_max=s.n_p_max,
            n_p_min=s.n_p_min, n_p=n_p, n_d_start=s.n_d_start, max_windows=s.max_windows,
            estimate_windows=False, noise=e.noise, n_k=cfg.n_k_matrix(), instruments=prep.r,
            feedback=e.feedback, tick=tick)
    except InstrumentError as exc:
        raise _instrument_error(cfg, prep, exc) from None
    except SingularSystemError as exc:
        raise _named(exc, prep) from None
    for trial in sr.nd_trace:  # the core numbers signals; the report names them
        if "error" in trial:
            trial["error"] = _signal_names(trial["error"], cfg, prep)
    return sr


def _signal_names(text: str, cfg, prep: Prepared) -> str:
    """A core message's ``input k`` / ``output k`` as the job's names and tags."""
    import re

    tags = cfg.tags()
    text = re.sub(r"\binput (\d+)\b", lambda m: f"input {prep.inputs[int(m.group(1))]} "
                  f"(tag {tags[prep.inputs[int(m.group(1))]]})", text)
    return re.sub(r"\boutput (\d+)\b", lambda m: f"output {prep.outputs[int(m.group(1))]}",
                  text)


def estimate_settings(cfg, sr: SearchResult, n_samples: int) -> tuple:
    """The positional settings :func:`estimate_window` takes after ``prep, window``: the
    search's choices and the estimator ``estimation.method`` resolves to, with its horizon
    (:func:`pipeline.identification.method_choice.choose_method`; one place for both paths).

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``estimation.method``).
    sr : SearchResult
        The order search's outcome (``n_p``, ``settled``, ``n_k``, ``noise``,
        ``instruments``).
    n_samples : int
        Samples of the conditioned record (``prep.x.shape[0]``).
    """
    mc = method_choice(cfg, sr, n_samples)
    return (mc.n_p, sr.n_k, sr.noise, sr.instruments, mc.method, sr.window_noise)


def searched_windows(sr: SearchResult, settings: tuple) -> dict:
    """The windows the search's stage 2 estimated (``SearchResult.window_estimates``,
    the first and last of ``sr.windows``) when the job estimates with the search's own
    settings -- least squares at the search's orders -- so that each window is
    estimated once; ``{}`` when the job's estimator differs (kernel FIR, the
    correlation method, another horizon).

    Parameters
    ----------
    sr : SearchResult
        The order search's outcome.
    settings : tuple
        :func:`estimate_settings` of the job.
    """
    n_p, _, _, _, method, _ = settings
    if method != "ls" or not np.array_equal(np.broadcast_to(n_p, sr.n_p.shape), sr.n_p):
        return {}
    return dict(sr.window_estimates)


def method_choice(cfg, sr: SearchResult, n_samples: int):
    """:func:`pipeline.identification.method_choice.choose_method` for the job and its search.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``estimation.method``).
    sr : SearchResult
        The order search's outcome.
    n_samples : int
        Samples of the conditioned record.
    """
    from pipeline.identification.method_choice import choose_method

    return choose_method(cfg.estimation.method, sr.n_p, sr.settled, n_samples,
                         instruments=sr.instruments)


def estimate_window(prep: Prepared, window: tuple[int, int] | None, n_p, n_k=0,
                    noise="white", use_instruments: bool = False, method: str = "ls",
                    window_noise: tuple = ()):
    """Estimate on one window (``None`` = every usable sample) with the search's choices
    (``n_p``, ``n_k``, the noise setting, whether to use the instruments and the disjoint
    windows' noise models: ``SearchResult.n_p, .n_k, .noise, .instruments,
    .window_noise``) by the job's ``estimation.method``.

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
        Order per pair; ``tc``/``dc`` take the largest for every pair.
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair (``SearchResult.n_k``).
    noise : ``"white"``, ``"auto"`` or int
        The estimator's noise setting (``SearchResult.noise``; not ``correlation``).
    use_instruments : bool
        Estimate with ``prep.r`` as instruments (``SearchResult.instruments``; ``ls`` only).
    method : ``"ls"``, ``"correlation"``, ``"tc"`` or ``"dc"``
        The estimator ``estimation.method`` resolved to (:func:`estimate_settings`).
    window_noise : tuple of NoiseModel
        The noise models a disjoint window of a least-squares estimate is estimated with
        (``SearchResult.window_noise``; ``()``: its own); the all-data estimate fits its
        own.
    """
    a, b = window if window is not None else (0, prep.x.shape[0])
    x, y = as_masked_zero(prep.x[a:b]), as_masked_zero(prep.y[a:b])
    try:
        if method == "correlation":  # masked samples enter as zeros (the conditioned mean)
            return estimate_correlation_method(x, y, n_p=n_p, dt=prep.dt_s,
                                               integrating=prep.integrating, n_k=n_k)
        if method in ("tc", "dc"):
            from pipeline.estimation.kernel_fir import estimate_kernel

            return estimate_kernel(x, y, n_p=int(np.max(n_p)), dt=prep.dt_s,
                                   integrating=prep.integrating, mask=prep.good_xy[a:b],
                                   n_k=n_k, noise=noise, kernel=method)
        return estimate_step_responses(
            x, y, n_p=n_p, dt=prep.dt_s,
            integrating=prep.integrating, mask=prep.good_xy[a:b], noise=noise, n_k=n_k,
            instruments=None if (prep.r is None or not use_instruments) else prep.r[a:b],
            noise_models=(window_noise or None) if window is not None else None)
    except DataQualityError as exc:
        exc = _named(exc, prep)
        if window is None:
            raise exc from None
        return WindowFailure(tuple(window), str(exc))


def write_run(cfg, summary: Summary, *, files: list[str], timings: dict[str, float],
              run_id: str | None = None, progress: Progress = quiet
              ) -> tuple[str, Path, Path | None]:
    """Write the run directory atomically (store) with its report and Rerun recording,
    each part a timed stage (``store/hash_inputs``, ``store/tables``,
    ``store/html_report``, ``store/rerun``, ``store/commit``) told to ``progress`` with its
    done line; all but the commit are recorded in the manifest's timings (the commit
    writes the manifest).

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
        Seconds per stage, recorded with the run; the store's parts are added to it.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message)
        Told when each part starts and ends.
    """
    from pipeline.adapters.store import ResultStore

    store = ResultStore(cfg.storage_root)
    resolved = cfg.model_dump(mode="json")
    stage = StageRunner(progress)
    rrd = None
    from pipeline.adapters.store.run_writer import normalise_inputs

    hashed = stage("store/hash_inputs", normalise_inputs, files)  # sha256 of every input
    with store.new_run(cfg.job, run_id=run_id, config=resolved, inputs=hashed) as run:
        stage("store/tables", _write_tables, run, summary)
        stage("store/html_report", _write_report_html, run, resolved, files)
        if cfg.rerun.enabled:
            stage("store/rerun", _write_recording, cfg, store, run, resolved)
        for name, sec in {**timings, **stage.timings}.items():
            key = name.removeprefix("store/")  # manifest keys: tables, html_report, …
            if key not in run.timings_s:  # add_report_html records its own
                run.record_timing(key, sec)
        rid = run.run_id
        progress("store/commit", "start")  # manifest, rename into place, catalog row
        t0 = time.perf_counter()
    stage.timings["store/commit"] = time.perf_counter() - t0
    progress("store/commit", f"done in {stage.timings['store/commit']:.2f} s")
    timings.update(stage.timings)
    run_dir = store.run_dir(cfg.job, rid)
    if cfg.rerun.enabled:
        rrd = run_dir / "recording.rrd"
    return rid, run_dir, rrd


def _write_tables(run, summary: Summary) -> None:
    """The run's tables and documents; the long ones a chunk at a time."""
    run.write_step_responses(summary.step_responses)
    run.write_signals(summary.signals)
    run.write_residuals(summary.residuals)
    run.write_checks(summary.checks)
    run.write_report(summary.report_md)
    run.set_status(summary.status)
    run.add_metrics(summary.metrics)


def _write_report_html(run, resolved: dict, files: list[str]) -> None:
    """``report.html`` from the files written so far (matplotlib is imported here, inside
    the timed stage)."""
    from pipeline.adapters.html_report import add_report_html

    add_report_html(run, config=resolved, inputs=files)


def _write_recording(cfg, store, run, resolved: dict) -> None:
    """``recording.rrd`` from the files written so far (and the job's earlier runs)."""
    from pipeline.adapters.rerun_sink import render_run

    trends = store.trend(cfg.job) if store.list_runs(cfg.job).height else None
    render_run(run.path, trends=trends, ident=f"{cfg.job}/{run.run_id}", config=resolved)


def run_job(cfg, *, files: list[Path] | None = None, run_id: str | None = None,
            progress: Progress = quiet, stage: StageRunner | None = None) -> RunReport:
    """Run an estimation job end to end: the one stage list of the estimation workflow.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    files : list of Path, optional
        Files to read; ``None`` resolves the job's ``source``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message)
        Told when each stage starts and ends and what it found; its ``bar`` (if any)
        shows ingest and search.
    stage : StageRunner, optional
        Runs each stage: in this process (default, ``--no-prefect``) or as Prefect tasks
        (``flows.common.TaskStages``, the ``estimate`` flow).
    """
    stage = stage if stage is not None else StageRunner(progress)
    rec = stage("ingest", load_recording, cfg, files, bar=("MB", 1e-6))
    progress("ingest", f"{rec.values.shape[0]} grid samples at {rec.grid_dt_s:g} s, "
             f"{sum(q['masked'] for q in rec.quality.values())} masked")
    prep = stage("prepare", prepare, cfg, rec)
    progress("prepare", f"T = {prep.dt_s:g} s (decimation {prep.decimation}), "
             f"conditioning {prep.conditioning['method']}")
    sr = stage("search", search_orders, cfg, prep, bar=("steps", 1.0))
    progress("search", f"N_p {sr.n_p.ravel().tolist()}, N_d {sr.n_d}, "
             f"{len(sr.windows)} windows")
    windows = [None, *(tuple(w) for w in sr.windows)]  # all data first
    settings = estimate_settings(cfg, sr, prep.x.shape[0])
    known = searched_windows(sr, settings)
    todo = [w for w in windows if w not in known]
    done = dict(zip(todo, stage.map("estimate", estimate_window, prep, todo, *settings,
                                    over=1)))
    ests = [known[w] if w in known else done[w] for w in windows]
    summary = stage("summarise", summarise, cfg, prep, sr, ests[0], ests[1:])
    if cfg.monitor is not None:  # the baseline is read before the new run is written
        summary, run_id = stage("monitor", monitor_run, cfg, summary, run_id)
        progress("monitor", monitor_banner(summary.checks["monitor"]))
    report = stage("store", finish_run, cfg, summary, prep, sr, dict(stage.timings),
                   run_id=run_id, progress=progress)
    report.timings_s.update(stage.timings)  # the store stage's own time
    return report


def finish_run(cfg, summary: Summary, prep: Prepared, sr: SearchResult, timings: dict,
               *, run_id: str | None = None, progress: Progress = quiet) -> RunReport:
    """Write the results and build the :class:`RunReport` (the ``store`` stage).

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
        Seconds per stage so far; the store's parts are added to it (the report's
        timings).
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message)
        Told when the parts of the store stage (``"store/…"``) start and end.
    """
    rid, run_dir, rrd = write_run(cfg, summary, files=list(prep.recording.files),
                                  timings=timings, run_id=run_id, progress=progress)
    ins, outs = prep.inputs, prep.outputs
    n_p = {f"{o}<-{u}": int(sr.n_p[i, j]) for i, o in enumerate(outs) for j, u in enumerate(ins)}
    verdicts = {f"{p['output']}<-{p['input']}": p["agreement"]["verdict"]
                for p in summary.checks["pairs"]}
    return RunReport(cfg.job, rid, run_dir, summary.status, prep.dt_s, n_p, sr.n_d, verdicts,
                     prep.recording.files, rrd, summary.report, timings)
