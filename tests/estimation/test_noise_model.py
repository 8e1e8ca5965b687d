"""The noise-model, level-form and instrument estimators against independent computations
(issue 9, build 2 and 4): explicit filtering with scipy.signal.lfilter and least squares
with numpy.linalg.lstsq on the regressor matrix, the prediction-error criterion minimised
by scipy.optimize, explicit two-stage least squares.  The lag Gram is never used by the
references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import scipy.signal as ss

from pipeline.identification.checks import ljung_box
from pipeline.errors import ConfigError, DataQualityError
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.estimation.gram_estimate import estimate_from_context, lag_gram_context
from pipeline.estimation.prediction import innovations
from pipeline.estimation.noise_model import ar_order_by_bic, levinson


def _record(n=4000, seed=0, phi=0.8, n_x=2):
    rng = np.random.default_rng(seed)
    x = ss.lfilter([1], [1, -0.7], rng.standard_normal((n, n_x)), axis=0)
    g = [np.array([0.0, 0.5, 0.3, 0.1]), np.array([0.2, -0.4, 0.1, 0.0])][:n_x]
    y = sum(np.convolve(x[:, j], g[j])[:n] for j in range(n_x))
    y = y + ss.lfilter([1], [1, -phi], 0.3 * rng.standard_normal(n))
    return x, y


def _regressor(x, P, ks):
    return np.stack([np.concatenate([x[k - l] for l in range(P)]) for k in ks])


def test_gls_with_a_given_filter_equals_least_squares_on_filtered_data():
    x, y = _record()
    P, d = 6, np.array([1.0, -0.8, 0.15])
    L = P + 5
    ctx = lag_gram_context(x, y, n_lags=L)
    est = estimate_from_context(ctx, n_p=P, n_k=0, dt=1.0, forms=["direct"], d_fixed=[d])
    xf = ss.lfilter(d, [1.0], x, axis=0)
    yf = ss.lfilter(d, [1.0], y)
    ks = range(L - 1, y.size)
    b, *_ = np.linalg.lstsq(_regressor(xf, P, ks), yf[list(ks)], rcond=None)
    assert np.allclose(est.delta_h[0], b.reshape(P, 2).T, atol=1e-10)


def test_prediction_error_fit_minimises_the_criterion():
    """Joint (FIR, AR(2)) fit equals scipy's minimisation of sum eps^2 with
    eps = D(q) (y - FIR(x)) over the same observations."""
    x, y = _record(n=3000, seed=1)
    P, L = 4, 4 + 21
    ctx = lag_gram_context(x, y, n_lags=L)
    est = estimate_from_context(ctx, n_p=P, n_k=0, dt=1.0, noise=2)
    ks = np.arange(L - 1, y.size)
    Phi = _regressor(x, P, range(y.size))  # rows k = 0.. (early rows unused)

    def eps(theta):
        b, dd = theta[: 2 * P], theta[2 * P:]
        e = y - np.concatenate([np.zeros(P - 1), Phi[P - 1:] @ b])
        f = ss.lfilter(np.concatenate([[1.0], dd]), [1.0], e)
        return f[ks]

    b0 = np.linalg.lstsq(Phi[P - 1:], y[P - 1:], rcond=None)[0]
    ref = scipy.optimize.least_squares(eps, np.concatenate([b0, [0.0, 0.0]]), xtol=1e-14,
                                       ftol=1e-14, gtol=1e-14)
    b_ref = ref.x[: 2 * P].reshape(P, 2).T
    assert np.allclose(est.delta_h[0], b_ref, atol=1e-6)
    assert np.allclose(est.noise_model[0].coefficients, ref.x[2 * P:], atol=1e-6)
    assert est.sigma2[0] == pytest.approx(np.sum(ref.fun**2) / (ks.size - 2 * P - 2), rel=1e-6)


def test_level_form_equals_regression_on_cumulated_inputs_with_polynomial_nuisances():
    """Level form: y(k) = sum_{l<P-1} dh(l+1) x(k-l) + dh(P) S(k-P+1) + (1, t, t^2)_seg,
    S the inputs cumulated from each segment's start — over two segments."""
    rng = np.random.default_rng(2)
    n, P = 3000, 5
    x = rng.standard_normal((n, 2))
    y = np.cumsum(rng.standard_normal(n)) * 0.1 + rng.standard_normal(n)
    good = np.ones(n, bool)
    good[1400:1410] = False
    ctx = lag_gram_context(x, y, integrating=True, mask=good, n_lags=P + 2)
    est = estimate_from_context(ctx, n_p=P, n_k=0, dt=1.0, noise=0, forms=["level"])
    rows, targets = [], []
    segs = [(0, 1400), (1410, n)]
    k0 = P + 2  # n_lags - 1 + 1 (a differenced signal in the layout)
    for si, (a, b) in enumerate(segs):
        xs, ys = x[a:b], y[a:b]
        S = np.cumsum(xs, axis=0)
        t = np.arange(b - a, dtype=float) / (b - a)
        for k in range(k0, b - a):
            nuis = np.zeros(6)
            nuis[3 * si: 3 * si + 3] = [1.0, t[k], t[k] ** 2]
            rows.append(np.concatenate([xs[k - np.arange(P - 1)].ravel(), S[k - P + 1], nuis]))
            targets.append(ys[k])
    theta, *_ = np.linalg.lstsq(np.array(rows), np.array(targets), rcond=None)
    dh = np.zeros((2, P))
    dh[:, : P - 1] = theta[: 2 * (P - 1)].reshape(P - 1, 2).T
    dh[:, P - 1] = theta[2 * (P - 1): 2 * P]
    assert np.allclose(est.delta_h[0], dh, atol=1e-9)
    assert np.allclose(est.rate[0], dh[:, -1], atol=1e-9)  # dt = 1


