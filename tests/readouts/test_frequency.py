"""Tests of pipeline.readouts.frequency: DTFT of step responses vs python-control, and the
least-squares-distance transfer-function fit."""

from __future__ import annotations

import json

import control
import numpy as np
import pytest

from pipeline.adapters.control_lti import transfer_function
from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError
from pipeline.readouts.frequency import (
    fit_transfer_function,
    fit_transfer_function_search,
    frequency_response_from_step,
    refine_within_error_bounds,
)


def zoh_step_samples(sys_c, dt, n):
    """Step response of the ZOH-discretised system at samples 0..n-1 (= the continuous
    step response at t = k dt), from python-control."""
    sys_d = control.sample_system(sys_c, dt, method="zoh")
    resp = control.step_response(sys_d, T=np.arange(n) * dt)
    return sys_d, np.asarray(resp.outputs).ravel()


def control_freq(sys, omega):
    return np.asarray(control.frequency_response(sys, omega).complex).ravel()


# --------------------------------------------------------- DTFT of the step response
@pytest.mark.parametrize(
    "num,den",
    [([2.0], [10.0, 1.0]), ([1.0], [1.0, 0.6, 1.0]), ([-3.0, 1.0], [4.0, 5.0, 1.0])],
    ids=["first_order", "second_order", "nonminimum_phase"],
)
def test_dtft_matches_control_zoh_frequency_response(num, den):
    """Truncating after 400 samples (200 s) leaves e^{-200 s/10 s} ≈ 2e-9 of the slowest
    mode, so the DTFT equals the ZOH system's response to ~1e-8 relative."""
    dt, n = 0.5, 400
    sys_d, h = zoh_step_samples(control.tf(num, den), dt, n)
    omega = np.linspace(0.001, 0.999 * np.pi / dt, 200)
    fr = frequency_response_from_step(step=h, dt_s=dt, omega=omega)
    expected = control_freq(sys_d, omega)
    np.testing.assert_allclose(fr.response, expected, rtol=1e-7, atol=1e-9 * np.abs(expected).max())
    # the same from delta_h, and the FFT grid equals direct evaluation on that grid
    dh = np.diff(h, prepend=0.0)
    grid = frequency_response_from_step(dh, dt_s=dt, n_fft=1024)
    direct = frequency_response_from_step(dh, dt_s=dt, omega=grid.omega_rad_s)
    np.testing.assert_allclose(grid.response, direct.response, rtol=1e-10, atol=1e-12)
    assert grid.omega_rad_s[-1] == pytest.approx(np.pi / dt)
    np.testing.assert_allclose(grid.response, control_freq(sys_d, grid.omega_rad_s), rtol=1e-7,
                               atol=1e-9 * np.abs(expected).max())


def test_dtft_integrating_pair_with_hold_tail():
    """G = 0.5/(s(8s+1)): delta_h tends to K·dt; 'hold' continues it (pole at z = 1)."""
    dt, n = 0.5, 400
    sys_d, h = zoh_step_samples(control.tf([0.5], [8.0, 1.0, 0.0]), dt, n)
    omega = np.logspace(-3, np.log10(0.999 * np.pi / dt), 100)
    fr = frequency_response_from_step(step=h, dt_s=dt, omega=omega, tail="hold")
    np.testing.assert_allclose(fr.response, control_freq(sys_d, omega), rtol=1e-7)
    grid = frequency_response_from_step(step=h, dt_s=dt, tail="hold")
    assert grid.omega_rad_s[0] > 0  # ω = 0 (infinite gain) left out
    # shapes: (n_y, n_x, n_p) in, (n_y, n_x, n_omega) out
    stacked = frequency_response_from_step(
        step=np.stack([[h, 2 * h]]), dt_s=dt, omega=omega, tail="hold"
    )
    assert stacked.response.shape == (1, 2, omega.size)
    np.testing.assert_allclose(stacked.response[0, 1], 2 * fr.response, rtol=1e-9)
    json.dumps(frequency_response_from_step(step=h[:5], dt_s=dt, omega=omega[:3]).to_dict())
    expected = control_freq(sys_d, omega)
    np.testing.assert_allclose(fr.magnitude, np.abs(expected), rtol=1e-7)
    np.testing.assert_allclose(fr.phase_rad, np.unwrap(np.angle(expected)), atol=1e-7)


def test_dtft_errors():
    with pytest.raises(ConfigError, match="exactly one of delta_h or step"):
        frequency_response_from_step(dt_s=1.0)
    with pytest.raises(ConfigError, match=r"omega must be a 1-D array in \[0, π/dt_s"):
        frequency_response_from_step(np.ones(4), dt_s=1.0, omega=[0.5, 4.0])
    with pytest.raises(ConfigError, match="tail must be 'zero' or 'hold'"):
        frequency_response_from_step(np.ones(4), dt_s=1.0, tail="extend")
    with pytest.raises(DataQualityError, match="NaN/inf"):
        frequency_response_from_step(np.array([0.0, np.nan]), dt_s=1.0)
    with pytest.raises(ConfigError, match="n_fft=2 is shorter than the 4 lags"):
        frequency_response_from_step(np.ones(4), dt_s=1.0, n_fft=2)


# ------------------------------------------------------------- transfer-function fit
SYSTEMS = {
    # name: (num, den) highest power first, den monic
    "second_order": ([4.0], [1.0, 0.8, 4.0]),
    "third_order_with_zero": ([3.0, 1.5], [1.0, 2.0, 5.0, 4.0]),  # 3(s+0.5)/((s+1)(s²+s+4))
    "unstable": ([1.0], [1.0, 2.0, -3.0]),  # poles +1, -3
    "non_minimum_phase": ([-4.0, 2.0], [1.0, 3.0, 2.0]),  # zero at +0.5
    "fast_poles": ([1e5], [1.0, 1100.0, 1e5]),  # poles -100, -1000: needs scaling
}


