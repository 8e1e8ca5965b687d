"""The ``discrepancy`` flow: the discrepancy workflow's one stage list
(:func:`pipeline.jobs.discrepancy.run_discrepancy`: ingest -> model -> prepare -> analyse
-> store), each stage a Prefect task wrapping its library function
(:class:`flows.common.TaskStages`), plus the flow's artifacts."""

from __future__ import annotations

import json
from pathlib import Path

from prefect import flow
from prefect.artifacts import create_markdown_artifact, create_table_artifact

from flows.common import (
    artifact_key,
    console_without_user_error_tracebacks,
    flow_started,
    flow_stages,
)
from pipeline.jobs import discrepancy as dj
from pipeline.adapters.config import load_job
from pipeline.discrepancy.report import candidate_records

#: The progress artifact's percentage when each stage has ended.
PROGRESS_PERCENT = {"ingest": 10.0, "model": 15.0, "prepare": 20.0, "analyse": 90.0,
                    "store": 100.0}


@flow(name="discrepancy", log_prints=True)
def discrepancy_flow(job_path: str, files: list[str] | None = None, run_id: str | None = None,
                     cfg: object | None = None):
    """Compare a job's simulation model with its measured data; name the missing effect.

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
    tell, stages = flow_stages(cfg.job, "discrepancy", PROGRESS_PERCENT)
    report = dj.run_discrepancy(cfg, files=[Path(f) for f in files] if files else None,
                                run_id=run_id, progress=tell, stage=stages)
    create_markdown_artifact(report.report_md, key=artifact_key(cfg.job, "report"),
                             description=f"{cfg.job} run {report.run_id}")
    doc = json.loads((Path(report.run_dir) / "discrepancy.json").read_text(encoding="utf-8"))
    create_table_artifact(candidate_records(doc), key=artifact_key(cfg.job, "candidates"),
                          description="candidate effects, best first (as report.md lists them)")
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
    cfg = cfg if cfg is not None else load_job(job_path)  # fast, clear errors first
    console_without_user_error_tracebacks()
    return discrepancy_flow(str(job_path), [str(f) for f in files] if files else None,
                            run_id, cfg)
