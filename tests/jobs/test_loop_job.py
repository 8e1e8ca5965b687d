"""A controlled loop through the pipeline (issue 9, must-show 3): a historian export of
SP, OP and PV run by ``plantdyn run`` with and without ``signals.instruments``.

The loop (tests/plants.py ``historian_loop_signals``): plant ``2 e^{-3 s}/(20 s + 1)``
integrated at 50 ms, a DCS PI controller scanned every 0.5 s acting on the previous
scan's PV, quantised output, a slow unmeasured disturbance and sensor noise on the PV,
operator setpoint moves; 12 hours exported as an exception-reported PI-style CSV.

The job fixes ``sampling.dt_s: 2`` as an engineer would for a fast flow loop: on a PV
dominated by setpoint steps the α_T criterion picks T = 25–90 s (a step signal's hold
error is small at any T), far beyond the loop's 20 s time constant, and a known delay
of one such sample would remove most of the response.

Known answers: gain 2 (PV % per OP %); no response in the first 3 s (lags 1 and 2 at
T = 2 s).  Tolerances are the must-show's: 5 % with the setpoint as instrument, 10 %
without; the estimates' own σ are ~2 % (measured over six seeds: IV within 3.5 %, direct
within 4.2 %).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import subprocess_env
from tests.plants import LOOP_GAIN, LOOP_TAGS, write_loop_export


@pytest.fixture(scope="module")
def loop_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("loop")
    write_loop_export(folder / "drop" / "fic301.csv", hours=12.0, seed=6_100_002)
    return folder


def _run(folder: Path, harness: str, *, instruments: bool) -> tuple[Path, dict, str]:
    name = "fic301_iv" if instruments else "fic301"
    job = {
        "job": name,
        "source": {"path": "drop/*.csv", "timezone": "UTC"},
        "signals": {"inputs": {"valve": {"tag": LOOP_TAGS["OP"], "unit": "%"}},
                    "outputs": {"flow": {"tag": LOOP_TAGS["PV"], "unit": "%"}},
                    **({"instruments": {"setpoint": {"tag": LOOP_TAGS["SP"]}}}
                       if instruments else {})},
        "storage": "storage",
        "sampling": {"dt_s": 2.0},
        "rerun": {"enabled": False},
    }
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(job, sort_keys=False))
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(path)],
                       capture_output=True, text=True, timeout=600,
                       env=subprocess_env(PREFECT_API_URL=harness))
    assert r.returncode == 0, r.stderr[-3000:]
    run_dir = Path(r.stdout.strip().splitlines()[-1])
    checks = json.loads((run_dir / "checks.json").read_text())
    return run_dir, checks, (run_dir / "report.md").read_text()


def test_without_instruments_feedback_is_found_and_the_same_sample_term_fixed(
        loop_folder, prefect_harness):
    run_dir, checks, report = _run(loop_folder, prefect_harness, instruments=False)
    pair = checks["pairs"][0]
    assert pair["feedback"]["detected"] and pair["feedback"]["p_value"] < 0.01
    assert pair["n_k"] == 1 and checks["search"]["n_k"]["flow<-valve"] == 1
    assert abs(pair["gain"] / LOOP_GAIN - 1) <= 0.10, pair["gain"]
    assert pair["method"] == "prediction_error"
    codes = [w["code"] for w in pair["warnings"]]
    assert "feedback" in codes
    assert "is moved by a controller that sees flow (FIC-301.PV)" in report
    assert "signals.instruments" in report  # what to change in the job YAML


def test_with_the_setpoint_as_instrument_the_gain_is_within_5_percent(
        loop_folder, prefect_harness):
    run_dir, checks, report = _run(loop_folder, prefect_harness, instruments=True)
    pair = checks["pairs"][0]
    assert checks["estimation"]["method"] == "instrumental_variables"
    assert checks["estimation"]["instruments"] == {"setpoint": LOOP_TAGS["SP"]}
    assert checks["estimation"]["first_stage"]["valve"]["F"] > 10
    assert pair["feedback"]["detected"] and pair["n_k"] == 0
    assert abs(pair["gain"] / LOOP_GAIN - 1) <= 0.05, pair["gain"]
    # the loop's dead time: nothing in the first 3 s, no wrong-way start
    import polars as pl

    steps = pl.read_parquet(run_dir / "step_responses.parquet").filter(
        pl.col("window") == "all").sort("lag")
    for lag in (1, 2):
        row = steps.filter(pl.col("lag") == lag)
        assert abs(row["step"][0]) <= 3 * row["step_std"][0] + 0.02 * LOOP_GAIN
    assert "instrumental variables (setpoint)" in report
    assert "consistent under feedback" in report


@pytest.mark.parametrize("kind", ["constant", "unrelated"])
def test_a_useless_instrument_is_a_clear_error_and_nothing_is_written(tmp_path, kind):
    """An instrument that does not move, or that does not move the input, exits 2 with the
    numbers and what to change in the job YAML; no run directory appears."""
    import numpy as np

    from tests.plants import historian_loop_signals, write_export

    sig = historian_loop_signals(2.0, 6_200_000)
    rng = np.random.default_rng(6_200_001)
    other = np.full(sig["PV"].size, 42.0) if kind == "constant" else \
        50.0 + np.repeat(rng.standard_normal(sig["PV"].size // 60 + 1), 60)[: sig["PV"].size]
    write_export(tmp_path / "drop" / "x.csv", {LOOP_TAGS["OP"]: sig["OP"],
                                             LOOP_TAGS["PV"]: sig["PV"], "XX-999.PV": other},
                 seed=6_200_002)
    job = {"job": "bad_iv", "source": {"path": "drop/*.csv", "timezone": "UTC"},
           "signals": {"inputs": {"valve": {"tag": LOOP_TAGS["OP"]}},
                       "outputs": {"flow": {"tag": LOOP_TAGS["PV"]}},
                       "instruments": {"other": {"tag": "XX-999.PV"}}},
           "storage": "storage", "sampling": {"dt_s": 2.0}, "search": {"n_p": 60},
           "rerun": {"enabled": False}}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(job))
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", "--no-prefect", str(path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    if kind == "constant":
        assert "signals.instruments.other (tag XX-999.PV) does not move" in r.stderr
    else:
        assert "barely move the input valve (tag FIC-301.OP): first-stage F =" in r.stderr
        assert "remove signals.instruments" in r.stderr
    assert not (tmp_path / "storage" / "bad_iv").exists() or \
        not any((tmp_path / "storage" / "bad_iv").iterdir())
