"""Nightly over a real backlog (issue 33, build 2), driven as a user: ``plantdyn nightly
JOB.yaml`` (the CLI's ``main``, ``--no-prefect``; the Dask test runs the command as a
subprocess through Prefect), reading the status lines and the result files.

* bounded concurrency: 12 small exports with ``nightly.max_parallel: 3`` — at most 3
  files are ever processed at once (start and duration of every file, from its status
  line); the default bound's formula;
* complete files only: a half-written export is skipped ("still being written") and taken
  the next night once complete (one run, of the complete file); the marker-file mode;
* data-time order, and one monitoring baseline per backlog (the earliest in data time),
  every later file compared with it;
* failures keyed to the file and the job's configuration, ``--retry-failed``;
* a vanished file is a skipped row; an empty ``dask.address`` is exit 2;
* a 2-worker Dask cluster: the per-file lines appear on the command's stderr.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from pipeline.adapters.config import load_job
from pipeline.adapters.drop_folder import default_max_parallel, per_file_memory_bytes
from pipeline.adapters.historian_writer import write_json_mcap, write_long_csv
from pipeline.adapters.store import ResultStore, file_sha256
from pipeline.errors import DataQualityError
from pipeline.jobs.nightly import job_config_sha256, nightly_run_id, plan_night, process_file
from tests.conftest import (
    INPUT_TAG,
    OUTPUT_TAG,
    plant_signals,
    subprocess_env,
    write_job,
)

JOB = "plant"
HOURS = 0.25  # 900 one-second samples: an estimate in about a second
FAST = {"search": {"n_p": 40}}  # no N_p search: orchestration is the point here
LINE = re.compile(r"^\[nightly\] (?P<status>[a-z_]+): (?P<path>/\S+)(?:  -> (?P<run>\S+))?"
                  r"(?:  \[(?P<start>\S+) to (?P<end>\S+), [0-9.]+ s(?: on (?P<on>\S+))?\])?")
HOUR_AGO = time.time() - 3600


def write_export(path: Path, *, seed: int, day: int, mtime: float | None = HOUR_AGO) -> Path:
    """The plant's export whose data starts ``day`` days after 2026-03-02 (last modified an
    hour ago unless ``mtime`` is None: a complete file)."""
    sig = plant_signals(seed=seed, hours=HOURS)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_long_csv(path, sig["time"] + np.timedelta64(day, "D"),
                   {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]})
    if mtime is not None:
        os.utime(path, (mtime, mtime))
    return path


def nightly(job: Path, capsys, *args: str) -> tuple[int, str, list[dict]]:
    """``plantdyn nightly JOB --no-prefect ARGS``: exit code, stderr, parsed status lines."""
    from flows.cli import main

    code = main(["nightly", str(job), "--no-prefect", *args])
    err = capsys.readouterr().err
    return code, err, [m.groupdict() for m in map(LINE.match, err.splitlines()) if m]


def by_name(lines: list[dict]) -> dict[str, str]:
    return {Path(m["path"]).name: m["status"] for m in lines}


def run_dirs(root: Path) -> list[str]:
    return sorted(p.name for p in (root / JOB).glob("file-*") if (p / "manifest.json").is_file())


def peak_overlap(intervals: list[tuple[float, float]]) -> int:
    """Largest number of intervals open at one instant (an end before a start at a tie)."""
    events = sorted([(a, 1) for a, _ in intervals] + [(b, -1) for _, b in intervals])
    now = peak = 0
    for _, step in events:
        now += step
        peak = max(peak, now)
    return peak


# ------------------------------------------------------------------ bounded concurrency
def test_backlog_of_12_runs_at_most_max_parallel_files_at_once(tmp_path, capsys):
    for k in range(12):
        write_export(tmp_path / "drop" / f"export_{k:02d}.csv", seed=k + 1, day=k)
    job = write_job(tmp_path, nightly={"max_parallel": 3}, **FAST)
    code, err, lines = nightly(job, capsys)
    assert code == 0, err
    assert "12 file(s) to process in data-time order, 0 skipped" in err
    assert "at most 3 at a time (nightly.max_parallel)" in err
    assert [m["status"] for m in lines] == ["ok"] * 12, err
    spans = [tuple(np.datetime64(m[k].removesuffix("Z"), "ms").astype(np.int64)
                   for k in ("start", "end")) for m in lines]
    assert 2 <= peak_overlap(spans) <= 3, spans  # side by side, never more than the bound
    assert len(run_dirs(tmp_path / "storage")) == 12
    done = ResultStore(tmp_path / "storage").processed(JOB)
    assert done["status"].to_list() == ["ok"] * 12 and done["attempts"].to_list() == [1] * 12


def test_default_bound_follows_cores_and_memory():
    gib = 1 << 30
    assert per_file_memory_bytes(0) == 256 << 20
    assert per_file_memory_bytes(100 << 20) == (256 + 200) << 20
    # 0.5 * 4 GiB / 256 MiB = 8 small files by memory; the cores bound first
    assert default_max_parallel(1000, cores=2, available_bytes=4 * gib) == 2
    assert default_max_parallel(0, cores=64, available_bytes=4 * gib) == 8
    # month-sized exports (2.5 GiB): 0.5 * 24 GiB / 5.25 GiB -> 2 of 8 cores; never 0
    assert default_max_parallel(5 * gib // 2, cores=8, available_bytes=24 * gib) == 2
    assert default_max_parallel(5 * gib // 2, cores=8, available_bytes=gib) == 1


# ------------------------------------------------------------------ complete files only
def test_half_written_export_is_taken_the_night_after_it_is_complete(tmp_path, capsys,
                                                                     monkeypatch):
    monkeypatch.setenv("PLANTDYN_SETTLE_S", "60")
    storage = tmp_path / "storage"
    write_export(tmp_path / "drop" / "a.csv", seed=1, day=0)
    full = write_export(tmp_path / "drop" / "b.csv", seed=2, day=1).read_bytes()
    half = tmp_path / "drop" / "b.csv"
    half.write_bytes(full[: int(len(full) * 0.4)])  # the exporter is still writing (now)
    job = write_job(tmp_path, **FAST)

    code, err, lines = nightly(job, capsys)
    assert code == 0, err
    assert by_name(lines) == {"a.csv": "ok", "b.csv": "skipped_writing"}
    assert re.search(r"skipped_writing: \S+b\.csv  \(still being written \(modified \d+ s "
                     r"ago, nightly.settle_s is 60\)", err), err
    assert run_dirs(storage) == [nightly_run_id(file_sha256(tmp_path / "drop" / "a.csv"))]

    half.write_bytes(full)  # the export is finished; a night later it has settled
    os.utime(half, (HOUR_AGO, HOUR_AGO))
    code, err, lines = nightly(job, capsys)
    assert code == 0, err
    assert by_name(lines) == {"a.csv": "skipped", "b.csv": "ok"}
    b_run = nightly_run_id(file_sha256(half))
    assert len(run_dirs(storage)) == 2 and b_run in run_dirs(storage)  # one run per export
    manifest = json.loads((storage / JOB / b_run / "manifest.json").read_text())
    assert [i["sha256"] for i in manifest["inputs"]] == [file_sha256(half)]  # the whole file


def test_marker_mode_takes_a_file_once_its_marker_exists(tmp_path):
    write_export(tmp_path / "drop" / "a.csv", seed=1, day=0, mtime=None)  # just written
    write_export(tmp_path / "drop" / "b.csv", seed=2, day=1, mtime=None)
    (tmp_path / "drop" / "a.csv.done").write_text("")
    cfg = load_job(write_job(tmp_path, source="drop/*", nightly={"marker": ".done"}))
    plan = plan_night(cfg)
    assert [Path(f.path).name for f in plan.files] == ["a.csv"]  # the marker is not a source
    assert [(Path(r["path"]).name, r["status"]) for r in plan.skipped] == [
        ("b.csv", "skipped_writing")]
    assert "no marker b.csv.done yet" in plan.skipped[0]["error"]


# ------------------------------------------------------------------ order and baseline
def test_files_are_planned_in_data_time_order(tmp_path):
    drop = tmp_path / "drop"
    write_export(drop / "a.csv", seed=1, day=3)
    write_export(drop / "b.csv", seed=2, day=1)
    sig = plant_signals(seed=3, hours=HOURS)
    write_json_mcap(drop / "c.mcap", sig["time"] + np.timedelta64(2, "D"),
                    {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]}, samples_per_message=60)
    (drop / "d.csv").write_text("not,an,export\n")  # unreadable: its mtime stands in
    os.utime(drop / "d.csv", (1e9, 1e9))  # 2001
    plan = plan_night(load_job(write_job(tmp_path, source="drop/*")))
    assert [(Path(f.path).name, f.time_source) for f in plan.files] == [
        ("d.csv", "mtime"), ("b.csv", "data"), ("c.mcap", "data"), ("a.csv", "data")]
    start = np.datetime64("2026-03-02T00:00:00", "s").astype(float)
    assert [f.data_start_s - start for f in plan.files[1:]] == [86_400, 2 * 86_400,
                                                                3 * 86_400]


def test_backlog_has_one_baseline_the_earliest_and_every_file_is_compared_with_it(
        tmp_path, capsys):
    # names in the reverse of the data's order: the backlog is taken by data time
    for name, day in (("a.csv", 3), ("b.csv", 2), ("c.csv", 1), ("d.csv", 0)):
        write_export(tmp_path / "drop" / name, seed=10 + day, day=day)
    job = write_job(tmp_path, monitor={"baseline": "first"}, nightly={"max_parallel": 2},
                    **FAST)
    code, err, lines = nightly(job, capsys)
    assert code == 0, err
    assert [m["status"] for m in lines] == ["ok"] * 4, err
    assert Path(lines[0]["path"]).name == "d.csv"  # the earliest, alone, first
    runs = {Path(m["path"]).name: m["run"] for m in lines}
    storage = tmp_path / "storage" / JOB
    monitor = {n: json.loads((storage / r / "checks.json").read_text())["monitor"]
               for n, r in runs.items()}
    assert [n for n, m in monitor.items() if m["is_baseline"]] == ["d.csv"]
    assert {n: m["baseline_run"] for n, m in monitor.items()} == dict.fromkeys(
        runs, runs["d.csv"])
    for n in ("a.csv", "b.csv", "c.csv"):
        assert set(monitor[n]["pairs"]) == {"y<-u"}, monitor[n]  # compared, pair by pair


# ------------------------------------------------------------------ failures and retries
def test_failed_file_is_keyed_to_the_job_configuration_and_retried_on_request(tmp_path,
                                                                              capsys):
    write_export(tmp_path / "drop" / "export.csv", seed=1, day=0)
    storage = tmp_path / "storage"
    typo = {"inputs": {"u": {"tag": INPUT_TAG}}, "outputs": {"y": {"tag": "Y.PVX"}}}
    job = write_job(tmp_path, signals=typo, **FAST)
    code, err, lines = nightly(job, capsys)
    assert code == 2 and by_name(lines) == {"export.csv": "failed"}, err
    assert "Y.PVX" in err

    code, err, lines = nightly(job, capsys)  # same file, same job: not tried again
    assert code == 0 and by_name(lines) == {"export.csv": "skipped_failed_before"}, err
    assert "Y.PVX" in err and f"plantdyn nightly {job} --retry-failed" in err
    # an edit that changes nothing computed (a comment, the bound) is the same job
    job.write_text("# checked by the night shift\n" + job.read_text().replace(
        "rerun:", "nightly:\n  max_parallel: 1\nrerun:"))
    code, err, lines = nightly(job, capsys)
    assert code == 0 and by_name(lines) == {"export.csv": "skipped_failed_before"}, err

    code, err, lines = nightly(job, capsys, "--retry-failed")  # tried again on request
    assert code == 2 and by_name(lines) == {"export.csv": "failed"}, err
    store = ResultStore(storage)
    assert store.processed(JOB)["attempts"].to_list() == [2]

    job.write_text(job.read_text().replace("Y.PVX", OUTPUT_TAG))  # fixed in the job
    code, err, lines = nightly(job, capsys)
    assert code == 0 and by_name(lines) == {"export.csv": "ok"}, err
    rid = nightly_run_id(file_sha256(tmp_path / "drop" / "export.csv"))
    assert run_dirs(storage) == [rid]
    assert (storage / JOB / rid / "step_responses.parquet").is_file()
    done = store.processed(JOB)
    assert (done["status"].to_list(), done["attempts"].to_list()) == (["ok"], [3])


def test_retry_failed_reruns_a_file_whose_fix_is_outside_the_job(tmp_path):
    """A failure fixed elsewhere (a new plantdyn, a repaired tool) keeps the job's hash: the
    file waits for ``--retry-failed``."""
    (tmp_path / "drop").mkdir()
    path = str(tmp_path / "drop" / "f.csv")
    Path(path).write_text("content\n")
    cfg = load_job(write_job(tmp_path))
    sha = file_sha256(path)

    def broken(c, files, run_id):
        raise DataQualityError(f"{files[0]}: every sample of tag U.PV is bad")

    def fixed(c, files, run_id):
        store = ResultStore(c.storage_root)
        with store.new_run(c.job, run_id=run_id, config={"job": c.job}, inputs=[]) as run:
            run.write_text("report.md", "stub\n")
        return type("Report", (), {"run_id": run_id})()

    assert process_file(cfg, path, sha, run=broken)["status"] == "failed"
    assert process_file(cfg, path, sha, run=fixed)["status"] == "skipped_failed_before"
    row = process_file(cfg, path, sha, run=fixed, retry_failed=True)
    assert (row["status"], row["run_id"]) == ("ok", nightly_run_id(sha))


def test_config_hash_ignores_runner_keys_and_follows_what_is_computed(tmp_path):
    base = load_job(write_job(tmp_path, file_name="a.yaml"))
    runner = load_job(write_job(tmp_path, file_name="b.yaml", nightly={"max_parallel": 4},
                                schedule="0 2 * * *", dask={"address": "tcp://h:8786"}))
    other = load_job(write_job(tmp_path, file_name="c.yaml", search={"n_p": 30}))
    assert job_config_sha256(base) == job_config_sha256(runner)
    assert job_config_sha256(base) != job_config_sha256(other)


# ------------------------------------------------------------------ vanished, bad config
def test_file_vanishing_before_or_while_it_is_processed_is_a_skipped_row(tmp_path):
    (tmp_path / "drop").mkdir()
    gone, going = (str(tmp_path / "drop" / f"{n}.csv") for n in ("gone", "going"))
    for p in (gone, going):
        Path(p).write_text(f"{p}\n")
    cfg = load_job(write_job(tmp_path))
    sha_gone, sha_going = file_sha256(gone), file_sha256(going)
    os.remove(gone)  # deleted after the folder was listed
    row = process_file(cfg, gone, sha_gone, run=None)
    assert row["status"] == "skipped_vanished" and "vanished" in row["error"]

    def deleted_while_read(c, files, run_id):
        os.remove(files[0])
        raise FileNotFoundError(2, "No such file or directory", str(files[0]))

    row = process_file(cfg, going, sha_going, run=deleted_while_read)
    assert row["status"] == "skipped_vanished" and "while it was processed" in row["error"]
    done = ResultStore(cfg.storage_root).processed(JOB)
    assert done["status"].to_list() == ["vanished"]  # not failed: a copy is taken again


def test_empty_dask_address_is_a_config_error(tmp_path, capsys):
    from flows.cli import main

    write_export(tmp_path / "drop" / "export.csv", seed=1, day=0)
    job = write_job(tmp_path)
    job.write_text(job.read_text() + "dask:\n  address:\n")
    assert main(["nightly", str(job), "--no-prefect"]) == 2
    err = capsys.readouterr().err
    assert re.search(r"dask: address is empty; give the Dask scheduler's address, e\.g\. "
                     r"dask: \{address: tcp://", err), err
    assert err.count("plantdyn: error:") == 1 and "Traceback" not in err
    assert not (tmp_path / "storage").exists()


# ------------------------------------------------------------------ Dask workers
def test_dask_workers_lines_appear_on_the_commands_stderr(tmp_path, prefect_harness):
    """Two worker processes process the files through the Prefect flow; the command (a
    subprocess of its own) prints every file's line, naming the worker that ran it."""
    from distributed import Client, LocalCluster

    for k in range(3):
        write_export(tmp_path / "drop" / f"export_{k}.csv", seed=k + 1, day=k)
    env = {"PREFECT_API_URL": prefect_harness, "PLANTDYN_SETTLE_S": "0",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).parents[2]),
                                                       os.environ.get("PYTHONPATH")]))}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, protocol="tcp",
                      dashboard_address=None, env=env) as cluster, \
            Client(cluster.scheduler_address) as client:
        job = write_job(tmp_path, dask={"address": cluster.scheduler_address}, **FAST)
        workers = {f"{host}:{pid}" for host, pid in client.run(
            lambda: (__import__("socket").gethostname(), os.getpid())).values()}
        done = subprocess.run([sys.executable, "-m", "flows.cli", "nightly", str(job)],
                              env=subprocess_env(**env), capture_output=True, text=True,
                              timeout=600, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = [m.groupdict() for m in map(LINE.match, done.stderr.splitlines()) if m]
    assert sorted(Path(m["path"]).name for m in lines) == [f"export_{k}.csv" for k in range(3)]
    assert {m["status"] for m in lines} == {"ok"}, done.stderr
    assert {m["on"] for m in lines} <= workers  # run on the workers, said by the command
    bound = int(re.search(r"at most (\d+) at a time", done.stderr)[1])
    spans = [tuple(np.datetime64(m[k].removesuffix("Z"), "ms").astype(np.int64)
                   for k in ("start", "end")) for m in lines]
    assert peak_overlap(spans) <= bound  # the bound holds on Dask too
    assert len(run_dirs(tmp_path / "storage")) == 3
    assert yaml.safe_load(job.read_text())["dask"]["address"].startswith("tcp://")
