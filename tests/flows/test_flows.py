"""The Prefect flows and the nightly exactly-once logic.

* ``estimate`` flow == ``run_job`` (same stages, with and without Prefect, and on a Dask
  cluster);
* ``nightly``: each file of a drop folder processed once; a corrupt file fails with its
  reason and is not retried until its content changes; a SIGKILLed nightly process
  restarted with a short claim lease ends with every file processed exactly once;
* ``process_file`` with stub runs (adoption, heartbeat, failed vs error, lease setting);
* the CLI's exit code 2 and messages for bad jobs (table-driven: add cases to ``BAD_JOBS``).
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import polars as pl
import pytest
import yaml
from polars.testing import assert_frame_equal

from pipeline.adapters.config import load_job
from pipeline.adapters.store import ResultStore, file_sha256
from pipeline.errors import ConfigError, DataQualityError
from pipeline.jobs.nightly import (
    LEASE_ENV,
    claim_lease_s,
    discover_files,
    nightly_run_id,
    process_file,
)
from tests.conftest import (
    INPUT_TAG,
    OUTPUT_TAG,
    PLANT_GAIN,
    latest_artifact,
    subprocess_env,
    write_job,
    write_plant_csv,
)

JOB = "plant"


# ------------------------------------------------------------------------- helpers
def run_dirs(storage: Path, job: str = JOB) -> list[str]:
    """Committed run directories (hidden ``.tmp-*`` ones excluded), sorted."""
    d = storage / job
    return sorted(p.name for p in d.iterdir() if p.is_dir() and not p.name.startswith(".")) \
        if d.is_dir() else []


def tmp_dirs(storage: Path, job: str = JOB) -> list[str]:
    d = storage / job
    return sorted(p.name for p in d.glob(".tmp-*")) if d.is_dir() else []


def drop_files(folder: Path) -> list[Path]:
    return sorted((folder / "drop").iterdir())


def step_responses(run_dir: Path) -> pl.DataFrame:
    return pl.read_parquet(run_dir / "step_responses.parquet").sort(
        ["window", "output", "input", "lag"])


def assert_plausible_plant(sr: pl.DataFrame) -> None:
    """The estimate is the plant's, not an empty or degenerate table: every window
    present, and the final step of window ``all`` near the gain K.  Tolerance 5 % of K:
    the estimate truncated at N_p·T ≈ 4.4 τ misses at most e^-4.4 ≈ 1.2 % of K (absorbed
    partly into the last coefficient), and its noise σ is ≈ 0.001 (step_std)."""
    windows = set(sr["window"].unique())
    assert "all" in windows and len(windows) >= 3, windows
    final = sr.filter(pl.col("window") == "all").sort("lag")["step"][-1]
    assert abs(final - PLANT_GAIN) < 0.05 * PLANT_GAIN, final


# --------------------------------------------------------------- estimate flow
def test_estimate_flow_equals_direct_run_job(prefect_harness, make_job):
    from flows.estimate import run_estimate
    from pipeline.jobs.estimation import run_job

    job = make_job(1, rerun={"enabled": True},  # the whole path, Rerun sink included
                   signals={"inputs": {"u": {"tag": INPUT_TAG, "unit": "%"}},
                            "outputs": {"y": {"tag": OUTPUT_TAG, "unit": "°C"}}})
    direct = run_job(load_job(job), run_id="direct")
    via_flow = run_estimate(job, run_id="flow")
    assert via_flow.run_dir == job.parent / "storage" / JOB / "flow"
    assert via_flow.recording == via_flow.run_dir / "recording.rrd"
    assert via_flow.recording.is_file() and direct.recording.is_file()
    a, b = step_responses(direct.run_dir), step_responses(via_flow.run_dir)
    assert_plausible_plant(a)
    # same code on the same data in one process: bit-for-bit equal, not just close
    assert_frame_equal(a, b, check_exact=True)
    assert (via_flow.n_p, via_flow.n_d, via_flow.dt_s) == (direct.n_p, direct.n_d, direct.dt_s)
    # one stage list: the flow ran exactly the stages (and store parts) the direct path ran
    assert list(via_flow.timings_s) == list(direct.timings_s)
    assert list(direct.timings_s)[:6] == ["ingest", "prepare", "search", "estimate",
                                          "summarise", "store/hash_inputs"]
    _assert_one_summary_everywhere(via_flow)


def _assert_one_summary_everywhere(report) -> None:
    """The terminal, report.md, report.html and the Prefect artifacts print the same
    gain text, grade and window verdict: each is a rendering of one summary."""
    import html as html_lib
    import json

    from flows.common import artifact_key

    stored = report.run_dir / "report.md"
    md = stored.read_text(encoding="utf-8")
    assert latest_artifact(artifact_key(JOB, "report")).data == md
    rows = latest_artifact(artifact_key(JOB, "pairs")).data
    rows = json.loads(rows) if isinstance(rows, str) else rows
    checks = json.loads((report.run_dir / "checks.json").read_text())
    page = html_lib.unescape(re.sub(r"<[^>]+>", " ", (report.run_dir / "report.html").read_text()))
    terminal = str(report)
    assert len(rows) == len(checks["pairs"]) == 1
    for row, pair in zip(rows, checks["pairs"]):
        # known answer, read from checks.json, not from the summary: gain ± σ to 4 and 2
        # significant figures and the unit, the grade the grade rule gives
        gain = f"{pair['gain']:.4g} ± {pair['gain_std']:.2g}"
        assert row["gain"] == f"{gain} °C/%"
        name = f"{pair['output']}<-{pair['input']}"
        line = next(ln for ln in terminal.splitlines() if ln.strip().startswith(name))
        assert f"grade {row['grade']}, gain {gain} °C/%" in line
        assert f"windows {pair['agreement']['verdict']}" in line
        md_row = next(ln for ln in md.splitlines() if ln.startswith(f"| {pair['output']} | "))
        assert f"| {row['grade']} |" in md_row and f"| {gain} °C/% |" in md_row
        assert row["windows"] in md_row and row["feedback"] in md_row
        assert f"{gain} {row['grade']}" in " ".join(page.split())  # the gain matrix cell


def test_flows_parse_the_job_once_when_given_it(prefect_harness, make_job, monkeypatch):
    """The CLI validates the YAML and hands the parsed job to the flow: no second parse
    (a deployment, which has only the path, parses it in the flow)."""
    import flows.estimate
    from flows.estimate import run_estimate

    job = make_job(1)
    cfg = load_job(job)

    def parse_again(_path):
        raise AssertionError("the job YAML was parsed a second time")

    monkeypatch.setattr(flows.estimate, "load_job", parse_again)
    report = run_estimate(job, run_id="once", cfg=cfg)
    assert report.run_dir == job.parent / "storage" / JOB / "once"


def test_estimate_on_dask_cluster_equals_default_runner(prefect_harness, tmp_path):
    from distributed import Client, LocalCluster

    from flows.estimate import run_estimate

    write_plant_csv(tmp_path / "drop" / "export.csv", seed=11)
    plain = write_job(tmp_path, file_name="plain.yaml")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp",
                      dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://")
        on_dask = write_job(tmp_path, file_name="dask.yaml",
                            dask={"address": cluster.scheduler_address})
        ref = run_estimate(plain, run_id="default-runner")
        dsk = run_estimate(on_dask, run_id="dask-runner")
        # the mapped window estimates really ran on the cluster's workers (tasks called
        # directly — ingest, prepare, search — run in the flow's thread by design)
        with Client(cluster.scheduler_address) as client:
            finished = client.run_on_scheduler(
                lambda dask_scheduler: {name: tp.state_counts.get("memory", 0) for name, tp
                                        in dask_scheduler.task_prefixes.items()})
    n_windows = step_responses(dsk.run_dir)["window"].n_unique()  # "all" + w0, w1, ...
    # (dask names a task by its function: the task wraps pipeline.jobs.estimation.estimate_window)
    # the all-data fit and the windows between the first and the last: those two come
    # from the search's stage 2, which estimated them with the job's settings (least
    # squares at the search's orders on this plant; each window is estimated once)
    assert n_windows >= 3 and finished.get("estimate_window") == n_windows - 2, finished
    a, b = step_responses(ref.run_dir), step_responses(dsk.run_dir)
    assert_plausible_plant(a)
    assert_frame_equal(a, b, check_exact=True)


# -------------------------------------------------------------- nightly flow
def test_nightly_processes_each_file_once(prefect_harness, make_job):
    from flows.nightly import run_nightly

    job = make_job(3)
    storage = job.parent / "storage"
    files = drop_files(job.parent)
    expected_ids = sorted(nightly_run_id(file_sha256(f)) for f in files)

    rows = run_nightly(job)
    assert sorted(r["status"] for r in rows) == ["ok"] * 3
    assert sorted(r["run_id"] for r in rows) == expected_ids
    assert run_dirs(storage) == expected_ids
    assert tmp_dirs(storage) == []
    store = ResultStore(storage)
    done = store.processed(JOB)
    assert done["status"].to_list() == ["ok"] * 3
    assert sorted(done["run_id"].to_list()) == expected_ids
    assert done["attempts"].to_list() == [1, 1, 1]
    assert sorted(store.list_runs(JOB)["run_id"].to_list()) == expected_ids
    mtimes = {r: (storage / JOB / r / "manifest.json").stat().st_mtime_ns for r in expected_ids}

    again = run_nightly(job)
    assert sorted(r["status"] for r in again) == ["skipped"] * 3
    assert run_dirs(storage) == expected_ids
    assert {r: (storage / JOB / r / "manifest.json").stat().st_mtime_ns
            for r in expected_ids} == mtimes  # nothing rewritten
    assert store.processed(JOB)["attempts"].to_list() == [1, 1, 1]


def test_nightly_corrupt_file_fails_alone_and_is_not_retried(prefect_harness, make_job):
    from flows.nightly import run_nightly
    from pipeline.adapters.historian_writer import write_json_mcap
    from tests.conftest import plant_signals

    job = make_job(2, source="drop/*")
    storage = job.parent / "storage"
    garbage = job.parent / "drop" / "export_98.csv"
    garbage.write_text("this is not,a historian export\n@@@,###,!!!\nfoo,bar,baz\n")
    sig = plant_signals(seed=7, hours=1.0)
    mcap = job.parent / "drop" / "export_99.mcap"
    write_json_mcap(mcap, sig["time"], {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]},
                    samples_per_message=60)
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])  # an interrupted copy

    rows = {Path(r["path"]).name: r for r in run_nightly(job)}
    assert {n: r["status"] for n, r in rows.items()} == {
        "export_00.csv": "ok", "export_01.csv": "ok",
        "export_98.csv": "failed", "export_99.mcap": "failed"}
    assert "no time column" in rows["export_98.csv"]["error"]
    assert "the file is truncated or corrupt" in rows["export_99.mcap"]["error"]
    assert len(run_dirs(storage)) == 2 and tmp_dirs(storage) == []

    rows = {Path(r["path"]).name: r for r in run_nightly(job)}
    assert {n: r["status"] for n, r in rows.items()} == {
        "export_00.csv": "skipped", "export_01.csv": "skipped",
        "export_98.csv": "skipped_failed_before", "export_99.mcap": "skipped_failed_before"}
    assert "no time column" in rows["export_98.csv"]["error"]  # the reason is kept

    write_plant_csv(garbage, seed=8)  # the export is redone: new content, new identity
    rows = {Path(r["path"]).name: r for r in run_nightly(job)}
    assert rows["export_98.csv"]["status"] == "ok"
    assert rows["export_98.csv"]["run_id"] == nightly_run_id(file_sha256(garbage))
    assert rows["export_99.mcap"]["status"] == "skipped_failed_before"
    assert len(run_dirs(storage)) == 3


def test_nightly_killed_midway_and_restarted_processes_each_file_exactly_once(
        prefect_harness, make_job):
    """A real ``plantdyn nightly`` process is SIGKILLed while it processes the files
    (after the first run directory appears: the short export finishes first, the long
    ones are still being processed), then restarted with a 1 s claim lease so the dead
    process's claims expire."""
    job = make_job(4, hours=[1.0, 12.0, 12.0, 12.0])
    storage = job.parent / "storage"
    files = drop_files(job.parent)
    expected_ids = sorted(nightly_run_id(file_sha256(f)) for f in files)
    cmd = [sys.executable, "-m", "flows.cli", "nightly", str(job)]
    # the harness server: the subprocess does not start its own embedded one
    env = subprocess_env(PREFECT_API_URL=prefect_harness, **{LEASE_ENV: None})
    with open(job.parent / "first.log", "wb") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120
        while not run_dirs(storage) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    killed_at = time.monotonic()
    assert proc.returncode == -signal.SIGKILL, (job.parent / "first.log").read_text()
    store = ResultStore(storage)
    at_kill = store.processed(JOB)
    n_ok_at_kill = int((at_kill["status"] == "ok").sum())
    # the kill interrupted work: some file was done, some was not
    assert 1 <= len(run_dirs(storage)) and n_ok_at_kill < 4, at_kill

    time.sleep(max(0.0, 1.5 - (time.monotonic() - killed_at)))  # > the 1 s lease
    second = subprocess.run(cmd, env={**env, LEASE_ENV: "1"}, capture_output=True, text=True,
                            timeout=180)
    assert second.returncode == 0, second.stdout + second.stderr

    done = store.processed(JOB)
    assert done["status"].to_list() == ["ok"] * 4
    assert sorted(done["run_id"].to_list()) == expected_ids  # one run per file ...
    assert run_dirs(storage) == expected_ids  # ... and no other run directory
    runs = store.list_runs(JOB)
    assert sorted(runs["run_id"].to_list()) == expected_ids  # no duplicate run ids
    assert not any(".tmp-" in p for p in runs["path"].to_list())
    for rid in expected_ids:  # every run complete and intact
        assert store.read_run(JOB, rid, verify=True).step_responses.height > 0
    reindexed = store.reindex()  # the catalog agrees with the directories
    assert (reindexed.n_runs, reindexed.skipped) == (4, ())
    # files already done before the kill were not processed again
    ok_before = set(at_kill.filter(pl.col("status") == "ok")["sha256"].to_list())
    attempts = dict(zip(done["sha256"].to_list(), done["attempts"].to_list(), strict=True))
    assert all(attempts[s] == 1 for s in ok_before)
    # partial directories of the killed process stay hidden; the store can sweep them
    leftovers = tmp_dirs(storage)
    assert [p.name for p in store.clean_stale(0.0)] == leftovers
    assert tmp_dirs(storage) == [] and run_dirs(storage) == expected_ids


