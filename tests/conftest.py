"""Shared test fixtures: an offline Prefect environment and small synthetic jobs.

* ``_prefect_env`` (session, autouse, cheap): ``PREFECT_HOME`` in a per-worker temporary
  folder, analytics and telemetry off — for every test, so nothing touches ``~/.prefect``;
  ``PLANTDYN_SETTLE_S=0`` (a nightly takes a test's files at once).
* ``prefect_harness`` (session, requested by the flow tests): enters
  ``prefect_test_harness()`` once per session — i.e. once per xdist worker, each with its
  own temporary database and server port — because starting it costs seconds.
* ``demo_cli_run`` / ``discrepancy_demo_run`` (session, shared by every xdist worker):
  one ``plantdyn demo [--discrepancy] --no-prefect`` run in a subprocess, as a user
  starts it, for the tests that only read its results (CLI lines, exports, the HTML
  page) — a demo costs 20–40 s a run.
* ``write_plant_csv`` / ``write_job`` (and the ``make_job`` fixture): a first-order plant
  driven by AR(1) noise, written as a historian long CSV, plus a job YAML whose storage
  lies inside the test's temporary folder.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import scipy.signal as ss
import yaml

#: Plant of the synthetic jobs: y = K/(tau s + 1) u, sampled at 1 s (zero-order hold).
PLANT_GAIN = 2.0
PLANT_TAU_S = 20.0
INPUT_TAG, OUTPUT_TAG = "U.PV", "Y.PV"
_START = np.datetime64("2026-03-02T00:00:00", "us")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session", autouse=True)
def _prefect_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Offline Prefect settings with a per-worker ``PREFECT_HOME`` (environment variables,
    plus the settings context when Prefect was imported before this fixture ran)."""
    home = tmp_path_factory.mktemp("prefect_home")
    mp = pytest.MonkeyPatch()
    mp.setenv("PREFECT_HOME", str(home))
    mp.setenv("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    mp.setenv("DO_NOT_TRACK", "1")
    mp.setenv("PREFECT_LOGGING_LEVEL", "WARNING")
    mp.delenv("PREFECT_API_URL", raising=False)  # flows must never reach a real server
    # files a test writes are complete: the nightly takes them at once (not after 60 s);
    # tests of the settle time set it themselves
    mp.setenv("PLANTDYN_SETTLE_S", "0")
    with contextlib.ExitStack() as stack:
        if "prefect.settings" in sys.modules:  # imported at collection: settings are loaded
            from prefect.settings import (
                PREFECT_HOME,
                PREFECT_SERVER_ANALYTICS_ENABLED,
                temporary_settings,
            )

            stack.enter_context(temporary_settings(
                updates={PREFECT_HOME: str(home), PREFECT_SERVER_ANALYTICS_ENABLED: False}))
        yield home
    mp.undo()
    # a command run on the default path with this PREFECT_HOME left the project's Prefect
    # server running for reuse (flows/server.py): tests leave no server behind
    from flows.server import stop_server

    stop_server(home, note=lambda _msg: None)


@pytest.fixture(scope="session")
def prefect_harness(_prefect_env: Path) -> Iterator[str]:
    """A temporary Prefect server and database for this session (xdist worker).

    Yields the API URL, so subprocesses can be pointed at the same server
    (``PREFECT_API_URL``) instead of each starting an embedded one.
    """
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    # generous: on 2 cores the other worker competes while the fresh database migrates
    with prefect_test_harness(server_startup_timeout=120):
        yield str(PREFECT_API_URL.value())


@dataclass(frozen=True)
class DemoRun:
    """What ``plantdyn demo --no-prefect --dir <dir>`` printed, and where it wrote."""

    dir: Path
    returncode: int
    stdout: str
    stderr: str

    @property
    def lines(self) -> dict[str, str]:
        """The ``label: value`` lines of stdout."""
        return {k.strip(): v.strip() for k, v in
                (ln.split(":", 1) for ln in self.stdout.splitlines() if ": " in ln)}

    @property
    def results(self) -> Path:
        """The run directory the demo names on its ``results:`` line."""
        return Path(self.lines["results"])


def _shared_cli_run(factory: pytest.TempPathFactory, name: str, *args: str) -> DemoRun:
    """``plantdyn <args> --dir <shared>/<name>/demo`` run once for the whole session;
    every xdist worker reads the same run.

    The first worker to take the lock runs the command and writes what it printed next
    to it; the others wait on the lock and read that (the pattern pytest-xdist documents
    for session data).  Tests must only read the run; a test that changes it copies it.
    """
    base = factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the folder all workers' temporary folders share
    root = base / f"shared_{name}"
    root.mkdir(exist_ok=True)
    done = root / "printed.json"
    with open(root / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            r = subprocess.run(
                [sys.executable, "-m", "flows.cli", *args, "--dir", str(root / "demo")],
                cwd=ROOT, capture_output=True, text=True, timeout=900)
            done.write_text(json.dumps({"returncode": r.returncode, "stdout": r.stdout,
                                        "stderr": r.stderr}))
        printed = json.loads(done.read_text())
    return DemoRun(dir=root / "demo", **printed)


@pytest.fixture(scope="session")
def demo_cli_run(tmp_path_factory: pytest.TempPathFactory, _prefect_env: Path) -> DemoRun:
    """The session's ``plantdyn demo --no-prefect`` run (read only)."""
    return _shared_cli_run(tmp_path_factory, "demo", "demo", "--no-prefect")


@pytest.fixture(scope="session")
def discrepancy_demo_run(tmp_path_factory: pytest.TempPathFactory,
                         _prefect_env: Path) -> DemoRun:
    """The session's ``plantdyn demo --discrepancy --no-prefect`` run (read only)."""
    return _shared_cli_run(tmp_path_factory, "discrepancy", "demo", "--discrepancy",
                           "--no-prefect")


def plant_signals(*, seed: int, hours: float = 2.0, phi: float = 0.9,
                  noise_std: float = 0.02) -> dict[str, np.ndarray]:
    """Input and output of the first-order plant, 1 s samples.

    The input is AR(1) noise ``u[k] = phi u[k-1] + sqrt(1 - phi^2) e[k]`` (unit variance);
    the output is the exact zero-order-hold discretisation of ``K/(tau s + 1)`` plus white
    measurement noise of standard deviation ``noise_std``.  Offsets 50 and 10 make them
    look like engineering values.

    Returns
    -------
    dict
        ``time`` (datetime64[us] UTC, (N,)), ``u`` and ``y`` ((N,) float).
    """
    rng = np.random.default_rng(seed)
    n = int(hours * 3600)
    u = ss.lfilter([np.sqrt(1 - phi**2)], [1, -phi], rng.standard_normal(n))
    a = np.exp(-1.0 / PLANT_TAU_S)
    y = ss.lfilter([0.0, PLANT_GAIN * (1 - a)], [1.0, -a], u) + noise_std * rng.standard_normal(n)
    time = _START + (np.arange(n) * 1_000_000).astype("timedelta64[us]")
    return {"time": time, "u": 50.0 + u, "y": 10.0 + y}


def write_plant_csv(path: Path, *, seed: int, hours: float = 2.0) -> Path:
    """Write the plant's signals as a PI-style long CSV (``tag,timestamp,value,status``)."""
    from pipeline.adapters.historian_writer import write_long_csv

    sig = plant_signals(seed=seed, hours=hours)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_long_csv(path, sig["time"], {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]})
    return path


def write_job(folder: Path, *, name: str = "plant", source: str = "drop/*.csv",
              timezone: str = "UTC", storage: str = "storage", file_name: str = "job.yaml",
              **extra) -> Path:
    """Write ``folder/<file_name>`` for the plant (storage inside ``folder``); ``extra``
    keys are added to (or replace) the top-level mapping.  Rerun output is off: the flow tests
    check orchestration, and rendering a recording would only cost time."""
    data = {
        "job": name,
        "source": {"path": source, "timezone": timezone},
        "signals": {"inputs": {"u": {"tag": INPUT_TAG}},
                    "outputs": {"y": {"tag": OUTPUT_TAG}}},
        "storage": storage,
        "rerun": {"enabled": False},
        **extra,
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / file_name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


@pytest.fixture
def make_job(tmp_path: Path) -> Callable[..., Path]:
    """``make_job(n_files=1, *, seeds=None, hours=2.0, **job_keys) -> job.yaml`` in
    ``tmp_path``, with plant exports ``tmp_path/drop/export_<k>.csv`` (seeds 1..n_files
    unless given; ``hours`` one value or one per file)."""

    def make(n_files: int = 1, *, seeds: list[int] | None = None,
             hours: float | list[float] = 2.0, **job_keys) -> Path:
        seeds = seeds if seeds is not None else list(range(1, n_files + 1))
        lengths = hours if isinstance(hours, list) else [hours] * len(seeds)
        for k, (seed, h) in enumerate(zip(seeds, lengths, strict=True)):
            write_plant_csv(tmp_path / "drop" / f"export_{k:02d}.csv", seed=seed, hours=h)
        return write_job(tmp_path, **job_keys)

    return make


def latest_artifact(key: str):
    """The latest Prefect artifact with ``key`` on the test's Prefect server (exactly one
    must exist), as Prefect returns it (``data``: the table's rows or the markdown)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    with get_client(sync_client=True) as client:
        found = client.read_latest_artifacts(
            artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[key])))
    assert len(found) == 1, key
    return found[0]


def subprocess_env(**overrides: str | None) -> dict[str, str]:
    """This process's environment with ``overrides`` (None removes a variable)."""
    env = dict(os.environ)
    for key, value in overrides.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return env
