"""The fast noise-model arithmetic against a straightforward reference (issue 33, build 5).

The reference is what method.md §10 says the estimate is, computed the plain way: filter
the output and every input by the output's ``D(q)`` sample by sample, build the
regressor of the filtered inputs explicitly and solve it with ``numpy.linalg.lstsq``;
the covariance is ``sigma^2 (Phi' Phi)^-1``.  The estimator never builds that regressor:
it combines lag products, shares the inputs' factor across outputs
(:mod:`pipeline.estimation.structured_gls`) or factors each output's filtered system, and the
search nests every candidate order in one factor.  All of them must give the
reference's numbers.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal as ss

import pipeline.estimation.prediction_error as pe
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.estimation.gram_estimate import (
    estimate_from_context,
    lag_gram_context,
    lags_needed,
    nested_fixed_noise,
)
from pipeline.estimation.structured_gls import StructuredFactor

N_X, N_Y, P, N = 3, 2, 8, 3000


def _mimo(seed: int = 7):
    rng = np.random.default_rng(seed)
    x = ss.lfilter([1.0], [1, -0.6], rng.standard_normal((N, N_X)), axis=0)
    y = np.zeros((N, N_Y))
    for i in range(N_Y):
        for j in range(N_X):
            y[:, i] += ss.lfilter([0.3 * (i + 1)], [1, -0.5 - 0.1 * j], x[:, j])
    noise = ss.lfilter([1.0], [1, -0.8], 0.2 * rng.standard_normal((N, N_Y)), axis=0)
    return x, y + noise


def _reference(x, y, i: int, d: np.ndarray, n_p: int, k0: int):
    """lstsq on the explicitly filtered regressor of output ``i``, observations
    ``k0..N-1``: ``(b lag-major, (Phi' Phi)^-1, residual variance)``."""
    yf = ss.lfilter(d, [1.0], y[:, i])
    xf = ss.lfilter(d, [1.0], x, axis=0)
    rows = np.arange(k0, N)
    Phi = np.hstack([xf[rows - lag] for lag in range(n_p)])  # lag-major columns
    b, *_ = np.linalg.lstsq(Phi, yf[rows], rcond=None)
    res = yf[rows] - Phi @ b
    s2 = res @ res / (rows.size - b.size - (d.size - 1))
    return b, np.linalg.inv(Phi.T @ Phi), s2


def _lag_major(est, i: int, n_p: int) -> np.ndarray:
    return est.delta_h[i, :, :n_p].T.reshape(-1)


def _step_std_ref(cov: np.ndarray, j: int, n_p: int) -> np.ndarray:
    idx = np.arange(n_p) * N_X + j
    T = np.tril(np.ones((n_p, n_p)))
    return np.sqrt(np.diag(T @ cov[np.ix_(idx, idx)] @ T.T))


@pytest.fixture(params=["structured", "dense"])
def path(request, monkeypatch):
    """Force the shared-factor solve (whenever the filter is coloured) or the per-output
    Cholesky factorisation, whatever the cost model would pick at this size."""
    if request.param == "structured":
        def force(ginv, d, sel, n_lag):
            if ginv is None or not ginv.ok or d.size == 1:
                return None
            return StructuredFactor(ginv, d, sel, n_lag)
        monkeypatch.setattr(pe, "structured_factor", force)
        monkeypatch.setattr(pe, "structured_pays", lambda *a: True)
    else:
        monkeypatch.setattr(pe, "structured_factor", lambda *a: None)
    return request.param


def test_fixed_filter_gls_equals_lstsq_on_filtered_data(path):
    x, y = _mimo()
    d = [np.array([1.0, -0.8]), np.array([1.0, -0.7, 0.1])]
    ctx = lag_gram_context(x, y, n_lags=lags_needed(np.array([[P]]), False, 2))
    s2 = [0.04, 0.05]  # fixed innovation variances (the search's reference ones)
    est = estimate_from_context(ctx, n_p=P, n_k=0, dt=1.0, forms=["direct"] * N_Y,
                                d_fixed=d, sigma2_fixed=s2, use_instruments=False)
    k0 = ctx.lg.n_lags - 1
    for i in range(N_Y):
        b_ref, inv_ref, _ = _reference(x, y, i, d[i], P, k0)
        np.testing.assert_allclose(_lag_major(est, i, P), b_ref, rtol=0, atol=1e-10)
        for j in range(N_X):
            np.testing.assert_allclose(est.step_std[i, j, :P],
                                       np.sqrt(s2[i]) * _step_std_ref(inv_ref, j, P),
                                       rtol=1e-9)


def test_nested_orders_equal_lstsq_at_every_order():
    x, y = _mimo(seed=8)
    d = [np.array([1.0, -0.8]), np.array([1.0, -0.6])]
    ctx = lag_gram_context(x, y, n_lags=lags_needed(np.array([[P]]), False, 1))
    est_at = nested_fixed_noise(ctx, P=P, n_k=np.zeros((N_Y, N_X), dtype=int), dt=1.0,
                                forms=["direct"] * N_Y, d_fixed=d, sigma2_fixed=[1.0, 1.0])
    assert est_at is not None
    k0 = ctx.lg.n_lags - 1
    for m in (3, 5, P):
        est = est_at(m)
        for i in range(N_Y):
            b_ref, inv_ref, _ = _reference(x, y, i, d[i], m, k0)
            np.testing.assert_allclose(_lag_major(est, i, m), b_ref, rtol=0, atol=1e-10)
            np.testing.assert_allclose(est.step_std[i, 0, :m], _step_std_ref(inv_ref, 0, m),
                                       rtol=1e-9)


def test_noise_model_estimate_is_the_gls_of_its_own_filter(path):
    """The prediction-error fit (alternation, Gauss–Newton, Schur covariance) ends where
    ``b`` is the GLS solution for the filter it found (the gradient in ``b`` vanishes)."""
    x, y = _mimo(seed=9)
    est = estimate_step_responses(x, y, n_p=P, dt=1.0, noise=2)
    n_lags = lags_needed(np.array([[P]]), False, 2)
    for i in range(N_Y):
        d = est.noise_model[i].d
        assert d.size == 3
        b_ref, inv_ref, s2 = _reference(x, y, i, d, P, n_lags - 1)
        b = _lag_major(est, i, P)
        assert np.max(np.abs(b - b_ref)) < 1e-6 * np.max(np.abs(b_ref))
        # GLS covariance with the filter known; the estimate's Schur complement adds the
        # filter's own uncertainty, which in open loop is small
        std_ref = np.sqrt(s2) * _step_std_ref(inv_ref, 0, P)
        np.testing.assert_allclose(est.step_std[i, 0, :P], std_ref, rtol=0.05)


def _explicit_lag_gram(segments, L: int) -> np.ndarray:
    """``G[l1, a, l2, b] = sum_k w_a(k - l1) w_b(k - l2)`` over ``k = L-1 .. n-1`` of each
    segment, summed — the definition, one regressor matrix per segment."""
    G = 0.0
    for w in segments:
        n = w.shape[0]
        Z = np.stack([w[L - 1 - lag : n - lag] for lag in range(L)], axis=1)  # (obs, L, n_w)
        G = G + np.einsum("kla,kmb->lamb", Z, Z)
    return G


def test_lazy_lag_gram_equals_its_definition():
    from pipeline.estimation.lag_products import ROW_GROUPS, build_lag_gram, signal_gram

    rng = np.random.default_rng(3)
    segs = [rng.standard_normal((400, 5)), rng.standard_normal((250, 5))]
    L = 7
    ref = _explicit_lag_gram(segs, L)
    lg = build_lag_gram(iter(segs), n_lags=L)
    lg.cache[ROW_GROUPS] = (((2, 5), (0, 2)),)  # signals 2..4 asked for one at a time
    scale = np.max(np.abs(ref))
    # sub-Grams assembled from the seeds, before the whole Gram exists
    for s1, s2 in [((0, 2), (0, 2)), ((3, 4), (0, 2)), ((2, 3), (2, 3)), ((4, 5), (4, 5)),
                   ((0, 3), (1, 5))]:
        sub = signal_gram(lg, 0, s1, s2)
        np.testing.assert_allclose(sub, ref[:, s1[0]:s1[1], :, s2[0]:s2[1]], rtol=0,
                                   atol=1e-12 * scale)
    assert lg._G is None  # nothing above needed the whole Gram
    np.testing.assert_allclose(lg.G, ref, rtol=0, atol=1e-12 * scale)
    assert lg.n_d == (400 - L + 1) + (250 - L + 1) and lg.n_segments == 2


def test_filtered_gram_is_the_filtered_regressors_product():
    from pipeline.estimation.lag_products import Block, filtered_gram

    rng = np.random.default_rng(4)
    w = rng.standard_normal((300, 4))
    L, d = 9, np.array([1.0, -0.7, 0.2])
    G = _explicit_lag_gram([w], L)
    wf = ss.lfilter(d, [1.0], w, axis=0)
    k = np.arange(L - 1, 300)
    b1, b2 = Block(0, 3, 0, 5), Block(3, 4, 1, 3)

    def regressor(blk):
        return np.hstack([wf[k - lag][:, blk.sig_lo:blk.sig_hi]
                          for lag in range(blk.lag_lo, blk.lag_hi)])

    ref = regressor(b1).T @ regressor(b2)
    np.testing.assert_allclose(filtered_gram(G, d, b1, b2), ref, rtol=1e-10,
                               atol=1e-10 * np.max(np.abs(ref)))


def _truncation_reference(ref, m: int) -> np.ndarray:
    """The truncation test's three p-values per pair, one pair at a time with scipy.stats
    (no shared factor, no stacking)."""
    import scipy.stats

    n_y, n_x, P = ref.step.shape
    D = np.eye(P) - np.eye(P, k=-1)
    out = np.ones((n_y, n_x))
    for i in range(n_y):
        for j in range(n_x):
            n = int(ref.n_p[i, j])
            if m >= n:
                continue
            inc = D[:n, :n] @ ref.step[i, j, :n]
            C = D[:n, :n] @ ref.step_cov[i, j, :n, :n] @ D[:n, :n].T
            b, Cm = inc[m:], C[m:, m:]
            k = min(b.size, max(3, m // 2))
            p_sum = scipy.stats.chi2.sf(b[:k].sum() ** 2 / Cm[:k, :k].sum(), 1)
            p_all = scipy.stats.chi2.sf(b @ np.linalg.solve(Cm, b), b.size)
            p_out = scipy.stats.chi2.sf(b.sum() ** 2 / Cm.sum(), 1)
            out[i, j] = min(1.0, 3 * min(p_sum, p_all, p_out))
    return out


def test_vectorised_truncation_test_equals_pair_by_pair():
    from pipeline.identification.truncation import truncation_test

    x, y = _mimo(seed=10)
    est = estimate_step_responses(x, y, n_p=P, dt=1.0, noise="auto")
    p_at = truncation_test(est)
    for m in (1, 3, 5, P - 1, P):
        np.testing.assert_allclose(p_at(m), _truncation_reference(est, m), rtol=1e-8,
                                   atol=1e-14)


def test_nested_orders_diagnostics_equal_each_orders_own():
    from pipeline.estimation.step_result import diagnostics_of

    x, y = _mimo(seed=11)
    d = [np.array([1.0, -0.8]), np.array([1.0, -0.6])]
    ctx = lag_gram_context(x, y, n_lags=lags_needed(np.array([[P]]), False, 1))
    est_at = nested_fixed_noise(ctx, P=P, n_k=np.zeros((N_Y, N_X), dtype=int), dt=1.0,
                                forms=["direct"] * N_Y, d_fixed=d, sigma2_fixed=[1.0, 1.0])
    for m in (2, 5, P):
        own = diagnostics_of(ctx.white_normal_equations(m))
        got = est_at(m).diagnostics
        np.testing.assert_allclose(got.condition_number, own.condition_number, rtol=1e-10)
        np.testing.assert_allclose(got.vif, own.vif, rtol=1e-12)


@pytest.mark.parametrize("d", [np.array([1.0]), np.array([1.0, -0.9]),
                               np.array([1.0, -0.7, 0.2])])
@pytest.mark.parametrize("subset", [False, True])
def test_structured_factor_is_the_inverse_of_the_filtered_gram(d, subset, monkeypatch):
    """``A~ = T' G T`` written out (``T`` the filter ``D`` along the lags, as a matrix) and
    inverted by numpy: the shared-factor solve and covariance factor give its inverse,
    for every unknown (built a few lags at a time: blocks of 2 lags here) and for a
    subset (unknowns left out join the projection); the banded QR gives its Cholesky
    factor (the search's nested orders)."""
    import pipeline.estimation.structured_gls as sg

    monkeypatch.setattr(sg, "_CHUNK_ROWS", 2 * N_X)
    rng = np.random.default_rng(12)
    n_lag, p = 7, d.size - 1
    L = n_lag + 3
    Z = rng.standard_normal((400, L * N_X))
    G = (Z.T @ Z).reshape(L, N_X, L, N_X)
    n1, m = (n_lag + p) * N_X, n_lag * N_X
    T = np.zeros((n1, m))
    for lag in range(n_lag):
        for a, da in enumerate(d):
            for j in range(N_X):
                T[(lag + a) * N_X + j, lag * N_X + j] = da
    A = T.T @ G.reshape(L * N_X, L * N_X)[:n1, :n1] @ T
    # the nested orders' factor: numpy's Cholesky factor of A~, every leading block
    Rt = sg.nested_cholesky(sg.InputGramInverse(G), d, n_lag)
    np.testing.assert_allclose(Rt, np.linalg.cholesky(A).T, rtol=0,
                               atol=1e-12 * np.abs(Rt).max())
    sel = np.delete(np.arange(m), [4, 10]) if subset else np.arange(m)
    inv = np.linalg.inv(A[np.ix_(sel, sel)])
    fac = StructuredFactor(sg.InputGramInverse(G), d, sel, n_lag)
    F = fac.inv_factor()
    np.testing.assert_allclose(F.T @ F, inv, rtol=0, atol=1e-9 * np.abs(inv).max())
    rhs = rng.standard_normal((sel.size, 2))
    np.testing.assert_allclose(fac.solve(rhs), inv @ rhs, rtol=0,
                               atol=1e-9 * np.abs(inv @ rhs).max())
    np.testing.assert_allclose(fac.solve(rhs[:, 0]), inv @ rhs[:, 0], rtol=0,
                               atol=1e-9 * np.abs(inv @ rhs).max())
    extra = rng.standard_normal((2, sel.size))
    Fx = fac.stacked_inv_factor(extra)
    np.testing.assert_allclose(Fx.T @ Fx, inv + extra.T @ extra, rtol=0,
                               atol=1e-9 * np.abs(inv).max())