# ------------------------------------------------- process_file with stub runs
@dataclass(frozen=True)
class _Report:
    run_id: str


def _stub_job(tmp_path: Path, n_files: int = 1) -> tuple:
    for k in range(n_files):
        (tmp_path / "drop").mkdir(parents=True, exist_ok=True)
        (tmp_path / "drop" / f"f{k}.csv").write_text(f"content {k}\n")
    cfg = load_job(write_job(tmp_path))
    items = discover_files(cfg)
    assert len(items) == n_files
    return cfg, items


def _must_not_run(cfg, files, run_id):
    raise AssertionError(f"run() called for {files} although the file needs no processing")


def _write_run(cfg, run_id: str) -> _Report:
    store = ResultStore(cfg.storage_root)
    with store.new_run(cfg.job, run_id=run_id, config={"job": cfg.job}, inputs=[]) as run:
        run.write_text("report.md", "stub\n")
    return _Report(run_id)


@pytest.mark.parametrize("died", ["before_marking", "before_catalog_insert"])
def test_process_file_adopts_run_dir_of_a_process_that_died(tmp_path, monkeypatch, died):
    """A process claimed the file and renamed its run directory into place, then died —
    before marking the file ``ok``, or even before inserting the run into the catalog."""
    cfg, [(path, sha)] = _stub_job(tmp_path)
    dead = ResultStore(cfg.storage_root)
    assert dead.claim_file(cfg.job, sha, path)
    if died == "before_catalog_insert":
        with monkeypatch.context() as m:
            def killed(self, manifest):
                raise SystemExit("killed")
            m.setattr(ResultStore, "_insert_run", killed)
            with pytest.raises(SystemExit, match="killed"):
                _write_run(cfg, nightly_run_id(sha))
        assert dead.list_runs(cfg.job).height == 0
    else:
        _write_run(cfg, nightly_run_id(sha))
    assert run_dirs(cfg.storage_root) == [nightly_run_id(sha)]
    assert process_file(cfg, path, sha, run=_must_not_run)["status"] == "skipped"  # live lease
    time.sleep(0.05)
    row = process_file(cfg, path, sha, lease_s=0.01, run=_must_not_run)
    assert (row["status"], row["run_id"], row.get("adopted")) == ("ok", nightly_run_id(sha), True)
    assert dead.processed(cfg.job)["status"].to_list() == ["ok"]
    assert dead.list_runs(cfg.job)["run_id"].to_list() == [nightly_run_id(sha)]


