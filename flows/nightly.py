"""The ``nightly`` flow: process every new export in a job's drop folder exactly once —
complete files only, in data-time order, at most ``max_parallel`` at a time, one baseline
per job (:mod:`pipeline.jobs.nightly`)."""

from __future__ import annotations

import sys

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed

from flows.common import (
    artifact_key,
    console_without_user_error_tracebacks,
    flow_started,
    task_runner_for,
)
from pipeline.adapters.config import load_job
from pipeline.adapters.progress import bar as progress_bar
from pipeline.jobs.nightly import drive, plan_header, plan_night, process_planned

#: ``plan_night`` and ``process_planned`` as tasks: each one call into ``pipeline``.
plan_task = task(plan_night, name="plan", cache_policy=NO_CACHE, persist_result=False)
process_file_task = task(process_planned, name="process-file", cache_policy=NO_CACHE,
                         persist_result=False)


def _say(line: str) -> None:
    # stderr directly, in the flow's process: the flow's log_prints would swallow it, and
    # a Dask worker's stderr is not the command's
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def _first_done(futures: set) -> set:
    return {next(as_completed(list(futures)))}


@flow(name="nightly", log_prints=True)
def nightly_flow(job_path: str, retry_failed: bool = False,
                 cfg: object | None = None) -> list[dict]:
    """Plan the night (complete files in data-time order, the concurrency bound) and
    process each file once, printing one line per file as it finishes.

    Parameters
    ----------
    job_path : str
        The job YAML file.
    retry_failed : bool
        Try files that failed before with this job configuration again.
    cfg : JobConfig, optional
        ``job_path`` already loaded and validated (the CLI's): the YAML is parsed once.
    """
    flow_started()
    cfg = cfg if cfg is not None else load_job(job_path)
    plan = plan_task(cfg, retry_failed=retry_failed)
    _say(plan_header(cfg, plan))
    with progress_bar("nightly", "files") as tick:  # a bar on a terminal only
        rows = drive(cfg, plan, say=_say, tick=tick, wait_any=_first_done, submit=lambda item: (
            process_file_task.submit(cfg, item, plan.config_sha256, plan.retry_failed)))
    failed = [r for r in rows if r["status"] in ("failed", "error")]
    lines = [f"# nightly {cfg.job}", "",
             (f"{len(rows)} file(s) seen, {sum(r['status'] == 'ok' for r in rows)} processed, "
              f"{sum(r['status'].startswith('skipped') for r in rows)} skipped, "
              f"{len(failed)} failed; at most {plan.max_parallel} at a time.")]
    lines += [f"- FAILED {r['path']}: {r['error']}" for r in failed]
    key = artifact_key(cfg.job, "nightly")
    create_markdown_artifact("\n".join(lines), key=key)
    if rows:
        create_table_artifact([{k: r.get(k) for k in ("path", "status", "run_id", "error")}
                               for r in rows], key=key + "-files")
    return rows


def run_nightly(job_path: str, *, retry_failed: bool = False, cfg=None):
    """Run the nightly flow: tasks in a pool of ``max_parallel`` threads, or on a Dask
    cluster when ``dask.address`` is configured (submitted ``max_parallel`` at a time).

    Parameters
    ----------
    job_path : str
        The job YAML file (validated before the flow starts).
    retry_failed : bool
        Try files that failed before with this job configuration again.
    cfg : JobConfig, optional
        ``job_path`` already loaded (the CLI checked it): not parsed again here.
    """
    from prefect.task_runners import ThreadPoolTaskRunner

    cfg = cfg if cfg is not None else load_job(job_path)
    console_without_user_error_tracebacks()
    runner = task_runner_for(cfg.dask.address) or ThreadPoolTaskRunner(
        max_workers=cfg.nightly.max_parallel or None)
    return nightly_flow.with_options(task_runner=runner)(str(job_path),
                                                         retry_failed=retry_failed, cfg=cfg)
