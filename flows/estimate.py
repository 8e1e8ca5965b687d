"""The ``estimate`` flow: the estimation workflow's one stage list
(:func:`pipeline.jobs.estimation.run_job`: ingest -> prepare -> search -> estimate (mapped over the
windows) -> summarise -> [monitor] -> store), each stage a Prefect task wrapping its
library function (:class:`flows.common.TaskStages`), plus the flow's artifacts."""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.artifacts import create_markdown_artifact, create_table_artifact

from flows.common import (
    artifact_key,
    console_without_user_error_tracebacks,
    flow_started,
    flow_stages,
    task_runner_for,
)
from pipeline.jobs import estimation as jobs
from pipeline.adapters.config import load_job
from pipeline.readouts.monitor import monitor_markdown

#: The progress artifact's percentage when each stage has ended.
PROGRESS_PERCENT = {"ingest": 15.0, "prepare": 25.0, "search": 50.0, "estimate": 80.0,
                    "summarise": 85.0, "monitor": 90.0, "store": 100.0}


@flow(name="estimate", log_prints=True)
def estimate_flow(job_path: str, files: list[str] | None = None, run_id: str | None = None,
                  cfg: object | None = None):
    """Estimate step responses for one job YAML (optionally on given files).

    Parameters
    ----------
    job_path : str
        The job YAML file.
    files : list of str, optional
        Files to read instead of the job's ``source.path``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    cfg : JobConfig, optional
        ``job_path`` already loaded and validated (the CLI's): the YAML is parsed once.
    """
    flow_started()
    cfg = cfg if cfg is not None else load_job(job_path)
    tell, stages = flow_stages(cfg.job, "estimation", PROGRESS_PERCENT)
    report = jobs.run_job(cfg, files=[Path(f) for f in files] if files else None,
                          run_id=run_id, progress=tell, stage=stages)
    # the artifacts show what was stored, read back from the run directory
    run_dir = Path(report.run_dir)
    create_markdown_artifact((run_dir / "report.md").read_text(encoding="utf-8"),
                             key=artifact_key(cfg.job, "report"),
                             description=f"{cfg.job} run {report.run_id}")
    create_table_artifact(report.summary.pair_records(), key=artifact_key(cfg.job, "pairs"),
                          description="pairs: grade, gain or rate, window and feedback verdicts")
    if cfg.monitor is not None:
        create_markdown_artifact(monitor_markdown(report.summary.checks["monitor"]),
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
    return fl(str(job_path), [str(f) for f in files] if files else None, run_id, cfg)
