"""Transfer functions with dead time fitted to step responses, and their exact sampled
form (pipeline/readouts/lti_fit.py).

Oracles are analytic step responses and python-control's own zero-order-hold
discretisation, never the code under test; the lag times are ``(l - 1/2)·dt``.
"""

from __future__ import annotations

import control
import numpy as np
import pytest

from pipeline.errors import ConfigError, DataQualityError
from pipeline.readouts.lti_fit import (
    fit_step_model,
    fopdt_step,
    rational_step,
    sampled_step,
    sopdt_step,
    zoh_with_delay,
)

DT = 1.0
T = (np.arange(1, 151) - 0.5) * DT  # lag times of 150 lags


def _ramp(t, delay):
    return np.maximum(t - delay, 0.0)


# ------------------------------------------------------------ exact sampled form
@pytest.mark.parametrize("delay", [0.0, 0.2, 0.5, 2.0, 3.7])
@pytest.mark.parametrize("case", ["fopdt", "underdamped", "lead_lag", "integrator"])
def test_sampled_step_is_the_continuous_response_at_the_lag_times(case, delay):
    """Analytic responses; delays on a lag time, between, below half a sample (the
    biproper sampled form) and zero."""
    num, den, exact = {
        "fopdt": ([0.1], [1.0, 0.05], fopdt_step(T, gain=2.0, time_constant_s=20.0,
                                                 delay_s=delay)),
        "underdamped": ([1 / 64], [1.0, 2 * 0.3 / 8, 1 / 64],
                        sopdt_step(T, gain=1.0, natural_period_s=8.0, damping=0.3,
                                   delay_s=delay)),
        # (3s + 1)/(10s + 1): 1 - 0.7 e^{-t/10}, a jump of 0.3 at the delay
        "lead_lag": ([0.3, 0.1], [1.0, 0.1],
                     np.where(T >= delay, 1 - 0.7 * np.exp(-_ramp(T, delay) / 10), 0.0)),
        "integrator": ([0.5], [1.0, 0.0], 0.5 * _ramp(T, delay)),
    }[case]
    got = sampled_step(num, den, delay_s=delay, dt_s=DT, n_lags=T.size)
    np.testing.assert_allclose(got, exact, atol=1e-10 * max(1.0, np.abs(exact).max()))
    np.testing.assert_allclose(rational_step(T, num, den, delay_s=delay), exact,
                               atol=1e-9 * max(1.0, np.abs(exact).max()))


@pytest.mark.parametrize("d", [0, 1, 4])
def test_zoh_with_delay_equals_python_control_on_whole_sample_delays(d):
    """python-control's ZOH discretisation times z^-d is the independent oracle."""
    num, den = [0.5, 0.2], [1.0, 0.7, 0.1]
    num_z, den_z = zoh_with_delay(num, den, delay_s=d * DT, dt_s=DT)
    ours = control.tf(num_z, den_z, DT)
    ref = control.sample_system(control.tf(num, den), DT, method="zoh") * \
        control.tf([1.0], [1.0] + [0.0] * d, DT)
    k = np.arange(60) * DT
    np.testing.assert_allclose(control.step_response(ours, T=k).outputs,
                               control.step_response(ref, T=k).outputs, atol=1e-12)


def test_zoh_with_delay_refuses_an_advance_beyond_a_sample():
    with pytest.raises(ConfigError, match="delay_s must be >= -dt_s"):
        zoh_with_delay([1.0], [1.0, 1.0], delay_s=-1.5, dt_s=1.0)


# ---------------------------------------------------------------------- the rule
def test_exact_fopdt_is_recovered_and_taken_first():
    h = fopdt_step(T, gain=2.0, time_constant_s=20.0, delay_s=3.7)
    fit = fit_step_model(h, dt_s=DT)
    assert fit.kind == "fopdt"
    assert fit.parameters["gain"] == pytest.approx(2.0, rel=1e-6)
    assert fit.parameters["time_constant_s"] == pytest.approx(20.0, rel=1e-6)
    assert fit.delay_s == pytest.approx(3.7, abs=1e-6)
    assert fit.fit_rms < 1e-8


