"""``plantdyn serve``: deployments from job schedules, the project's Prefect server, a real
cron firing, and ``prefect.yaml``.

The two slow tests use the project server (``flows/server.py``, no test harness) of one
module-wide ``PREFECT_HOME``: the first starts it, the second reuses it (serve leaves it
running, like every command), and the module's fixture stops it.
"""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from flows.serve import build_deployments, scheduled_jobs, serve
from flows.server import healthy, read_state, stop_server
from pipeline.adapters.config import load_job
from pipeline.adapters.store import ResultStore, file_sha256
from pipeline.errors import ConfigError
from pipeline.jobs.nightly import nightly_run_id
from tests.conftest import subprocess_env, write_job, write_plant_csv

PROJECT_ROOT = Path(__file__).resolve().parents[2]
SERVER_LINE = re.compile(r"Prefect server (?:ready )?at http://127\.0\.0\.1:(\d+)/api "
                         r"\(pid (\d+)\)")


def _alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _wait_gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    return not _alive(pid)


def _drop(folder: Path, n: int) -> list[Path]:
    return [write_plant_csv(folder / "drop" / f"export_{k:02d}.csv", seed=k + 1, hours=2.0)
            for k in range(n)]


def _committed(storage: Path, job: str = "plant") -> list[str]:
    d = storage / job
    return sorted(p.name for p in d.iterdir() if not p.name.startswith(".")) if d.is_dir() else []


# ------------------------------------------------------------------- fast checks
def test_scheduled_jobs_skips_unscheduled_and_names_bad_cron(tmp_path, capsys):
    nightly = write_job(tmp_path / "a", name="boiler", schedule="30 1 * * *",
                        timezone="Europe/Berlin")
    adhoc = write_job(tmp_path / "b", name="adhoc")
    jobs = scheduled_jobs([nightly, adhoc])
    assert [(j.name, j.path, j.cron, j.timezone) for j in jobs] == \
        [("boiler", nightly.resolve(), "30 1 * * *", "Europe/Berlin")]
    assert f"{adhoc.resolve()}: no 'schedule:' key, not served" in capsys.readouterr().err

    bad = write_job(tmp_path / "c", name="bad", schedule="61 * * * *")
    with pytest.raises(ConfigError, match=re.escape(str(bad.resolve())) +
                       r": schedule: '61 \* \* \* \*' is not a valid cron string"):
        scheduled_jobs([nightly, bad])
    twin = write_job(tmp_path / "d", name="boiler", schedule="0 3 * * *")
    with pytest.raises(ConfigError, match=r"job name 'boiler' is also used by .*a/job\.yaml"):
        scheduled_jobs([nightly, twin])


def test_serve_refuses_without_scheduled_jobs_or_with_bad_limit(tmp_path):
    adhoc = write_job(tmp_path, name="adhoc")
    with pytest.raises(ConfigError, match=r"none of the 1 job file\(s\) has a 'schedule:' key"):
        serve([adhoc])
    with pytest.raises(ConfigError, match=r"--limit 0: the number of concurrent runs must be"):
        serve([adhoc], limit=0)


def test_deployments_carry_cron_zone_and_absolute_job_path(tmp_path):
    job = write_job(tmp_path, schedule="0 2 * * *",
                    timezone="Europe/Berlin")
    [dep] = build_deployments(scheduled_jobs([job]))
    assert dep.name == "plant" and dep.flow_name == "nightly"
    assert dep.parameters == {"job_path": str(job.resolve())}
    assert dep.entrypoint == "flows.nightly.nightly_flow"  # independent of the cwd
    [sched] = dep.schedules
    assert (sched.schedule.cron, sched.schedule.timezone) == ("0 2 * * *", "Europe/Berlin")


def test_prefect_yaml_declares_the_demo_nightly_deployment():
    from prefect.flows import load_flow_from_entrypoint

    spec = yaml.safe_load((PROJECT_ROOT / "prefect.yaml").read_text())
    [step] = spec["pull"]
    assert list(step) == ["prefect.deployments.steps.set_working_directory"]
    [dep] = spec["deployments"]
    path, name = dep["entrypoint"].split(":")
    assert (path, name) == ("flows/nightly.py", "nightly_flow")
    assert load_flow_from_entrypoint(str(PROJECT_ROOT / path) + ":" + name).name == "nightly"
    cfg = load_job(PROJECT_ROOT / dep["parameters"]["job_path"])  # relative to the root
    [sched] = dep["schedules"]
    assert sched["cron"] == "0 2 * * *" == cfg.schedule
    assert sched["timezone"] == cfg.source.timezone  # as plantdyn serve reads the cron
    assert dep["name"] == cfg.job