def test_process_file_heartbeat_keeps_a_short_lease_alive(tmp_path):
    """A run lasting 3 leases is not taken over: its claim is refreshed every lease/3
    (0.2 s), so at each check the heartbeat is ~0.2 s old, well inside the 0.6 s lease."""
    cfg, [(path, sha)] = _stub_job(tmp_path)
    lease_s = 0.6
    seen = []

    def slow_run(c, files, run_id):
        for _ in range(3):
            time.sleep(lease_s)
            seen.append(process_file(c, path, sha, lease_s=lease_s, run=_must_not_run)["status"])
        return _write_run(c, run_id)

    row = process_file(cfg, path, sha, lease_s=lease_s, run=slow_run)
    assert row["status"] == "ok" and seen == ["skipped"] * 3


def test_process_file_takes_over_an_expired_claim_and_adopts_the_racing_result(tmp_path):
    """Two claimants of one file (the first stalled past its lease): the run directory is
    written once, and both end with the file ``ok`` (never ``failed`` on the collision)."""
    cfg, [(path, sha)] = _stub_job(tmp_path)
    stalled = threading.Event()
    release = threading.Event()
    rows = {}

    def first_run(c, files, run_id):
        stalled.set()
        release.wait(10)  # stalls (no heartbeat beyond lease: lease_s is huge, beat rare)
        return _write_run(c, run_id)

    t = threading.Thread(target=lambda: rows.setdefault(
        "first", process_file(cfg, path, sha, lease_s=3600, run=first_run)))
    t.start()
    assert stalled.wait(10)

    def second_run(c, files, run_id):
        report = _write_run(c, run_id)
        release.set()  # the first one now finishes and collides with this run dir
        return report

    time.sleep(0.05)
    rows["second"] = process_file(cfg, path, sha, lease_s=0.01, run=second_run)
    t.join(10)
    assert rows["second"]["status"] == "ok"
    assert (rows["first"]["status"], rows["first"].get("adopted")) == ("ok", True)
    assert run_dirs(cfg.storage_root) == [nightly_run_id(sha)]
    assert ResultStore(cfg.storage_root).processed(cfg.job)["status"].to_list() == ["ok"]


