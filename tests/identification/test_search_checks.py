"""N_p/N_d search and consistency checks (issue 2, must-show 7)."""

from __future__ import annotations

import control as ct
import numpy as np
import pytest

from pipeline.identification.checks import (
    AgreementResult,
    cross_correlation_check,
    ljung_box,
    pair_agreement,
    windows_agree,
    windows_disagree,
)
from pipeline.errors import InsufficientDataError
from pipeline.identification.search import search
from pipeline.identification.windows import split_windows_by_length
from tests.estimation.test_estimate import ar1, simulate


def settling_time_98(G, *, integrating: bool, t_max: float = 600.0, dt: float = 0.01) -> float:
    """98 % settling time of the continuous step response (of its slope if integrating),
    computed independently on a fine grid with python-control."""
    t = np.arange(0, t_max, dt)
    h = ct.step_response(G, T=t).outputs
    q = np.gradient(h, t) if integrating else h
    final = q[-1]
    outside = np.flatnonzero(np.abs(q - final) > 0.02 * abs(final))
    return float(t[outside[-1] + 1])


SYSTEMS = {
    "first_order": (ct.tf([2.0], [10.0, 1.0]), False),
    "second_order_oscillatory": (ct.tf([1.0], [25.0, 3.0, 1.0]), False),  # zeta = 0.3
    "integrator_with_lag": (ct.tf([0.05], [8.0, 1.0, 0.0]), True),
}


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_np_search_lands_near_settling_time(name):
    """N_p*T within 0.8–1.5x the 98 % settling time (plus T for integrating outputs,
    method.md eq. 3.15); noise 5 % of the output (of its difference if integrating)."""
    G, integ = SYSTEMS[name]
    rng = np.random.default_rng(30)
    n, dt = 20000, 1.0
    u = ar1(n, np.exp(-0.3), rng)
    y = simulate(G, u, dt)
    y = y + 0.05 * np.std(np.diff(y) if integ else y) * rng.standard_normal(n)
    res = search(u, y, dt=dt, integrating=integ, n_p_max=150)
    ts = settling_time_98(G, integrating=integ) + (dt if integ else 0.0)
    ratio = res.n_p[0, 0] * dt / ts
    print(f"{name}: T_s={ts:.1f} s, N_p={res.n_p[0, 0]}, ratio {ratio:.2f}, N_d={res.n_d}")
    assert 0.8 <= ratio <= 1.5
    assert res.settled[0, 0]
    # every trial is recorded: the grid and the refinement around the choice
    tried = [t["n_p"] for t in res.order_trace]
    assert res.n_p[0, 0] in tried and len(tried) >= 10
    assert all("bic" in t for t in res.order_trace)
    # a time-invariant plant: disjoint windows agree
    assert res.agreement[0][0].verdict == "pass"


