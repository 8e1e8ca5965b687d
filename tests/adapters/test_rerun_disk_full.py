"""A full disk while the Rerun recording is written (issue 33, build 4): exit 2, one message,
nothing half-written (no run folder, no temporary ``.part`` recording, no ``.tmp`` run).

Rerun's file writer runs in its own thread: when a write fails it logs the OS error and
the next ``flush`` raises a bare ``RuntimeError("File-writer thread shut down
prematurely")`` (measured with rerun-sdk 0.41 under ``RLIMIT_FSIZE``: "File too large (os
error 27)").  The faults are injected where they surface, as tests/adapters/test_storage_faults.py
does (no root, no private mount): ``OSError(ENOSPC)`` from the flush; the bare
``RuntimeError`` with the disk reporting 640 KB free (the case reported); the same with
space to spare; and one real failure of the writer, a subprocess whose file-size limit
stops the recording half-way.
"""

from __future__ import annotations

import errno
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import rerun as rr

from pipeline.adapters.rerun_sink import common
from tests.conftest import subprocess_env, write_job, write_plant_csv
from tests.flows.test_cli_hostile_inputs import cli

STOPPED = "File-writer thread shut down prematurely"


@pytest.fixture
def job(tmp_path):
    write_plant_csv(tmp_path / "drop" / "export.csv", seed=21, hours=1.0)
    return write_job(tmp_path, rerun={"enabled": True})


def nothing_half_written(storage: Path) -> None:
    leftovers = [p for p in storage.rglob("*")
                 if p.name.startswith(".tmp") or p.name.endswith(".part")
                 or p.name.endswith(".rrd")]
    assert leftovers == [], leftovers
    assert not any(p.is_dir() for p in (storage / "plant").glob("*")), \
        list((storage / "plant").iterdir())


def one_message(rc: int, err: str, *needles: str) -> None:
    assert rc == 2, err[-3000:]
    assert "Traceback" not in err and err.count("plantdyn: error:") == 1, err[-3000:]
    for needle in needles:
        assert needle in err, err[-3000:]


def _flush_raises(monkeypatch, exc: BaseException) -> None:
    def flush(self, *args, **kwargs):
        raise exc

    monkeypatch.setattr(rr.RecordingStream, "flush", flush)


def test_enospc_from_the_rerun_writer(job, monkeypatch):
    _flush_raises(monkeypatch, OSError(errno.ENOSPC, "No space left on device"))
    rc, out, err = cli("run", "--no-prefect", str(job))
    one_message(rc, err, "the disk is full", "nothing was written",
                "free space or point storage: at another disk")
    assert out == ""
    nothing_half_written(job.parent / "storage")


class _Full:
    f_bavail = f_bfree = 160  # 640 KB free
    f_blocks, f_frsize = 1 << 20, 4096


def test_writer_thread_stopped_on_a_nearly_full_disk(job, monkeypatch):
    _flush_raises(monkeypatch, RuntimeError(STOPPED))
    monkeypatch.setattr(common.os, "statvfs", lambda path: _Full())
    rc, _, err = cli("run", "--no-prefect", str(job))
    one_message(rc, err, "the disk is full", "nothing was written")
    nothing_half_written(job.parent / "storage")


def test_writer_thread_stopped_with_space_to_spare(job, monkeypatch):
    _flush_raises(monkeypatch, RuntimeError(STOPPED))
    rc, _, err = cli("run", "--no-prefect", str(job))
    one_message(rc, err, f"the Rerun writer stopped ({STOPPED}) while writing the recording",
                "set rerun: {enabled: false} in the job", "nothing was written")
    nothing_half_written(job.parent / "storage")


def _limit_file_size(limit: int):
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_a_real_writer_failure_in_a_subprocess(job):
    """The recording of this job is about 750 kB and every other file below 200 kB: a 400 kB
    file-size limit stops Rerun's writer half-way (EFBIG; not a full disk, so the
    message is the writer's)."""
    proc = subprocess.run([sys.executable, "-m", "flows.cli", "run", "--no-prefect", str(job)],
                          cwd=Path(__file__).resolve().parents[2], env=subprocess_env(),
                          capture_output=True, text=True, timeout=300, check=False,
                          preexec_fn=_limit_file_size(400 << 10))
    one_message(proc.returncode, proc.stderr, "the Rerun writer stopped", STOPPED,
                "nothing was written")
    nothing_half_written(job.parent / "storage")
    assert os.path.getsize(job) < 400 << 10
