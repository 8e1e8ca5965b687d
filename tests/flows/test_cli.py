"""The plantdyn CLI as a user runs it: demo, runs (catalog and trends)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import polars as pl

ROOT = Path(__file__).resolve().parents[2]


def cli(*args: str, cwd: Path = ROOT, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flows.cli", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def test_demo_writes_export_runs_job_and_says_where_results_are(demo_cli_run):
    demo, r = demo_cli_run.dir, demo_cli_run  # `plantdyn demo --dir D --no-prefect`, once
    assert r.returncode == 0, r.stderr
    export = demo / "exports" / "boiler_export.csv"
    head = export.read_text().splitlines()[:2]
    assert head[0] == "tag,timestamp,value,status"
    lines = dict(line.split(":", 1) for line in r.stdout.splitlines() if ":" in line)
    run_dir = Path(lines["results"].strip())
    assert run_dir.is_dir()
    for f in ("manifest.json", "step_responses.parquet", "checks.json", "report.md",
              "recording.rrd", "signals.parquet", "residuals.parquet"):
        assert (run_dir / f).is_file(), f
    assert "rerun" in lines["view it"]
    # progress was shown on stderr, stage by stage
    for stage in ("ingest", "prepare", "search", "summarise", "store"):
        assert f"] {stage}:" in r.stderr
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["job"] == "demo_boiler"
    assert manifest["inputs"][0]["path"].endswith("boiler_export.csv")
    # the demo plant is known (configs/demo_boiler.yaml): the pressure follows its
    # setpoint (gain 1) and the fuel follows the load one to one (feedforward + integral
    # action: model units, the fuel block's 65 x demand 1/65 per kg/s) -- read off the
    # stored step responses, each within 3 sigma of the physics
    sr = pl.read_parquet(run_dir / "step_responses.parquet").filter(pl.col("window") == "all")
    for out, inp in (("turbine_pressure", "pressure_sp"), ("fuel_flow", "steam_flow")):
        last = sr.filter((pl.col("output") == out) & (pl.col("input") == inp)).sort("lag")[-1]
        assert abs(last["step"][0] - 1.0) < max(3 * last["step_std"][0], 1e-3), (out, inp)
    checks = json.loads((run_dir / "checks.json").read_text())
    masked = {n: q["masked"] for n, q in checks["data_quality"]["signals"].items()}
    # the digital states injected into FI-101, PI-102 and FI-103 are masked
    assert all(masked[n] > 0 for n in ("steam_flow", "turbine_pressure", "fuel_flow"))
    # runs: the catalog lists it and trends its metrics
    r2 = cli("runs", str(demo / "demo_boiler.yaml"))
    assert r2.returncode == 0, r2.stderr
    assert run_dir.name in r2.stdout and "gain" in r2.stdout


def test_runs_of_unknown_job_says_so(tmp_path):
    from pipeline.adapters.store import ResultStore

    ResultStore(tmp_path / "storage")  # a results root with a catalog, no runs
    r = cli("runs", "nojob", "--storage", str(tmp_path / "storage"))
    assert r.returncode == 0 and "no runs of job 'nojob'" in r.stdout


def test_runs_with_a_mistyped_storage_is_an_error_and_creates_nothing(tmp_path):
    r = cli("runs", "nojob", "--storage", str(tmp_path / "storgae"))
    assert r.returncode == 2 and "no catalog (catalog.sqlite) — not a plantdyn results " \
        "folder, or a typo" in r.stderr
    assert not (tmp_path / "storgae").exists()


def test_bad_command_line_is_exit_2():
    r = cli("run")
    assert r.returncode == 2 and "the following arguments are required: job" in r.stderr