def test_process_file_user_error_is_final_other_errors_are_retried(tmp_path):
    cfg, [(p0, s0), (p1, s1)] = _stub_job(tmp_path, 2)

    def bad_data(c, files, run_id):
        raise DataQualityError(f"{files[0]}: every sample of tag U.PV is bad")

    def crash(c, files, run_id):
        raise RuntimeError("disk hiccup")

    assert process_file(cfg, p0, s0, run=bad_data)["status"] == "failed"
    assert process_file(cfg, p1, s1, run=crash)["status"] == "error"
    again = process_file(cfg, p0, s0, run=_must_not_run)
    assert again["status"] == "skipped_failed_before"
    assert "every sample of tag U.PV is bad" in again["error"]
    assert process_file(cfg, p1, s1, run=lambda c, f, r: _write_run(c, r))["status"] == "ok"


def test_claim_lease_from_argument_or_environment(monkeypatch):
    monkeypatch.delenv(LEASE_ENV, raising=False)
    assert claim_lease_s() is None
    assert claim_lease_s(5) == 5.0
    monkeypatch.setenv(LEASE_ENV, "2.5")
    assert claim_lease_s() == 2.5 and claim_lease_s(7) == 7.0
    monkeypatch.setenv(LEASE_ENV, "an hour")
    with pytest.raises(ConfigError, match=r"PLANTDYN_CLAIM_LEASE_S='an hour' is not a number"):
        claim_lease_s()
    monkeypatch.setenv(LEASE_ENV, "0")
    with pytest.raises(ConfigError, match=r"claim lease 0.0 s must be > 0"):
        claim_lease_s()