# ------------------------------------------------------------- real servers (slow)
@pytest.fixture(scope="module")
def server_home(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``PREFECT_HOME`` of the module's project server, stopped at the end."""
    home = tmp_path_factory.mktemp("served_prefect_home")
    yield home
    stop_server(home, note=lambda _msg: None)


@pytest.fixture
def no_api(monkeypatch) -> Iterator[None]:
    """No API configured — not in the environment and not in the settings (the harness
    of another test module on this worker may have set it)."""
    from prefect.settings import (
        PREFECT_API_URL,
        get_current_settings,
        temporary_settings,
    )

    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    with temporary_settings(restore_defaults={PREFECT_API_URL}):
        assert get_current_settings().api.url is None
        yield


@pytest.mark.slow
def test_serve_once_starts_a_server_runs_the_deployment_and_keeps_the_server(
        tmp_path, server_home, no_api, capfd):
    files = _drop(tmp_path, 2)
    job = write_job(tmp_path, schedule="0 2 * * *")
    adhoc = write_job(tmp_path, name="adhoc", file_name="adhoc.yaml")

    code = serve([job, adhoc], once=True, prefect_home=server_home)
    out, err = capfd.readouterr()
    assert code == 0, out + err
    assert f"{adhoc.resolve()}: no 'schedule:' key, not served" in err
    assert re.search(r"nightly/plant: flow run \S+ Completed; 2 file\(s\): "
                     r"export_00\.csv ok, export_01\.csv ok", out), out + err
    storage = tmp_path / "storage"
    expected = sorted(nightly_run_id(file_sha256(f)) for f in files)
    assert _committed(storage) == expected
    assert ResultStore(storage).processed("plant")["status"].to_list() == ["ok", "ok"]
    assert not (storage / "adhoc").exists()
    # the project server serve used keeps running for the next command
    match = SERVER_LINE.search(err)
    assert match, err
    port, pid = int(match[1]), int(match[2])
    state = read_state(server_home)
    assert state is not None and (state.port, state.pid) == (port, pid)
    assert _alive(pid) and healthy(state.api_url)


@pytest.mark.slow
def test_cron_schedule_fires_under_plantdyn_serve(tmp_path, server_home):
    """``plantdyn serve`` with cron ``* * * * *`` in a subprocess: the scheduled run
    comes (the next minute boundary, so ≤ 60 s after registration plus the runner's
    10 s poll), processes the drop folder, and SIGINT stops serve; the project server
    stays for the next command (``plantdyn server stop`` stops it)."""
    [export] = _drop(tmp_path, 1)
    job = write_job(tmp_path, schedule="* * * * *")
    manifest = tmp_path / "storage" / "plant" / nightly_run_id(file_sha256(export)) / \
        "manifest.json"
    env = subprocess_env(PREFECT_API_URL=None, PREFECT_HOME=str(server_home))
    err_log = tmp_path / "serve.stderr.log"
    with open(tmp_path / "serve.stdout.log", "wb") as out, open(err_log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "serve", str(job)],
                                env=env, stdout=out, stderr=err)
    store = ResultStore(tmp_path / "storage")

    def recorded() -> bool:
        """The run is complete once its ledger row is final: the manifest is written
        first and the ``ok`` after it (an interrupt between them leaves a ``running``
        claim that the next night adopts, ``tests/flows/test_flows.py`` covers that), so
        waiting for the manifest alone races the ledger."""
        if not manifest.is_file() or not (tmp_path / "storage" / "plant").is_dir():
            return False
        return store.processed("plant")["status"].to_list() == ["ok"]

    try:
        deadline = time.monotonic() + 150
        while not recorded() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        fired = manifest.is_file()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=45)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    log = err_log.read_text()
    assert fired, f"no scheduled run within 150 s; serve stderr:\n{log}"
    assert proc.returncode == 0, log  # stopped by SIGINT, cleanly
    assert store.processed("plant")["status"].to_list() == ["ok"]
    match = SERVER_LINE.search(log)
    assert match, log
    port, pid = int(match[1]), int(match[2])
    assert _alive(pid) and _port_open(port)  # kept for reuse
    stop = subprocess.run([sys.executable, "-m", "flows.cli", "server", "stop"], env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert stop.returncode == 0 and f"(pid {pid})" in stop.stdout, stop.stdout + stop.stderr
    assert _wait_gone(pid, 30) and not _port_open(port)
