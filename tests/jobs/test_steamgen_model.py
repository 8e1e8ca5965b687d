"""The first-principles steam-generator model and the discrepancy workflow on the real
record (issue 4, "It must show" 3): configs/models/steamgen.yaml against
../shared/data/steamgen.dat (DaISy 98-003, 8 h at 3 s).

No ground truth exists for the plant, so the known answers are:

* an independent computation: step responses estimated from the FIRST half of the
  record (the half the model was calibrated on) by the project's least-squares FIR
  estimator, against the model's own step responses (a simulated unit step);
* physics: the drum level is under closed-loop control with integral behaviour (an
  integrating drum with a proportional controller), so level <- level_ref settles at
  exactly 1 in the model, and the data agree;
* invariants of the workflow: the augmented model re-simulates to the reported held-out
  RMS, and no accepted candidate makes the held-out prediction worse.

Tolerances: the FIR steady-state gains of the main pairs have standard errors of
0.3-2 % (sigma^2 A^-1, printed by the estimator); the model is a linear small-signal
model of a nonlinear closed-loop plant calibrated by simulation error (not by the FIR),
so agreement is expected to the accuracy of such a model, 15 %, not to the standard
errors.  Each tolerance below is the measured gap (in the model header) with a margin.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline.adapters.daisy import STEAMGEN_COLUMNS, convert, read_daisy
from flows.cli import main
from pipeline.identification.conditioning import condition
from pipeline.discrepancy import DiscrepancyConfig, analyse_discrepancy
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.models.model import model_from_dict
from pipeline.models.simulate import simulate
from tests.helpers_steamgen import require_steamgen

ROOT = Path(__file__).resolve().parents[2]
MODEL_YAML = ROOT / "configs" / "models" / "steamgen.yaml"
JOB_YAML = ROOT / "configs" / "steamgen_discrepancy.yaml"
COLUMNS = [c for c in STEAMGEN_COLUMNS if c != "time"]
N_P = 120  # 6 min at 3 s: the energy loop settles in ~4 time constants of 60-75 s


@pytest.fixture(scope="module")
def model():
    return model_from_dict(yaml.safe_load(MODEL_YAML.read_text())["model"])


@pytest.fixture(scope="module")
def record():
    return read_daisy(require_steamgen()).values  # steamgen's column names by default


@pytest.fixture(scope="module")
def deviations(record):
    """Signals minus the job's operating point (first-half means, the model header)."""
    op = yaml.safe_load(JOB_YAML.read_text())["discrepancy"]["operating_point"]
    return {n: record[n] - op[n] for n in COLUMNS}


def test_operating_point_is_the_first_half_mean(record):
    op = yaml.safe_load(JOB_YAML.read_text())["discrepancy"]["operating_point"]
    for n in COLUMNS:
        assert op[n] == pytest.approx(np.mean(record[n][:4800]), rel=1e-5, abs=1e-8)


@pytest.fixture(scope="module")
def steps(model, record):
    """(data step responses from the first half, model step responses), by (out, in)."""
    ins, outs = list(model.inputs), list(model.outputs)
    x = np.column_stack([record[n][:4800] for n in ins])
    y = np.column_stack([record[n][:4800] for n in outs])
    cond = condition(x, y, method="detrend", dt_s=3.0)
    est = estimate_step_responses(cond.x, cond.y, n_p=N_P, dt=3.0)
    data, sim = {}, {}
    for j, u in enumerate(ins):
        drive = {k: np.zeros(N_P) for k in ins}
        drive[u][:] = 1.0
        s = simulate(model, drive, dt_s=3.0)
        for i, o in enumerate(outs):
            data[o, u] = (est.step[i, j, :N_P], est.step_std[i, j, :N_P])
            sim[o, u] = s.signals[o]
    return data, sim


@pytest.mark.parametrize(("out", "inp", "rtol"), [
    ("steam", "fuel", 0.10),       # data 27.0, model 27.9 (all heat leaves as steam)
    ("pressure", "fuel", 0.15),    # data 245, model 222
    ("pressure", "load", 0.10),    # data -7830, model -7560
    ("o2", "fuel", 0.15),          # data -14.5, model -14.0
    ("level", "level_ref", 0.03),  # data 1.014, model 1 (closed-loop level control)
])
def test_model_steady_gains_match_the_data(steps, out, inp, rtol):
    data, sim = steps
    (h, h_std), m = data[out, inp], sim[out, inp]
    assert np.sign(m[-1]) == np.sign(h[-1])
    assert m[-1] == pytest.approx(h[-1], rel=rtol), (
        f"{out}<-{inp}: model {m[-1]:.4g}, data {h[-1]:.4g} +- {h_std[-1]:.2g}")


