"""``plantdyn serve``: serve the nightly deployments of scheduled jobs, no work pool needed.

Every job YAML with a ``schedule:`` (a cron string) becomes a deployment of the
``nightly`` flow named after the job, with ``job_path`` as its parameter.  The process
that calls :func:`serve` executes the runs itself (``prefect.serve``), so there is no
work pool or worker to set up; ``prefect.yaml`` declares the same deployments for people
who prefer ``prefect deploy`` with a work pool.

Serving needs a Prefect API server.  When none is configured (``PREFECT_API_URL`` unset
in the environment and the active Prefect profile), a local one is started from this
environment (``python -m prefect server start --host 127.0.0.1 --port <free port>``) with
its database under ``PREFECT_HOME`` (default ``<project>/storage/.prefect``), used for
the duration of :func:`serve`, and stopped on exit — also on Ctrl-C, SIGTERM, and (on
Linux) when this process is killed outright.

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
import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from flows.common import prefect_env_defaults
from pipeline.errors import ConfigError, PipelineError

__all__ = [
    "DEFAULT_PREFECT_HOME",
    "LocalServer",
    "ScheduledJob",
    "build_deployments",
    "local_prefect_server",
    "scheduled_jobs",
    "serve",
]

DEFAULT_PREFECT_HOME = Path("storage") / ".prefect"
"""Relative to the current folder (``plantdyn serve`` runs where the jobs are)."""
#: A fresh database runs its migrations on first start (≈ 15 s on 2 cores); later ≈ 5 s.
SERVER_STARTUP_TIMEOUT_S = 120.0
#: How long a stopping server may take before it is killed.
SERVER_STOP_TIMEOUT_S = 20.0


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


# ---------------------------------------------------------------------- local server
@dataclass(frozen=True)
class LocalServer:
    """A running local Prefect server started by :func:`local_prefect_server`.

    Attributes
    ----------
    api_url : str
        ``http://127.0.0.1:<port>/api``.
    pid : int
        Process id of the server.
    prefect_home : Path
        Its ``PREFECT_HOME`` (database ``prefect.db``, logs ``server.*.log``).
    """

    api_url: str
    pid: int
    prefect_home: Path


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _tail(path: Path, n_lines: int = 25) -> str:
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return "(no log)"
    return "\n".join(lines[-n_lines:]) or "(empty)"


# Runs in the child before exec: die with the parent (Linux), so a `kill -9` of the
# serving process does not leave an orphaned server holding the port and the database.
_LAUNCHER = (
    "import ctypes, os, signal, sys\n"
    "ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit(0)  # the parent died before prctl took effect\n"
    "os.execv(sys.executable, [sys.executable, *sys.argv[2:]])\n"
)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)  # uvicorn shuts down cleanly on SIGINT
    try:
        proc.wait(timeout=SERVER_STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@contextlib.contextmanager
def local_prefect_server(*, prefect_home: Path, host: str = "127.0.0.1",
                         startup_timeout_s: float = SERVER_STARTUP_TIMEOUT_S) -> Iterator[LocalServer]:
    """Start ``prefect server start`` on a free port, wait until healthy, stop on exit.

    Parameters
    ----------
    prefect_home : Path
        ``PREFECT_HOME`` of the server (created if missing).
    host : str
        Address to listen on (loopback by default: the server has no authentication).
    startup_timeout_s : float
        Longest wait for ``GET /api/health``, s.

    Yields
    ------
    LocalServer

    Raises
    ------
    PipelineError
        The server exited or did not answer within ``startup_timeout_s``; the message
        includes the tail of its stderr.
    """
    prefect_home = Path(prefect_home).resolve()
    prefect_home.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PREFECT_HOME": str(prefect_home),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1"}
    env.pop("PREFECT_API_URL", None)  # the server must not talk to another server
    out_log, err_log = prefect_home / "server.stdout.log", prefect_home / "server.stderr.log"
    for _attempt in range(3):  # the free port can be taken between probing and binding
        port = _free_port(host)
        args = ["-m", "prefect", "server", "start", "--host", host, "--port", str(port)]
        cmd = ([sys.executable, "-c", _LAUNCHER, str(os.getpid()), *args]
               if sys.platform.startswith("linux") else [sys.executable, *args])
        with open(out_log, "wb") as out, open(err_log, "wb") as err:
            # own session: a Ctrl-C in the terminal reaches only us; we stop the server
            # after the runner has shut down (it still needs the API to pause schedules)
            proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=out,
                                    stderr=err, start_new_session=True)
        try:
            base = f"http://{host}:{port}"
            deadline = time.monotonic() + startup_timeout_s
            healthy = False
            while time.monotonic() < deadline and proc.poll() is None:
                try:
                    with urllib.request.urlopen(f"{base}/api/health", timeout=2) as resp:
                        healthy = resp.status == 200
                except (urllib.error.URLError, OSError):
                    healthy = False
                if healthy:
                    break
                time.sleep(0.25)
            if not healthy:
                code = proc.poll()
                _stop(proc)
                stderr_tail = _tail(err_log)
                if code is not None and "already in use" in stderr_tail + _tail(out_log):
                    continue
                what = (f"exited with code {code}" if code is not None else
                        f"did not answer GET {base}/api/health within {startup_timeout_s:g} s")
                raise PipelineError(
                    f"the local Prefect server (PREFECT_HOME={prefect_home}) {what}; its stderr "
                    f"ends with:\n{stderr_tail}\nfix the cause above, or start a server yourself "
                    "(prefect server start) and set PREFECT_API_URL to its /api address"
                )
            yield LocalServer(f"{base}/api", proc.pid, prefect_home)
            return
        finally:
            _stop(proc)
    raise PipelineError(f"could not find a free port on {host} for the Prefect server after 3 "
                        "attempts; set PREFECT_API_URL to a running server instead")


@contextlib.contextmanager
def _prefect_api(prefect_home: Path | None, startup_timeout_s: float) -> Iterator[str]:
    """The configured API, or a local server started for the duration of the block."""
    from prefect.settings import PREFECT_API_URL, get_current_settings, temporary_settings

    configured = get_current_settings().api.url
    if configured:
        _note(f"using the Prefect API at {configured} (PREFECT_API_URL)")
        yield str(configured)
        return
    home = Path(prefect_home) if prefect_home is not None else \
        Path(os.environ.get("PREFECT_HOME") or DEFAULT_PREFECT_HOME)
    _note(f"PREFECT_API_URL is not set: starting a local Prefect server (PREFECT_HOME={home})...")
    with local_prefect_server(prefect_home=home, startup_timeout_s=startup_timeout_s) as srv:
        _note(f"Prefect server at {srv.api_url} (pid {srv.pid}); dashboard "
              f"{srv.api_url.removesuffix('/api')}; it stops when serve exits")
        previous = os.environ.get("PREFECT_API_URL")
        # this process reads the setting; the runner's flow-run subprocesses get both
        os.environ["PREFECT_API_URL"] = srv.api_url
        try:
            with temporary_settings(updates={PREFECT_API_URL: srv.api_url}):
                yield srv.api_url
        finally:
            if previous is None:
                os.environ.pop("PREFECT_API_URL", None)
            else:
                os.environ["PREFECT_API_URL"] = previous


# ----------------------------------------------------------------------------- serve
def serve(job_paths: Sequence[Path | str], *, limit: int = 1, once: bool = False,
          prefect_home: Path | None = None,
          startup_timeout_s: float = SERVER_STARTUP_TIMEOUT_S) -> int:
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
        ``PREFECT_HOME`` of the local server started when no API is configured; default
        ``$PREFECT_HOME`` if set, else ``<project>/storage/.prefect``.
    startup_timeout_s : float
        Longest wait for the local server to answer, s.

    Returns
    -------
    int
        Exit code: 0; with ``once``, 2 when a run did not complete or a file failed.

    Raises
    ------
    ConfigError
        No job has a schedule, an invalid job file or cron string, ``limit < 1``.
    PipelineError
        The local Prefect server did not start.
    """
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ConfigError(f"--limit {limit!r}: the number of concurrent runs must be an integer >= 1")
    prefect_env_defaults()
    jobs = scheduled_jobs(job_paths)  # validate everything before starting a server
    if not jobs:
        raise ConfigError(
            f"none of the {len(job_paths)} job file(s) has a 'schedule:' key, so there is "
            "nothing to serve; add e.g. schedule: \"0 2 * * *\" to a job YAML"
        )
    with _prefect_api(prefect_home, startup_timeout_s):
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
