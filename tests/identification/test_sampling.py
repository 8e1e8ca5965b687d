"""Tests of pipeline.identification.sampling: the α_T criterion, the sample-period choice, resampling."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.optimize
import scipy.signal
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.errors import ConfigError, DataQualityError
from pipeline.identification.sampling import (
    alpha_t,
    alpha_t_curve,
    alpha_t_first_order,
    choose_sample_period,
    hold_period_s,
    resample_average,
    resample_average_masked,
)


# --------------------------------------------------------------------------- signals
def first_order_ou(n: int, omega0_dt: float, rng) -> np.ndarray:
    """AR(1) = Ornstein–Uhlenbeck sampled every dt: correlation r^|j|, r = exp(-w0 dt)."""
    r = np.exp(-omega0_dt)
    e = rng.standard_normal(n) * np.sqrt(1 - r * r)
    return scipy.signal.lfilter([1.0], [1.0, -r], e)


def first_order_multisine(n: int, omega0_dt: float, rng) -> np.ndarray:
    """Random-phase multisine with exactly the AR(1) power spectrum.

    Its mean square is fixed (Parseval), so α_T estimates scatter only through the
    hold error itself — much less than an OU record of the same length, whose
    mean(x²) has relative std sqrt(2/(w0 N dt)).  Its (circular) correlation is the
    AR(1) one, r^|j|, so the closed forms apply.
    """
    r = np.exp(-omega0_dt)
    om = 2 * np.pi * np.arange(n // 2 + 1) / n
    spec = (1 - r * r) / np.abs(1 - r * np.exp(-1j * om)) ** 2
    coef = np.sqrt(spec * n / 2) * np.exp(2j * np.pi * rng.random(om.size))
    coef[0] = 0.0
    coef[-1] = abs(coef[-1])
    return np.fft.irfft(coef, n)


def discrete_alpha_ar1(m, r):
    """Exact E[α] of an m-sample hold of AR(1): (1/m) Σ_{j<m} 2(1 - r^j) (mean-square 1)."""
    m = np.asarray(m, dtype=float)
    return 2 * (1 - (1 - r**m) / (m * (1 - r)))


def brute_force_alpha(x: np.ndarray, m: int) -> float:
    x = x - x.mean()
    held = np.repeat(x[::m], m)[: x.size]
    return float(np.mean((x - held) ** 2) / np.mean(x**2))


@pytest.fixture(scope="module")
def long_ou():
    # 2^24 samples, w0·dt = 1e-3: 16 777 correlation times.
    return first_order_ou(2**24, 1e-3, np.random.default_rng(20240301))


# ------------------------------------------------------------------------ α_T itself
def test_alpha_t_first_order_low_pass_matches_closed_form(long_ou):
    """Issue text: α_T of a first-order low-pass signal matches 2[1-(1-e^{-u})/u],
    u = w0 T/2, within 5 % (relative) for w0 T in [0.02, 1].

    One OU record, w0 fixed, w0 T varied through the hold length m.  A hold of m record
    samples measures the continuous hold T/2 = (m-1) dt (module notes), so
    w0 T = 2 (m-1) w0 dt.  Tolerance:
      * discretisation: the exact discrete expectation (discrete_alpha_ar1) differs from
        the continuous form at (m-1) dt by < 0.05 % here (asserted below), where the
        naive m·dt mapping would be off by 1/m = 10 % at m = 11;
      * sampling: mean(x²) of an OU record has relative std sqrt(2/(w0 N dt)) =
        sqrt(2/16777) = 1.1 %, the dominant error (the hold error itself averages over
        N/m >= 1.3e4 holds), so 5 % is 4.5 standard deviations.
    """
    w = 1e-3
    omega0_t = np.array([0.02, 0.05, 0.1, 0.2, 0.5, 1.0])
    holds = np.rint(omega0_t / (2 * w)).astype(int) + 1
    omega0_t_actual = 2 * (holds - 1) * w
    closed = alpha_t_first_order(omega0_t_actual)
    r = np.exp(-w)
    np.testing.assert_allclose(discrete_alpha_ar1(holds, r), closed, rtol=5e-4)
    got_holds, got = alpha_t_curve(long_ou, hold_samples=holds)
    np.testing.assert_array_equal(got_holds, holds)
    rel = got / closed - 1
    assert np.all(np.abs(rel) < 0.05), f"relative errors {rel}"
    # Sanity of the naive mapping claim above: at m = 11 it is off by ~1/m.
    naive = alpha_t_first_order(2 * holds[0] * w)
    assert abs(got[0] / naive - 1) > 0.05


def test_alpha_t_single_hold_equals_curve(long_ou):
    m = 101
    _, curve = alpha_t_curve(long_ou[:200_000], hold_samples=[m])
    assert alpha_t(long_ou[:200_000], hold_samples=m) == pytest.approx(curve[0], rel=1e-12)


def test_alpha_t_matches_exact_discrete_expectation_small_holds():
    """Holds of 2..50 samples against the exact AR(1) expectation (no approximation).

    Multisine record, N = 2^20, w0 dt = 0.01: over 20 seeds the relative error had
    std 0.15–0.53 % (largest at m = 50, fewest holds) and max 1.2 %; 2 % is > 3.7 std.
    """
    w = 0.01
    holds = np.array([2, 3, 5, 10, 20, 50])
    x = first_order_multisine(2**20, w, np.random.default_rng(7))
    _, got = alpha_t_curve(x, hold_samples=holds)
    np.testing.assert_allclose(got, discrete_alpha_ar1(holds, np.exp(-w)), rtol=0.02)


@settings(max_examples=200, deadline=None)
@given(
    x=arrays(np.float64, st.integers(2, 120), elements=st.floats(-1e3, 1e3)),
    m=st.integers(1, 120),
)
def test_alpha_t_equals_brute_force_hold(x, m):
    """The one-pass formula equals an explicit sample-and-hold (incomplete tail held)."""
    assume(np.ptp(x) > 1e-3)  # constant signals are an error, tested separately
    m = min(m, x.size)
    assert alpha_t(x, hold_samples=m) == pytest.approx(brute_force_alpha(x, m), rel=1e-8, abs=1e-12)


def test_alpha_t_is_scale_and_offset_invariant():
    x = first_order_ou(5000, 0.05, np.random.default_rng(3))
    a = alpha_t(x, hold_samples=7)
    assert alpha_t(3.5 * x + 100.0, hold_samples=7) == pytest.approx(a, rel=1e-9)


def test_hold_of_one_sample_is_exact():
    x = np.random.default_rng(1).standard_normal(100)
    assert alpha_t(x, hold_samples=1) == 0.0


def test_first_order_closed_form_five_percent_is_omega0_t_about_0_1():
    # 2[1 - (1 - e^-0.05)/0.05] = 0.0492 (series u - u²/3 + ...).
    assert alpha_t_first_order(0.1) == pytest.approx(0.05 - 0.05**2 / 3 + 0.05**3 / 12, rel=1e-5)
    root = scipy.optimize.brentq(lambda z: alpha_t_first_order(z) - 0.05, 1e-3, 1.0)
    assert root == pytest.approx(0.1017, abs=1e-4)
    # series branch and exact branch agree at the switch
    below, above = alpha_t_first_order(2e-4 * 0.999), alpha_t_first_order(2e-4 * 1.001)
    assert below == pytest.approx(above, rel=1e-2)


def test_hold_period_mapping():
    np.testing.assert_allclose(hold_period_s([1, 2, 11], dt_s=0.5), [0.0, 0.5, 5.0])


def test_alpha_t_errors():
    with pytest.raises(DataQualityError, match="constant"):
        alpha_t(np.ones(50), hold_samples=3)
    with pytest.raises(DataQualityError, match="NaN/inf value.*first at sample 2"):
        alpha_t(np.array([1.0, 2.0, np.nan, 4.0]), hold_samples=2)
    with pytest.raises(ConfigError, match="hold_samples must be a positive integer"):
        alpha_t(np.arange(10.0), hold_samples=0)
    with pytest.raises(ConfigError, match="exceeds the record length of 10"):
        alpha_t(np.arange(10.0), hold_samples=11)


# ------------------------------------------------------------- choosing the period
def test_choose_sample_period_five_percent_gives_omega0_t_about_0_1():
    """An input with w0 = 2 rad/s, record dt = 1 ms: T should be 0.1017/w0 = 50.85 ms.

    OU record of 2^22 samples = 8389 correlation times: α̂ relative std
    sqrt(2/8389) = 1.5 %, and T ∝ α near 5 % (d ln T / d ln α = 1.03), so 4 std = 6 %;
    rounding T down to a whole number of 1 ms samples costs up to 1 sample = 2 %.
    """
    omega0, dt = 2.0, 1e-3
    x = first_order_ou(2**22, omega0 * dt, np.random.default_rng(11))
    choice = choose_sample_period({"u": x}, grid_dt_s=dt, roles={"u": "input"})
    t_true = scipy.optimize.brentq(lambda z: alpha_t_first_order(z) - 0.05, 1e-3, 1.0) / omega0
    assert choice.preferred_dt_s["u"] == pytest.approx(t_true, rel=0.06)
    assert -0.08 < choice.dt_s / t_true - 1 < 0.06
    assert choice.decimation == int(np.floor(choice.preferred_dt_s["u"] / dt))
    assert choice.dt_s == pytest.approx(choice.decimation * dt)
    assert omega0 * choice.dt_s == pytest.approx(0.1, abs=0.01)
    assert choice.alpha_t["u"] <= 0.05 + 1e-12


def test_choose_sample_period_takes_smallest_period_over_channels():
    """Targets 5 % (input) and 1 % (output); the smallest preferred T wins.

    Closed-form periods: input w0 = 1 → 0.1017 s; output w0 = 0.1 → 0.2007 s; output
    w0 = 0.25 → 0.0803 s.  Linear detrending removes ≈ 4/(w0 N dt) of an AR(1) signal's
    mean square (two fitted components × spectral density 2/(w0 dt) / N), raising α_T
    and lowering T by about as much: 0.05 %, 1.9 % and 0.8 %; that bias is expected.
    Multisine records of 2^21 samples at dt = 1 ms: over 8 other seeds the preferred-T
    errors had std 0.33 %, 0.60 % and 0.65 % and, after the detrend bias, means within
    0.4 %; 2.5 % is > 3.8 std.
    """
    dt, n = 1e-3, 2**21
    rng = np.random.default_rng(5)
    omega0 = {"u": 1.0, "y_slow": 0.1, "y_fast": 0.25}
    sig = {k: first_order_multisine(n, omega0[k] * dt, rng) for k in ("u", "y_slow")}
    closed = {
        k: scipy.optimize.brentq(lambda z: alpha_t_first_order(z) - tgt, 1e-4, 1) / omega0[k]
        for k, tgt in (("u", 0.05), ("y_slow", 0.01), ("y_fast", 0.01))
    }
    detrend_bias = {k: -4 / (w0 * n * dt) for k, w0 in omega0.items()}
    roles = {"u": "input", "y_slow": "output", "y_fast": "output"}
    first = choose_sample_period(sig, grid_dt_s=dt, roles=roles)
    assert first.limiting_signal == "u"
    assert first.targets == {"u": 0.05, "y_slow": 0.01}
    for k in sig:
        assert abs(first.preferred_dt_s[k] / closed[k] - 1 - detrend_bias[k]) < 0.025
    assert first.decimation == int(np.floor(first.preferred_dt_s["u"] / dt))

    sig["y_fast"] = first_order_multisine(n, omega0["y_fast"] * dt, rng)
    second = choose_sample_period(sig, grid_dt_s=dt, roles=roles)
    assert second.limiting_signal == "y_fast"
    rel = second.preferred_dt_s["y_fast"] / closed["y_fast"] - 1
    assert abs(rel - detrend_bias["y_fast"]) < 0.025
    assert second.decimation == int(np.floor(second.preferred_dt_s["y_fast"] / dt))
    # Rounding down keeps every channel at or below its target.
    for k, a in second.alpha_t.items():
        assert a <= second.targets[k] + 1e-12
    json.dumps(second.to_dict())  # JSON-ready
    assert "limited by y_fast" in str(second)


def test_choose_sample_period_array_input_and_trend_removal():
    """A 2-D array with names gives the same answer; a large linear trend is removed."""
    dt = 0.01
    rng = np.random.default_rng(9)
    x = first_order_ou(100_000, 2.0 * dt, rng)
    y = first_order_ou(100_000, 0.5 * dt, rng)
    t = np.arange(x.size) * dt
    base = choose_sample_period({"x": x, "y": y}, grid_dt_s=dt, roles=["input", "output"])
    trended = choose_sample_period(
        np.column_stack([x + 50 + 0.3 * t, y - 2 * t]),
        grid_dt_s=dt,
        roles=["input", "output"],
        names=["x", "y"],
    )
    assert trended.decimation == base.decimation
    for k in ("x", "y"):
        # detrend is a projection: the detrended signals differ only by round-off
        assert trended.preferred_dt_s[k] == pytest.approx(base.preferred_dt_s[k], rel=1e-6)


def test_choose_sample_period_record_too_slow_uses_record_dt():
    """White noise: α_T ≈ 1 for any hold (far above 1 %), so T = record dt with a note."""
    x = np.random.default_rng(2).standard_normal(10_000)
    choice = choose_sample_period({"y": x}, grid_dt_s=0.5, roles={"y": "output"})
    assert choice.dt_s == 0.5 and choice.decimation == 1
    assert any("sampled too slowly" in note for note in choice.notes)
    # α at the hold T/2 = dt/2 is half-way between hold 1 (α=0) and hold 2 (α≈1).
    assert choice.alpha_t["y"] == pytest.approx(0.5, abs=0.05)


def test_choose_sample_period_target_not_reached():
    """A very slow signal stays below target over the holds examined."""
    x = first_order_ou(4000, 1e-5, np.random.default_rng(4)) + np.sin(np.arange(4000) * 1e-3)
    choice = choose_sample_period({"u": x}, grid_dt_s=1.0, roles={"u": "input"}, max_hold_samples=10)
    assert np.isinf(choice.preferred_dt_s["u"])
    assert choice.decimation == 18  # 2 (max_hold - 1)
    assert any("no signal reaches" in note for note in choice.notes)
    assert choice.to_dict()["preferred_dt_s"]["u"] is None


def test_choose_sample_period_errors():
    x = np.random.default_rng(0).standard_normal(1000)
    with pytest.raises(ConfigError, match="unknown role.*'sensor'"):
        choose_sample_period({"x": x}, grid_dt_s=1.0, roles={"x": "sensor"})
    with pytest.raises(ConfigError, match="roles has no entry for signal"):
        choose_sample_period({"x": x}, grid_dt_s=1.0, roles={})
    with pytest.raises(ConfigError, match="dt_s must be a positive number"):
        choose_sample_period({"x": x}, grid_dt_s=0.0, roles=["input"])
    with pytest.raises(ConfigError, match="target_output must lie in"):
        choose_sample_period({"x": x}, grid_dt_s=1.0, roles=["input"], target_output=5)
    with pytest.raises(ConfigError, match="needs names="):
        choose_sample_period(np.column_stack([x, x]), grid_dt_s=1.0, roles=["input", "output"])
    with pytest.raises(DataQualityError, match="signal 'c' is constant"):
        choose_sample_period({"x": x, "c": np.full(1000, 3.0)}, grid_dt_s=1.0, roles=["input"] * 2)
    with pytest.raises(DataQualityError, match="same length"):
        choose_sample_period({"x": x, "y": x[:500]}, grid_dt_s=1.0, roles=["input"] * 2)


# ----------------------------------------------------------------------- resampling
def test_resample_average_known_answer_and_shapes():
    x = np.arange(10.0)
    np.testing.assert_array_equal(resample_average(x, 3), [1.0, 4.0, 7.0])  # tail (9) dropped
    x2 = np.column_stack([np.arange(8.0), 10 * np.arange(8.0)])
    np.testing.assert_array_equal(resample_average(x2, 4), [[1.5, 15.0], [5.5, 55.0]])
    np.testing.assert_array_equal(resample_average(x, 1), x)


def test_resample_average_masked_rules():
    x = np.array([1.0, 2.0, 3.0, np.nan, 5.0, 7.0, 8.0, 9.0])
    good = np.isfinite(x)
    strict, g = resample_average_masked(x, good, 4)
    np.testing.assert_array_equal(g, [False, True])
    assert np.isnan(strict[0]) and strict[1] == 7.25
    loose, g2 = resample_average_masked(x, good, 4, max_bad_fraction=0.25)
    np.testing.assert_array_equal(g2, [True, True])
    assert loose[0] == pytest.approx(2.0)  # mean of the good samples 1, 2, 3
    # 1-D mask applies to every column
    x2 = np.column_stack([np.arange(6.0), np.arange(6.0) * 2])
    out, g3 = resample_average_masked(x2, np.array([1, 1, 1, 1, 0, 1], bool), 2)
    np.testing.assert_array_equal(g3, [[True, True], [True, True], [False, False]])
    np.testing.assert_array_equal(out[:2], [[0.5, 1.0], [2.5, 5.0]])


def test_resample_average_errors():
    with pytest.raises(ConfigError, match="factor must be a positive integer"):
        resample_average(np.arange(5.0), 0)
    with pytest.raises(DataQualityError, match="shorter than one block of factor=10"):
        resample_average(np.arange(5.0), 10)
    with pytest.raises(DataQualityError, match="good has shape"):
        resample_average_masked(np.arange(6.0), np.ones(5, bool), 2)
    with pytest.raises(ConfigError, match="max_bad_fraction must lie in"):
        resample_average_masked(np.arange(6.0), np.ones(6, bool), 2, max_bad_fraction=1.0)
