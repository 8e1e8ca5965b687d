"""Storage faults through the CLI (issue 10, must-show 5): a full disk, a read-only
storage root and a read-only catalog give one clear message (exit 2, the path, the cause,
the fix), leave nothing half-written, and ``plantdyn reindex`` restores the catalog.

The faults are injected where the operating system would raise them (the tests run as
root, which ignores permission bits, and may not mount a small tmpfs in CI): ``ENOSPC``
from the parquet write, ``EROFS`` from creating the run folder, SQLite's "attempt to write
a readonly database" from the catalog insert.
"""

from __future__ import annotations

import errno
import json
import os
import re
import sqlite3
from pathlib import Path

import pytest

from pipeline.adapters import store as store_mod
from tests.conftest import write_job, write_plant_csv
from tests.flows.test_cli_hostile_inputs import cli


@pytest.fixture
def job(tmp_path):
    write_plant_csv(tmp_path / "drop" / "export.csv", seed=21, hours=1.0)
    return write_job(tmp_path)


def _nothing_half_written(storage: Path) -> None:
    if not storage.exists():
        return
    for p in storage.rglob("*"):
        assert not p.name.startswith(".tmp"), p
        if p.is_dir() and p.parent.parent == storage:
            assert (p / "manifest.json").is_file(), p


def test_disk_full_while_writing_the_run(job, monkeypatch):
    # signals.parquet is written a chunk at a time (RunWriter.write_parquet_chunks)
    real = store_mod.RunWriter.write_parquet_chunks

    def full(self, name, chunks):
        if name == "signals.parquet":
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path / name))
        return real(self, name, chunks)

    monkeypatch.setattr(store_mod.RunWriter, "write_parquet_chunks", full)
    rc, _, err = cli("run", "--no-prefect", str(job))
    assert rc == 2 and "Traceback" not in err, err[-2000:]
    assert "signals.parquet: the disk is full" in err and "nothing was written" in err
    assert "free space or point storage: at another disk" in err
    _nothing_half_written(job.parent / "storage")
    assert not any((job.parent / "storage" / "plant").iterdir())