def test_instrumental_variables_equal_explicit_two_stage_least_squares():
    """With a white noise model the IV estimate is textbook 2SLS: Phi' Z (Z'Z)^-1 Z' Phi b
    = Phi' Z (Z'Z)^-1 Z' y, Z the instruments' lags 0..2P-1."""
    rng = np.random.default_rng(3)
    n, P = 5000, 4
    r = np.repeat(rng.standard_normal(n // 50 + 1), 50)[:n]
    e = ss.lfilter([1], [1, -0.9], rng.standard_normal(n))
    u = r - 0.5 * e  # the input carries the noise: least squares is biased
    y = np.convolve(u, [0.0, 1.0, 0.5, 0.2])[:n] + e
    L = 2 * P + 1
    ctx = lag_gram_context(u, y, instruments=r, n_lags=L, level_form=False)
    est = estimate_from_context(ctx, n_p=P, n_k=0, dt=1.0, noise=0)
    ks = range(L - 1, n)
    Phi = _regressor(u[:, None], P, ks)
    Z = _regressor(r[:, None], 2 * P, ks)
    PZ = Z @ np.linalg.lstsq(Z, Phi, rcond=None)[0]
    b = np.linalg.lstsq(PZ, y[list(ks)], rcond=None)[0]
    assert est.method == "instrumental_variables"
    assert np.allclose(est.delta_h[0, 0], b, atol=1e-8)
    ls = estimate_step_responses(u, y, n_p=P, dt=1.0)
    assert abs(ls.step[0, 0, -1] - 1.7) > 0.1 > abs(est.step[0, 0, -1] - 1.7)


def test_levinson_and_bic_recover_an_ar2_noise():
    rng = np.random.default_rng(4)
    v = ss.lfilter([1], [1, -1.2, 0.5], rng.standard_normal(50_000))
    r = np.array([v[: v.size - k] @ v[k:] for k in range(11)])
    p, d, bic = ar_order_by_bic(r, v.size, 10)
    assert p == 2
    assert np.allclose(d, [-1.2, 0.5], atol=0.02)
    coefs, err = levinson(r, 3)
    assert err[2] / v.size == pytest.approx(1.0, abs=0.02)  # the unit innovation variance
    assert err[0] > err[1] > err[2] and err[3] == pytest.approx(err[2], rel=1e-3)
    assert np.allclose(coefs[2], d, atol=1e-12)


def test_auto_noise_model_whitens_the_prediction_errors():
    x, y = _record(n=20_000, seed=5, phi=0.95)
    e_white = estimate_step_responses(x, y, n_p=8, dt=1.0)
    e_auto = estimate_step_responses(x, y, n_p=8, dt=1.0, noise="auto")
    assert e_auto.noise_model[0].order >= 1
    assert e_auto.noise_model[0].coefficients[0] == pytest.approx(-0.95, abs=0.02)
    assert ljung_box(innovations(e_white, x, y)[:, 0])["p_value"] < 1e-10
    assert ljung_box(innovations(e_auto, x, y)[:, 0])["white"]


def test_known_delay_fixes_leading_increments_at_zero():
    x, y = _record(seed=6, phi=0.0)
    P = 6
    est = estimate_step_responses(x, y, n_p=P, dt=1.0, n_k=[[2, 1]])
    assert np.all(est.delta_h[0, 0, :2] == 0) and np.all(est.step_std[0, 0, :2] == 0)
    assert est.delta_h[0, 1, 0] == 0 and est.step_std[0, 1, 0] == 0
    ks = range(P - 1, y.size)
    full = _regressor(x, P, ks)
    keep = [c for c in range(2 * P) if not ((c % 2 == 0 and c // 2 < 2) or (c % 2 == 1 and c // 2 < 1))]
    b, *_ = np.linalg.lstsq(full[:, keep], y[list(ks)], rcond=None)
    got = [est.delta_h[0, c % 2, c // 2] for c in keep]
    assert np.allclose(got, b, atol=1e-10)


def test_bad_keywords_say_what_is_allowed():
    x, y = _record(n=500)
    with pytest.raises(ConfigError, match=r"noise='bogus' is not allowed; use 'white', 'auto'"):
        estimate_step_responses(x, y, n_p=4, dt=1.0, noise="bogus")
    with pytest.raises(ConfigError, match=r"n_k=4 fixes every one of the n_p=4 increments"):
        estimate_step_responses(x, y, n_p=4, dt=1.0, n_k=4)
    with pytest.raises(DataQualityError, match=r"instruments have 10 samples but x and y have 500"):
        estimate_step_responses(x, y, n_p=4, dt=1.0, instruments=np.ones(10))


def test_white_noise_default_is_the_thesis_estimate():
    """noise='white' (the default) is the thesis' least squares to the last digit."""
    x, y = _record(seed=7)
    a = estimate_step_responses(x, y, n_p=5, dt=1.0)
    ks = range(4, y.size)
    b, *_ = np.linalg.lstsq(_regressor(x, 5, ks), y[list(ks)], rcond=None)
    assert a.method == "least_squares" and a.noise_model[0].kind == "white"
    assert np.allclose(a.delta_h[0], b.reshape(5, 2).T, atol=1e-11)


def test_fit_ar_on_a_series_recovers_an_ar2_and_matches_explicit_least_squares():
    """The discrepancy workflow's noise model (a residual series) is the same AR fit:
    on a seeded AR(2) (poles 0.8 ± 0.3j) of 20 000 samples BIC picks order 2, the
    coefficients are within 4 standard errors (sqrt((1 - phi_2^2) / n) ~ 0.005) of the
    truth and of an explicit least-squares regression on the lagged series (an
    independent computation), and the innovation std within 2 %."""
    from pipeline.estimation.noise_model import fit_ar

    rng = np.random.default_rng(7)
    d_true = np.array([1.0, -1.6, 0.73])
    e = ss.lfilter([1.0], d_true, 0.5 * rng.standard_normal(20_000))
    d, s, p = fit_ar(e, 8)
    assert p == 2
    assert np.allclose(d, d_true, atol=4 * np.sqrt((1 - 0.73**2) / e.size))
    lagged = np.column_stack([e[1:-1], e[:-2]])
    phi, *_ = np.linalg.lstsq(lagged, e[2:], rcond=None)
    assert np.allclose(d[1:], -phi, atol=0.01)
    assert abs(s / 0.5 - 1) < 0.02
    white, s0, p0 = fit_ar(rng.standard_normal(5000), 8)
    assert p0 == 0 and white.tolist() == [1.0] and abs(s0 - 1) < 0.05
