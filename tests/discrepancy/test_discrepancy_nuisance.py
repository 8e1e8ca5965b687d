"""The discrepancy workflow on a plant that is not the model (issue 12, CI sample).

The plant is ``tests/plants.boiler_nuisance_record``: the design.md boiler loop written
out as equations and integrated at 0.05 s (Euler, dead time and lag in continuous time)
— not ``pipeline.models.simulate`` — with a DCS that acts on the previous second's measurement,
quantised fuel demand, a slow unmeasured disturbance, 5 % sensor noise and 2 % noise on
the measured steam flow; 4 h at 1 s.  The nominal model is the shipped
``configs/models/boiler_pressure.yaml``.  Seeds 301–303 were never used for tuning
(tuning used seeds 1–2).

Tolerances: the nuisances bias the fitted parameters by a few percent (the one-second
DCS delay reads as extra controller gain: 1.307 for 1.25; the fuel lag fits 8.9 s for
10 s), so parameters are checked within 10 % (gain, dead time) and 15 % (lag).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from flows.cli import main
from pipeline.jobs.demo import BOILER_MODEL, boiler_model
from pipeline.discrepancy import DiscrepancyConfig, analyse_discrepancy
from pipeline.discrepancy.select import same_class
from tests.plants import boiler_nuisance_record


def _analyse(seed: int, **hidden):
    inputs, measured = boiler_nuisance_record(4.0, seed, **hidden)
    return analyse_discrepancy(boiler_model(), inputs=inputs, measured=measured, dt_s=1.0)


@pytest.mark.parametrize("seed", [301, 302])
def test_no_hidden_effect_under_nuisance_mismatch_is_no_significant_effect(seed):
    """The key case: nothing is missing but the plant is not the model.  One-percent
    gain changes pass every statistical test (ΔBIC > 100, z > 4) while closing 1–2 % of
    the held-out gap: they are minor effects, the verdict is no_significant_effect."""
    r = _analyse(seed)
    assert r.verdict == "no_significant_effect", str(r)
    assert r.effect is None and r.effects == ()
    assert r.minor_effects, "the statistically detectable nuisance should be listed"
    cfg = DiscrepancyConfig()
    for c in r.minor_effects:
        assert c.passed and c.gap_reduction < cfg.min_gap_reduction
    assert r.gap["reduction"] == 0.0
    d = r.to_dict()
    assert d["effects"] == [] and len(d["minor_effects"]) == len(r.minor_effects)


def test_extra_dead_time_is_named_dead_time_not_its_pade_lookalike():
    """An extra 10 s on the fuel path: an inverse response of magnitude ~1 (the first-order
    Padé approximant of the delay, 2 parameters) wins on BIC, but the exact dead time
    (1 parameter) closes as much of the held-out gap: parsimony names the dead time."""
    r = _analyse(303, extra_fuel_delay_s=10.0)
    assert r.verdict == "effect_found", str(r)
    assert (r.effect.name, r.effect.location) == ("dead_time", "fuel")
    assert abs(r.effect.parameters["delay_s"] - 10.0) <= 1.0
    ir = [c for c in r.candidates if c.effect.name == "inverse_response"
          and c.effect.location == "fuel"]
    assert ir and ir[0].criterion < next(c.criterion for c in r.candidates
                                         if c.effect is r.effect)  # the look-alike fit better
    assert r.effects[0].candidate.gap_reduction > 0.5


@pytest.mark.parametrize("hidden, name, location, key, truth, tol", [
    ({"kp_factor": 1.25}, "gain", "controller", "factor", 1.25, 0.10),
    ({"extra_fuel_lag_s": 10.0}, "extra_lag", "fuel", "tau_s", 10.0, 0.15),
])
def test_real_missing_effects_are_found_under_nuisance_mismatch(hidden, name, location, key,
                                                                truth, tol):
    r = _analyse(302, **hidden)
    assert r.verdict == "effect_found", str(r)
    assert (r.effect.name, r.effect.location) == (name, location)
    assert abs(r.effect.parameters[key] / truth - 1) <= tol, r.effect
    assert r.effects[0].candidate.gap_reduction >= 0.3
    # the chain adds nothing spurious: whatever else passes closes < 5 % of the gap
    assert len(r.effects) == 1, [e.candidate.effect.describe() for e in r.effects]


def test_practical_significance_through_plantdyn_discrepancy(tmp_path, capsys):
    """As a user runs it: a historian export of the nuisance plant with nothing missing,
    ``plantdyn discrepancy --no-prefect``; discrepancy.json says no_significant_effect and
    lists the minor effects with their gap reductions, report.md names them, and
    ``discrepancy.min_gap_reduction: 0.0`` (a job that wants every detectable effect)
    turns the same data into a finding."""
    from pipeline.adapters.historian_writer import write_long_csv

    inputs, measured = boiler_nuisance_record(4.0, 304)
    n = inputs["steam_flow"].size
    times = np.datetime64("2026-06-01T00:00:00", "us") + (
        np.arange(n) * 1_000_000).astype("timedelta64[us]")
    export = tmp_path / "drop" / "boiler.csv"
    export.parent.mkdir(parents=True)
    write_long_csv(export, times, {"FI-101.PV": 50.0 + inputs["steam_flow"],
                                   "PI-102.PV": 120.0 + measured["turbine_pressure"]})
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "boiler.yaml").write_text(BOILER_MODEL.read_text())

    def job(name: str, **section) -> Path:
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump({
            "job": name, "source": {"path": "drop/*.csv", "timezone": "UTC"},
            "signals": {"inputs": {"steam_flow": {"tag": "FI-101.PV"}},
                        "outputs": {"turbine_pressure": {"tag": "PI-102.PV"}}},
            "storage": "storage", "sampling": {"dt_s": 1.0}, "rerun": {"enabled": False},
            "model": "models/boiler.yaml", "discrepancy": {"max_effects": 2, **section}}))
        return path

    assert main(["discrepancy", "--no-prefect", str(job("null"))]) == 0
    run_dir = Path(capsys.readouterr().out.strip().splitlines()[-1])
    d = json.loads((run_dir / "discrepancy.json").read_text())
    assert d["verdict"] == "no_significant_effect" and d["effect"] is None
    assert d["effects"] == [] and d["minor_effects"]
    assert all(m["gap_reduction"] < 0.05 and m["passed"] for m in d["minor_effects"])
    assert d["config"]["min_gap_reduction"] == 0.05 and d["config"]["max_effects"] == 2
    report = (run_dir / "report.md").read_text()
    assert "**No significant effect**" in report and "## Minor effects" in report
    assert f"`{d['minor_effects'][0]['name']}` at `{d['minor_effects'][0]['location']}`" in report

    assert main(["discrepancy", "--no-prefect", str(job("every", min_gap_reduction=0.0))]) == 0
    d0 = json.loads((Path(capsys.readouterr().out.strip().splitlines()[-1])
                     / "discrepancy.json").read_text())
    assert d0["verdict"] in ("effect_found", "inconclusive")
    if d0["verdict"] == "effect_found":
        assert d0["effects"][0]["gap_reduction"] < 0.05
        assert math.isclose(d0["effects"][0]["gap_before"], d["gap"]["holdout_rms_before"],
                            rel_tol=1e-9)


def test_a_delay_like_inverse_response_gives_way_to_its_dead_time():
    """Issue 12, build 3 (degenerate forms): a hidden 20 s dead time on the boiler's demand
    path under nuisance mismatch (tests/nuisance_trials.py, the trial this rule was built
    on): the inverse response of magnitude 0.977 and tau 9.6 s -- the delay's first-order
    Padé approximant -- fits best in-sample and leaves 16 % less of the held-out gap,
    yet the exact 20 s dead time closes 94 % as much with 96.5 % of its BIC improvement:
    the dead time is named, with the look-alike still ranked first among candidates."""
    from tests.benchmarks.bench_discrepancy import make_trial

    trial, _ = make_trial("nuisance", "dead_time", 301_000)
    r = analyse_discrepancy(trial.model, inputs=trial.inputs, measured=trial.measured,
                            dt_s=trial.dt_s, seed=301_000)
    assert trial.effect.describe() == "dead_time at demand: delay_s=20"
    assert r.verdict == "effect_found", str(r)
    assert r.effect.name == "dead_time" and r.effect.parameters["delay_s"] == 20.0
    assert "demand" in {r.effect.location, *r.effect.equivalent_locations}
    first = r.candidates[0]
    assert first.effect.name == "inverse_response"
    assert abs(first.effect.parameters["magnitude"] - 1) < 0.15
    assert abs(2 * first.effect.parameters["tau_s"] - 20.0) < 6.0


def test_no_second_effect_the_final_chain_does_not_need():
    """Nuisance suite trial 907030 (``tests/nuisance_trials.py``: the independent plant,
    a DCS acting one scan late, quantised controller outputs, a slow disturbance, noisy
    measured inputs): a controller saturation is hidden.  After it was accepted, a fuel
    gain of x1.017 passed its search -- the saturation refitted jointly with it closed the
    gap -- but closed -0.3 % in the final chain.  The final chain must not hold it
    (``chain.prune``): exactly the saturation, its limits within the issue's 10 %
    parameter-error target, and the gain, if listed at all, under ``minor_effects``.
    (The limits are 2-7 % off under these nuisances: 2-3 % as refitted jointly with the
    since-pruned gain; 7 % and 3 % as the first search fits them, which is where they
    stay since the later search, with the jointly screened candidates, accepts nothing --
    so this trial no longer reaches the pruning itself; the scripted tests in
    ``tests/discrepancy/test_discrepancy_chain.py`` check that rule.)"""
    from tests.benchmarks.bench_discrepancy import make_trial

    trial, _ = make_trial("nuisance", "saturation", 907030)
    [truth] = trial.effects
    result = analyse_discrepancy(trial.model, inputs=trial.inputs, measured=trial.measured,
                                 dt_s=trial.dt_s, seed=907030)
    chain = [s.candidate.effect for s in result.effects]
    assert [(e.name, e.location) for e in chain] == [("saturation", "controller")], \
        [e.describe() for e in chain]
    for key in ("low", "high"):
        assert chain[0].parameters[key] == pytest.approx(truth.parameters[key], rel=0.10)
    # the pruned gain, if listed at all, is a minor effect: never in the chain (above)
    assert all(m.effect.name != "gain" or not any(
        same_class(m.effect, s.candidate.effect) for s in result.effects)
        for m in result.minor_effects)
