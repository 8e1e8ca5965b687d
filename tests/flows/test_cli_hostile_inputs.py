"""Hostile inputs through the CLI (issue 10): each ends with exit 2 and one message naming
the file, key or line and the fix — or, for spikes, a run that masks and reports them —
never a traceback, a hang, a blow-up or a half-written result.

The cases run ``plantdyn run --no-prefect`` in-process (``flows.cli.main``, the same
entry point the console script calls) so the suite stays fast; ``tests/flows/test_bad_inputs.py``
drives the default Prefect path in subprocesses.
"""

from __future__ import annotations

import contextlib
import io
import json
import resource
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest


from flows.cli import main
from tests.conftest import INPUT_TAG, OUTPUT_TAG, plant_signals, write_job, write_plant_csv


def cli(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(argv))
    return rc, out.getvalue(), err.getvalue()


def assert_clean_exit_2(rc: int, err: str, pattern: str, folder: Path) -> None:
    import re

    assert rc == 2, err[-2000:]
    assert "Traceback" not in err
    assert err.count("plantdyn: error: ") == 1, err[-2000:]
    assert re.search(pattern, err), err[-2000:]
    storage = folder / "storage"
    left = [p for p in storage.rglob("*")] if storage.exists() else []
    assert not [p for p in left if p.is_dir() and p.name != "catalog.sqlite"
                and p.parent != storage], left


# ------------------------------------------------------------------------- YAML
def _job_text(folder: Path) -> str:
    write_plant_csv(folder / "drop" / "export.csv", seed=3, hours=1.0)
    return write_job(folder).read_text()


