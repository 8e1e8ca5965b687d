"""Bad inputs through the CLI (issue 3, must-show 4): exit code 2, one specific message,
nothing written under storage.  The first cases live in tests/flows/test_flows.py (BAD_JOBS);
these complete the list to more than 15."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import INPUT_TAG, OUTPUT_TAG, subprocess_env, write_job
from tests.flows.test_flows import BAD_JOBS, BadJob, _good, _with_raw


def _rewrite_export(folder: Path, edit) -> Path:
    job = _good(folder)
    csv = folder / "drop" / "export.csv"
    csv.write_text(edit(csv.read_text()))
    return job


def _all_bad_output(text: str) -> str:
    out = []
    for line in text.splitlines():
        parts = line.split(",")
        if parts[0] == OUTPUT_TAG:
            parts[2], parts[3] = "Bad Input", "Bad"
        out.append(",".join(parts))
    return "\n".join(out) + "\n"


def _constant_input(text: str) -> str:
    out = []
    for line in text.splitlines():
        parts = line.split(",")
        if parts[0] == INPUT_TAG:
            parts[2] = "42.0"
        out.append(",".join(parts))
    return "\n".join(out) + "\n"


def _duplicate_times(text: str) -> str:
    lines = text.splitlines()
    return "\n".join(lines[:50] + [lines[40].replace(lines[40].split(",")[2], "9.9")]
                     + lines[50:]) + "\n"


def _garbage_time(text: str) -> str:
    lines = text.splitlines()
    parts = lines[7].split(",")
    parts[1] = "yesterday at noon"
    lines[7] = ",".join(parts)
    return "\n".join(lines) + "\n"


def _cp1252(folder: Path) -> Path:
    job = _good(folder)
    csv = folder / "drop" / "export.csv"
    text = csv.read_text().replace("tag,timestamp", "tag°C,timestamp", 1)
    csv.write_bytes(text.encode("cp1252"))
    return job


def _truncated_mcap(folder: Path) -> Path:
    from pipeline.adapters.historian_writer import write_json_mcap
    from tests.conftest import plant_signals

    sig = plant_signals(seed=3, hours=1.0)
    path = folder / "drop" / "export.mcap"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_mcap(path, sig["time"], {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return write_job(folder, source="drop/*.mcap")


def _spring_gap_time(folder: Path) -> Path:
    path = folder / "drop" / "export.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = ["tag,timestamp,value,status"]
    for tag in (INPUT_TAG, OUTPUT_TAG):
        for minute in range(0, 180, 5):  # 01:00..03:55 local on the spring-forward night
            rows.append(f"{tag},2024-03-31 {1 + minute // 60:02d}:{minute % 60:02d}:00,"
                        f"{minute * 0.1},Good")
    path.write_text("\n".join(rows) + "\n")
    return write_job(folder, timezone="Europe/Berlin")


MORE_BAD_JOBS = [
    BadJob("all-bad-signal", lambda f: _rewrite_export(f, _all_bad_output),
           r"signal 'y' \(tag Y\.PV\): every sample is bad or missing"),
    BadJob("constant-input", lambda f: _rewrite_export(f, _constant_input),
           r"signal 'u' is constant"),
    BadJob("too-short-for-n_p", lambda f: _with_raw(f, lambda d: d.update(search={"n_p": 3000})),
           r"n_p=3000 .*supply more data|cannot hold two disjoint windows"),
    BadJob("duplicate-times-strict", lambda f: _edit(
        _rewrite_export(f, _duplicate_times), lambda d: d["source"].update(time_order="strict")),
        r"non-monotonic or duplicate times: tag U\.PV: 1 duplicate"),
    BadJob("unparseable-timestamp", lambda f: _rewrite_export(f, _garbage_time),
           r"yesterday at noon"),
    BadJob("wrong-encoding", _cp1252, r"not (valid )?UTF-8|encoding"),
    BadJob("truncated-mcap", _truncated_mcap, r"export\.mcap.*offset \d+"),
    BadJob("time-in-skipped-dst-hour", _spring_gap_time, r"02:\d\d:00.*(skipped|does not exist|DST)"),
    BadJob("unknown-timezone", lambda f: _with_raw(f, lambda d: d["source"].update(timezone="Mars/Olympus")),
           r"source\.timezone: unknown time zone 'Mars/Olympus'"),
    BadJob("bad-n_p", lambda f: _with_raw(f, lambda d: d.update(search={"n_p": 0})),
           r"search\.n_p: Input should be greater than or equal to 1 \(got 0\)"),
    BadJob("signal-both-input-and-output", lambda f: _with_raw(
        f, lambda d: d["signals"]["outputs"].update(u={"tag": INPUT_TAG})),
        r"signal names \['u'\] appear as both input and output"),
    BadJob("unknown-conditioning", lambda f: _with_raw(
        f, lambda d: d.update(conditioning={"method": "wavelet"})),
        r"conditioning\.method: Input should be 'mean', 'detrend', 'difference' or 'highpass'"),
    BadJob("dt-not-multiple-of-grid", lambda f: _with_raw(f, lambda d: d.update(sampling={"dt_s": 2.5})),
           r"sampling\.dt_s=2\.5 is not an integer multiple of the grid period"),
    BadJob("wrong-suffix", lambda f: _edit(_xlsx(f), lambda d: d["source"].update(path="drop/*.xlsx")),
           r"'export\.xlsx' has suffix '\.xlsx'; allowed: \.csv, \.txt, \.mcap"),
    BadJob("integrating-not-bool", lambda f: _with_raw(
        f, lambda d: d["signals"]["outputs"]["y"].update(integrating="maybe")),
        r"signals\.outputs\.y\.integrating: Input should be a valid boolean"),
    BadJob("empty-file", lambda f: _rewrite_export(f, lambda t: ""), r"export\.csv.*empty"),
    BadJob("unknown-noise-model", lambda f: _with_raw(
        f, lambda d: d.update(estimation={"noise": "pink"})),
        r"estimation\.noise: must be 'auto', 'white' or an AR order 0\.\.40 \(got 'pink'\)"),
    BadJob("n_k-of-unknown-output", lambda f: _with_raw(
        f, lambda d: d.update(estimation={"n_k": {"level": {"u": 1}}})),
        r"estimation\.n_k: 'level' is not an output \(signals\.outputs: \['y'\]\)"),
    BadJob("n_k-not-below-n_p", lambda f: _with_raw(
        f, lambda d: d.update(estimation={"n_k": 5}, search={"n_p": 5})),
        r"estimation\.n_k \(5\) must be smaller than search\.n_p \(5\)"),
    BadJob("instrument-named-like-an-input", lambda f: _with_raw(
        f, lambda d: d["signals"].update(instruments={"u": {"tag": INPUT_TAG}})),
        r"signal names \['u'\] appear as instruments and as inputs or outputs"),
]


def _edit(job: Path, edit) -> Path:
    """Edit the job YAML in place (the data stays as written)."""
    data = yaml.safe_load(job.read_text())
    edit(data)
    job.write_text(yaml.safe_dump(data, sort_keys=False))
    return job


def _xlsx(folder: Path) -> Path:
    job = _good(folder)
    (folder / "drop" / "export.xlsx").write_bytes(b"PK\x03\x04 not really excel")
    return job


def test_more_than_fifteen_distinct_bad_inputs():
    ids = [c.id for c in BAD_JOBS + MORE_BAD_JOBS]
    assert len(set(ids)) == len(ids) >= 15


@pytest.mark.parametrize("case", MORE_BAD_JOBS, ids=[c.id for c in MORE_BAD_JOBS])
def test_cli_bad_input_exits_2_with_message_and_writes_nothing(case, tmp_path, prefect_harness):
    job = case.make(tmp_path)
    env = subprocess_env(PREFECT_API_URL=prefect_harness, PLANTDYN_ALLOWED_ROOTS=None)
    res = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(job)], env=env,
                         capture_output=True, text=True, timeout=180)
    assert res.returncode == 2, res.stderr[-3000:]
    assert res.stderr.count("plantdyn: error: ") == 1, res.stderr[-3000:]
    assert "Traceback" not in res.stderr, res.stderr[-3000:]
    assert re.search(case.stderr, res.stderr), res.stderr[-3000:]
    assert res.stdout == ""
    storage = job.parent / "storage"
    left = [p.relative_to(storage).as_posix() for p in storage.rglob("*")
            if p.is_dir()] if storage.exists() else []
    assert left == [], left
