"""``plantdyn serve``: serve the nightly deployments of scheduled jobs, no work pool needed.

Every job YAML with a ``schedule:`` (a cron string) becomes a deployment of the
``nightly`` flow named after the job, with ``job_path`` as its parameter.  The process
that calls :func:`serve` executes the runs itself (``prefect.serve``), so there is no
work pool or worker to set up; ``prefect.yaml`` declares the same deployments for people
who prefer ``prefect deploy`` with a work pool.

Serving needs a Prefect API server.  When none is configured (``PREFECT_API_URL`` unset
in the environment and the active Prefect profile), the project server of the first
served job's storage root is used -- started if none runs (:mod:`flows.server`: state in
``$PREFECT_HOME`` or ``<storage>/.prefect``) -- the same server ``plantdyn run`` of that
job uses.  It keeps running after serve exits (``plantdyn server stop``).

Decisions:

* The cron string is interpreted in the job's ``source.timezone`` — the plant's local
  zone, in which the historian writes its nightly export — so ``"0 2 * * *"`` is 02:00
  at the plant, not 02:00 UTC.
* ``once=True`` registers the deployments, runs each one now through the same runner,
  waits, prints the final states and the per-file outcome of each nightly run, and
  returns 0 when every run completed with no failed file, else 2: a quick check of the
  whole setup (server, deployments, drop folders, jobs).
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from flows.common import prefect_env_defaults
from pipeline.errors import ConfigError

__all__ = [
    "ScheduledJob",
    "build_deployments",
    "scheduled_jobs",
    "serve",
]


def _note(message: str) -> None:
    print(f"plantdyn serve: {message}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------- deployments
@dataclass(frozen=True)
class ScheduledJob:
    """A job YAML that has a ``schedule:``.

    Attributes
    ----------
    name : str
        The job name (``job:``); also the deployment name.
    path : Path
        The job file (absolute).
    cron : str
        The cron string, validated.
    timezone : str
        IANA zone the cron string is read in (the job's ``source.timezone``).
    """

    name: str
    path: Path
    cron: str
    timezone: str


def scheduled_jobs(job_paths: Sequence[Path | str]) -> list[ScheduledJob]:
    """Load job files and keep those with a ``schedule:`` (others are noted on stderr).

    Parameters
    ----------
    job_paths : sequence of path
        Job YAML files.

    Returns
    -------
    list of ScheduledJob
        In the order given.

    Raises
    ------
    ConfigError
        A job file is invalid, a cron string is invalid (the message names the file and
        the cron text), or two files define the same job name.
    """
    from prefect.client.schemas.schedules import CronSchedule
    from pydantic import ValidationError

    from pipeline.adapters.config import load_job

    out: list[ScheduledJob] = []
    seen: dict[str, Path] = {}
    for raw in job_paths:
        path = Path(raw).resolve()
        cfg = load_job(path)
        if not cfg.schedule:
            _note(f"{path}: no 'schedule:' key, not served (add e.g. schedule: \"0 2 * * *\")")
            continue
        try:
            CronSchedule(cron=cfg.schedule, timezone=cfg.source.timezone)
        except ValidationError:
            raise ConfigError(
                f"{path}: schedule: {cfg.schedule!r} is not a valid cron string; use five "
                "fields 'minute hour day-of-month month day-of-week', e.g. \"0 2 * * *\" for "
                "02:00 every night"
            ) from None
        if cfg.job in seen:
            raise ConfigError(
                f"{path}: job name {cfg.job!r} is also used by {seen[cfg.job]}; deployments are "
                "named after the job, so give each scheduled job a unique 'job:' name"
            )
        seen[cfg.job] = path
        out.append(ScheduledJob(cfg.job, path, cfg.schedule, cfg.source.timezone))
    return out


def build_deployments(jobs: Sequence[ScheduledJob]) -> list:
    """One ``nightly`` deployment per scheduled job (``prefect.deployments.RunnerDeployment``).

    The entrypoint is the module path ``flows.nightly.nightly_flow`` so the runs do not
    depend on the working directory of the serving process.

    Parameters
    ----------
    jobs : sequence of ScheduledJob
        The jobs to deploy (:func:`scheduled_jobs`).
    """
    from prefect.schedules import Cron
    from prefect.types.entrypoint import EntrypointType

    from flows.nightly import nightly_flow

    return [
        nightly_flow.to_deployment(
            name=job.name,
            schedule=Cron(job.cron, timezone=job.timezone),
            parameters={"job_path": str(job.path)},
            description=f"plantdyn nightly processing of {job.path}",
            tags=["plantdyn", "nightly"],
            entrypoint_type=EntrypointType.MODULE_PATH,
        )
        for job in jobs
    ]


# ----------------------------------------------------------------------------- serve
def serve(job_paths: Sequence[Path | str], *, limit: int = 1, once: bool = False,
          prefect_home: Path | None = None) -> int:
    """Serve the nightly deployments of the scheduled jobs among ``job_paths``.

    Parameters
    ----------
    job_paths : sequence of path
        Job YAML files; those without ``schedule:`` are skipped with a note.
    limit : int
        Flow runs executed at the same time.
    once : bool
        Register the deployments, run each once now, wait, print the states and exit
        (instead of serving until interrupted).
    prefect_home : Path, optional
        ``PREFECT_HOME`` of the project server used when no API is configured; default
        ``$PREFECT_HOME`` if set, else ``<storage>/.prefect`` of the first served job.

    Returns
    -------
    int
        Exit code: 0; with ``once``, 2 when a run did not complete or a file failed.

    Raises
    ------
    ConfigError
        No job has a schedule, an invalid job file or cron string, ``limit < 1``.
    PrefectStartError
        The project server could not be started.
    """
    from flows.server import project_prefect
    from pipeline.adapters.config import load_job

    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ConfigError(f"--limit {limit!r}: the number of concurrent runs must be an integer >= 1")
    prefect_env_defaults()
    jobs = scheduled_jobs(job_paths)  # validate everything before starting a server
    if not jobs:
        raise ConfigError(
            f"none of the {len(job_paths)} job file(s) has a 'schedule:' key, so there is "
            "nothing to serve; add e.g. schedule: \"0 2 * * *\" to a job YAML"
        )
    with project_prefect(load_job(jobs[0].path).storage_root, home=prefect_home) as api:
        _note(f"Prefect API {api}; dashboard {api.removesuffix('/api')}")
        deployments = build_deployments(jobs)
        for job in jobs:
            _note(f"deployment nightly/{job.name}: cron {job.cron!r} ({job.timezone}), "
                  f"job {job.path}")
        if once:
            return asyncio.run(_run_once(deployments, limit=limit))
        import prefect

        prefect.serve(*deployments, limit=limit)  # returns on Ctrl-C / SIGTERM
        return 0


async def _run_once(deployments: list, *, limit: int) -> int:
    """Register, trigger one run of each deployment now, execute them, report."""
    from prefect import get_client
    from prefect.runner import Runner

    runner = Runner(name="plantdyn-serve-once", limit=limit)
    ids = [await runner.aadd_deployment(d) for d in deployments]
    async with get_client() as client:
        runs = [await client.create_flow_run_from_deployment(i) for i in ids]
        _note(f"triggered {len(runs)} run(s): {', '.join(r.name for r in runs)}; executing...")
        # one poll of the runner: executes the runs scheduled for now and waits for them
        await runner.start(run_once=True)
        code = 0
        for dep, run in zip(deployments, runs):
            final = await client.read_flow_run(run.id)
            state = final.state.name if final.state else "unknown"
            files = await _nightly_files(client, run.id)
            bad = [f for f in files if f.get("status") in ("failed", "error")]
            print(f"nightly/{dep.name}: flow run {final.name} {state}; "
                  f"{len(files)} file(s): " + (", ".join(
                      f"{Path(str(f.get('path'))).name} {f.get('status')}" for f in files)
                      or "none in the drop folder"), flush=True)
            for f in bad:
                print(f"    {f.get('status')}: {f.get('path')}: {f.get('error')}", flush=True)
            if not (final.state and final.state.is_completed()) or bad:
                code = 2
        return code


async def _nightly_files(client, flow_run_id) -> list[dict]:
    """The per-file table the nightly flow publishes as an artifact (empty if none)."""
    import json

    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId

    arts = await client.read_artifacts(artifact_filter=ArtifactFilter(
        flow_run_id=ArtifactFilterFlowRunId(any_=[flow_run_id])))
    for art in arts:
        if art.type == "table" and (art.key or "").endswith("-files"):
            data = json.loads(art.data) if isinstance(art.data, str) else art.data
            return list(data) if isinstance(data, list) else []
    return []
