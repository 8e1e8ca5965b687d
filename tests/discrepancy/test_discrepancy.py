"""The discrepancy workflow: catalogue realisations, nesting, the demo, the API contract.

The statistical targets (correct name and location, false positives, parameter error)
are measured by ``python -m tests.benchmarks.bench_discrepancy``; here each test checks one behaviour against a
known answer: analytic step responses of the effect blocks, exact equivalences, the
bundled demo (controller gain 20 % high), noise-free recovery, the JSON contract and the
re-simulation of the augmented model.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.signal
import yaml

from pipeline.discrepancy import DiscrepancyConfig, analyse_discrepancy
from pipeline.simulated.synthetic import make_discrepancy_demo
from pipeline.discrepancy.localise import input_relevance
from pipeline.discrepancy.problem import Problem
from pipeline.discrepancy.effects import (
    EFFECT_NAMES,
    EFFECT_PARAMETERS,
    Effect,
    apply_effect,
    output_offsets,
    predict_outputs,
)
from pipeline.simulated.effect_trials import make_hidden_effect_trial
from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError, ModelError
from pipeline.models.model import model_from_dict, model_to_dict
from pipeline.models.simulate import simulate

MODELS = Path(__file__).resolve().parents[2] / "configs" / "models"


def _model(name: str):
    return model_from_dict(yaml.safe_load((MODELS / f"{name}.yaml").read_text()))


@pytest.fixture(scope="module")
def boiler():
    return _model("boiler_pressure")


@pytest.fixture(scope="module")
def drum():
    return _model("drum_level")


@pytest.fixture(scope="module")
def demo_result(boiler):
    inputs, measured, dt_s = make_discrepancy_demo(boiler, seed=0)
    result = analyse_discrepancy(boiler, inputs=inputs, measured=measured, dt_s=dt_s)
    return inputs, measured, dt_s, result


# -- catalogue realisations against analytic answers --------------------------------
def _open_loop():
    """u -> gain 2 -> y: effects on block "plant" are visible directly."""
    return model_from_dict({"model": {
        "name": "open", "inputs": ["u"], "outputs": ["y"],
        "blocks": [{"name": "plant", "type": "gain", "input": "u", "k": 2.0},
                   {"name": "y", "type": "sum", "inputs": ["plant"]}]}})


def _step_response(model, effect, n=200, dt_s=1.0, extra=None):
    inputs = {"u": np.ones(n)}
    inputs.update(extra or {})
    return predict_outputs(model, effect, inputs, dt_s=dt_s)["y"]


def test_inverse_response_step_is_wrong_way_then_settles():
    # (1 - m tau s)/(tau s + 1) after a gain of 2: ZOH step response at the samples is
    # exactly 2 (1 - (1 + m) exp(-k dt / tau)): starts at -2 m, crosses zero at
    # t = tau ln(1 + m), ends at 2.
    m, tau = 1.5, 10.0
    y = _step_response(_open_loop(), Effect("inverse_response", "plant",
                                            {"tau_s": tau, "magnitude": m}))
    k = np.arange(y.size)
    np.testing.assert_allclose(y, 2.0 * (1 - (1 + m) * np.exp(-k / tau)), atol=1e-12)
    assert y[0] == pytest.approx(-2 * m)


def test_extra_lag_dead_time_and_unmodelled_input_steps():
    model = _open_loop()
    k = np.arange(200)
    lag = _step_response(model, Effect("extra_lag", "plant", {"tau_s": 7.0}))
    # strictly proper ZOH lag: the output moves one sample after the step
    np.testing.assert_allclose(lag, 2.0 * (1 - np.exp(-k / 7.0)), atol=1e-12)
    dead = _step_response(model, Effect("dead_time", "plant", {"delay_s": 5.0}))
    np.testing.assert_allclose(dead, np.where(k >= 5, 2.0, 0.0), atol=0)
    # a step on an extra measured signal w reaches y through k/(tau s + 1) after 3 s
    unm = predict_outputs(
        model, Effect("unmodelled_input", "w->y", {"k": -0.5, "tau_s": 4.0, "delay_s": 3.0}),
        {"u": np.zeros(200), "w": np.ones(200)}, dt_s=1.0)["y"]
    expected = np.where(k >= 3, -0.5 * (1 - np.exp(-(k - 3) / 4.0)), 0.0)
    np.testing.assert_allclose(unm, expected, atol=1e-12)


def test_static_nonlinear_effects_and_sensor_offsets():
    model = _open_loop()
    u = np.linspace(-3, 3, 61)
    # deadband of width 2 on the gain's input: 2 * (u -+ 1) outside |u| <= 1
    db = predict_outputs(model, Effect("deadband", "plant", {"width": 2.0}), {"u": u}, dt_s=1.0)["y"]
    np.testing.assert_allclose(db, 2.0 * np.where(np.abs(u) <= 1, 0.0, u - np.sign(u)), atol=1e-12)
    sat = predict_outputs(model, Effect("saturation", "plant", {"low": -1.0, "high": 4.0}),
                          {"u": u}, dt_s=1.0)["y"]
    np.testing.assert_allclose(sat, np.clip(2.0 * u, -1.0, 4.0), atol=1e-12)
    opg = predict_outputs(model, Effect("operating_point_gain", "plant",
                                        {"slope": 0.1, "signal": "w"}),
                          {"u": u, "w": 3.0 * u}, dt_s=1.0)["y"]
    np.testing.assert_allclose(opg, 2.0 * u * (1 + 0.3 * u), atol=1e-12)
    # bias + drift: t_h = k dt / 3600 from the first sample, measurement side only
    bias = predict_outputs(model, Effect("sensor_bias_drift", "y",
                                         {"bias": 0.5, "drift_per_h": -2.0}),
                           {"u": np.zeros(61)}, dt_s=60.0)["y"]
    np.testing.assert_allclose(bias, 0.5 - 2.0 * np.arange(61) / 60.0, atol=1e-12)


@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_every_effect_is_nested_at_its_null_value(boiler, name):
    # At the catalogue's null value the augmented model simulates exactly like the
    # nominal one (the candidates are nested in the nominal model).
    rng = np.random.default_rng(1)
    inputs = {"steam_flow": np.cumsum(rng.normal(size=600)) * 0.1, "aux_flow": rng.normal(size=600)}
    location = {"sensor_bias_drift": "turbine_pressure",
                "unmodelled_input": "aux_flow->turbine_pressure"}.get(name, "fuel")
    params = dict(EFFECT_PARAMETERS[name])
    if name == "operating_point_gain":
        params["signal"] = "aux_flow"
    nominal = simulate(boiler, {"steam_flow": inputs["steam_flow"]}, dt_s=2.0).signals[
        "turbine_pressure"]
    nested = predict_outputs(boiler, Effect(name, location, params), inputs, dt_s=2.0)
    np.testing.assert_allclose(nested["turbine_pressure"], nominal, rtol=0, atol=1e-12)


def test_augmented_models_round_trip_through_dict(boiler, drum):
    effects = [
        Effect("gain", "controller", {"factor": 1.2}),
        Effect("dead_time", "fuel", {"delay_s": 6.0}),
        Effect("extra_lag", "drum", {"tau_s": 12.0}),
        Effect("inverse_response", "fuel", {"tau_s": 9.0, "magnitude": 0.8}),
        Effect("operating_point_gain", "fuel", {"slope": 0.02, "signal": "aux_flow"}),
        Effect("deadband", "fuel", {"width": 0.1}),
        Effect("saturation", "controller", {"low": -math.inf, "high": 0.5}),
        Effect("unmodelled_input", "aux_flow->turbine_pressure",
               {"k": 0.01, "tau_s": 20.0, "delay_s": 4.0}),
    ]
    for effect in effects:
        augmented = apply_effect(boiler, effect, dt_s=2.0)
        assert model_from_dict(model_to_dict(augmented)) == augmented
        assert effect.name in augmented.description
    drum_aug = apply_effect(drum, Effect("extra_lag", "feedwater_flow", {"tau_s": 5.0}))
    assert drum_aug.outputs == drum.outputs  # outputs keep their measured names


def test_gain_on_a_sum_feeding_one_gain_is_equivalent(boiler):
    # demand (sum) feeds only fuel (gain): a gain change on either is the same plant.
    rng = np.random.default_rng(2)
    inputs = {"steam_flow": np.cumsum(rng.normal(size=800)) * 0.1}
    a = predict_outputs(boiler, Effect("gain", "demand", {"factor": 1.3}), inputs, dt_s=2.0)
    b = predict_outputs(boiler, Effect("gain", "fuel", {"factor": 1.3}), inputs, dt_s=2.0)
    np.testing.assert_allclose(a["turbine_pressure"], b["turbine_pressure"], rtol=1e-12,
                               atol=1e-15)


def test_effect_validation_messages(boiler):
    with pytest.raises(ConfigError, match="not in the catalogue"):
        Effect("friction", "fuel", {})
    with pytest.raises(ConfigError, match=r"parameters \['k'\] but the catalogue defines"):
        Effect("gain", "fuel", {"k": 2.0})
    with pytest.raises(ModelError, match="no block 'fule'"):
        apply_effect(boiler, Effect("gain", "fule", {"factor": 1.1}))
    with pytest.raises(ModelError, match="not a model output"):
        apply_effect(boiler, Effect("sensor_bias_drift", "fuel", {"bias": 1.0, "drift_per_h": 0.0}))


# -- the bundled demo ------------------------------------------------------------------
def test_demo_names_controller_gain_and_shrinks_gap(demo_result):
    _, _, _, result = demo_result
    assert result.verdict == "effect_found"
    assert (result.effect.name, result.effect.location) == ("gain", "controller")
    # Issue: recover ~1.2 within 5 %.  The fit's own precision is far better (the
    # hidden-effect suite's median gain error is a few 1e-3), so 5 % is the spec.
    assert result.effect.parameters["factor"] == pytest.approx(1.2, rel=0.05)
    gap = result.gap
    assert gap["holdout_rms_after"] < gap["holdout_rms_before"]
    assert gap["reduction"] == pytest.approx(
        1 - gap["holdout_rms_after"] / gap["holdout_rms_before"])
    # the winner beats every other fitted candidate on the criterion
    assert result.candidates[0].effect == result.effect
    assert all(c.criterion >= result.candidates[0].criterion for c in result.candidates)


def test_demo_augmented_model_resimulates_to_reported_numbers(boiler, demo_result):
    inputs, measured, dt_s, result = demo_result
    reloaded = model_from_dict(json.loads(json.dumps(model_to_dict(result.augmented_model))))
    assert reloaded == result.augmented_model
    assert reloaded.block("controller").kp == pytest.approx(
        boiler.block("controller").kp * result.effect.parameters["factor"], rel=1e-12)
    y = simulate(reloaded, {k: inputs[k] for k in reloaded.inputs}, dt_s=dt_s).signals[
        "turbine_pressure"]
    np.testing.assert_allclose(y, result.series.augmented["turbine_pressure"], atol=1e-12)
    h = slice(result.series.holdout_start, None)
    after = float(np.sqrt(np.mean((measured["turbine_pressure"][h] - y[h]) ** 2)))
    assert after == pytest.approx(result.gap["holdout_rms_after"], rel=1e-10)
    nominal = simulate(boiler, {"steam_flow": inputs["steam_flow"]}, dt_s=dt_s).signals[
        "turbine_pressure"]
    before = float(np.sqrt(np.mean((measured["turbine_pressure"][h] - nominal[h]) ** 2)))
    assert before == pytest.approx(result.gap["holdout_rms_before"], rel=1e-10)


def test_to_dict_is_strict_json_and_small(demo_result):
    _, measured, _, result = demo_result
    d = result.to_dict()
    text = json.dumps(d, allow_nan=False)
    # no per-sample arrays: the record has 28 800 samples, the summary a few kB
    assert len(text) < 100_000
    for key in ("verdict", "effect", "candidates", "localization", "gap", "lookalikes"):
        assert key in d
    assert set(d["gap"]) >= {"holdout_rms_before", "holdout_rms_after", "reduction"}
    first = d["candidates"][0]
    assert set(first) >= {"name", "location", "parameters", "criterion", "holdout_rms"}
    loc = d["localization"]["turbine_pressure"]
    assert set(loc) >= {"residual_rms", "signals", "time_windows", "operating_range", "locations"}
    assert loc["signals"]["steam_flow"]["frequency_bands"]
    series = result.series
    assert series.t_s.size == measured["turbine_pressure"].size
    np.testing.assert_allclose(series.residual_after["turbine_pressure"],
                               measured["turbine_pressure"] - series.augmented["turbine_pressure"])


def test_demo_localisation_points_at_the_load_and_the_controller(demo_result):
    _, _, _, result = demo_result
    loc = result.localization["turbine_pressure"]
    # the residual of a wrong controller gain is driven by the load (steam flow); the
    # unrelated aux_flow must not be singled out: its bootstrap p-value is not minimal
    assert loc["signals"]["steam_flow"]["p_value"] == pytest.approx(1 / 100)
    assert "steam_flow" in loc["explained_by"]
    assert loc["locations"][0]["location"] == "controller" or any(
        s["name"] == "gain" and s["location"] == "controller" for s in loc["locations"][:3])


# -- behaviour on constructed cases --------------------------------------------------
def test_noise_free_gain_is_recovered_exactly(drum):
    trial = make_hidden_effect_trial(drum, None, seed=5, n=6000)
    truth_effect = Effect("gain", "feedwater_flow", {"factor": 1.37})
    truth = predict_outputs(drum, truth_effect, trial.inputs, dt_s=trial.dt_s)
    result = analyse_discrepancy(drum, inputs=trial.inputs, measured=truth, dt_s=trial.dt_s)
    assert result.verdict == "effect_found"
    assert (result.effect.name, result.effect.location) == ("gain", "feedwater_flow")
    # noise-free: only the optimiser's tolerance limits the estimate
    assert result.effect.parameters["factor"] == pytest.approx(1.37, rel=1e-4)
    assert result.gap["reduction"] > 0.99


def test_saturation_refinement_near_crossed_limits_does_not_crash(drum):
    """Hidden-effect trial 104017 (a sensor bias/drift on the drum level): a saturation
    candidate's final refinement grid held limit pairs with low >= high, which are never
    simulated, and the search looked them up (KeyError).  The trial must now name its
    hidden effect, the known answer of the trial generator."""
    trial = make_hidden_effect_trial(drum, "sensor_bias_drift", seed=104017, n=10_000)
    result = analyse_discrepancy(drum, inputs=trial.inputs, measured=trial.measured,
                                 dt_s=trial.dt_s, seed=104017)
    assert result.verdict == "effect_found"
    assert (result.effect.name, result.effect.location) == (trial.effect.name,
                                                             trial.effect.location)
    # AR(1)/white noise at 10-30 % of the level's std over 1e4 samples: the offset
    # (22.45) is good to ~2 % and the drift (-1.10 per h) to ~20 %
    assert result.effect.parameters["bias"] == pytest.approx(trial.effect.parameters["bias"],
                                                             rel=0.05)
    assert result.effect.parameters["drift_per_h"] == pytest.approx(
        trial.effect.parameters["drift_per_h"], rel=0.25)


def test_hidden_effects_are_visible_in_the_held_out_third(boiler):
    """Trial 106010 first drew a deadband at `fuel` that the PI loop's integrator
    absorbed exactly after ~5500 samples (truth = nominal to 1e-14 on the held-out
    third): no held-out selection can judge that.  The generator redraws such effects;
    the drawn effect must shrink the last third's gap (noise + effect against noise alone,
    recomputed here from the truth) by at least TRIAL_GAP_REDUCTION."""
    from pipeline.simulated.effect_trials import HOLDOUT_FRACTION, TRIAL_GAP_REDUCTION

    trial = make_hidden_effect_trial(boiler, "deadband", seed=106010, n=10_000)
    nominal = simulate(boiler, {k: trial.inputs[k] for k in boiler.inputs}, dt_s=trial.dt_s)
    held = slice(10_000 - round(HOLDOUT_FRACTION * 10_000), None)
    (o,) = boiler.outputs
    sigma = trial.noise["relative_std"] * np.std(trial.truth[o])
    effect_ms = np.mean((trial.truth[o][held] - nominal.signals[o][held]) ** 2)
    reduction = 1 - np.sqrt(sigma**2 / (sigma**2 + effect_ms))
    assert trial.redraws >= 1
    assert reduction >= TRIAL_GAP_REDUCTION


def test_each_effect_of_a_pair_trial_is_a_finding_by_the_chains_rule(boiler):
    """Pair trial 1 700 080 first drew a deadband at the controller (78 % of the
    nominal gap) and a turbine-pressure sensor drift that closed 12 % of what the
    deadband left but 3 % of the nominal gap: by the chain's rule (a later effect must
    close ``min_gap_reduction`` of the nominal gap with the sensor corrections only) a
    minor effect, so no trial.  The generator redraws such pairs: recomputed here from
    the truth (expected held-out gaps, noise of the drawn std), every effect left out
    opens the gap by at least TRIAL_GAP_REDUCTION of that reference."""
    from pipeline.simulated.effect_trials import HOLDOUT_FRACTION, TRIAL_GAP_REDUCTION, \
        make_hidden_effects_trial

    trial = make_hidden_effects_trial(boiler, ("deadband", "sensor_bias_drift"),
                                      seed=1_700_080, n=10_000)
    held = slice(10_000 - round(HOLDOUT_FRACTION * 10_000), None)
    (o,) = boiler.outputs
    sigma2 = (trial.noise["relative_std"] * np.std(trial.truth[o])) ** 2
    scale2 = np.var(trial.truth[o][held]) + sigma2

    def gap(effects):  # expected held-out RMS of the plant's model with `effects`
        model = boiler
        for e in effects:
            model = apply_effect(model, e, dt_s=trial.dt_s)
        y = simulate(model, {k: trial.inputs[k] for k in model.inputs},
                     dt_s=trial.dt_s).signals[o][held]
        for e in effects:
            if e.name == "sensor_bias_drift":
                t_h = np.arange(10_000)[held] * trial.dt_s / 3600.0
                y = y + e.parameters["bias"] + e.parameters["drift_per_h"] * t_h
        return math.sqrt((sigma2 + np.mean((trial.truth[o][held] - y) ** 2)) / scale2)

    deadband, drift = trial.effects
    assert (deadband.name, drift.name) == ("deadband", "sensor_bias_drift")
    full, reference = gap([deadband, drift]), gap([drift])
    assert full == pytest.approx(math.sqrt(sigma2 / scale2), rel=1e-9)
    assert gap([drift]) - full >= TRIAL_GAP_REDUCTION * reference
    assert gap([deadband]) - full >= TRIAL_GAP_REDUCTION * reference
    assert trial.redraws >= 1


def test_a_pair_one_effect_absorbs_when_refitted_is_no_pair_trial(drum):
    """Pair trial 1 800 001 hid gains x1.40 on the feedwater demand and x0.74 on the
    feedwater flow: in series through a linear lag they commute, so one gain of their
    product reproduces the plant exactly (checked here by simulation) and by the chain's
    rule the other is no finding -- yet with the true parameters each left out opens the
    expected gap by far more than the bar.  The generator refits the remaining effect
    before it judges (``_refitted``) and rejects the pair; a pair whose effects do not
    stand in for each other (a gain on the demand, a lag on the swell) stays."""
    from pipeline.simulated.effect_trials import (
        TRIAL_GAP_REDUCTION,
        each_needed,
        expected_gap,
        plant_outputs,
        trial_inputs,
    )

    n, dt = 6_000, 2.0
    inputs = trial_inputs(drum.name, n=n, dt_s=dt, rng=np.random.default_rng(5))
    nominal = simulate(drum, {k: inputs[k] for k in drum.inputs}, dt_s=dt)
    rel = 0.1  # noise std / output std: each gain alone opens 2-3.4 times the bar

    def outputs(effects):
        return plant_outputs(drum, effects, inputs, dt)[1]

    a = Effect("gain", "feedwater_demand", {"factor": 1.40})
    b = Effect("gain", "feedwater_flow", {"factor": 0.74})
    truth = outputs([a, b])
    product = outputs([Effect("gain", "feedwater_demand", {"factor": 1.40 * 0.74})])
    for o in drum.outputs:
        np.testing.assert_allclose(product[o], truth[o], rtol=1e-9, atol=1e-9 * np.std(truth[o]))
    bar = TRIAL_GAP_REDUCTION * expected_gap(drum, truth, nominal.signals, rel, n)
    full = expected_gap(drum, truth, truth, rel, n)
    without = [outputs([b]), outputs([a])]
    assert all(expected_gap(drum, truth, w, rel, n) - full >= bar for w in without)
    assert not each_needed(drum, [a, b], truth, without, nominal, inputs, dt_s=dt, rel=rel, n=n)

    lag = Effect("extra_lag", "swell", {"tau_s": 60.0})
    truth = outputs([a, lag])
    assert each_needed(drum, [a, lag], truth, [outputs([lag]), outputs([a])], nominal,
                        inputs, dt_s=dt, rel=rel, n=n)


def test_drawn_limits_are_met_where_the_workflow_fits_and_no_inverse_response_is_delay_like(drum):
    """The hidden-effect trials draw a saturation's limits at the 3-15 % and 85-97 %
    quantiles of the block's nominal output on the part the workflow fits (nuisance
    trials 2 107 019/023/034/037 met an upper limit only in the held-out third: nothing
    to estimate it from), and no inverse response in the Padé band around magnitude 1
    (a dead time's degenerate form, named as the dead time by design).  Counted here on
    the nominal simulation of each trial's own inputs."""
    from pipeline.simulated.effect_trials import HOLDOUT_FRACTION, make_hidden_effect_trial as make
    from pipeline.discrepancy.effects import PADE_MAGNITUDE

    n = 6_000
    fit = slice(0, n - round(HOLDOUT_FRACTION * n))
    for seed in range(8):
        trial = make(drum, "saturation", seed=90_000 + seed, n=n)
        (sat,) = trial.effects
        v = simulate(drum, {k: trial.inputs[k] for k in drum.inputs},
                     dt_s=trial.dt_s).signals[sat.location][fit]
        assert 0.029 <= np.mean(v < sat.parameters["low"]) <= 0.151
        assert 0.029 <= np.mean(v > sat.parameters["high"]) <= 0.151
    magnitudes = [make(drum, "inverse_response", seed=91_000 + s, n=n).effect.parameters["magnitude"]
                  for s in range(30)]
    assert all(0.4 <= m <= 2.0 and abs(m - 1.0) >= PADE_MAGNITUDE for m in magnitudes)
    assert min(magnitudes) < 1.0 < max(magnitudes)


def test_a_gain_and_a_dead_time_act_on_the_block_a_saturation_wrapped(boiler):
    """A later search fits a gain at ``fuel__saturation_upstream`` -- the fuel block as an
    earlier saturation wrapped it -- and reports it at ``fuel``; rebuilt from the nominal
    model the gain must act there too (pairs trial 1 800 040 stopped with an internal
    error: the gain was applied to the saturation).  Checked against the blocks
    themselves and against a simulation of the gain placed on the wrapped block by hand;
    a block that is a saturation in the model as given still takes no gain."""
    sat = Effect("saturation", "fuel", {"low": -5.0, "high": 8.0})
    wrapped = apply_effect(boiler, sat, dt_s=2.0)
    core = wrapped.block("fuel__saturation_upstream")
    both = apply_effect(wrapped, Effect("gain", "fuel", {"factor": 1.3}), dt_s=2.0)
    assert both.block("fuel") == wrapped.block("fuel")  # the saturation is untouched
    by_hand = wrapped.with_block(dataclasses.replace(
        core, **{core.GAIN_PARAMETER: 1.3 * getattr(core, core.GAIN_PARAMETER)}))
    delayed = apply_effect(wrapped, Effect("dead_time", "fuel", {"delay_s": 4.0}), dt_s=2.0)
    assert delayed.block("fuel__saturation_upstream").dead_time_s == core.dead_time_s + 4.0
    rng = np.random.default_rng(1)
    u = {k: np.cumsum(rng.standard_normal(600)) * 0.05 for k in boiler.inputs}
    got = simulate(both, u, dt_s=2.0).signals
    want = simulate(by_hand, u, dt_s=2.0).signals
    for o in boiler.outputs:
        assert np.array_equal(got[o], want[o])
    with pytest.raises(ModelError, match="no gain to scale"):
        apply_effect(by_hand.with_block(dataclasses.replace(wrapped.block("fuel"),
                                                            name="fuel2")),
                     Effect("gain", "fuel2", {"factor": 1.1}), dt_s=2.0)


def test_one_sample_dead_time_and_a_very_short_lag_are_lookalikes(boiler):
    # With a zero-order hold, a first-order lag with tau << dt IS a one-sample delay, so
    # the data cannot tell dead_time (1 sample) from extra_lag (tiny tau) at the same
    # block: the workflow names the simplest member of the tie and reports the others as
    # equivalent explanations (issue 34, build 4), not "inconclusive".
    trial = make_hidden_effect_trial(boiler, None, seed=11, n=6000)
    truth = predict_outputs(boiler, Effect("dead_time", "turbine_pressure", {"delay_s": 2.0}),
                            trial.inputs, dt_s=2.0)
    rng = np.random.default_rng(0)
    noisy = {k: v + 0.05 * np.std(v) * rng.normal(size=v.size) for k, v in truth.items()}
    result = analyse_discrepancy(boiler, inputs=trial.inputs, measured=noisy, dt_s=2.0)
    assert result.verdict == "effect_found"
    tie = [result.effects[0].candidate, *result.equivalent_effects]
    assert {"dead_time", "extra_lag"} <= {c.effect.name for c in tie}
    assert all(c.effect.location in ("turbine_pressure", *c.effect.equivalent_locations)
               or "turbine_pressure" in c.effect.equivalent_locations for c in tie)
    # the named one has the fewest parameters of the tie, and it closes the gap
    assert result.effects[0].candidate.n_parameters == min(c.n_parameters for c in tie)
    assert result.gap["holdout_rms_after"] < 0.5 * result.gap["holdout_rms_before"]
    names = [e["name"] for e in result.to_dict()["equivalent_effects"]]
    assert names == [c.effect.name for c in result.equivalent_effects]


def test_coloured_noise_alone_is_not_an_effect(drum):
    # AR(1) phi = 0.9 noise at 30 % of each output's std on the nominal model: a
    # discrepancy analysis that ignored the colour would "explain" the slow noise with
    # a drift or a lag.  (One seed: the false-positive rate is measured in the suite.)
    trial = make_hidden_effect_trial(drum, None, seed=21, n=8000)
    rng = np.random.default_rng(3)
    measured = {}
    for k, v in trial.truth.items():
        e = scipy.signal.lfilter([math.sqrt(1 - 0.81)], [1, -0.9], rng.normal(size=v.size))
        measured[k] = v + 0.3 * np.std(v) * e
    result = analyse_discrepancy(drum, inputs=trial.inputs, measured=measured, dt_s=2.0)
    assert result.verdict == "no_significant_effect"
    # the noise model found the colour: AR(1) coefficient near 0.9 on both outputs
    # (sd of the estimate ~ sqrt((1 - 0.81)/5000) = 0.006; 0.05 allows for the FIR fit)
    for out in drum.outputs:
        assert result.noise[out]["ar_order"] >= 1
        assert result.noise[out]["ar_coefficients"][0] == pytest.approx(0.9, abs=0.05)
    assert result.gap["reduction"] == 0.0


def test_circular_shift_bootstrap_p_values_are_calibrated():
    # Residual and signal are independent AR(1) (phi 0.95): an ordinary F test would
    # reject far too often.  Over 60 replicates the fraction of p < 0.1 must stay near
    # 0.1: binomial sd sqrt(0.1*0.9/60) = 0.039, so <= 0.1 + 3 sd = 0.22.
    rejections = 0
    reps = 60
    cfg = DiscrepancyConfig(n_bootstrap=19)
    for rep in range(reps):
        rng = np.random.default_rng(100 + rep)
        n = 1500
        x = scipy.signal.lfilter([1], [1, -0.95], rng.normal(size=n))
        r = scipy.signal.lfilter([1], [1, -0.95], rng.normal(size=n))
        problem = Problem(model=None, inputs={"x": x}, outputs=("y",), y=r[:, None],  # type: ignore[arg-type]
                           dt_s=1.0, n=n, fit_start=0, holdout_start=n, config=cfg,
                           settling_s=40.0, n_p=20, max_delay=10, nominal_signals={},
                           y_nominal=np.zeros((n, 1)))
        p = input_relevance(problem, r, ["x"], 0, rng)["x"]["p_value"]
        rejections += p < 0.1
    assert rejections / reps <= 0.22


# -- API contract ----------------------------------------------------------------------
def test_input_validation_messages(boiler):
    n = 1000
    good_in = {"steam_flow": np.zeros(n)}
    good_out = {"turbine_pressure": np.zeros(n)}
    with pytest.raises(ConfigError, match=r"needs inputs \['steam_flow'\]"):
        analyse_discrepancy(boiler, inputs={"flow": np.zeros(n)}, measured=good_out, dt_s=2.0)
    with pytest.raises(ConfigError, match="subset of the model outputs"):
        analyse_discrepancy(boiler, inputs=good_in, measured={"pressure": np.zeros(n)}, dt_s=2.0)
    bad = np.zeros(n)
    bad[17] = np.nan
    with pytest.raises(DataQualityError, match="first at sample 17"):
        analyse_discrepancy(boiler, inputs={"steam_flow": bad}, measured=good_out, dt_s=2.0)
    with pytest.raises(DataQualityError, match="different lengths"):
        analyse_discrepancy(boiler, inputs={"steam_flow": np.zeros(n + 1)}, measured=good_out,
                            dt_s=2.0)
    with pytest.raises(InsufficientDataError, match="too few"):
        analyse_discrepancy(boiler, inputs={"steam_flow": np.zeros(100)},
                            measured={"turbine_pressure": np.zeros(100)}, dt_s=2.0)
    with pytest.raises(ConfigError, match="dt_s"):
        analyse_discrepancy(boiler, inputs=good_in, measured=good_out, dt_s=-1.0)
    with pytest.raises(ModelError, match="not a whole number of samples"):
        analyse_discrepancy(boiler, inputs=good_in, measured=good_out, dt_s=3.0)


def test_config_validation_messages():
    with pytest.raises(ConfigError, match=r"contains unknown \['friction'\]"):
        DiscrepancyConfig(effects=("gain", "friction"))
    with pytest.raises(ConfigError, match="holdout_fraction=0.9 is invalid"):
        DiscrepancyConfig(holdout_fraction=0.9)
    with pytest.raises(ConfigError, match="initial='hot' is invalid"):
        DiscrepancyConfig(initial="hot")


def test_output_offsets_only_for_sensor_effects():
    offsets = output_offsets(Effect("gain", "x", {"factor": 2.0}), n=5, dt_s=1.0, outputs=["y"])
    np.testing.assert_array_equal(offsets["y"], np.zeros(5))
    offsets = output_offsets(Effect("sensor_bias_drift", "y", {"bias": 1.0, "drift_per_h": 3600.0}),
                             n=3, dt_s=1.0, outputs=["y", "z"])
    np.testing.assert_allclose(offsets["y"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(offsets["z"], np.zeros(3))


def test_saturation_limits_serialise_as_strings():
    d = Effect("saturation", "fuel", {"low": -math.inf, "high": 2.0}).to_dict()
    assert d["parameters"] == {"low": "-inf", "high": 2.0}
    json.dumps(d, allow_nan=False)


def test_a_candidate_whose_simulation_diverges_is_dropped_with_its_parameters(drum,
                                                                              monkeypatch):
    """Issue 34, build 6: a fitted candidate whose whole-record simulation diverges is
    dropped from the selection and listed with its parameters (``diverged``), and the
    run goes on.  The noise-free drum record of the test above, with every gain
    candidate's whole-record simulation made to diverge (what an effect that
    destabilises a loop does): the hidden gain cannot be named, it is listed as diverged
    with its fitted factor (each class once), and no error escapes."""
    import pipeline.discrepancy.fit as fit_module

    trial = make_hidden_effect_trial(drum, None, seed=5, n=6000)
    truth = predict_outputs(drum, Effect("gain", "feedwater_flow", {"factor": 1.37}),
                            trial.inputs, dt_s=trial.dt_s)
    real = fit_module.predict_with

    def diverging_gains(P, effect, inputs):
        whole = next(iter(inputs.values())).size == P.n
        return None if whole and effect.name == "gain" else real(P, effect, inputs)

    monkeypatch.setattr(fit_module, "predict_with", diverging_gains)
    # one search (the chain's joint refits simulate through the chain, not this path)
    result = analyse_discrepancy(drum, inputs=trial.inputs, measured=truth, dt_s=trial.dt_s,
                                 config=DiscrepancyConfig(max_effects=1))
    assert result.effect is None or result.effect.name != "gain"
    assert all(c.effect.name != "gain" for c in result.candidates)
    gains = {e.location: e.parameters["factor"] for e in result.diverged if e.name == "gain"}
    assert gains.get("feedwater_flow") == pytest.approx(1.37, rel=1e-3)  # fitted, then dropped
    assert len(gains) == len([e for e in result.diverged if e.name == "gain"])  # once each
    d = result.to_dict()
    assert {"name": "gain", "location": "feedwater_flow"}.items() <= d["diverged"][
        [e["location"] for e in d["diverged"]].index("feedwater_flow")].items()