def test_discover_files_empty_folder_is_normal_but_bad_paths_raise(tmp_path, monkeypatch):
    monkeypatch.delenv("PLANTDYN_ALLOWED_ROOTS", raising=False)
    cfg = load_job(write_job(tmp_path / "a" / "b"))
    assert discover_files(cfg) == []  # nothing in the drop folder tonight
    outside = tmp_path / "elsewhere" / "x.csv"
    outside.parent.mkdir()
    outside.write_text("x\n")
    cfg = load_job(write_job(tmp_path / "a" / "b", source="../../elsewhere/*.csv"))
    with pytest.raises(ConfigError, match=r"source.path: .* is outside the allowed roots"):
        discover_files(cfg)


# ------------------------------------------------------------- CLI bad input
@dataclass(frozen=True)
class BadJob:
    """A job that must fail with exit code 2 and a message matching ``stderr``.

    ``make(folder) -> job path`` writes the job (and any data) under ``folder``, with
    ``storage: storage`` (beside the job file) so the test can check nothing was left.
    """

    id: str
    make: Callable[[Path], Path]
    stderr: str


def _good(folder: Path, **keys) -> Path:
    write_plant_csv(folder / "drop" / "export.csv", seed=3, hours=1.0)
    return write_job(folder, **keys)


def _malformed_yaml(folder: Path) -> Path:
    path = _good(folder)
    path.write_text(path.read_text() + "extra: [unclosed\n")
    return path


