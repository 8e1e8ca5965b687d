"""The ``discrepancy`` flow: ingest -> model -> prepare -> analyse -> store + Rerun.

Each task body is one call into :mod:`pipeline.discrepancy_job` (the same stages
:func:`pipeline.discrepancy_job.run_discrepancy` runs without Prefect)."""

from __future__ import annotations

import time
from pathlib import Path

from prefect import flow, task
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
)
from pipeline import discrepancy_job as dj
from pipeline import recording
from pipeline.adapters.config import load_job
from pipeline.stages import StageRunner

_T = {"cache_policy": NO_CACHE, "persist_result": False}


# Stages that add nothing to the library call are the library function as a task.
ingest_task = task(recording.load_recording, name="ingest", retries=2, retry_delay_seconds=1,
                   retry_condition_fn=retry_transient_io, **_T)
model_task = task(dj.load_discrepancy_model, name="model", **_T)
prepare_task = task(dj.prepare_discrepancy, name="prepare", **_T)
store_task = task(dj.finish_discrepancy, name="store", retries=2, retry_delay_seconds=1,
                  retry_condition_fn=retry_transient_io, **_T)


@task(name="analyse", **_T)
def analyse_task(cfg, model, data):
    """Run the discrepancy core (:func:`pipeline.discrepancy_job.analyse`), its stages
    reported on stderr.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    model : Model
        The nominal model.
    data : DiscrepancyData
        The analysed stretch from :func:`prepare_task`.
    """
    start = time.perf_counter()
    return dj.analyse(cfg, model, data,
                      progress=lambda stage, message: say(start, f"analyse/{stage}", message))


@flow(name="discrepancy", log_prints=True)
def discrepancy_flow(job_path: str, files: list[str] | None = None, run_id: str | None = None):
    """Compare a job's simulation model with its measured data; name the missing effect.

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
                                        description=f"{cfg.job}: discrepancy progress")
    start = time.perf_counter()
    stage = StageRunner(lambda name, message: say(start, name, message))
    rec = stage("ingest", ingest_task, cfg, [Path(f) for f in files] if files else None)
    update_progress_artifact(progress, 10.0, description="ingested")
    model, source = stage("model", model_task, cfg)
    data = stage("prepare", prepare_task, cfg, rec, model)
    update_progress_artifact(progress, 20.0, description=f"{data.summary['analysed_samples']} "
                                                         "samples prepared")
    result = stage("analyse", analyse_task, cfg, model, data)
    update_progress_artifact(progress, 90.0, description=f"verdict {result.verdict}")
    timings = stage.timings
    report = store_task(cfg, model, source, data, result, timings, run_id=run_id)
    update_progress_artifact(progress, 100.0, description=f"stored {report.run_id}")
    create_markdown_artifact(report.report_md,
                             key=artifact_key(cfg.job, "report"),
                             description=f"{cfg.job} run {report.run_id}")
    create_table_artifact(
        [{"effect": c.effect.describe(), "delta_bic": round(c.delta_bic, 2),
          "holdout_z": round(c.holdout_z, 2), "passed": c.passed}
         for c in result.candidates[:10]],
        key=artifact_key(cfg.job, "candidates"), description="candidate effects, best first")
    return report


def run_discrepancy_flow(job_path: str | Path, *, files=None, run_id=None, cfg=None):
    """Run the discrepancy flow (the CLI's ``plantdyn discrepancy``).

    Parameters
    ----------
    job_path : str or Path
        The job YAML file (validated before the flow starts).
    files : iterable of path, optional
        Files to read instead of the job's ``source.path``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    cfg : JobConfig, optional
        ``job_path`` already loaded and validated (the CLI checked it).
    """
    if cfg is None:
        load_job(job_path)  # validate before the flow starts: fast, clear errors
    console_without_user_error_tracebacks()
    return discrepancy_flow(str(job_path), [str(f) for f in files] if files else None, run_id)
