"""Closed loops (issue 9, must-show 2): feedback detection, the direct estimate with a
noise model and a known delay, and the setpoint as an instrument.

The loop of the issue, simulated by an explicit loop in tests/plants.py: plant
``y(k) = 0.9 y(k-1) + 0.1 u(k-1)`` (gain 1, one sample of delay), a PI controller that
reacts to the same sample's measurement, setpoint steps, AR(1) output noise of s.d. 1
(the setpoint steps have s.d. 1 too), 2e4 samples.  On these records the thesis' white
least squares is 5 % (white noise), 24 % (φ = 0.9) and 39 % (φ = 0.97) low in gain while
claiming a σ of well under 1 % — the test below measures that as well.

Tolerances: 40 records each (80 until the suite's time budget of issue 35; the
benchmark ``bench_oracle``'s PI case runs 30 more through the job path).  Coverage: the
pass mark 85 % is the must-show; the nominal 95.4 % sits 3 standard errors above it.
Detection: measured 100 % on 80 records; at a true rate of 99 %, fewer than 38 of 40 is
a 0.8 % event.  Detection/false-alarm rates are
binomial: the false-alarm rate is nominally 1 % (the test's α), so more than 5 % of 200
open-loop records would be a 1e-4 event.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom

from pipeline.identification.conditioning import condition
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.estimation.gram_estimate import estimate_from_context, lag_gram_context, lags_needed
from pipeline.identification.feedback import FEEDBACK_ALPHA, FEEDBACK_LEADS, feedback_test
from pipeline.identification.search import default_n_p_max, search
from tests.plants import (LEVEL_NOISES, open_level_record, open_loop_record,
                          pi_controlled_record, pi_loop_record, pi_loop_truth)

N = 20_000
RECORDS = 40  # module notes
SEARCH_RECORDS = 20  # the search test's records (its notes)
N_P = 60  # 0.9^59 < 0.2 %: the plant has settled
TRUTH = pi_loop_truth(N_P)


def _gain_error_and_coverage(est) -> tuple[float, float, bool]:
    s, sd = est.step[0, 0], est.step_std[0, 0]
    return (abs(s[-1] - TRUTH[-1]) / TRUTH[-1], float(np.mean(np.abs(s - TRUTH) <= 2 * sd)),
            bool(abs(s[-1] - TRUTH[-1]) <= 2 * sd[-1]))


@pytest.mark.statistical
def test_direct_estimate_with_noise_model_and_known_delay_is_consistent():
    rows = {"white": [], "auto": [], "iv": []}
    for k in range(RECORDS):
        u, y, r = pi_loop_record(N, 0.9, 3_100_000 + k)
        rows["white"].append(_gain_error_and_coverage(
            estimate_step_responses(u, y, n_p=N_P, dt=1.0)))
        rows["auto"].append(_gain_error_and_coverage(
            estimate_step_responses(u, y, n_p=N_P, dt=1.0, noise="auto", n_k=1)))
        rows["iv"].append(_gain_error_and_coverage(
            estimate_step_responses(u, y, n_p=N_P, dt=1.0, noise="auto", instruments=r)))
    stats = {m: (float(np.median([e for e, _, _ in v])), float(np.mean([c for _, c, _ in v])),
                 float(np.mean([f for _, _, f in v]))) for m, v in rows.items()}
    print({m: f"gain error {a:.1%}, coverage lags {b:.0%}, final {c:.0%}"
           for m, (a, b, c) in stats.items()})
    # the problem: white least squares is badly biased and claims a tiny sigma
    assert stats["white"][0] > 0.15 and stats["white"][2] < 0.1
    # direct with noise model and n_k = 1
    assert stats["auto"][0] <= 0.05
    assert stats["auto"][1] >= 0.85 and stats["auto"][2] >= 0.85
    # the setpoint as instrument
    assert stats["iv"][0] <= 0.04
    assert stats["iv"][1] >= 0.85 and stats["iv"][2] >= 0.85


@pytest.mark.statistical
def test_search_detects_the_loop_and_fixes_the_same_sample_term():
    """Through the search a job runs: feedback detected, n_k = 1 set, gain right.
    ``SEARCH_RECORDS`` records: at a true detection rate of 99 % fewer than 18 of 20 is
    a 0.1 % event (binomial)."""
    detected, errors, n_k = [], [], []
    for k in range(SEARCH_RECORDS):
        u, y, _ = pi_loop_record(N, 0.9, 3_200_000 + k)
        sr = search(u, y, dt=1.0, noise="auto", feedback="auto", n_p=N_P)
        fb = sr.feedback[0][0]
        detected.append(fb is not None and fb.detected)
        n_k.append(int(sr.n_k[0, 0]))
        est = estimate_step_responses(u, y, n_p=sr.n_p, dt=1.0, noise="auto", n_k=sr.n_k)
        errors.append(abs(est.step[0, 0, -1] - 1.0))
    print(f"detected {np.mean(detected):.0%}, median gain error {np.median(errors):.1%}")
    assert sum(detected) >= binom.ppf(0.01, SEARCH_RECORDS, 0.99)  # 18 of 20
    assert all(nk == 1 for nk, d in zip(n_k, detected) if d)
    assert np.median(errors) <= 0.05


def test_feedback_test_false_alarms_in_open_loop_stay_at_its_rate():
    """200 open-loop records with white and coloured noise: the non-causal lead terms are
    chi^2(leads) under no feedback, so about 1 % are flagged."""
    flagged = 0
    total = 0
    for phi in (0.0, 0.5, 0.9, 0.97):
        for k in range(50):
            u, y = open_loop_record(8000, phi, 3_300_000 + 1000 * int(phi * 100) + k)
            ctx = lag_gram_context(u, y, n_lags=70 + FEEDBACK_LEADS + 21)
            est = estimate_from_context(ctx, n_p=70, n_k=0, dt=1.0)
            fb = feedback_test(ctx, n_p=np.full((1, 1), 70), n_k=np.zeros((1, 1), int),
                               noise_models=est.noise_model)[0][0]
            flagged += fb.detected
            total += 1
            assert fb.alpha == FEEDBACK_ALPHA and fb.leads == FEEDBACK_LEADS
    print(f"open loop flagged {flagged}/{total}")
    assert flagged / total <= 0.05


@pytest.mark.parametrize("phi", [0.0, 0.97])
def test_feedback_is_detected_with_white_and_slow_noise(phi):
    hits = 0
    for k in range(20):
        u, y, _ = pi_loop_record(N, phi, 3_400_000 + k)
        ctx = lag_gram_context(u, y, n_lags=N_P + FEEDBACK_LEADS + 21)
        est = estimate_from_context(ctx, n_p=N_P, n_k=0, dt=1.0)
        fb = feedback_test(ctx, n_p=np.full((1, 1), N_P), n_k=np.zeros((1, 1), int),
                           noise_models=est.noise_model)[0][0]
        hits += fb.detected
    assert hits >= 19  # >= 95 % of 20


def _job_feedback_test(x: np.ndarray, y: np.ndarray, *, integrating: bool,
                       n_p: int | None = None) -> list:
    """The feedback test as a job runs it: detrended signals, the noise model of the fit at
    ``n_p`` (default: the default ``n_p_max``; its form chosen by BIC), the test there."""
    c = condition(x, y[:, None], method="detrend", dt_s=1.0)
    n_x = x.shape[1]
    npm = np.full((1, n_x), n_p or default_n_p_max(x.shape[0], n_x))
    ctx = lag_gram_context(c.x, c.y, integrating=integrating,
                           n_lags=lags_needed(npm, False, None, FEEDBACK_LEADS))
    est = estimate_from_context(ctx, n_p=npm, n_k=0, dt=1.0, noise="auto")
    return feedback_test(ctx, n_p=npm, n_k=np.zeros((1, n_x), int),
                         noise_models=est.noise_model)[0]


def test_feedback_false_alarms_on_short_integrating_records_stay_at_its_rate():
    """Issue 36: open-loop levels of 250 samples (what α_T's decimation leaves of a level
    record), two inputs, white sensor noise alone or with an AR(1), a random walk or an
    integrated AR(1) disturbance.  The test's regression keeps ~30 residual degrees of
    freedom; with chi^2 references and the level form alone the test flagged 3 of these 40
    pairs (17 of 160 with 20 such records per disturbance).  At its 1 % rate more than 2
    of 40 is a 0.8 % event."""
    flagged, dofs = 0, []
    for k in range(20):
        x, y, _ = open_level_record(250, LEVEL_NOISES[k % 4], 3_600_000 + k, n_x=2)
        for fb in _job_feedback_test(x, y, integrating=True):
            flagged += fb.detected
            dofs.append(fb.residual_dof)
            if fb.p_by_form:  # a level-form output: the differenced form referees it
                assert set(fb.p_by_form) == {"level", "differenced"}
                assert fb.p_value == max(fb.p_by_form.values())
    print(f"open-loop integrating pairs flagged {flagged}/40, residual dof {min(dofs)}-"
          f"{max(dofs)}")
    assert max(dofs) < 60  # the regime the F reference is for
    assert flagged <= 2


def test_feedback_is_detected_on_controlled_levels_and_outputs():
    """Five PI loops, the controller output as the input (three levels, two
    self-regulating outputs), 6000 samples, at N_p = 100 (the loops settle within ~80
    samples; a job with ``search.settling_time_s``): feedback is found in every one."""
    for k, integrating in enumerate((True, True, True, False, False)):
        u, y, _ = pi_controlled_record(6000, integrating, 3_700_000 + k)
        fb = _job_feedback_test(u, y, integrating=integrating, n_p=100)[0]
        assert fb.detected, (k, integrating, fb.p_value)
