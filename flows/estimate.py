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
from pipeline.adapters.progress import bar as progress_bar
from pipeline.monitor import monitor_banner, monitor_markdown
from pipeline.stages import StageRunner

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


# Stages that add nothing to the library call are the library function as a task.
prepare_task = task(jobs.prepare, name="prepare", **_T)
estimate_task = task(jobs.estimate_window, name="estimate-window", **_T)
summarise_task = task(jobs.summarise, name="summarise", **_T)
monitor_task = task(monitor_job.monitor_run, name="monitor", **_T)
store_task = task(jobs.finish_run, name="store", retries=2, retry_delay_seconds=1,
                  retry_condition_fn=retry_transient_io, **_T)


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
    report = store_task(cfg, summary, prep, sr, timings, run_id=run_id,
                        progress=lambda name, message: say(start, name, message))
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


def run_estimate(job_path: str | Path, *, files=None, run_id=None, cfg=None):
    """Run the estimate flow, on a Dask cluster when ``dask.address`` is configured.

    Parameters
    ----------
    job_path : str or Path
        The job YAML file (validated before the flow starts).
    files : iterable of path, optional
        Files to read instead of the job's ``source.path``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    cfg : JobConfig, optional
        ``job_path`` already loaded (the CLI checked it): not parsed again here.
    """
    cfg = cfg if cfg is not None else load_job(job_path)
    console_without_user_error_tracebacks()
    runner = task_runner_for(cfg.dask.address)
    fl = estimate_flow.with_options(task_runner=runner) if runner else estimate_flow
    return fl(str(job_path), [str(f) for f in files] if files else None, run_id)