def _outside_roots(folder: Path) -> Path:
    write_plant_csv(folder / "elsewhere" / "export.csv", seed=3, hours=1.0)
    return write_job(folder / "jobs" / "site", source="../../elsewhere/*.csv")


def _with_raw(folder: Path, edit: Callable[[dict], None]) -> Path:
    path = _good(folder)
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data))
    return path


BAD_JOBS = [
    BadJob("malformed-yaml", _malformed_yaml,
           r"job\.yaml: malformed YAML at line \d+, column \d+: .*; fix the syntax"),
    BadJob("unknown-key", lambda f: _with_raw(f, lambda d: d.update(colour="red")),
           r"invalid job configuration in .*job\.yaml: colour: unknown key"),
    BadJob("missing-tag",
           lambda f: _with_raw(f, lambda d: d["signals"]["outputs"]["y"].update(tag="NOPE.PV")),
           r"tag\(s\) \['NOPE\.PV'\] requested but not in the recording; it has 2 tags: "
           r"\['U\.PV', 'Y\.PV'\]"),
    BadJob("outside-allowed-roots", _outside_roots,
           r"source\.path: '.*elsewhere/export\.csv' is outside the allowed roots"),
    BadJob("no-file-matches", lambda f: _with_raw(
        f, lambda d: d["source"].update(path="drop/*.mcap")),
        r"source\.path: no file matches 'drop/\*\.mcap'"),
]


@pytest.mark.parametrize("case", BAD_JOBS, ids=[c.id for c in BAD_JOBS])
def test_cli_run_bad_job_exits_2_with_message_and_writes_nothing(case, tmp_path,
                                                                 prefect_harness):
    job = case.make(tmp_path)
    env = subprocess_env(PREFECT_API_URL=prefect_harness, PLANTDYN_ALLOWED_ROOTS=None)
    res = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(job)], env=env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("plantdyn: error: ") == 1, res.stderr
    assert "Traceback" not in res.stderr, res.stderr
    assert re.search(case.stderr, res.stderr), res.stderr
    assert res.stdout == ""  # no run directory printed
    storage = job.parent / "storage"
    left = [p.relative_to(storage).as_posix() for p in storage.rglob("*")
            if p.is_dir()] if storage.exists() else []
    assert left == [], left  # no run directory, no .tmp-* directory