def test_pressure_after_a_load_step_has_the_data_s_time_constant(steps):
    """63 % rise times of pressure <- load: data and model within 10 % (both ~150 s)."""
    data, sim = steps
    h, m = data["pressure", "load"][0], sim["pressure", "load"]

    def t63(s: np.ndarray, half_sample: bool) -> float:
        k = int(np.argmax(np.abs(s) >= 0.63 * abs(s[-1])))
        # estimator lags sit at (l - 1/2) dt, simulated samples at k dt
        return (k + (0.5 if half_sample else 0.0)) * 3.0

    assert t63(m, False) == pytest.approx(t63(h, True), rel=0.10)


def test_level_shows_swell_before_the_mass_balance_takes_over(steps):
    """More fuel -> more steam: the level first rises (swell), in data and model alike."""
    data, sim = steps
    h, m = data["level", "fuel"][0], sim["level", "fuel"]
    assert h[:30].max() > 5 * data["level", "fuel"][1][:30].max()
    assert m[:30].max() == pytest.approx(h[:30].max(), rel=0.25)  # data 8.2, model 7.7
    assert abs(h[-1]) < 0.1 * h[:30].max() and abs(m[-1]) < 0.1 * m[:30].max()


def test_a_flattening_o2_clip_is_rejected_on_the_held_out_gap(model, deviations):
    """Regression from the real record: with only saturation allowed, the whitened
    criteria favour clipping O2 into a narrow band (the AR noise model is near a unit
    root), which raised its held-out RMS by 70 %.  The held-out gap rule rejects it.

    One search (``max_effects=1``): the rule is the first search's; with the default
    chain the masked-pair searches that follow a rejected candidate (each refitting
    saturation limits on 9600 samples) took 200 of this test's 210 s and decide nothing
    it checks (the end-to-end job test below runs the default chain on this record)."""
    result = analyse_discrepancy(
        model, inputs={k: deviations[k] for k in model.inputs},
        measured={"o2": deviations["o2"]}, dt_s=3.0,
        config=DiscrepancyConfig(effects=("saturation",), max_effects=1))
    gap_nominal = result.gap["holdout_rms_before"]
    assert any(c.delta_bic >= 10 and c.holdout_z >= 2 and c.holdout_gap > gap_nominal
               for c in result.candidates), "the case this test guards against did not arise"
    for c in result.candidates:
        whitened = c.delta_bic >= 10 and c.holdout_z >= 2 and c.holdout_gap < gap_nominal
        plain = c.holdout_rms_p <= 0.01 and c.holdout_gap < gap_nominal
        assert c.passed == (whitened or plain)
        if c.holdout_gap > gap_nominal:
            assert not c.passed  # the flattening clip: neither way lets it through
    # what passes (a clip at the analyser's 0 % reading) closes < 5 % of the gap: minor
    assert result.verdict == "no_significant_effect"
    assert all(c.gap_reduction < 0.05 for c in result.minor_effects)
    assert result.gap["holdout_rms_after"] == gap_nominal


