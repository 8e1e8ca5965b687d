"""The steam-generator record through `plantdyn run` with the defaults (issue 9,
must-show 6): DaISy 98-003 converted to a historian CSV, estimation.noise: auto and
estimation.feedback: auto (configs/steamgen.yaml).

No plant ground truth exists; physics and the control structure give known answers: the
drum level is under PI control (its manipulated feedwater is not in the record), so its
closed-loop response to the level reference settles at gain 1; more fuel raises drum
pressure and steam flow and lowers excess O2; more air raises excess O2.  With the noise
models the one-step prediction errors of every output must be white (the thesis'
residuals are not: Ljung-Box p < 1e-10 on all four outputs).
"""

from __future__ import annotations

import re

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    if not DATA.is_dir():
        pytest.skip(f"shared data folder {DATA} is absent (a fresh clone without ../shared)")
    folder = tmp_path_factory.mktemp("steamgen")
    csv = folder / "demo" / "steamgen" / "steamgen.csv"
    r = subprocess.run([sys.executable, "-m", "pipeline.adapters.daisy",
                        str(DATA / "steamgen.dat"), str(csv)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    job = yaml.safe_load((ROOT / "configs" / "steamgen.yaml").read_text())
    job["rerun"] = {"enabled": False}
    (folder / "configs").mkdir()
    path = folder / "configs" / "steamgen.yaml"
    path.write_text(yaml.safe_dump(job, sort_keys=False))
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", "--no-prefect", str(path)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    run_dir = Path(r.stdout.strip().splitlines()[-1])
    RUN_DIRS["steamgen"] = run_dir
    return json.loads((run_dir / "checks.json").read_text()), (run_dir / "report.md").read_text()


RUN_DIRS: dict[str, Path] = {}


def test_no_bare_gain_off_a_moving_curve_and_the_export_is_the_reported_model(run, tmp_path):
    """Issue 32, must-show 2 on the real record with the default job: every pair either
    reports a settled gain or none (moving: no number, the note says why), and
    ``plantdyn export --format control`` writes a transfer function whose DC gain is
    within max(2σ, 10 %) of the reported gain, or leaves the pair out with its reason."""
    from tests.export_checks import assert_export_matches_report

    checks, _ = run
    assert_export_matches_report(RUN_DIRS["steamgen"], checks, tmp_path)


def _pair(checks, out, inp):
    return next(p for p in checks["pairs"] if p["output"] == out and p["input"] == inp)


def test_defaults_use_noise_models_that_whiten_every_output(run):
    """Every output gets an AR noise model, and its prediction errors are far closer to
    white than the thesis' residuals on the same record (Ljung–Box statistic at most a
    twentieth; the thesis' residuals are computed here from the raw table, detrended,
    with the job's N_p)."""
    import numpy as np

    from pipeline.identification.checks import ljung_box
    from pipeline.identification.conditioning import condition
    from pipeline.estimation.estimate import estimate_step_responses
    from pipeline.estimation.prediction import residuals

    checks, report = run
    assert checks["estimation"]["method"] == "prediction_error"
    d = np.loadtxt(DATA / "steamgen.dat")
    c = condition(d[:, 1:5], d[:, 5:9], method="detrend", dt_s=3.0)
    ins, outs = ["fuel", "air", "level_ref", "load"], ["pressure", "o2", "level", "steam"]
    n_p = np.array([[checks["search"]["n_p"][f"{o}<-{i}"] for i in ins] for o in outs])
    white = estimate_step_responses(c.x, c.y, n_p=n_p, dt=3.0)
    res = residuals(white, c.x, c.y)
    for k, out in enumerate(outs):
        nm = checks["noise_model"][out]
        assert nm["order"] >= 1, out  # slow disturbances in every output
        q_auto = checks["residuals"]["whiteness"][out]["statistic"]
        q_white = ljung_box(res[:, k], lags=20)["statistic"]
        assert q_auto < q_white / 20, (out, q_auto, q_white)
    assert "AR(" in report


def test_level_tracks_its_reference_and_the_physical_signs_hold(run):
    checks, _ = run
    lvl = _pair(checks, "level", "level_ref")
    assert abs(lvl["gain"] - 1.0) < max(0.05, 3 * lvl["gain_std"])
    for out, inp, sign in [("pressure", "fuel", +1), ("steam", "fuel", +1),
                           ("o2", "fuel", -1), ("o2", "air", +1)]:
        p = _pair(checks, out, inp)
        # the physical sign, established (beyond 2σ; o2<-air 10.6 ± 3.7: its σ holds the
        # 2.9σ change its longest fit adds beyond the horizon)
        assert sign * p["gain"] > 2 * p["gain_std"], (out, inp, p["gain"], p["gain_std"])


def test_every_pair_is_tested_for_feedback_and_judged(run):
    checks, report = run
    for p in checks["pairs"]:
        fb = p["feedback"]
        assert fb is not None and 0.0 <= fb["p_value"] <= 1.0 and fb["leads"] == 40
        assert p["agreement"]["verdict"] in ("pass", "fail", "insufficient_data")
        assert p["agreement"]["p_value"] is not None
    assert "## When to distrust a pair" in report
    # each cause said once, with every pair it touches and the pair's grade (a shared
    # cause such as an output's coloured residuals is not repeated per pair)
    section = report.split("## When to distrust a pair", 1)[1].split("\n## ", 1)[0]
    items = [ln for ln in section.splitlines() if ln.startswith("- **")]
    assert items and len(items) == len(set(items))
    grades = dict(re.findall(r"^- (\S+<-\S+): \*\*([ABCD])\*\*", report, re.M))
    assert len(grades) == len(checks["pairs"])
    said = {}
    for ln in items:
        who, cause = ln[2:].split(" — ", 1)
        code, message = cause.split(": ", 1)
        assert (code, message) not in said, "a cause repeated"
        said[code, message] = who
        for name, grade in re.findall(r"\*\*(\S+<-\S+)\*\* \(([ABCD])\)", who):
            assert grades[name] == grade
    warned = {f"{p['output']}<-{p['input']}" for p in checks["pairs"] if p["warnings"]}
    assert warned == {n for who in said.values()
                      for n in re.findall(r"\*\*(\S+<-\S+)\*\*", who)}