@pytest.mark.parametrize("delay", [3e-4, 0.004])
def test_a_delay_below_the_resolution_is_zero_and_its_pade_form_stays_finite(delay):
    """A dead time under DELAY_RESOLUTION of a sample is reported as 0 (the demo's
    pressure<-steam pair once got 3e-4 s, whose Padé(6) form stepped to NaN); the stated
    fit error is then that of the zero-delay model, still tiny (slope·delay)."""
    from pipeline.adapters.control_lti import pade_transfer_function
    from pipeline.readouts.lti_fit import DELAY_RESOLUTION

    h = fopdt_step(T, gain=2.0, time_constant_s=3.0, delay_s=delay)
    fit = fit_step_model(h, dt_s=DT)
    assert delay < DELAY_RESOLUTION * DT and fit.delay_s == 0.0
    assert fit.fit_rms < 2.0 / 3.0 * delay  # the response's largest slope times the delay
    g = pade_transfer_function(fit.num, fit.den, delay_s=fit.delay_s, order=6)
    y = control.step_response(g, T=np.arange(301) * DT / 2).outputs[1::2]
    assert np.all(np.isfinite(y)) and np.abs(y - h).max() < 2.0 / 3.0 * delay + 1e-6


@pytest.mark.parametrize("shift", [0, 3])
@pytest.mark.parametrize("scale", [1.0, -0.5])
def test_dead_time_follows_a_time_shift_and_the_gain_a_scaling(shift, scale):
    """Property: prepending ``shift`` zero lags adds ``shift·dt`` to the dead time;
    scaling the response scales the gain and leaves the times."""
    h = fopdt_step(T, gain=2.0, time_constant_s=20.0, delay_s=1.3)
    h = scale * np.r_[np.zeros(shift), h[: T.size - shift]]
    fit = fit_step_model(h, dt_s=DT)
    assert fit.kind == "fopdt"
    assert fit.delay_s == pytest.approx(1.3 + shift * DT, abs=1e-6)
    assert fit.parameters["gain"] == pytest.approx(2.0 * scale, rel=1e-6)
    assert fit.parameters["time_constant_s"] == pytest.approx(20.0, rel=1e-6)


def test_underdamped_sopdt_is_recovered():
    h = sopdt_step(T, gain=1.0, natural_period_s=8.0, damping=0.3, delay_s=5.0)
    fit = fit_step_model(h, dt_s=DT)
    assert fit.kind == "sopdt"  # an FOPDT misses the overshoot by 12 % RMS
    assert fit.parameters["natural_period_s"] == pytest.approx(8.0, rel=1e-5)
    assert fit.parameters["damping"] == pytest.approx(0.3, rel=1e-5)
    assert fit.delay_s == pytest.approx(5.0, abs=1e-5)
    assert fit.trials[1]["kind"] == "fopdt" and fit.trials[1]["fit_rms"] > 0.1


def test_lead_lag_response_needs_the_section7_rational_fit():
    """2(30s + 1)/((10s + 1)(5s + 1)): the zero makes the response overshoot its gain
    without oscillating; no FOPDT/SOPDT fits it, the rational (2, 1) candidate started
    from the §7 fit does."""
    num, den = [1.2, 0.04], [1.0, 0.3, 0.02]  # the same, monic
    h = rational_step(T, num, den, delay_s=1.0)
    assert h.max() > 1.3 * h[-1]
    fit = fit_step_model(h, dt_s=DT)
    assert fit.kind == "rational" and (fit.parameters["n"], fit.parameters["m"]) == (2, 1)
    np.testing.assert_allclose(fit.num, num, rtol=1e-5)
    np.testing.assert_allclose(fit.den, den, rtol=1e-5)
    assert fit.delay_s == pytest.approx(1.0, abs=1e-5)
    assert fit.parameters["gain"] == pytest.approx(2.0, rel=1e-5)
    assert fit.fit_rms_rel < 1e-6
    assert [t["kind"] for t in fit.trials[:3]] == ["zero", "fopdt", "sopdt"]
    assert min(t["fit_rms"] for t in fit.trials[1:3]) > 0.01