def test_discrepancy_job_runs_end_to_end_on_the_real_record(tmp_path, capsys):
    convert(require_steamgen(), tmp_path / "data" / "steamgen.csv")
    job = yaml.safe_load(JOB_YAML.read_text())
    job.update(source={**job["source"], "path": "data/steamgen.csv"}, storage="storage",
               model=yaml.safe_load(MODEL_YAML.read_text())["model"])
    (tmp_path / "job.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    assert main(["discrepancy", str(tmp_path / "job.yaml"), "--no-prefect"]) == 0
    run_dir = Path(capsys.readouterr().out.strip().splitlines()[-1])
    names = {p.name for p in run_dir.iterdir()}
    assert {"discrepancy.json", "model_augmented.yaml", "discrepancy_series.parquet",
            "report.md", "recording.rrd", "manifest.json"} <= names
    d = json.loads((run_dir / "discrepancy.json").read_text())
    assert d["n_samples"] == 9600 and d["data"]["left_out_samples"] == 0
    assert d["verdict"] in ("effect_found", "inconclusive", "no_significant_effect")
    check = d["augmented_model_check"]
    for o, v in check["holdout_rms_reported"].items():
        assert check["holdout_rms_resimulated"][o] == pytest.approx(v, rel=1e-9)
    before = d["gap"]["holdout_rms_before"]
    for c in d["candidates"]:  # passed: better on some output, worse on none
        if c["passed"]:
            assert not c["worse_on"] and any(
                c["holdout_rms"][o] < g["holdout_rms_before"]
                for o, g in d["gap"]["per_output"].items())
    # Issue 12 build 5: the whitened criteria take slow O2 errors for noise (the AR
    # noise model is near a unit root); the held-out RMS test lets the air-scheduled
    # combustion gain through -- the 25 % what-if below -- while the whitened winners
    # (an O2 lag / dead time) close ~1 % and are minor.  The gain clears the practical
    # bar, not by a wide margin: its share of O2's held-out gap at the lower bound
    # (practical.practical_share: the largest of five bounds -- four outputs and the
    # pooled gap -- each at 1 %; 0.063 when written, O2's point estimate 0.251: the
    # hold-out runs at lower load, and a slow O2 disturbance could shift much of the
    # held-out level the gain does).
    (gain,) = [c for c in d["candidates"] if (c["name"], c["location"]) == (
        "operating_point_gain", "combustion") and c["parameters"]["signal"] == "air"]
    assert gain["passed"] and gain["passed_by"] in ("held-out RMS", "both")
    assert gain["holdout_rms_p"] <= 0.01 and gain["gap_reduction"] > 0.1
    assert gain["gap_reduction_low"] >= d["config"]["min_gap_reduction"]
    assert gain["gap_reduction_low_output"] == "o2"
    assert d["verdict"] == "effect_found"
    effect = d["effects"][0]
    assert (effect["name"], effect["location"], effect["parameters"]["signal"]) == (
        "operating_point_gain", "combustion", "air")
    assert d["gap"]["per_output"]["o2"]["reduction"] > 0.2  # 3.625 -> 2.715 (25.1 %)
    assert d["gap"]["holdout_rms_after"] < before
    assert all(m["gap_reduction_low"] < d["config"]["min_gap_reduction"]
               for m in d["minor_effects"])
    # the localisation names, per output, which inputs explain the residual
    assert set(d["localization"]) == {"pressure", "o2", "level", "steam"}
    assert "fuel" in d["localization"]["steam"]["explained_by"]


def test_what_if_o2_effects_on_the_held_out_part(model, deviations):
    """What the engineer's physics says about O2, checked on the held-out last third:
    the analyser cannot read below 0 % (it does for 45 % of the record, fuel-rich), so
    clipping the model's O2 at 0 % (low = -3.35 in deviations) must help; the air/fuel
    ratio is nonlinear, so an air-scheduled combustion gain helps much more.  Neither
    passes the whitened criteria (docs/discrepancy-accuracy.md: the AR noise model is near
    a unit root and takes slow O2 errors for noise); run with -s to print the numbers
    docs/discrepancy-accuracy.md quotes."""
    from pipeline.discrepancy.effects import Effect, predict_outputs

    held = slice(6400, None)  # holdout_fraction 1/3 of 9600 samples

    def rms(effect):
        p = predict_outputs(model, effect, deviations, dt_s=3.0, outputs=["o2"])
        return float(np.sqrt(np.mean((deviations["o2"][held] - p["o2"][held]) ** 2)))

    nominal = rms(None)
    assert np.mean(deviations["o2"] + 3.34993 <= 0.05) > 0.4
    clip = rms(Effect("saturation", "o2", {"low": -3.34993, "high": np.inf}))
    scheduled = rms(Effect("operating_point_gain", "combustion",
                           {"slope": 1.372, "signal": "air"}))
    print(f"held-out O2 RMS: nominal {nominal:.4g}, clipped at 0 % {clip:.4g}, "
          f"air-scheduled combustion gain {scheduled:.4g}")
    assert clip < 0.97 * nominal       # measured 3.625 -> 3.464 (-4.5 %)
    assert scheduled < 0.8 * nominal   # measured 3.625 -> 2.715 (-25 %)
