"""``estimation.method: ls | correlation | tc`` driven as a user does (issue 11): a job YAML
on a historian export through ``plantdyn run``, results read back from the run directory.

The plant is the suite's first-order one (tests/conftest.py: ``2/(20 s + 1)`` driven by
AR(1) noise, discretised exactly by zero-order hold with scipy's ``lfilter`` — not by
``pipeline.models.simulate``), written as an exception-reported PI-style long CSV.  The true step
response ``s[l] = K (1 - a^l)``, ``a = exp(-1/20)``, is the known answer.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from flows.cli import main
from pipeline.adapters.historian_writer import write_long_csv
from tests.conftest import (
    INPUT_TAG,
    OUTPUT_TAG,
    PLANT_GAIN,
    PLANT_TAU_S,
    plant_signals,
    subprocess_env,
    write_job,
)


def _truth(n: int) -> np.ndarray:
    return PLANT_GAIN * (1 - np.exp(-np.arange(1, n + 1) / PLANT_TAU_S))


def _export(folder: Path, *, seed: int, hours: float, noise_std: float) -> None:
    sig = plant_signals(seed=seed, hours=hours, noise_std=noise_std)
    path = folder / "drop" / "export.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_long_csv(path, sig["time"], {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]},
                   irregular=np.random.default_rng(seed))


def _all_step(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    s = pl.read_parquet(run_dir / "step_responses.parquet").filter(
        pl.col("window") == "all").sort("lag")
    return s["step"].to_numpy(), s["step_std"].to_numpy()


def _run_no_prefect(job: Path, capsys) -> Path:
    assert main(["run", "--no-prefect", str(job)]) == 0
    return Path(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def short_noisy(tmp_path_factory):
    """30 min at 1 s with white sensor noise of 0.5 (the output's own s.d. is ~1.3):
    N_d ≈ 1800 for ~100 unknowns per window — the short-record case TC is for."""
    folder = tmp_path_factory.mktemp("short")
    _export(folder, seed=7_300_001, hours=0.5, noise_std=0.5)
    return folder


def test_tc_job_through_prefect_stores_hyperparameters_and_a_closer_estimate(
        short_noisy, prefect_harness, capsys):
    """The TC run (Prefect flow path, estimate tasks mapped over windows) records the
    marginal-likelihood hyperparameters per output; its noise variance is the sensor's
    (0.25, within 25 %: sd of a variance estimate from ~1800 samples is ~3 %, plus the
    conditioning's share), and its all-data step response is closer to the truth than
    the least-squares run's on the same export (RMS over the lags)."""
    job_tc = write_job(short_noisy, name="short_tc", sampling={"dt_s": 1.0},
                       estimation={"method": "tc"}, file_name="tc.yaml")
    env = subprocess_env(PREFECT_API_URL=prefect_harness)
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(job_tc)],
                       capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    tc_dir = Path(r.stdout.strip().splitlines()[-1])
    checks = json.loads((tc_dir / "checks.json").read_text())
    est = checks["estimation"]
    assert est["method"] == "regularized_tc" and est["noise"] == "auto"
    h = est["hyperparameters"]["y"]  # per-input lists since the kernel module (one input)
    assert all(0 < a < 1 for a in h["alpha"]) and all(v > 0 for v in h["lambda"])
    assert h["sigma2"] == pytest.approx(0.25, rel=0.25)
    assert "TC prior" in (tc_dir / "report.md").read_text()
    # every window estimated with the same method: one uniform N_p per pair
    steps = pl.read_parquet(tc_dir / "step_responses.parquet")
    assert steps["window"].n_unique() >= 3

    job_ls = write_job(short_noisy, name="short_ls", sampling={"dt_s": 1.0},
                       estimation={"noise": "white"}, file_name="ls.yaml")
    ls_dir = _run_no_prefect(job_ls, capsys)
    s_tc, sd_tc = _all_step(tc_dir)
    s_ls, _ = _all_step(ls_dir)
    n = min(s_tc.size, s_ls.size)
    err_tc = np.sqrt(np.mean((s_tc[:n] - _truth(n)) ** 2))
    err_ls = np.sqrt(np.mean((s_ls[:n] - _truth(n)) ** 2))
    print(f"short record: RMS step error TC {err_tc:.4f}, LS {err_ls:.4f}")
    assert err_tc < err_ls
    # the posterior band covers the truth at the gain (4 sigma: one record, one point)
    assert abs(s_tc[n - 1] - _truth(n)[-1]) < 4 * sd_tc[n - 1]


def test_correlation_job_matches_least_squares_on_a_long_stationary_record(tmp_path, capsys):
    """Without drift and with plenty of data the correlation method and least squares
    have the same limit (method.md §2): through ``plantdyn run --no-prefect`` on a 3 h
    export the correlation method's gain is within 3 % of the plant's and its whole step
    response within 3 % of the gain of the least-squares one.  (The curve itself is
    compared with least squares, not with ``K(1 - a^l)``: averaging exception-reported
    samples onto the grid smooths the first lags for both methods alike.)"""
    _export(tmp_path, seed=7_300_002, hours=3.0, noise_std=0.05)
    common = {"sampling": {"dt_s": 1.0}, "search": {"n_p": 120}}
    job_c = write_job(tmp_path, name="corr", estimation={"method": "correlation"},
                      file_name="corr.yaml", **common)
    job_l = write_job(tmp_path, name="ls", estimation={"noise": "white"},
                      file_name="ls.yaml", **common)
    c_dir, l_dir = _run_no_prefect(job_c, capsys), _run_no_prefect(job_l, capsys)
    checks = json.loads((c_dir / "checks.json").read_text())
    assert checks["estimation"]["method"] == "correlation"
    assert "correlation method" in (c_dir / "report.md").read_text()
    s_c, _ = _all_step(c_dir)
    s_l, _ = _all_step(l_dir)
    assert s_c.size == s_l.size == 120
    print(f"correlation vs LS: max difference {np.max(np.abs(s_c - s_l)):.4f}, "
          f"gain {s_c[-1]:.4f} (plant {PLANT_GAIN})")
    assert abs(s_c[-1] - PLANT_GAIN) < 0.03 * PLANT_GAIN
    assert np.max(np.abs(s_c - s_l)) < 0.03 * PLANT_GAIN
    assert np.max(np.abs(s_c - s_l)) > 0  # two different estimators, not one twice
    assert {p["agreement"]["verdict"] for p in checks["pairs"]} <= {"pass", "fail"}


@pytest.mark.parametrize("estimation, extra, words", [
    ({"method": "correlation", "noise": "auto"}, {},
     ["estimation.noise", "correlation method", "white"]),
    ({"method": "tc"}, {"instruments": {"r": {"tag": INPUT_TAG}}},
     ["estimation.method: tc", "signals.instruments", "method: ls"]),
    ({"method": "correlation"}, {"instruments": {"r": {"tag": INPUT_TAG}}},
     ["estimation.method: correlation", "signals.instruments", "method: ls"]),
    ({"method": "lasso"}, {}, ["estimation.method", "auto", "ls", "correlation", "tc", "dc"]),
])
def test_method_settings_that_cannot_work_are_refused_in_yaml_terms(
        tmp_path, capsys, estimation, extra, words):
    _export(tmp_path, seed=7_300_003, hours=0.2, noise_std=0.05)
    job = write_job(tmp_path, estimation=estimation)
    if extra:
        import yaml

        data = yaml.safe_load(job.read_text())
        data["signals"].update(extra)
        job.write_text(yaml.safe_dump(data))
    assert main(["run", "--no-prefect", str(job)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for w in words:
        assert w in err, (w, err)
