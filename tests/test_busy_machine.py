"""The default (Prefect) path on a busy machine (issue 33, must-show 1).

``plantdyn run`` and ``plantdyn nightly`` as a new user runs them -- no ``--no-prefect``, no
``PREFECT_API_URL``, so each command starts Prefect's embedded server -- while busy loops
load every core; both started at the same time (two commands racing on one Prefect
database's migration gave a traceback).  Exit 0, no traceback, results written.  Also:
``nightly --no-prefect`` gives the same results without Prefect, and a server that does
not answer ends in one message with the fix and exit 2.  Prefect's state lives in a
private ``PREFECT_HOME`` under the test's temp folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tests.conftest import subprocess_env

BUSY = "import time\nt = time.time()\nwhile time.time() - t < 600: pass\n"


def _env(tmp_path: Path, **extra: str) -> dict:
    return subprocess_env(PREFECT_API_URL=None, PREFECT_HOME=str(tmp_path / "prefect-home"),
                          **extra)


def _cli(*args: str, env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "flows.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_run_and_nightly_through_prefect_on_a_loaded_machine(tmp_path, make_job):
    job = make_job(2, hours=1.0)
    env = _env(tmp_path)
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(os.cpu_count() or 2)]
    try:
        procs = {"run": _cli("run", str(job), env=env), "nightly": _cli("nightly", str(job),
                                                                          env=env)}
        out = {k: p.communicate(timeout=600) for k, p in procs.items()}
    finally:
        for b in busy:
            b.kill()
            b.wait()
    for k, p in procs.items():
        stdout, stderr = out[k]
        assert p.returncode == 0, (k, stderr[-3000:])
        assert "Traceback" not in stderr, (k, stderr[-3000:])
    run_dir = Path(out["run"][0].strip().splitlines()[-1])
    assert json.loads((run_dir / "checks.json").read_text())["pairs"]
    assert "nightly: 2 file(s): 2 ok" in out["nightly"][1]


def test_nightly_without_prefect_processes_each_file_once(tmp_path, make_job):
    job = make_job(2, hours=1.0)
    env = _env(tmp_path)
    first = _cli("nightly", str(job), "--no-prefect", env=env)
    stdout, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    assert stderr.count("[nightly] ok: ") == 2 and "starting" not in stderr
    assert len(stdout.strip().splitlines()) == 2  # one line per file
    again = _cli("nightly", str(job), "--no-prefect", env=env)
    _, stderr2 = again.communicate(timeout=300)
    assert again.returncode == 0 and stderr2.count("[nightly] skipped: ") == 2, stderr2
    assert not (tmp_path / "prefect-home").exists()  # Prefect was not touched


def test_a_server_that_does_not_answer_is_one_message_and_exit_2(tmp_path, make_job):
    job = make_job(1, hours=1.0)
    # 0 s: no embedded server can answer in time
    env = _env(tmp_path, PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="0")
    p = _cli("run", str(job), env=env)
    _, stderr = p.communicate(timeout=300)
    assert p.returncode == 2, stderr[-3000:]
    assert "Traceback" not in stderr
    assert "did not answer within 0 s" in stderr and "--no-prefect" in stderr
    assert not (job.parent / "storage").exists() or not any(
        (job.parent / "storage").rglob("manifest.json"))
