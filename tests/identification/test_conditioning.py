"""Tests of pipeline.identification.conditioning: known answers and the same-transform-on-both property."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.identification.conditioning import (
    METHODS,
    Conditioning,
    condition,
    detrend_linear,
    difference,
    highpass,
    highpass_gain,
    remove_mean,
)
from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError


def test_detrend_removes_a_linear_ramp_exactly():
    dt = 0.5
    t = np.arange(1001) * dt
    x = np.column_stack([3.0 + 0.2 * t, -1.0 - 4e-3 * t])
    y = 7.0 - 0.05 * t
    c = condition(x, y, method="detrend", dt_s=dt)
    np.testing.assert_allclose(c.x, 0.0, atol=1e-10)
    np.testing.assert_allclose(c.y, 0.0, atol=1e-10)
    np.testing.assert_allclose(c.x_slope_per_s, [0.2, -4e-3], rtol=1e-10)
    np.testing.assert_allclose(c.y_slope_per_s, [-0.05], rtol=1e-10)
    np.testing.assert_allclose(c.x_offset, x.mean(axis=0), rtol=1e-12)
    assert c.y.shape == (1001,)  # 1-D stays 1-D


def test_detrend_keeps_the_fluctuation_around_the_line():
    t = np.arange(400.0)
    wave = np.sin(2 * np.pi * t / 40)  # 10 whole periods: orthogonal to 1 and nearly to t
    out, mean, slope = detrend_linear(wave + 5 + 0.01 * t, dt_s=1.0)
    expected = scipy.signal.detrend(wave)  # what is left of the wave itself
    np.testing.assert_allclose(out, expected, atol=1e-12)
    assert slope == pytest.approx(0.01 + np.polyfit(t, wave, 1)[0], rel=1e-9)
    assert mean == pytest.approx(5 + 0.01 * t.mean() + wave.mean(), rel=1e-12)


def test_difference_of_a_known_sequence():
    k = np.arange(10.0)
    np.testing.assert_array_equal(difference(k**2, kdiff1=2), 4 * k[:8] + 4)
    c = condition(k**2, np.column_stack([k, -k]), method="difference", dt_s=1.0, kdiff1=3)
    np.testing.assert_array_equal(c.x, 6 * k[:7] + 9)
    np.testing.assert_array_equal(c.y, np.tile([3.0, -3.0], (7, 1)))
    assert c.samples_dropped == 3 and dict(c.params) == {"kdiff1": 3}


def test_difference_commutes_with_the_plant_filter():
    """Differencing both sides keeps y = Δh * x with the same Δh (exactly)."""
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.standard_normal(500))  # drifting input
    delta_h = np.array([0.0, 0.5, 0.3, 0.15, 0.05])
    y = scipy.signal.lfilter(delta_h, [1.0], x)
    c = condition(x, y, method="difference", dt_s=1.0, kdiff1=7)
    refit = scipy.signal.lfilter(delta_h, [1.0], c.x)
    np.testing.assert_allclose(c.y[4:], refit[4:], rtol=1e-12, atol=1e-10)


def test_highpass_removes_slow_and_keeps_fast_sinusoid_by_filter_gain():
    """Zero-phase: each steady sinusoid comes out scaled by |H(f)|² with no phase shift.

    dt = 0.1 s, cutoff 0.01 Hz, order 2: the filter's transients decay in a few
    1/(2π fc) ≈ 16 s, so on the middle 60 % of a 20 000 s record (edges > 4000 s away)
    they are below round-off.
    """
    dt, fc = 0.1, 0.01
    t = np.arange(200_000) * dt
    f_slow, f_fast = 0.0005, 0.1
    slow = 2.0 * np.sin(2 * np.pi * f_slow * t)
    fast = 0.5 * np.cos(2 * np.pi * f_fast * t + 0.3)
    out = highpass(slow + fast + 10.0, dt_s=dt, cutoff_hz=fc, order=2)
    g_slow, g_fast = highpass_gain([f_slow, f_fast], dt_s=dt, cutoff_hz=fc, order=2)
    # Butterworth single-pass power gain q/(1+q), q = (f/fc)^(2n), is the forward-backward
    # amplitude gain (bilinear warping at these f·dt changes it by < 1 %).
    q = (np.array([f_slow, f_fast]) / fc) ** 4
    np.testing.assert_allclose([g_slow, g_fast], q / (1 + q), rtol=1e-2)
    mid = slice(40_000, 160_000)
    np.testing.assert_allclose(out[mid], g_slow * slow[mid] + g_fast * fast[mid], atol=1e-6)
    assert g_slow < 1e-5 and g_fast > 0.999


def test_highpass_cutoff_as_period_is_the_same_filter():
    x = np.random.default_rng(1).standard_normal((3000, 2))
    a = condition(x, x[:, 0], method="highpass", dt_s=1.0, cutoff_hz=0.02, order=3)
    b = condition(x, x[:, 0], method="highpass", dt_s=1.0, cutoff_period_s=50.0, order=3)
    np.testing.assert_array_equal(a.x, b.x)
    assert dict(b.params) == {"cutoff_hz": 0.02, "order": 3}


@pytest.mark.parametrize(
    "method,params",
    [
        ("none", {}),
        ("mean", {}),
        ("detrend", {}),
        ("difference", {"kdiff1": 5}),
        ("highpass", {"cutoff_period_s": 200.0, "order": 2}),
    ],
)
def test_inputs_and_outputs_get_the_same_transform(method, params):
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal((2000, 2)), axis=0) + [5.0, -2.0]
    y = np.column_stack([x[:, 1], x[:, 0], 2 * x[:, 0] + 1.0])
    c = condition(x, y, method=method, dt_s=1.0, **params)
    np.testing.assert_allclose(c.y[:, 0], c.x[:, 1], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(c.y[:, 1], c.x[:, 0], rtol=1e-12, atol=1e-9)
    if method != "none":  # every other method removes the constant 1.0
        np.testing.assert_allclose(c.y[:, 2], 2 * c.x[:, 0], rtol=1e-9, atol=1e-9)
    assert c.method == method
    json.dumps(c.to_dict())


@settings(max_examples=60, deadline=None)
@given(
    x=arrays(np.float64, (40, 2), elements=st.floats(-100, 100)),
    y=arrays(np.float64, (40,), elements=st.floats(-100, 100)),
    cx=st.floats(-1e4, 1e4),
    cy=st.floats(-1e4, 1e4),
)
def test_mean_removal_is_offset_invariant(x, y, cx, cy):
    a = condition(x, y, method="mean", dt_s=1.0)
    b = condition(x + cx, y + cy, method="mean", dt_s=1.0)
    # round-off of the shifted mean: ~ eps * |offset| per sample
    np.testing.assert_allclose(b.x, a.x, atol=1e-9 * (1 + abs(cx)))
    np.testing.assert_allclose(b.y, a.y, atol=1e-9 * (1 + abs(cy)))
    np.testing.assert_allclose(b.x_offset - a.x_offset, cx, atol=1e-9 * (1 + abs(cx)))
    np.testing.assert_allclose(np.mean(b.x, axis=0), 0.0, atol=1e-9 * (1 + abs(cx)))


@settings(max_examples=40, deadline=None)
@given(
    x=arrays(np.float64, (50,), elements=st.floats(-10, 10)),
    offset=st.floats(-1e3, 1e3),
    slope=st.floats(-10, 10),
)
def test_detrend_is_invariant_to_added_lines(x, offset, slope):
    t = np.arange(50.0)
    a = condition(x, x, method="detrend", dt_s=2.0)
    b = condition(x + offset + slope * t, x, method="detrend", dt_s=2.0)
    np.testing.assert_allclose(b.x, a.x, atol=1e-9 * (1 + abs(offset) + 50 * abs(slope)))
    added = b.x_slope_per_s - a.x_slope_per_s
    assert added == pytest.approx(slope / 2.0, abs=1e-9 * (1 + abs(slope)))


def test_remove_mean_returns_the_mean():
    out, m = remove_mean(np.array([[1.0, 10.0], [3.0, 20.0]]))
    np.testing.assert_array_equal(m, [2.0, 15.0])
    np.testing.assert_array_equal(out, [[-1.0, -5.0], [1.0, 5.0]])


def test_conditioning_spec_maps_onto_condition():
    x = np.random.default_rng(4).standard_normal((300, 1))
    spec = Conditioning(method="difference", kdiff1=4)
    assert spec.params == {"kdiff1": 4}
    np.testing.assert_array_equal(spec.apply(x, x, dt_s=1.0).x, difference(x, kdiff1=4))
    hp = Conditioning(method="highpass", cutoff_period_s=60.0, order=2)
    np.testing.assert_array_equal(
        hp.apply(x, x, dt_s=1.0).y, highpass(x, dt_s=1.0, cutoff_hz=1 / 60.0, order=2)
    )
    assert Conditioning().method == "mean" and Conditioning().params == {}


def test_errors_name_the_problem_and_the_fix():
    x = np.arange(100.0)
    allowed = ", ".join(METHODS)
    msg = f"unknown conditioning method 'lowpass'; allowed: {allowed}"
    with pytest.raises(ConfigError, match=msg):
        condition(x, x, method="lowpass", dt_s=1.0)
    with pytest.raises(ConfigError, match=r"'mean' takes no parameter\(s\) \['kdiff1'\]"):
        condition(x, x, method="mean", dt_s=1.0, kdiff1=2)
    with pytest.raises(ConfigError, match="kdiff1 .* must be a positive integer; got None"):
        condition(x, x, method="difference", dt_s=1.0)
    with pytest.raises(InsufficientDataError, match="kdiff1=100 leaves no samples"):
        condition(x, x, method="difference", dt_s=1.0, kdiff1=100)
    with pytest.raises(ConfigError, match="exactly one of cutoff_hz or cutoff_period_s"):
        condition(x, x, method="highpass", dt_s=1.0)
    with pytest.raises(ConfigError, match=r"cutoff 0.6 Hz must lie in \(0, Nyquist = 0.5 Hz\)"):
        condition(x, x, method="highpass", dt_s=1.0, cutoff_hz=0.6)
    with pytest.raises(InsufficientDataError, match="needs more than .* samples; the record has"):
        condition(x[:10], x[:10], method="highpass", dt_s=1.0, cutoff_hz=0.1, order=4)
    with pytest.raises(DataQualityError, match="x has 100 samples but y has 99"):
        condition(x, x[:99], method="mean", dt_s=1.0)
    bad = x.copy()
    bad[17] = np.nan
    with pytest.raises(DataQualityError, match="y column 0 has 1 NaN/inf value.*sample 17"):
        condition(x, bad, method="mean", dt_s=1.0)
    with pytest.raises(ConfigError, match="dt_s must be a positive number"):
        condition(x, x, method="mean", dt_s=-1.0)
    with pytest.raises(ConfigError, match="'highpass' needs exactly one of cutoff_hz"):
        Conditioning(method="highpass", cutoff_hz=0.1, cutoff_period_s=10.0)
    with pytest.raises(ConfigError, match="'difference' needs kdiff1"):
        Conditioning(method="difference")
    with pytest.raises(ConfigError, match="highpass order must be a positive integer"):
        Conditioning(method="highpass", cutoff_hz=0.1, order=0)
    with pytest.raises(ConfigError, match="unknown conditioning method 'Mean'"):
        Conditioning(method="Mean")


def test_masked_samples_reach_the_estimators_as_the_conditioned_mean():
    """The missing-data policy: NaN (bad) samples become 0, the conditioned mean; good
    samples and the caller's array are untouched."""
    from pipeline.identification.conditioning import MASKED_VALUE, as_masked_zero

    x = np.array([[1.5, np.nan], [np.nan, -2.0], [0.25, 3.0]])
    out = as_masked_zero(x)
    assert MASKED_VALUE == 0.0
    np.testing.assert_array_equal(out, [[1.5, 0.0], [0.0, -2.0], [0.25, 3.0]])
    assert np.isnan(x[0, 1]) and np.isnan(x[1, 0])  # a copy