def exact_response(name):
    num, den = SYSTEMS[name]
    # log-spaced, from 1/100 to 100x the corner frequencies (>= 10x the bandwidth)
    omega = np.logspace(0, 5, 60) if name == "fast_poles" else np.logspace(-2, 2, 60)
    return omega, np.polyval(num, 1j * omega) / np.polyval(den, 1j * omega)


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_exact_recovery_of_known_transfer_functions(name):
    num, den = SYSTEMS[name]
    omega, H = exact_response(name)
    fit = fit_transfer_function(omega, H, m=len(num) - 1, n=len(den) - 1)
    np.testing.assert_allclose(fit.num, num, rtol=1e-6)
    np.testing.assert_allclose(fit.den, den, rtol=1e-6)
    assert fit.rms_rel_error < 1e-9 and fit.J < 1e-20
    assert fit.rank == len(num) + len(den) - 1
    # python-control object reproduces H
    np.testing.assert_allclose(control_freq(transfer_function(fit), omega), H, rtol=1e-9)
    np.testing.assert_allclose(
        np.sort_complex(fit.poles), np.sort_complex(np.roots(den)), rtol=1e-6
    )
    json.dumps(fit.to_dict())
    assert f"m={len(num) - 1}, n={len(den) - 1}" in str(fit)


@pytest.mark.parametrize("name", ["second_order", "unstable", "non_minimum_phase"])
@pytest.mark.parametrize("extra", [1, 2])
def test_too_high_degrees_cancel_pole_zero_pairs(name, extra):
    num, den = SYSTEMS[name]
    omega, H = exact_response(name)
    fit = fit_transfer_function(omega, H, m=len(num) - 1 + extra, n=len(den) - 1 + extra)
    np.testing.assert_allclose(fit.evaluate(omega), H, rtol=1e-6)
    assert fit.rank < fit.m + fit.n + 1  # a family of exact fits
    # every extra pole has a zero on top of it; the true poles survive
    poles, zeros = fit.poles, fit.zeros
    dist = np.abs(poles[:, None] - zeros[None, :]) / (1 + np.abs(poles[:, None]))
    cancelled = dist.min(axis=1) < 1e-6
    assert cancelled.sum() >= extra
    for p in np.roots(den):
        assert np.min(np.abs(poles - p)) < 1e-6 * (1 + abs(p))


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_degree_search_finds_true_degrees(name):
    num, den = SYSTEMS[name]
    omega, H = exact_response(name)
    res = fit_transfer_function_search(omega, H, max_m=4, max_n=5, rel_tol=1e-6)
    assert res.within_tolerance
    assert (res.best.m, res.best.n) == (len(num) - 1, len(den) - 1)
    # every smaller (n, m) in search order was tried and rejected
    assert all(t.rms_rel_error > 1e-6 for t in res.trials[:-1])
    assert [(t.n, t.m) for t in res.trials] == sorted((t.n, t.m) for t in res.trials)
    json.dumps(res.to_dict())


def test_degree_search_reports_when_nothing_fits():
    omega, H = exact_response("third_order_with_zero")
    res = fit_transfer_function_search(omega, H, max_m=1, max_n=2, rel_tol=1e-6)
    assert not res.within_tolerance
    assert res.best.rms_rel_error == min(t.rms_rel_error for t in res.trials)


def test_random_search_reduces_J_within_bounds():
    """Bounded relative error e = 2 % (uniform on magnitude and phase, seeded): moving the
    points within ±e lowers J and never leaves the bounds; the search is reproducible."""
    num, den = SYSTEMS["second_order"]
    omega, H = exact_response("second_order")
    rng = np.random.default_rng(42)
    e = 0.02
    mag_err, phase_err = rng.uniform(-e, e, omega.size), rng.uniform(-e, e, omega.size)
    measured = H * (1 + mag_err) * np.exp(1j * phase_err)
    ref = refine_within_error_bounds(omega, measured, m=0, n=2, rel_error=e, n_iter=600, seed=3)
    assert ref.J_final < 0.5 * ref.J_initial and ref.n_accepted > 0
    ratio = ref.H_adjusted / measured
    assert np.all(np.abs(np.abs(ratio) - 1) <= e + 1e-12)
    assert np.all(np.abs(np.angle(ratio)) <= e + 1e-12)
    again = refine_within_error_bounds(omega, measured, m=0, n=2, rel_error=e, n_iter=600, seed=3)
    np.testing.assert_array_equal(again.fit.den, ref.fit.den)
    # the refined model stays consistent with the measurement: within the error bound
    rel = np.abs(ref.fit.evaluate(omega) / measured - 1)
    assert np.max(rel) < 3 * e


def test_fit_errors():
    omega, H = exact_response("second_order")
    msg = "4 real equations from 2 frequencies cannot determine 5"
    with pytest.raises(InsufficientDataError, match=msg):
        fit_transfer_function(omega[:2], H[:2], m=2, n=2)
    with pytest.raises(DataQualityError, match="equal length"):
        fit_transfer_function(omega, H[:-1], m=0, n=2)
    with pytest.raises(ConfigError, match="degree n must be a non-negative integer"):
        fit_transfer_function(omega, H, m=0, n=-1)
    with pytest.raises(ConfigError, match="omega must be >= 0"):
        fit_transfer_function(-omega, H, m=0, n=2)
    with pytest.raises(ConfigError, match="rel_error must lie in"):
        refine_within_error_bounds(omega, H, m=0, n=2, rel_error=0.0)