def test_read_only_storage(job, monkeypatch):
    real_mkdir = Path.mkdir

    def read_only(self, *a, **k):
        if "plant" in self.parts and (job.parent / "storage") in self.parents:
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real_mkdir(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", read_only)
    rc, _, err = cli("run", "--no-prefect", str(job))
    assert rc == 2 and "Traceback" not in err, err[-2000:]
    assert "not writable (Read-only file system) while creating the run folder" in err
    assert "point storage: at a writable folder" in err
    _nothing_half_written(job.parent / "storage")


def test_read_only_catalog_then_reindex_restores_it(job, monkeypatch):
    def refuse(self, manifest):
        raise sqlite3.OperationalError("attempt to write a readonly database")

    monkeypatch.setattr(store_mod.ResultStore, "_insert_run", refuse)
    rc, out, err = cli("run", "--no-prefect", str(job))
    assert rc == 2 and "Traceback" not in err, err[-2000:]
    assert "the catalog is read-only while cataloguing run plant/" in err
    assert "is complete but missing from the catalog; `plantdyn reindex" in err
    storage = job.parent / "storage"
    runs = [p for p in (storage / "plant").iterdir() if not p.name.startswith(".")]
    assert len(runs) == 1 and (runs[0] / "manifest.json").is_file()  # the run landed whole
    monkeypatch.undo()
    rc, out, _ = cli("runs", str(job))
    assert "no runs of job 'plant'" in out  # not catalogued yet
    rc, out, err = cli("reindex", str(storage))
    assert rc == 0 and "catalog rebuilt from 1 run folder(s)" in out, err
    rc, out, _ = cli("runs", str(job))
    assert rc == 0 and runs[0].name in out


def test_runs_reads_an_archive_without_writing_to_it(job):
    rc, out, err = cli("run", "--no-prefect", str(job))
    assert rc == 0, err
    run_id = Path(out.strip().splitlines()[-1]).name
    storage = job.parent / "storage"
    for suffix in ("-wal", "-shm"):
        Path(f"{storage / 'catalog.sqlite'}{suffix}").unlink(missing_ok=True)
    before = {p: p.stat().st_mtime_ns for p in storage.rglob("*")}
    rc, out, err = cli("runs", str(job))
    assert rc == 0 and run_id in out, err
    after = {p: p.stat().st_mtime_ns for p in storage.rglob("*")}
    assert sorted(map(str, after)) == sorted(map(str, before))  # nothing created
    assert {p for p in after if after[p] != before[p]} == set()  # nothing touched


def test_a_catalog_symlink_is_refused(tmp_path, job):
    storage = job.parent / "storage"
    storage.mkdir()
    outside = tmp_path.parent / f"{tmp_path.name}-elsewhere.sqlite"
    outside.write_bytes(b"")
    os.symlink(outside, storage / "catalog.sqlite")
    rc, _, err = cli("run", "--no-prefect", str(job))
    assert rc == 2 and "the catalog is a symbolic link" in err, err[-2000:]
    assert outside.read_bytes() == b""


def test_storage_that_is_a_file(tmp_path):
    write_plant_csv(tmp_path / "drop" / "export.csv", seed=22, hours=1.0)
    (tmp_path / "results").write_text("not a folder")
    job = write_job(tmp_path, storage="results")
    rc, _, err = cli("run", "--no-prefect", str(job))
    assert rc == 2 and "is a file, not a folder" in err, err[-2000:]
    assert json.dumps(err)  # one message, no traceback
    assert "Traceback" not in err


def test_nightly_prints_each_file_and_a_summary(tmp_path, prefect_harness):
    """`plantdyn nightly` says what happened to every file; a bad file is exit 2 with one
    error line naming it (it printed nothing at all before)."""
    import subprocess
    import sys

    from tests.conftest import subprocess_env

    write_plant_csv(tmp_path / "drop" / "a.csv", seed=31, hours=1.0)
    write_plant_csv(tmp_path / "drop" / "b.csv", seed=32, hours=1.0)
    (tmp_path / "drop" / "c.csv").write_text("tag,timestamp,value,status\nU.PV,garbage,1,Good\n")
    job = write_job(tmp_path)
    r = subprocess.run([sys.executable, "-m", "flows.cli", "nightly", "--progress", "always",
                        str(job)], capture_output=True, text=True, timeout=600,
                       env=subprocess_env(PREFECT_API_URL=prefect_harness,
                                          PLANTDYN_PROGRESS_EVERY_S="0"))
    assert r.returncode == 2, r.stderr[-3000:]
    # the file loop's progress (asked for: stderr is a pipe here), ending at all files
    assert re.search(r"^nightly: 100 % 3 of 3 files, [\d.]+ files/s, ETA 0 s$", r.stderr, re.M), \
        r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    assert r.stderr.count("plantdyn: error: ") == 1
    assert ("1 of 3 file(s) failed with bad data (not retried until they or the job change, "
            "or --retry-failed): c.csv") in r.stderr
    assert "[nightly] plant: 3 file(s)" in r.stderr
    assert r.stderr.count("[nightly] ok: ") == 2 and "[nightly] failed: " in r.stderr
    assert "nightly: 3 file(s): 1 failed, 2 ok" in r.stderr
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 3 and sum(ln.split()[0] == "ok" for ln in lines) == 2
    assert any("file-" in ln for ln in lines)


def test_default_prefect_path_reports_progress(tmp_path, prefect_harness):
    import subprocess
    import sys

    from tests.conftest import subprocess_env

    write_plant_csv(tmp_path / "drop" / "a.csv", seed=33, hours=1.0)
    job = write_job(tmp_path)
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", "--progress", "always",
                        str(job)], capture_output=True, text=True, timeout=600,
                       env=subprocess_env(PREFECT_API_URL=prefect_harness,
                                          PLANTDYN_PROGRESS_EVERY_S="0"))
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stderr.startswith("starting the Prefect flow 'estimate'")
    # the bars inside the flow's tasks: ingest in MB of the file, the search in steps
    mb = (tmp_path / "drop" / "a.csv").stat().st_size / 1e6
    m = re.search(r"^ingest: 100 % ([\d.,]+) of ([\d.,]+) MB, ", r.stderr, re.M)
    assert r.stderr.count("ingest: 100 %") == 1
    assert m and m.group(1) == m.group(2) == f"{mb:.2f}", r.stderr[-3000:]
    assert re.search(r"^search: 100 % (\d+) of \1 steps, .* ETA 0 s$", r.stderr, re.M)
    for stage in ("ingest", "prepare", "search", "estimate", "store"):
        assert f"] {stage}: " in r.stderr, stage
