"""The ``estimate`` flow: ingest -> condition -> sample period -> windows -> N_p/N_d search
-> estimates -> checks -> [monitor vs the baseline run] -> store -> Rerun.  Each task body
is one call into ``pipeline.jobs`` (``pipeline.monitor_job`` for the monitor)."""

from __future__ import annotations

import time
from pathlib import Path

from prefect import flow, task, unmapped
from prefect.artifacts import (
    create_markdown_artifact,
    create_progress_artifact,
    create_table_artifact,
    update_progress_artifact,
)
from prefect.cache_policies import NO_CACHE

from flows.common import (
    artifact_key,
    console_without_user_error_tracebacks,
    flow_started,
    retry_transient_io,
    say,
    task_runner_for,
)
from pipeline import jobs, monitor_job, recording
from pipeline.adapters.config import load_job
from pipeline.monitor import monitor_banner, monitor_markdown
from pipeline.stages import StageRunner
from pipeline.adapters.progress import bar as progress_bar

# Big arrays flow between tasks: hashing them for a cache key would cost more than the
# work, and results are not persisted, so caching is off.
_T = {"cache_policy": NO_CACHE, "persist_result": False}


@task(name="ingest", retries=2, retry_delay_seconds=1, retry_condition_fn=retry_transient_io, **_T)
def ingest_task(cfg, files):
    """Ingest and grid the job's files (:func:`pipeline.recording.load_recording`), with a
    progress bar on a terminal.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    files : list of Path or None
        Files to read; ``None`` resolves the job's ``source``.
    """
    with progress_bar("ingest", "MB", 1e-6) as tick:  # a bar on a terminal only
        return recording.load_recording(cfg, files, tick=tick)


@task(name="prepare", **_T)
def prepare_task(cfg, rec):
    """Sample period, decimation and conditioning (:func:`pipeline.jobs.prepare`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    rec : Recording
        The gridded signals from :func:`ingest_task`.
    """
    return jobs.prepare(cfg, rec)


@task(name="search", **_T)
def search_task(cfg, prep):
    """N_p/N_d search (:func:`pipeline.jobs.search_orders`), with a progress bar on a
    terminal.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    prep : Prepared
        The conditioned record from :func:`prepare_task`.
    """
    with progress_bar("search", "steps") as tick:
        return jobs.search_orders(cfg, prep, tick=tick)


@task(name="estimate-window", **_T)
def estimate_task(prep, window, n_p, n_k, noise, use_instruments, method):
    """Estimate on one window (:func:`pipeline.jobs.estimate_window`); mapped over windows.

    Parameters
    ----------
    prep : Prepared
        The conditioned record.
    window : (int, int) or None
        Sample slice of ``prep``; ``None`` for every sample.
    n_p, n_k : int array (n_y, n_x)
        Order and known delay per pair (``SearchResult.n_p``, ``.n_k``).
    noise : ``"white"``, ``"auto"`` or int
        The estimator's noise setting (``SearchResult.noise``).
    use_instruments : bool
        Estimate with the instruments (``SearchResult.instruments``).
    method : str
        The job's ``estimation.method``.
    """
    return jobs.estimate_window(prep, window, n_p, n_k, noise, use_instruments, method)


@task(name="summarise", **_T)
def summarise_task(cfg, prep, sr, all_est, wins):
    """Tables, checks and report of the run (:func:`pipeline.jobs.summarise`).

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
    wins : list of StepResponseEstimate or WindowFailure
        One per ``sr.windows``, in order.
    """
    return jobs.summarise(cfg, prep, sr, all_est, wins)


@task(name="monitor", **_T)
def monitor_task(cfg, summary, run_id):
    """Compare the run with the job's baseline run before it is written
    (:func:`pipeline.monitor_job.monitor_run`); returns ``(summary, run_id)``.

    Parameters
    ----------
    cfg : JobConfig
        The validated job, with a ``monitor`` section.
    summary : Summary
        From :func:`summarise_task`.
    run_id : str or None
        Id of the run directory; ``None`` chooses one now.
    """
    return monitor_job.monitor_run(cfg, summary, run_id)


@task(name="store", retries=2, retry_delay_seconds=1, retry_condition_fn=retry_transient_io, **_T)
def store_task(cfg, summary, prep, sr, timings, run_id, progress=None):
    """Write the run directory and build the report (:func:`pipeline.jobs.finish_run`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    summary : Summary
        From :func:`summarise_task`.
    prep : Prepared
        The conditioned record.
    sr : SearchResult
        The order search's outcome.
    timings : dict
        Seconds per stage, recorded with the run.
    run_id : str or None
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message), optional
        Told when the store stage and its parts start and end (with their done lines).
    """
    return jobs.finish_run(cfg, summary, prep, sr, timings, run_id=run_id,
                           progress=progress or (lambda stage, message: None))