def test_agreement_fails_when_gain_changes_30_percent_between_windows():
    rng = np.random.default_rng(31)
    G = ct.tf([2.0], [10.0, 1.0])
    n, dt = 20000, 1.0
    u = ar1(n, np.exp(-0.3), rng)
    y = np.concatenate([simulate(G, u[: n // 2], dt), simulate(1.3 * G, u[n // 2:], dt)])
    y = y + 0.05 * rng.standard_normal(n)
    res = search(u, y, dt=dt, n_p=45)
    assert res.agreement[0][0].verdict == "fail"
    # N_d grew until the data ran out (windows never agree), and every trial is recorded
    assert len(res.nd_trace) >= 2
    assert res.nd_trace[-1]["n_d"] > res.nd_trace[0]["n_d"]
    assert res.agreement[0][0].gain_spread == pytest.approx(0.3 / 1.3, abs=0.05)


def test_nd_grows_until_noisy_windows_become_informative():
    """High noise: 10*N_p observations cannot detect a 30 % change, so N_d doubles."""
    rng = np.random.default_rng(32)
    G = ct.tf([1.0], [5.0, 1.0])
    n = 40000
    u = ar1(n, 0.5, rng)
    y = simulate(G, u, 1.0) + 2.0 * rng.standard_normal(n)
    res = search(u, y, dt=1.0, n_p=25)
    # the shorter lengths were skipped as predicted uninformative or estimated so
    assert len(res.nd_trace) >= 2
    assert all("skipped" in t or t["pairs"][0]["verdict"] == "insufficient_data"
               for t in res.nd_trace[:-1])
    assert res.nd_trace[-1]["pairs"][0]["verdict"] == "pass"
    assert res.n_d > 250


def _agreeing(p_value=0.5, gain_p=0.5, verdict="pass", detect=0.1):
    # informative as pair_agreement decides it for a pair with a response
    return AgreementResult(1.0, verdict, 0.0, detect, 2, p_value, 8, 0.01, 1.0, gain_p,
                           detect <= 0.3)


def test_windows_agree_is_one_question_about_the_whole_plant():
    """Stage 2's stopping rule: each of the m pairs at 1/m of its false-alarm rates
    (Wald 1 %, gain 4 %), every pair informative.  Answers set by hand."""
    m = 400  # a 20 x 20 plant
    grid = [[_agreeing() for _ in range(20)] for _ in range(20)]
    assert windows_agree(grid)
    # a pair failing at its own 1 % (p = 0.005) is what 400 pairs give by chance ...
    grid[3][7] = _agreeing(p_value=0.005, verdict="fail")
    assert windows_agree(grid)
    # ... one below 1 % / 400 is not, nor a gain below 4 % / 400
    grid[3][7] = _agreeing(p_value=0.9 * 0.01 / m, verdict="fail")
    assert not windows_agree(grid)
    grid[3][7] = _agreeing(gain_p=0.9 * 0.04 / m, verdict="fail")
    assert not windows_agree(grid)
    # a failing pair whose windows could not see a 30 % change is not informative
    grid[3][7] = _agreeing(p_value=0.005, verdict="fail", detect=0.31)
    assert not windows_agree(grid)
    grid[3][7] = _agreeing(verdict="insufficient_data", detect=0.5)
    assert not windows_agree(grid)
    # one pair: the pair's own rates
    assert not windows_agree([[_agreeing(p_value=0.009, verdict="fail")]])
    assert windows_agree([[_agreeing(p_value=0.011)]])
    assert not windows_agree([])


def test_a_run_says_windows_disagree_only_for_the_whole_plant():
    """The run's status asks windows_agree's question the other way round: some
    informative pair fails at 1/m of its rates.  A pair without the evidence to tell
    (insufficient_data) makes the plant not agree, but it is no disagreement; a pair
    failing at its own rate among 4 is chance at the plant level.  Answers set by hand."""
    grid = [[_agreeing() for _ in range(2)] for _ in range(2)]
    assert not windows_disagree(grid)
    grid[1][0] = _agreeing(gain_p=0.015, verdict="fail")  # below 4 % but above 4 % / 4
    assert not windows_disagree(grid) and windows_agree(grid)
    grid[1][0] = _agreeing(gain_p=0.009, verdict="fail")  # below 4 % / 4
    assert windows_disagree(grid) and not windows_agree(grid)
    grid[1][0] = _agreeing(verdict="insufficient_data", detect=0.5)
    assert not windows_disagree(grid) and not windows_agree(grid)
    grid[1][0] = None  # a pair no two windows compared
    assert not windows_disagree(grid)
    assert not windows_disagree([])


def test_a_pair_is_informative_when_its_windows_could_see_a_30_percent_change():
    """pair_agreement decides informativeness once, whatever the verdict: two identical
    windows at 5 with sigma 1 cannot see a 30 % change (3.86 * sqrt(2) * 1 / 5 = 1.09 of
    the peak), so they are insufficient_data; at sigma 0.01 they can (0.011); a pair with
    no response at all (within 2 sigma of zero) is judged as it is."""
    h = np.full(8, 5.0)
    noisy = pair_agreement([h, h], [np.ones(8), np.ones(8)])
    assert not noisy.informative and noisy.verdict == "insufficient_data"
    assert noisy.detectable_change == pytest.approx(3.86 * np.sqrt(2) / 5, rel=0.01)
    sharp = pair_agreement([h, h], [np.full(8, 0.01), np.full(8, 0.01)])
    assert sharp.informative and sharp.verdict == "pass"
    null = pair_agreement([np.zeros(8), np.zeros(8)], [np.ones(8), np.ones(8)])
    assert null.informative and null.verdict == "pass"
    assert "informative" not in noisy.to_dict()  # checks.json keeps its keys


def test_window_check_starts_where_a_window_holds_two_observations_per_unknown():
    """8 inputs at N_p 20: 160 unknowns per output, so a window needs 2 x 160 = 320
    observations, more than 10 N_p = 200.  Two such windows fit in 3,000 samples, so the
    check runs and starts there (it used to stop at the first, too small, window)."""
    rng = np.random.default_rng(7)
    n, n_x, P = 3000, 8, 20
    u = np.column_stack([ar1(n, 0.5, rng) for _ in range(n_x)])
    G = ct.tf([1.0], [3.0, 1.0])
    y = sum((0.5 + 0.1 * j) * simulate(G, u[:, j], 1.0) for j in range(n_x))
    y = y + 0.2 * rng.standard_normal(n)
    res = search(u, y, dt=1.0, n_p=P)
    assert res.nd_trace[0]["n_d"] == 2 * n_x * P
    assert "error" not in res.nd_trace[0] and res.agreement
    assert res.n_d >= 2 * n_x * P


def test_pair_agreement_statistic_is_the_wald_test_of_the_difference():
    """Two windows: the statistic is d' (C_a + C_b)^-1 d with the lags' full covariance
    (here the covariance of a cumulative sum of independent increments), chi^2(n_p)."""
    import scipy.stats

    rng = np.random.default_rng(35)
    n = 6
    T = np.tril(np.ones((n, n)))
    Ca = T @ np.diag(rng.uniform(0.01, 0.02, n)) @ T.T
    Cb = T @ np.diag(rng.uniform(0.01, 0.02, n)) @ T.T
    h_a = np.cumsum(rng.standard_normal(n))
    h_b = h_a + rng.standard_normal(n) * 0.2
    r = pair_agreement([h_a, h_b], [np.sqrt(np.diag(Ca)), np.sqrt(np.diag(Cb))], [Ca, Cb])
    d = h_a - h_b
    expected = float(d @ np.linalg.inv(Ca + Cb) @ d)
    assert r.statistic == pytest.approx(expected, rel=1e-9)
    assert r.df == n
    assert r.p_value == pytest.approx(scipy.stats.chi2.sf(expected, n), rel=1e-9)
    assert (r.verdict == "fail") == (r.p_value < 0.01)


def test_pair_agreement_with_three_windows_is_the_homogeneity_test():
    """K windows: sum_w (h_w - h_bar)' C_w^-1 (h_w - h_bar), h_bar the precision-weighted
    mean, chi^2((K-1) n_p) — computed here from the stacked GLS problem."""
    rng = np.random.default_rng(36)
    n, K = 4, 3
    covs = []
    for _ in range(K):
        M = rng.standard_normal((n, n))
        covs.append(M @ M.T + n * np.eye(n))
    hs = [rng.standard_normal(n) for _ in range(K)]
    r = pair_agreement(hs, [np.sqrt(np.diag(c)) for c in covs], covs)
    # GLS of the stacked windows on a common mean, residual quadratic form
    X = np.vstack([np.eye(n)] * K)
    V = np.zeros((K * n, K * n))
    for k, c in enumerate(covs):
        V[k * n:(k + 1) * n, k * n:(k + 1) * n] = c
    Vi = np.linalg.inv(V)
    y = np.concatenate(hs)
    mean = np.linalg.solve(X.T @ Vi @ X, X.T @ Vi @ y)
    res = y - X @ mean
    assert r.statistic == pytest.approx(float(res @ Vi @ res), rel=1e-9)
    assert r.df == (K - 1) * n


def test_pair_agreement_verdicts():
    s = np.full(10, 0.01)
    h = np.linspace(0, 1, 10)
    assert pair_agreement([h, h + 0.01], [s, s]).verdict == "pass"
    assert pair_agreement([h, 1.3 * h], [s, s]).verdict == "fail"
    wide = np.full(10, 1.0)
    # a clear response (final 5 = 5 sigma) but 2*sqrt(2)/5 = 57 % > 30 % detectable change
    assert pair_agreement([5 * h, 5 * h], [wide, wide]).verdict == "insufficient_data"
    assert pair_agreement([h], [s]).verdict == "insufficient_data"
    # a pair without any response passes: there is no gain to compare
    z = np.zeros(10)
    assert pair_agreement([z, z + 0.001], [wide, wide]).verdict == "pass"


def test_ljung_box_white_vs_coloured():
    rng = np.random.default_rng(33)
    e = rng.standard_normal(5000)
    assert ljung_box(e, lags=20)["white"]
    ar = ar1(5000, 0.5, rng)
    lb = ljung_box(ar, lags=20)
    assert not lb["white"] and lb["autocorrelation"][0] == pytest.approx(0.5, abs=0.05)


def test_cross_correlation_detects_missing_input_effect():
    rng = np.random.default_rng(34)
    x = rng.standard_normal(4000)
    e_indep = rng.standard_normal(4000)
    ok = cross_correlation_check(x, e_indep, max_lag=20)
    assert ok["ok"]
    assert ok["band"] == pytest.approx(2.5758 / np.sqrt(4000), rel=1e-3)
    e_dep = e_indep + 0.3 * np.concatenate([np.zeros(5), x[:-5]])  # effect at lag 5
    bad = cross_correlation_check(x, e_dep, max_lag=20)
    assert not bad["ok"]
    assert bad["lags"][int(np.argmax(np.abs(bad["r"])))] == 5


def test_windows_are_disjoint_and_spread():
    w = split_windows_by_length(1000, 200, 3)
    assert w == [(0, 200), (400, 600), (800, 1000)]
    assert split_windows_by_length(100, 200, 2) == []


def test_search_on_too_short_record_says_what_to_do():
    # the default longest horizon is N // (5 n_x) lags: 12 samples give 2 < n_p_min = 3
    rng = np.random.default_rng(0)
    with pytest.raises(InsufficientDataError, match=r"too short for the N_p search"):
        search(rng.standard_normal(12), rng.standard_normal(12), dt=1.0)


def _gls_by_hand(u: np.ndarray, y: np.ndarray, d: np.ndarray, n_p: int):
    """Generalised least squares of an FIR with a known AR noise filter ``d``, in plain
    numpy: filter the output and every lagged input with ``D(q)`` and solve; the step
    response and its standard deviation (``sigma^2 = RSS / (N - n_p - p)``).  The first
    observation is sample ``n_p + p``, as in the estimator's lag Gram (which holds
    ``n_p + p + 1`` lags, method.md §10)."""
    p = d.size - 1
    k0 = n_p + p
    ks = np.arange(k0, u.size)
    yf = sum(d[i] * y[ks - i] for i in range(p + 1))
    Phi = np.column_stack([sum(d[i] * u[ks - lag - i] for i in range(p + 1))
                           for lag in range(n_p)])
    b, rss = np.linalg.lstsq(Phi, yf, rcond=None)[:2]
    s2 = float(rss[0]) / (ks.size - n_p - p)
    cum = np.tril(np.ones((n_p, n_p)))
    cov = cum @ (s2 * np.linalg.inv(Phi.T @ Phi)) @ cum.T
    return cum @ b, np.sqrt(np.diag(cov))


def test_windows_are_estimated_with_the_record_noise_model():
    """A noise-model search estimates each disjoint window by generalised least squares
    with the noise model found on the whole record (SearchResult.window_noise): the same
    step response and standard deviation as that filter applied by hand."""
    from tests.plants import open_loop_record

    u, y = open_loop_record(6000, 0.9, 4_100_001)
    res = search(u, y, dt=1.0, n_p=40, noise="auto")
    [model] = res.window_noise
    assert model.order >= 1 and model is res.noise_model[0]
    d = np.r_[1.0, model.coefficients]
    assert len(res.window_estimates) == 2
    for (a, b), est in res.window_estimates.items():
        step, std = _gls_by_hand(u[a:b], y[a:b], d, 40)
        np.testing.assert_allclose(est.step[0, 0, :40], step, atol=1e-9 * std.max())
        np.testing.assert_allclose(est.step_std[0, 0, :40], std, rtol=1e-9)
        assert est.noise_model[0].coefficients == model.coefficients
    from pipeline.errors import ConfigError
    from pipeline.estimation.estimate import estimate_step_responses

    with pytest.raises(ConfigError, match="1 models for 2 outputs"):
        estimate_step_responses(u, np.column_stack([y, y]), n_p=40, dt=1.0,
                                noise_models=res.window_noise)
    with pytest.raises(ConfigError, match="instrumental variables refit their own"):
        estimate_step_responses(u, y, n_p=40, dt=1.0, noise_models=res.window_noise,
                                instruments=u)


def _two_input_record(seed: int, *, ends_excited: bool):
    """Two AR(1) 0.8 inputs through first-order lags (gains 1 and -0.5), coloured noise;
    with ``ends_excited`` the inputs move 10x more (in amplitude) in the first and last
    fifths of the record than in between, so the windows at the record's ends hold about
    2.5x the record's average excitation."""
    rng = np.random.default_rng(seed)
    n = 40_000
    u = np.column_stack([ar1(n, 0.8, rng) for _ in range(2)])
    if ends_excited:
        amp = np.full(n, 0.3)
        amp[: n // 5] = amp[-n // 5:] = 3.0
        u = u * amp[:, None]
    y = simulate(ct.tf([1.0], [6.0, 1.0]), u[:, 0], 1.0) \
        + simulate(ct.tf([-0.5], [3.0, 1.0]), u[:, 1], 1.0)
    return u, y + simulate(ct.tf([1.0], [10.0, 1.0]), 3.0 * rng.standard_normal(n), 1.0)


@pytest.mark.parametrize("seed,ends_excited", [(4_100_002, False), (4_100_007, True)])
def test_window_lengths_skipped_as_uninformative_are_so_when_estimated(seed, ends_excited):
    """Stage 2 does not estimate a window length whose windows the whole-record fit
    predicts to be uninformative (a pair's detectable change above sqrt(2) x 30 %, its
    variance scaled by N / N_d and by how much less its input moves in the windows); each
    skipped length, estimated here anyway, indeed leaves a responding pair unable to
    detect a 30 % change.  With the excitation at the record's ends the windows there
    know more than N / N_d says: scaled by N / N_d alone, the length where these windows
    agree (1 320) was skipped and N_d doubled past it."""
    from pipeline.estimation.estimate import estimate_step_responses
    from pipeline.identification.checks import window_agreement

    u, y = _two_input_record(seed, ends_excited=ends_excited)
    n = u.shape[0]
    res = search(u, y, dt=1.0, noise="auto")
    skipped = [t for t in res.nd_trace if "skipped" in t]
    assert skipped and "pairs" in res.nd_trace[-1]
    for t in skipped:
        wins = split_windows_by_length(n, t["window_samples"], 2)
        ests = [estimate_step_responses(u[a:b], y[a:b], n_p=res.n_p, dt=1.0, n_k=res.n_k,
                                        noise_models=res.window_noise) for a, b in wins]
        agr = [a for row in window_agreement(ests) for a in row]
        assert any(a.verdict == "insufficient_data" for a in agr), t
        assert {(p["output"], p["input"]) for p in t["uninformative"]} <= \
            {(0, j) for j, a in enumerate(agr) if a.detectable_change > 0.3}
    assert res.nd_trace[-1]["windows_agree"] and res.n_d == res.nd_trace[-1]["n_d"]


def test_a_window_that_cannot_be_estimated_is_a_recorded_trial():
    """Two inputs that move together in the first 3,000 samples (the same signal) make
    that window singular although each moves (so no prediction skips it): the trial is
    recorded with the window and the error, and N_d grows until both windows can be
    estimated.  (A window where an input does not move at all is skipped as surely
    uninformative: its power ratio is infinite.)"""
    rng = np.random.default_rng(4_100_003)
    n = 12_000
    u = np.column_stack([ar1(n, 0.8, rng) for _ in range(2)])
    u[:3000, 1] = u[:3000, 0]
    y = simulate(ct.tf([1.0], [4.0, 1.0]), u[:, 0], 1.0) \
        + simulate(ct.tf([2.0], [4.0, 1.0]), u[:, 1], 1.0) + 0.1 * rng.standard_normal(n)
    res = search(u, y, dt=1.0, n_p=20)
    failed = [t for t in res.nd_trace if "failed_window" in t]
    assert failed and failed[0]["failed_window"][0] == 0
    assert all("singular" in t["error"] and "move together" in t["error"] for t in failed)
    assert res.n_d > failed[-1]["n_d"] and res.agreement


@pytest.mark.parametrize("noise,form", [("white", "level"), ("walk", "differenced")])
def test_integrating_windows_keep_the_record_form_and_filter(noise, form):
    """An integrating output: the form the record's fit chose (level form for white level
    noise, differenced for a random walk) is the form every window is estimated in, with
    the record's filter."""
    from tests.plants import open_level_record

    u, y, _ = open_level_record(8000, noise, 11)
    res = search(u, y, dt=1.0, integrating=True, noise="auto")
    [model] = res.window_noise
    assert model.form == form
    for est in res.window_estimates.values():
        assert est.noise_model[0].form == form
        assert est.noise_model[0].coefficients == model.coefficients
        assert np.all(np.isfinite(est.rate)) and np.all(est.rate_std > 0)


def test_null_windows_of_a_pair_the_record_shows_responding_are_not_agreement():
    """Very noisy windows are null (every lag within 2 sigma): evidence of agreement only
    for a pair with no response.  Gain 1, noise 8 (s.d.), 40 000 samples at N_p 25: the
    record shows the response, so windows of 10 N_p = 250 observations, null, do not
    agree by default (they did: the search stopped there with a detectable change of
    470 %); N_d grows to the record's end and the pair stays insufficient_data."""
    rng = np.random.default_rng(32)
    n = 40_000
    u = ar1(n, 0.5, rng)
    y = simulate(ct.tf([1.0], [5.0, 1.0]), u, 1.0) + 8.0 * rng.standard_normal(n)
    res = search(u, y, dt=1.0, n_p=25)
    assert not any(t.get("windows_agree") for t in res.nd_trace)
    assert res.n_d > n // 2 - 100
    assert res.agreement[0][0].verdict == "insufficient_data"
    h, wide = np.linspace(0.1, 1.0, 8), np.ones(8)
    assert pair_agreement([h, h], [wide, wide]).verdict == "pass"  # null, nothing known
    assert pair_agreement([h, h], [wide, wide], responds=True).verdict == "insufficient_data"
