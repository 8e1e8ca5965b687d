"""The default (Prefect) path through the project's Prefect server (issue 33, build 1 and
must-show 1).

``plantdyn run`` and ``plantdyn nightly`` as a new user runs them -- no ``--no-prefect``, no
``PREFECT_API_URL``, no ``PREFECT_HOME`` -- so the first command starts the project's
Prefect server under the job's storage root (``<storage>/.prefect``) and the others reuse
it.  Three commands started together while busy loops load every core start exactly one
server and all exit 0; a later command reuses it (same pid); ``plantdyn server stop`` stops
it.  A stale state file is replaced, a process that is not our server is never signalled,
and a server that cannot start is one message and exit 2.  Every server a test starts is
stopped by the ``storage`` fixture (each start costs 10-40 s here, so the tests are few).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from flows.server import STATE_FILE, healthy, read_state, stop_server
from tests.conftest import subprocess_env, write_job

BUSY = "import time\nt = time.time()\nwhile time.time() - t < 600: pass\n"
READY = re.compile(r"Prefect server ready at (http://127\.0\.0\.1:\d+/api) \(pid (\d+)\)")
REUSED = re.compile(r"reusing the Prefect server at (http://127\.0\.0\.1:\d+/api) \(pid (\d+)\)")


@pytest.fixture
def storage(tmp_path: Path) -> Iterator[Path]:
    """The jobs' private storage root (``tmp_path/storage``); its project server, if a test
    started one, is stopped afterwards."""
    root = tmp_path / "storage"
    yield root
    stop_server(root / ".prefect", note=lambda _msg: None)


def _env(**extra: str | None) -> dict:
    # no PREFECT_HOME: the server's state goes under the job's storage root
    return subprocess_env(**{"PREFECT_API_URL": None, "PREFECT_HOME": None, **extra})


def _cli(*args: str, env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "flows.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _done(proc: subprocess.Popen, timeout_s: float = 600) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout_s)
    return proc.returncode, out, err


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_commands_started_together_on_a_loaded_machine_share_one_server(
        storage, make_job):
    job = make_job(2, hours=1.0)
    env = _env()
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(os.cpu_count() or 2)]
    try:
        procs = {name: _cli(*args, str(job), env=env) for name, args in
                 (("run1", ["run"]), ("run2", ["run"]), ("nightly", ["nightly"]))}
        res = {name: _done(p) for name, p in procs.items()}
    finally:
        for b in busy:
            b.kill()
            b.wait()
    for name, (code, _, err) in res.items():
        assert code == 0, (name, err[-3000:])
        assert "Traceback" not in err, (name, err[-3000:])
    errs = "".join(err for _, _, err in res.values())
    # exactly one server started; the other two commands waited and reused it
    assert errs.count("starting the project's Prefect server") == 1, errs[-3000:]
    [(url, pid)] = READY.findall(errs)
    assert sorted(REUSED.findall(errs)) == [(url, pid)] * 2, errs[-3000:]
    state = read_state(storage / ".prefect")
    assert state is not None and (state.api_url, state.pid) == (url, int(pid))
    for name in ("run1", "run2"):
        run_dir = Path(res[name][1].strip().splitlines()[-1])
        assert json.loads((run_dir / "checks.json").read_text())["pairs"]
    assert "nightly: 2 file(s): 2 ok" in res["nightly"][2]

    # the server outlives the commands; the next command reuses it
    assert _alive(state.pid) and healthy(state.api_url)
    code, _, err = _done(_cli("run", str(job), env=env))
    assert code == 0, err[-3000:]
    assert REUSED.findall(err) == [(url, pid)] and "starting the project's" not in err
    assert read_state(storage / ".prefect") == state

    code, out, _ = _done(_cli("server", "stop", "--job", str(job), env=env), 120)
    assert code == 0 and out.strip() == f"stopped the Prefect server at {url} (pid {pid})"
    assert not _alive(state.pid) and not (storage / ".prefect" / STATE_FILE).exists()


def test_a_stale_state_file_is_replaced(storage, tmp_path):
    job = write_job(tmp_path)
    home = storage / ".prefect"
    home.mkdir(parents=True)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # its pid is no process now
    stale = {"pid": dead.pid, "port": 9, "api_url": "http://127.0.0.1:9/api",
             "prefect_home": str(home), "prefect_version": "3.8.8",
             "started_utc": "2026-01-01T00:00:00+00:00"}
    (home / STATE_FILE).write_text(json.dumps(stale))
    env = _env()
    code, out, _ = _done(_cli("server", "status", "--job", str(job), env=env), 120)
    assert code == 0 and out.startswith(f"stale: the state file names pid {dead.pid}"), out

    code, out, err = _done(_cli("server", "start", "--job", str(job), env=env))
    assert code == 0, err[-3000:]
    assert f"replacing a stale Prefect server record (pid {dead.pid}" in err
    state = read_state(home)
    assert state is not None and state.pid != dead.pid and healthy(state.api_url)
    assert out.startswith(f"running: {state.api_url} (pid {state.pid})")


def test_a_state_file_naming_another_process_is_stale_and_the_process_left_alone(tmp_path):
    """A recorded pid reused by another process (here: a sleeping Python) is not our
    server: status says stale, stop removes the record and signals nothing."""
    home = tmp_path / "home"
    home.mkdir()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        (home / STATE_FILE).write_text(json.dumps(
            {"pid": other.pid, "port": 9, "api_url": "http://127.0.0.1:9/api",
             "prefect_home": str(home), "prefect_version": "3.8.8",
             "started_utc": "2026-01-01T00:00:00+00:00"}))
        env = _env(PREFECT_HOME=str(home))
        code, out, _ = _done(_cli("server", "status", env=env), 120)
        assert code == 0 and out.startswith(f"stale: the state file names pid {other.pid}")
        code, out, _ = _done(_cli("server", "stop", env=env), 120)
        assert code == 0 and out.startswith("removed a stale state file"), out
        assert other.poll() is None  # not signalled
        assert not (home / STATE_FILE).exists()
    finally:
        other.kill()
        other.wait()


def _server_processes(port: str) -> list[int]:
    """Pids of ``prefect server start`` processes on ``port``."""
    out = []
    for proc in Path("/proc").iterdir():
        try:
            args = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"prefect" in args and b"server" in args and port.encode() in args:
            out.append(int(proc.name))
    return out


CANNOT_START = {
    # the server cannot open its database: it exits during start-up
    "exits": ({"PREFECT_SERVER_DATABASE_CONNECTION_URL":
               "sqlite+aiosqlite:////nonexistent/plantdyn/prefect.db"},
              r"exited with code \d+; its log .* says: .*unable to open database file.*"),
    # no answer in time (a 0 s wait): the half-started server is stopped, not left behind
    "times out": ({"PLANTDYN_PREFECT_START_TIMEOUT_S": "0"},
                  r"did not answer GET http://127\.0\.0\.1:\d+/api/health within 0 s; .*"),
}


@pytest.mark.parametrize("case", sorted(CANNOT_START))
def test_a_server_that_cannot_start_is_one_message_and_exit_2(case, storage, make_job):
    job = make_job(1, hours=1.0)
    extra, says = CANNOT_START[case]
    code, _, err = _done(_cli("run", str(job), env=_env(**extra)))
    assert code == 2, err[-3000:]
    assert "Traceback" not in err and err.count("plantdyn: error: ") == 1, err[-3000:]
    assert re.search(r"plantdyn: error: the project's Prefect server \(PREFECT_HOME=.*\) " +
                     says + r"; run the command again with --no-prefect .*set PREFECT_API_URL",
                     err), err[-3000:]
    [port] = re.findall(r"starting the project's Prefect server on 127\.0\.0\.1:(\d+)", err)
    assert _server_processes(port) == []
    assert not (storage / ".prefect" / STATE_FILE).exists()
    assert not any(storage.rglob("manifest.json"))


def test_a_local_prefect_api_url_that_does_not_answer_is_exit_2(storage, make_job):
    """The user's PREFECT_API_URL wins over the project server -- and when it names a local
    server that is not running, that is said before any work."""
    job = make_job(1, hours=1.0)
    code, _, err = _done(_cli("run", str(job), env=_env(PREFECT_API_URL="http://127.0.0.1:9/api")))
    assert code == 2 and "Traceback" not in err, err[-3000:]
    assert "plantdyn: error: PREFECT_API_URL=http://127.0.0.1:9/api does not answer GET " \
        "http://127.0.0.1:9/api/health; start that server, unset PREFECT_API_URL" in err
    assert not (storage / ".prefect").exists() and not any(storage.rglob("manifest.json"))


def test_nightly_without_prefect_processes_each_file_once(storage, make_job):
    job = make_job(2, hours=1.0)
    env = _env()
    code, out, err = _done(_cli("nightly", str(job), "--no-prefect", env=env), 300)
    assert code == 0, err
    assert err.count("[nightly] ok: ") == 2 and "starting" not in err
    assert len(out.strip().splitlines()) == 2  # one line per file
    code, _, err2 = _done(_cli("nightly", str(job), "--no-prefect", env=env), 300)
    assert code == 0 and err2.count("[nightly] skipped: ") == 2, err2
    assert not (storage / ".prefect").exists()  # Prefect was not touched