def _estimate_windows(prep, windows: list, settings: tuple) -> list:
    """:func:`estimate_task` mapped over ``windows`` (all data first), results in order."""
    return estimate_task.map(unmapped(prep), windows,
                             *[unmapped(v) for v in settings]).result()


@flow(name="estimate", log_prints=True)
def estimate_flow(job_path: str, files: list[str] | None = None, run_id: str | None = None):
    """Estimate step responses for one job YAML (optionally on given files).

    Parameters
    ----------
    job_path : str
        The job YAML file.
    files : list of str, optional
        Files to read instead of the job's ``source.path``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    """
    flow_started()
    cfg = load_job(job_path)
    progress = create_progress_artifact(0.0, key=artifact_key(cfg.job, "progress"),
                                        description=f"{cfg.job}: estimation progress")
    start = time.perf_counter()
    stage = StageRunner(lambda name, message: say(start, name, message))
    rec = stage("ingest", ingest_task, cfg, [Path(f) for f in files] if files else None)
    update_progress_artifact(progress, 15.0, description="ingested")
    say(start, "ingest", f"{rec.values.shape[0]} grid samples at {rec.dt_s:g} s, "
         f"{sum(q['masked'] for q in rec.quality.values())} masked")
    prep = stage("prepare", prepare_task, cfg, rec)
    say(start, "prepare", f"T = {prep.dt_s:g} s (decimation {prep.decimation}), "
         f"conditioning {prep.conditioning['method']}")
    sr = stage("search", search_task, cfg, prep)
    update_progress_artifact(progress, 50.0, description=f"N_p chosen, N_d={sr.n_d}")
    say(start, "search", f"N_p {sr.n_p.ravel().tolist()}, N_d {sr.n_d}, "
         f"{len(sr.windows)} windows")
    windows = [None] + [tuple(w) for w in sr.windows]
    ests = stage("estimate", _estimate_windows, prep, windows, jobs.estimate_settings(cfg, sr, prep.x.shape[0]))
    update_progress_artifact(progress, 80.0, description=f"{len(windows)} estimates done")
    summary = stage("summarise", summarise_task, cfg, prep, sr, ests[0], ests[1:])
    if cfg.monitor is not None:  # the baseline is read before the new run is written
        summary, run_id = stage("monitor", monitor_task, cfg, summary, run_id)
        say(start, "monitor", monitor_banner(summary.checks["monitor"]))
    timings = stage.timings
    report = store_task(cfg, summary, prep, sr, timings, run_id,
                        lambda name, message: say(start, name, message))
    update_progress_artifact(progress, 100.0, description=f"stored {report.run_id}")
    create_markdown_artifact(summary.report_md, key=artifact_key(cfg.job, "report"),
                             description=f"{cfg.job} run {report.run_id}")
    create_table_artifact(
        [{"output": p["output"], "input": p["input"], "n_p": p["n_p"],
          "gain": None if p["gain"] is None else round(p["gain"], 6),
          "gain_std": None if p["gain_std"] is None else float(f"{p['gain_std']:.3g}"),
          "settled": p["settled"]["verdict"],
          "rate": None if p["rate"] is None else round(p["rate"], 9),
          "verdict": p["agreement"]["verdict"],
          "feedback": None if p["feedback"] is None else p["feedback"]["detected"],
          "warnings": ", ".join(w["code"] for w in p["warnings"])}
         for p in summary.checks["pairs"]],
        key=artifact_key(cfg.job, "pairs"), description="pairs and window-agreement verdicts")
    if cfg.monitor is not None:
        create_markdown_artifact(monitor_markdown(summary.checks["monitor"]),
                                 key=artifact_key(cfg.job, "monitor"),
                                 description=f"{cfg.job} run {report.run_id} vs baseline")
    return report


def run_estimate(job_path: str | Path, *, files=None, run_id=None):
    """Run the estimate flow, on a Dask cluster when ``dask.address`` is configured.

    Parameters
    ----------
    job_path : str or Path
        The job YAML file (validated before the flow starts).
    files : iterable of path, optional
        Files to read instead of the job's ``source.path``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    """
    cfg = load_job(job_path)
    console_without_user_error_tracebacks()
    runner = task_runner_for(cfg.dask.address)
    fl = estimate_flow.with_options(task_runner=runner) if runner else estimate_flow
    return fl(str(job_path), [str(f) for f in files] if files else None, run_id)
