"""Integrating outputs end to end (issue 9, build 1): a drum-level export through
``plantdyn run`` (default Prefect path), the nightly flow and the Rerun sink, with the rate
and the wrong-way peak checked against the plant's known answers.

The plant (tests/plants.py, python-control ZOH): steam flow -> -0.01/s + 0.59/(10 s + 1)
(rate -0.01 cm/(kg/s)/s, wrong-way peak 0.312 cm/(kg/s)), feedwater ->
0.008/(s (3 s + 1)) with 2 s dead time, 1 cm of white level-sensor noise; 6 hours at 1 s,
written as an exception-reported PI-style CSV.  Tolerances are the must-show's (rates 3 %,
peak 20 %); the estimates' own σ are ~0.5 % and ~8 % of them.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest
import yaml

from pipeline.adapters.store import ResultStore
from tests.conftest import subprocess_env
from tests.plants import DRUM_RATES, DRUM_TAGS, drum_truth, write_drum_export

PEAK = float(drum_truth(80)[0].max())


def _job(folder: Path, *, rerun: bool) -> Path:
    job = {
        "job": "drum",
        "source": {"path": "drop/*.csv", "timezone": "UTC"},
        "signals": {
            "inputs": {"steam_flow": {"tag": DRUM_TAGS["steam_flow"], "unit": "kg/s"},
                       "feedwater": {"tag": DRUM_TAGS["feedwater"], "unit": "kg/s"}},
            "outputs": {"drum_level": {"tag": DRUM_TAGS["drum_level"], "unit": "cm",
                                       "integrating": True}},
        },
        "storage": "storage",
        "sampling": {"dt_s": 1.0},
        "rerun": {"enabled": rerun},
    }
    path = folder / "drum.yaml"
    path.write_text(yaml.safe_dump(job, sort_keys=False))
    return path


def _check_run(run_dir: Path) -> dict:
    checks = json.loads((run_dir / "checks.json").read_text())
    pairs = {p["input"]: p for p in checks["pairs"]}
    for j, inp in enumerate(("steam_flow", "feedwater")):
        p = pairs[inp]
        assert p["integrating"] and p["gain"] is None
        assert abs(p["rate"] / DRUM_RATES[j] - 1) <= 0.03, (inp, p["rate"])
        assert p["characteristics"]["rate"] == pytest.approx(p["rate"])
    peak = pairs["steam_flow"]["characteristics"]["inverse_peak"]
    assert abs(peak / PEAK - 1) <= 0.20, peak
    assert checks["noise_model"]["drum_level"]["form"] == "level"
    steps = pl.read_parquet(run_dir / "step_responses.parquet")
    assert set(steps["window"]) >= {"all", "w0", "w1"}
    return checks


@pytest.fixture(scope="module")
def drum_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("drum")
    write_drum_export(folder / "drop" / "drum_2026-05-04.csv", hours=6.0, seed=5_100_000)
    return folder


def test_plantdyn_run_stores_rates_peak_and_a_recording(drum_folder, prefect_harness):
    job = _job(drum_folder, rerun=True)
    env = subprocess_env(PREFECT_API_URL=prefect_harness)
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(job)],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    run_dir = Path(r.stdout.strip().splitlines()[-1])  # stdout's last line: the run dir
    assert run_dir.parent == drum_folder / "storage" / "drum"
    _check_run(run_dir)
    # metrics in the catalog, each once (the store refused a second 'rate' before)
    store = ResultStore(drum_folder / "storage")
    trend = store.trend("drum")
    rates = trend.filter(pl.col("metric") == "rate")
    assert rates.height == 2
    # the recording has the integrating pair's step response and band
    from tests.jobs.test_recording import decoded

    data = decoded(run_dir / "recording.rrd")
    assert any(k.startswith("/step/drum_level/steam_flow/") for k in data)
    report = (run_dir / "report.md").read_text()
    assert "rate K" in report and "drum_level" in report
    r2 = subprocess.run([sys.executable, "-m", "flows.cli", "runs", str(job)],
                        capture_output=True, text=True, env=env, timeout=120)
    assert r2.returncode == 0 and "rate" in r2.stdout


def test_nightly_flow_processes_the_integrating_export(tmp_path, prefect_harness):
    from flows.nightly import run_nightly

    write_drum_export(tmp_path / "drop" / "drum_a.csv", hours=6.0, seed=5_200_000)
    job = _job(tmp_path, rerun=False)
    rows = run_nightly(job)
    assert [r["status"] for r in rows] == ["ok"], rows
    run_dir = tmp_path / "storage" / "drum" / rows[0]["run_id"]
    _check_run(run_dir)
    done = ResultStore(tmp_path / "storage").processed("drum")
    assert done["status"].to_list() == ["ok"]
