"""Tests of pipeline.readouts.characteristics against analytic step responses."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.readouts.characteristics import (
    integrating_characteristics,
    integrating_model_step,
    self_regulating_characteristics,
)
from pipeline.errors import ConfigError, DataQualityError


def fopdt(t, k, tau, theta):
    return np.where(t >= theta, k * (1 - np.exp(-(t - theta) / tau)), 0.0)


def second_order(t, k, wn, zeta):
    wd = wn * math.sqrt(1 - zeta**2)
    c = zeta / math.sqrt(1 - zeta**2)
    return k * (1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + c * np.sin(wd * t)))


# ------------------------------------------------------------------ self-regulating
@pytest.mark.parametrize("k", [2.0, -2.0])
@pytest.mark.parametrize("theta", [3.0, 3.2])
def test_first_order_plus_dead_time(k, theta):
    """K = 2, τ = 10 s, θ = 3 s (and 3.2 s, off the 0.5 s grid), sampled analytically.

    Gain: the tail (80..100 s) still lacks K e^{-(t-θ)/τ} <= 2 e^{-7.7} = 9e-4, so
    |gain - K| < 1e-3.  Times within one sample (0.5 s); with θ on the grid the dead
    time and 63 % point fall on samples and come out exact up to the tiny gain error.
    """
    dt, tau = 0.5, 10.0
    t = np.arange(201) * dt
    c = self_regulating_characteristics(fopdt(t, k, tau, theta), dt_s=dt)
    assert abs(c.gain - k) < 1e-3
    assert abs(c.dead_time_s - theta) < dt
    assert abs(c.time_constant_s - tau) < dt
    assert abs(c.settling_time_s - (theta + tau * math.log(50))) < dt  # θ + 3.91 τ
    assert c.overshoot_pct == 0.0 and math.isnan(c.peak_time_s)
    assert c.settled
    if theta == 3.0:
        assert c.dead_time_s == pytest.approx(3.0, abs=1e-9)
        assert c.time_constant_s == pytest.approx(10.0, abs=0.01)
    json.dumps(c.to_dict())


@pytest.mark.parametrize("zeta", [0.1, 0.3, 0.6])
def test_second_order_underdamped_overshoot(zeta):
    """Overshoot = exp(-πζ/sqrt(1-ζ²)) within 1 % (relative); peak at π/ω_d within dt.

    dt = 0.01 s, ω_n = 1 rad/s: the sampled peak misses the true one by at most
    dt/2, an error ~ (ω_d dt/2)² / 2 ~ 1e-5 of the peak.  The record (0..120 s) has an
    envelope e^{-ζ ω_n t} below 6e-6 in its tail at ζ = 0.1.
    """
    dt, wn, k = 0.01, 1.0, 1.5
    t = np.arange(12001) * dt
    c = self_regulating_characteristics(second_order(t, k, wn, zeta), dt_s=dt)
    expected = 100 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2))
    assert c.overshoot_pct == pytest.approx(expected, rel=0.01)
    assert abs(c.peak_time_s - math.pi / (wn * math.sqrt(1 - zeta**2))) <= dt
    assert c.gain == pytest.approx(k, rel=1e-4)
    # 2 % settling of an oscillation: the last band exit lies under the envelope time
    envelope_time = math.log(1 / (0.02 * math.sqrt(1 - zeta**2))) / (zeta * wn)
    assert c.settling_time_s <= envelope_time + dt
    assert c.settling_time_s > envelope_time - 2 * math.pi / (wn * math.sqrt(1 - zeta**2))


def test_noisy_first_order_gain_and_dead_time():
    """Independent noise σ = 0.01 per point, step_std = σ.

    Gain: mean of 41 tail points, std σ/√41 = 0.0016; 5 std = 0.008.  Dead-time
    threshold max(1 % of 2, 2σ) = 0.02; the rise passes it within one sample of θ
    (h(θ + 0.5 s) = 0.0975 ≈ 10σ).  Walking back from the half-gain point, the start
    moves earlier only if the sample at θ itself is a > 2σ spike (p = 4.6 %) — then by
    one more sample unless its neighbour spikes too (p ≈ 0.2 %) — so 2 samples
    covers it.  (Over 30 seeds: max dead-time error 0.5 s, max gain error 3.4 std.)
    """
    dt = 0.5
    t = np.arange(201) * dt
    sigma = 0.01
    rng = np.random.default_rng(12)
    h = fopdt(t, 2.0, 10.0, 3.0) + sigma * rng.standard_normal(t.size)
    c = self_regulating_characteristics(h, dt_s=dt, step_std=np.full(t.size, sigma))
    assert abs(c.gain - 2.0) < 5 * sigma / math.sqrt(41)
    assert c.gain_std == pytest.approx(sigma)
    assert abs(c.dead_time_s - 3.0) <= 2 * dt


def test_inverse_response_dead_time_is_the_start_of_the_dip():
    """(1 - 3s)/((10s+1)(2s+1)) delayed 2 s: the dip (to -0.10) and its swing back
    through zero belong to the response; the dead time is where the dip starts."""
    dt = 0.5
    t = np.arange(241) * dt
    tp = np.maximum(t - 2.0, 0.0)
    # partial fractions of G(s)/s: h = 1 + a e^{-t/10} + b e^{-t/2} with the residues
    # a = (1 + 0.3)/((1 - 0.2)(-0.1)·10) = -1.625, b = (1 + 1.5)/((1 - 5)(-0.5)·2) = 0.625
    a = (1 - 3 * (-0.1)) / ((2 * (-0.1) + 1) * (-0.1)) / 10
    b = (1 - 3 * (-0.5)) / ((10 * (-0.5) + 1) * (-0.5)) / 2
    assert 1 + a + b == pytest.approx(0.0, abs=1e-12)  # h(0+) = 0
    h = np.where(t >= 2.0, 1 + a * np.exp(-tp / 10) + b * np.exp(-tp / 2), 0.0)
    assert h.min() < -0.09  # a visible wrong-way dip
    c = self_regulating_characteristics(h, dt_s=dt)
    assert c.dead_time_s == pytest.approx(2.0, abs=dt)
    assert c.gain == pytest.approx(1.0, abs=1e-3)


def test_no_response_gives_nan_times():
    h = 1e-3 * np.random.default_rng(0).standard_normal(100)
    c = self_regulating_characteristics(h, dt_s=1.0, step_std=np.full(100, 1e-3))
    assert math.isnan(c.dead_time_s) and math.isnan(c.time_constant_s)
    assert not c.settled
    assert c.to_dict()["dead_time_s"] is None


def test_unsettled_response_is_flagged():
    t = np.arange(50) * 1.0
    c = self_regulating_characteristics(fopdt(t, 1.0, 30.0, 0.0), dt_s=1.0)
    assert not c.settled


@settings(max_examples=40, deadline=None)
@given(shift=st.integers(0, 30), scale=st.floats(0.05, 50).map(lambda v: v) | st.floats(-50, -0.05))
def test_time_shift_adds_dead_time_and_scaling_scales_gain(shift, scale):
    dt = 0.5
    t = np.arange(240) * dt
    base = fopdt(t, 1.0, 6.0, 2.0) + 0.3 * fopdt(t, -1.0, 2.0, 1.0)  # non-trivial shape
    shifted = scale * np.concatenate([np.zeros(shift), base])[: t.size + shift]
    a = self_regulating_characteristics(base, dt_s=dt)
    b = self_regulating_characteristics(shifted, dt_s=dt)
    assert b.dead_time_s == pytest.approx(a.dead_time_s + shift * dt, abs=1e-9)
    assert b.time_constant_s == pytest.approx(a.time_constant_s, abs=1e-6)
    # the shifted record's tail covers other lags: the gain (and band) move by ~1e-7
    assert b.settling_time_s == pytest.approx(a.settling_time_s + shift * dt, abs=1e-4)
    assert b.gain == pytest.approx(scale * a.gain, rel=1e-6)
    assert b.overshoot_pct == pytest.approx(a.overshoot_pct, abs=1e-6)


# ------------------------------------------------------------------- integrating
def test_model_step_matches_closed_forms():
    t = np.linspace(0, 50, 501)
    # integrator + one lag: K (t - τ (1 - e^{-t/τ}))
    np.testing.assert_allclose(
        integrating_model_step(t, rate=0.5, dead_time_s=0, t1_s=8, t2_s=0),
        0.5 * (t - 8 * (1 - np.exp(-t / 8))), atol=1e-12,
    )
    # equal lags use the double-pole limit: continuous across T1 = T2
    near = integrating_model_step(t, rate=1, dead_time_s=0, t1_s=5 * (1 + 1e-4), t2_s=5)
    equal = integrating_model_step(t, rate=1, dead_time_s=0, t1_s=5, t2_s=5)
    np.testing.assert_allclose(near, equal, atol=1e-3)
    # inverse response K (t - (τ + a)(1 - e^{-t/τ}))
    np.testing.assert_allclose(
        integrating_model_step(t, rate=1, dead_time_s=0, t1_s=10, t2_s=0, ta_s=5),
        t - 15 * (1 - np.exp(-t / 10)), atol=1e-12,
    )


def test_pure_integrator_with_dead_time():
    """h = K (t - θ)+, K = 0.3, θ = 4 s."""
    dt = 0.5
    t = np.arange(121) * dt
    h = 0.3 * np.maximum(t - 4.0, 0)
    c = integrating_characteristics(h, dt_s=dt)
    assert c.rate == pytest.approx(0.3, rel=1e-9)
    assert c.dead_time_s == pytest.approx(4.0, abs=0.05 * dt)
    assert c.time_constant_1_s + c.time_constant_2_s + c.zero_time_constant_s < 0.1 * dt
    assert c.apparent_delay_s == pytest.approx(4.0, abs=0.05 * dt)
    assert c.inverse_peak == 0.0 and math.isnan(c.inverse_peak_time_s)
    assert c.fit_rms < 1e-6
    json.dumps(c.to_dict())


def test_integrator_plus_lag_with_dead_time():
    """K = 0.5, θ = 2 s, τ = 8 s.

    The rate is the tail slope (90..120 s), short of K by K e^{-(t-θ)/τ} <= 1.7e-5
    relative.  A lag far below one sample (0.5 s) looks like dead time on the grid, so
    the split of the start between T_d and a tiny T_2 is only fixed to within a fraction
    of a sample, their sum much better.
    """
    dt = 0.5
    t = np.arange(241) * dt
    h = integrating_model_step(t, rate=0.5, dead_time_s=2.0, t1_s=8.0, t2_s=0.0)
    c = integrating_characteristics(h, dt_s=dt)
    assert c.rate == pytest.approx(0.5, rel=2e-5)
    assert c.dead_time_s == pytest.approx(2.0, abs=0.25 * dt)
    assert c.dead_time_s + c.time_constant_2_s == pytest.approx(2.0, abs=0.01)
    assert c.time_constant_1_s == pytest.approx(8.0, rel=0.01)
    assert c.time_constant_2_s < 0.25 * dt and c.zero_time_constant_s == 0.0
    assert c.apparent_delay_s == pytest.approx(10.0, rel=0.01)


def test_integrator_two_lags_negative_rate_given():
    """K = -1.2 (given, as from the estimator), T_d = 3, T_1 = 10, T_2 = 4 s."""
    dt = 0.5
    t = np.arange(301) * dt
    h = integrating_model_step(t, rate=-1.2, dead_time_s=3.0, t1_s=10.0, t2_s=4.0)
    c = integrating_characteristics(h, dt_s=dt, rate=-1.2, rate_std=0.01)
    assert c.rate == -1.2 and c.rate_std == 0.01
    assert c.dead_time_s == pytest.approx(3.0, abs=0.02)
    assert c.time_constant_1_s == pytest.approx(10.0, rel=0.01)
    assert c.time_constant_2_s == pytest.approx(4.0, rel=0.01)
    assert c.inverse_peak == 0.0


def test_integrator_inverse_response_peak():
    """G(s) = K (1 - a s) / (s (1 + τ s)): h = K [t - (τ + a)(1 - e^{-t/τ})].

    h' = K [1 - ((τ+a)/τ) e^{-t/τ}] = 0 at t_L = τ ln(1 + a/τ), where
    h(t_L) = -K [a - τ ln(1 + a/τ)], so L = K (a - τ ln(1 + a/τ)).
    K = 1, a = 5 s, τ = 10 s: L = 0.9453 at t_L = 4.055 s.  Sampled every 0.5 s the data
    minimum misses it by at most h''·(dt/2)²/2 = 0.1·0.0625/2 = 0.003 (0.3 %).
    """
    k, a, tau, dt = 1.0, 5.0, 10.0, 0.5
    t = np.arange(301) * dt
    h = k * (t - (tau + a) * (1 - np.exp(-t / tau)))
    peak = k * (a - tau * math.log(1 + a / tau))
    t_peak = tau * math.log(1 + a / tau)
    c = integrating_characteristics(h, dt_s=dt)
    assert c.inverse_peak == pytest.approx(peak, rel=0.02)
    assert abs(c.inverse_peak_time_s - t_peak) <= dt
    assert c.inverse_peak_model == pytest.approx(peak, rel=0.02)
    assert c.zero_time_constant_s == pytest.approx(a, rel=0.01)
    assert c.time_constant_1_s == pytest.approx(tau, rel=0.01)
    assert c.dead_time_s < 0.05


def test_integrator_inverse_response_with_noise_threshold():
    """A wrong-way dip smaller than 2 std is not reported."""
    t = np.arange(301) * 0.5
    h = t - 10.5 * (1 - np.exp(-t / 10))  # a = 0.5 s: L = 0.5 - 10 ln 1.05 = 0.0121
    c_clean = integrating_characteristics(h, dt_s=0.5)
    assert c_clean.inverse_peak == pytest.approx(0.5 - 10 * math.log(1.05), rel=0.02)
    c_noisy = integrating_characteristics(h, dt_s=0.5, step_std=np.full(t.size, 0.01))
    assert c_noisy.inverse_peak == 0.0


def test_errors():
    with pytest.raises(DataQualityError, match="1-D response of at least 3 lags"):
        self_regulating_characteristics(np.ones((2, 3)), dt_s=1.0)
    with pytest.raises(ConfigError, match="dt_s must be a positive number"):
        self_regulating_characteristics(np.ones(10), dt_s=0.0)
    with pytest.raises(DataQualityError, match="step_std has shape"):
        self_regulating_characteristics(np.ones(10), dt_s=1.0, step_std=np.ones(9))
    with pytest.raises(ConfigError, match="tail_fraction must lie in"):
        self_regulating_characteristics(np.ones(10), dt_s=1.0, tail_fraction=1.5)
    with pytest.raises(DataQualityError, match="does not ramp"):
        integrating_characteristics(np.ones(20), dt_s=1.0)
    with pytest.raises(DataQualityError, match="NaN/inf"):
        integrating_characteristics(np.array([0, 1, np.nan, 3.0]), dt_s=1.0)


def test_quantities_that_do_not_exist_are_omitted_with_the_reason():
    """A response that peaks and returns near zero (a washout, e.g. a loop that rejects
    the step) has no overshoot: stored as null with the reason, not 8524 %."""
    t = np.arange(60.0)
    h = 0.8 * (np.exp(-t / 20) - np.exp(-t / 3)) + 0.01  # peak ~0.5, final ~0.03
    s = np.full(60, 0.002)
    c = self_regulating_characteristics(h, dt_s=1.0, step_std=s, gain=float(h[-1]),
                                        gain_std=0.002)
    d = c.to_dict()
    assert d["overshoot_pct"] is None and d["time_constant_s"] is None
    assert "returns towards it" in d["undefined"]["overshoot_pct"]
    assert d["gain"] == pytest.approx(h[-1])  # the given gain, not the tail mean
    flat = self_regulating_characteristics(0.001 * np.sin(t), dt_s=1.0, step_std=s,
                                           gain=0.0005, gain_std=0.002)
    fd = flat.to_dict()
    assert fd["dead_time_s"] is None and "within 2 standard deviations" in \
        fd["undefined"]["dead_time_s"]
    # a normal first-order response has every quantity
    ok = self_regulating_characteristics(2 * (1 - np.exp(-t / 5)), dt_s=1.0)
    assert ok.to_dict()["undefined"] == {}