def test_within_the_noise_the_simpler_model_wins():
    """SOPDT data (τ 15 s and 6 s) with a step_std of 0.01: an FOPDT misses by 0.016 RMS,
    within 2σ, so the FOPDT is taken; with a step_std 10x smaller it is not."""
    h = sopdt_step(T, gain=-1.5, time_constants_s=(15.0, 6.0), delay_s=2.2)
    loose = fit_step_model(h, dt_s=DT, step_std=np.full(T.size, 0.01))
    assert loose.kind == "fopdt" and loose.within_noise
    assert loose.fit_rms <= loose.tolerance == pytest.approx(0.02)
    tight = fit_step_model(h, dt_s=DT, step_std=np.full(T.size, 0.001))
    assert tight.kind == "sopdt" and tight.parameters["time_constants_s"] == pytest.approx(
        [15.0, 6.0], rel=1e-5)


def test_a_response_inside_its_noise_is_exported_as_zero():
    rng = np.random.default_rng(3)
    std = np.full(T.size, 0.05)
    h = np.cumsum(rng.normal(0, 0.05 / np.sqrt(T.size), T.size))  # a random walk, σ <= 0.05
    fit = fit_step_model(h, dt_s=DT, step_std=std)
    assert fit.kind == "zero" and fit.within_noise and len(fit.trials) == 1
    assert sampled_step(fit.num, fit.den, delay_s=fit.delay_s, dt_s=DT, n_lags=3).tolist() == \
        [0.0, 0.0, 0.0]


def test_integrating_pair_gets_the_integrating_model():
    """K e^{-θs}/(s(τs + 1)): rate K, the lag and dead time separated (θ + τ = 7 s)."""
    K, tau, theta = 0.01, 4.0, 3.0
    tp = _ramp(T, theta)
    h = K * (tp - tau * (1 - np.exp(-tp / tau)))
    fit = fit_step_model(h, dt_s=DT, integrating=True, rate=K)
    assert fit.kind == "integrating"
    assert fit.parameters["rate"] == pytest.approx(K, rel=1e-9)
    assert fit.delay_s + fit.parameters["time_constant_1_s"] + \
        fit.parameters["time_constant_2_s"] == pytest.approx(theta + tau, abs=0.05)
    assert fit.fit_rms_rel < 1e-3


def test_bad_responses_are_refused_with_the_reason():
    with pytest.raises(DataQualityError, match="at least 3 lags"):
        fit_step_model([1.0, 2.0], dt_s=1.0)
    with pytest.raises(DataQualityError, match="step_std must be finite"):
        fit_step_model(np.ones(5), dt_s=1.0, step_std=np.ones(4))
    with pytest.raises(ConfigError, match="dt_s must be a positive"):
        fit_step_model(np.ones(5), dt_s=0.0)


def test_a_numeric_failure_of_the_fit_leaves_the_model_out_with_the_reason(monkeypatch):
    """The run fits the reported model in its summary (checks.json); a numeric failure
    inside the fit must leave the pair's transfer function out, not stop the run."""
    import pipeline.readouts.lti_fit as lti

    def broken(*_args, **_kwargs):
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    monkeypatch.setattr(lti, "fit_step_model", broken)
    why = lti.reported_model(fopdt_step(T, gain=2.0, time_constant_s=20.0, delay_s=3.0),
                             dt_s=DT, value=2.0, std=0.01)
    assert why == ("no transfer function: the fit failed (LinAlgError: Eigenvalues did not "
                   "converge)")
    assert lti.model_record(why) == {"left_out": why}
    assert lti.reported_model(None, dt_s=DT, value=2.0, std=0.01,
                              stored=lti.model_record(why)) == why


def test_a_stored_fit_reads_back_as_the_fit():
    """What the run stores (model_record, through JSON) is the fit the export uses."""
    import json

    from pipeline.readouts.lti_fit import model_record, reported_model

    h = fopdt_step(T, gain=2.0, time_constant_s=20.0, delay_s=3.0)
    fit = reported_model(h, dt_s=DT, value=2.0, std=0.01)
    back = reported_model(None, dt_s=DT, value=2.0, std=0.01,
                          stored=json.loads(json.dumps(model_record(fit))))
    assert (back.kind, back.delay_s, back.parameters, back.rule) == \
        (fit.kind, fit.delay_s, fit.parameters, fit.rule)
    np.testing.assert_array_equal(back.num, fit.num)
    np.testing.assert_array_equal(back.den, fit.den)
    assert back.fit_rms == fit.fit_rms and back.tolerance == fit.tolerance