def test_nested_alias_bomb_is_refused_at_once_with_little_memory(tmp_path):
    text = _job_text(tmp_path)
    bomb = ['  a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    bomb += [f"  a{k}: &a{k} [" + ",".join([f"*a{k - 1}"] * 9) + "]" for k in range(1, 9)]
    (tmp_path / "job.yaml").write_text(text + "model:\n" + "\n".join(bomb) + "\n")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    rc, _, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert time.perf_counter() - t0 < 5
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 1024
    assert_clean_exit_2(rc, err, r"job\.yaml: the YAML at line \d+ expands to more than "
                                 r"100,000 values", tmp_path)


@pytest.mark.parametrize("text,pattern", [
    ("job: a\njob: b\n", r"duplicate key 'job' at line 2 \(first at line 1\)"),
    ("job: x\nmodel: " + "[" * 5000 + "]" * 5000 + "\n", r"nesting too deep"),
    ("job: x\nmodel: " + "[" * 60 + "]" * 60 + "\n", r"nesting deeper than 40 levels at line 2"),
    ("job: x\x0b\n", r"malformed YAML.*special characters"),
    ("!!python/object/apply:os.system ['true']\n", r"malformed YAML at line 1"),
])
def test_yaml_structure_errors_name_the_line(tmp_path, text, pattern):
    (tmp_path / "job.yaml").write_text(text)
    rc, _, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert_clean_exit_2(rc, err, pattern, tmp_path)


# ------------------------------------------------------------------- timestamps
def test_stray_timestamps_are_left_out_and_reported(tmp_path):
    """One row in year 9999 and one in 1970: the grid follows the samples (it asked for
    1.8 TiB before); the run reports them."""
    path = write_plant_csv(tmp_path / "drop" / "export.csv", seed=4, hours=2.0)
    lines = path.read_text().splitlines()
    lines[10] = lines[10].replace("2026-03-02", "9999-03-02")
    lines[-10] = lines[-10].replace("2026-03-02", "1970-03-02")
    path.write_text("\n".join(lines) + "\n")
    write_job(tmp_path)
    rc, out, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert rc == 0, err[-2000:]
    run_dir = Path(out.strip().splitlines()[-1])
    checks = json.loads((run_dir / "checks.json").read_text())
    stray = checks["data_quality"]["ingest"]["grid"]["stray_samples"]
    assert {d["first"][:4] for d in stray} == {"9999", "1970"}
    assert all(d["samples"] == 1 for d in stray)
    assert checks["data_quality"]["grid_dt_s"] == 1.0
    assert checks["data_quality"]["samples_at_dt"] < 2 * 7200
    assert "Stray samples left out" in (run_dir / "report.md").read_text()


def test_a_second_export_a_month_later_costs_its_samples_not_the_month(tmp_path):
    """Two 1-hour exports 30 days apart: two islands of grid, not 30 days of it."""
    from pipeline.adapters.historian_writer import write_long_csv

    (tmp_path / "drop").mkdir()
    for k, day in enumerate((2, 32)):
        sig = plant_signals(seed=5 + k, hours=1.0)
        t = sig["time"] + np.timedelta64(day - 2, "D")
        write_long_csv(tmp_path / "drop" / f"e{k}.csv", t, {INPUT_TAG: sig["u"],
                                                           OUTPUT_TAG: sig["y"]})
    write_job(tmp_path)
    rc, out, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert rc == 0, err[-2000:]
    checks = json.loads((Path(out.strip().splitlines()[-1]) / "checks.json").read_text())
    islands = checks["data_quality"]["ingest"]["grid"]["islands"]
    assert len(islands) == 2 and sum(i["points"] for i in islands) <= 2 * 3600 + 10
    assert checks["data_quality"]["samples_at_dt"] <= 2 * 3600 + 10


def test_a_grid_beyond_the_limit_says_what_to_change(tmp_path, monkeypatch):
    import pipeline.adapters.grid as grid

    monkeypatch.setattr(grid, "MAX_GRID_VALUES", 1000)
    monkeypatch.setattr(grid.to_grid, "__kwdefaults__",
                        {**grid.to_grid.__kwdefaults__, "max_values": 1000})
    write_plant_csv(tmp_path / "drop" / "export.csv", seed=6, hours=1.0)
    write_job(tmp_path)
    rc, _, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert_clean_exit_2(rc, err, r"the grid would hold 3,600 points x 2 signals = 7,200 values "
                                 r"\(limit 1,000.*set source\.grid_dt_s larger", tmp_path)


# ------------------------------------------------------------------- CSV shapes
def test_decimal_commas_in_a_comma_separated_export_are_an_error_not_shifted_columns(tmp_path):
    sig = plant_signals(seed=7, hours=1.0)
    rows = ["Time,U.PV,Y.PV"]
    for t, u, y in zip(sig["time"].astype("datetime64[s]").astype(str), sig["u"], sig["y"]):
        rows.append(f"{t.replace('T', ' ')},{u:.3f},{y:.3f}".replace(".", ",")
                    .replace(",", ".", 0))
    # the timestamp keeps its own format; only the values carry decimal commas
    rows = [rows[0]] + [r.split(",", 1)[0] + "," + r.split(",", 1)[1] for r in rows[1:]]
    (tmp_path / "drop").mkdir()
    (tmp_path / "drop" / "export.csv").write_text("\n".join(rows) + "\n")
    write_job(tmp_path)
    rc, _, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert_clean_exit_2(rc, err, r"export\.csv, line 2: 5 fields but the header has 3 — the "
                                 r"columns after it would shift; likely cause: values split at "
                                 r"a decimal comma", tmp_path)


def test_spikes_are_masked_named_in_the_report_and_leave_the_estimate_unchanged(tmp_path):
    """Five samples x1e6 in the output (0.2 % of them): before, the final step was 7297
    instead of 1.98 and both windows passed.  Now they are masked and reported, and the
    step response is within 3 sigma of the spike-free run's."""
    clean = tmp_path / "clean"
    spiky = tmp_path / "spiky"
    write_plant_csv(clean / "drop" / "export.csv", seed=8, hours=1.0)
    write_job(clean)
    path = write_plant_csv(spiky / "drop" / "export.csv", seed=8, hours=1.0)
    lines = path.read_text().splitlines()
    out_rows = [k for k, ln in enumerate(lines) if ln.startswith(OUTPUT_TAG + ",")]
    rng = np.random.default_rng(9)
    for k in rng.choice(out_rows[100:-100], 5, replace=False):
        f = lines[k].split(",")
        f[2] = repr(float(f[2]) * 1e6)
        lines[k] = ",".join(f)
    path.write_text("\n".join(lines) + "\n")
    write_job(spiky)
    results = {}
    for name, folder in (("clean", clean), ("spiky", spiky)):
        rc, out, err = cli("run", "--no-prefect", str(folder / "job.yaml"))
        assert rc == 0, err[-2000:]
        results[name] = Path(out.strip().splitlines()[-1])
    report = (results["spiky"] / "report.md").read_text()
    assert "Spikes masked in y: 5 sample(s)" in report
    q = json.loads((results["spiky"] / "checks.json").read_text())["data_quality"]
    assert q["signals"]["y"]["masked_by_reason"]["spike"] == 5
    a = pl.read_parquet(results["clean"] / "step_responses.parquet").filter(pl.col("window") == "all")
    b = pl.read_parquet(results["spiky"] / "step_responses.parquet").filter(pl.col("window") == "all")
    n = min(a.height, b.height)
    da, db = a.sort("lag").head(n), b.sort("lag").head(n)
    diff = np.abs(da["step"].to_numpy() - db["step"].to_numpy())
    sd = np.hypot(da["step_std"].to_numpy(), db["step_std"].to_numpy())
    assert np.all(diff <= 3 * sd)
    assert abs(db["step"][-1] - 2.0) < 0.1  # the plant's gain, not thousands


def test_spikes_off_keeps_every_sample(tmp_path):
    path = write_plant_csv(tmp_path / "drop" / "export.csv", seed=10, hours=1.0)
    lines = path.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith(OUTPUT_TAG + ",")) + 500
    f = lines[k].split(",")
    f[2] = repr(float(f[2]) * 1e6)
    lines[k] = ",".join(f)
    path.write_text("\n".join(lines) + "\n")
    job = write_job(tmp_path, quality={"spikes": "off"})
    rc, out, err = cli("run", "--no-prefect", str(job))
    assert rc == 0, err
    q = json.loads((Path(out.strip().splitlines()[-1]) / "checks.json").read_text())
    assert "spike" not in q["data_quality"]["signals"]["y"]["masked_by_reason"]



# ------------------------------------------------------------------------ MCAP
def test_mcap_log_time_beyond_int64_names_topic_and_message(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "drop" / "export.mcap"
    path.parent.mkdir(parents=True)
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("s", "jsonschema", b"{}")
        chans = {t: w.register_channel("/" + t, "json", sid) for t in (INPUT_TAG, OUTPUT_TAG)}
        for k in range(400):
            for t, c in chans.items():
                lt = 2**64 - 1 if (t == OUTPUT_TAG and k == 7) else (1_700_000_000 + k) * 10**9
                w.add_message(c, log_time=lt, publish_time=lt,
                              data=json.dumps({"value": float(k % 7)}).encode())
        w.finish()
    write_job(tmp_path, source="drop/*.mcap")
    rc, _, err = cli("run", "--no-prefect", str(tmp_path / "job.yaml"))
    assert_clean_exit_2(rc, err, r"topic '/Y\.PV', message 7: log time 18446744073709551615 ns "
                                 r"is beyond year 2262", tmp_path)
