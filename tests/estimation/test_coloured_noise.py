"""Open loop with coloured noise (issue 9, must-show 1): calibrated bands, honest window
agreement, accuracy against white least squares and a high-order ARX.

Records: a second-order plant with 3 s dead time (tests/plants.py, python-control ZOH),
an input that moves like normal operation, AR(1) noise at 30 % of the output's s.d.;
10 000 samples; 80 seeded records per noise pole.  Every estimate goes through the
automatic N_p/N_d search (``search(noise="auto")``), as a job does.

The peer tools' estimate is an ARX model whose order is chosen by BIC from 1..40, fitted
by explicit least squares (``tests/plants.arx_bic_step``), as MATLAB's arxstruc/selstruc
does; accuracy is the largest error of the step response over twice the settling time
(an estimate continued by its last value beyond its N_p) against white least squares,
and the RMS error over the same horizon against the ARX (a parametric step response is
smooth by construction; the largest error of a 60-lag FIR is the random walk of its last
lags, 1.0-1.25x the ARX's at these noise levels — printed, not asserted), medians over
the records.

Tolerances.  The full Monte Carlo (80 records per noise pole, 40 with a gain change) is
``tests/benchmarks/bench_coloured_noise.py``, which holds the must-show's 90–98 % band; the
suite runs a CI sample of 40 records per pole (20 with a gain change) so that it stays in
its time budget.  With 40 records the coverage over lags (~60 correlated lags per record,
so roughly 40 independent draws) has a standard error of about 3.5 %, so the CI sample
checks the side users are hurt by — bands too narrow — at 88 %: a calibrated ±2σ band
(95.4 %) fails it with probability 2 % per pole, a band at 85 % fails it with probability
~80 %; the upper side (bands too wide, 98 %) is the benchmark's, whose 80 records resolve it.
The CI sample runs the two strongly coloured poles (0.9, 0.97) for the bands and the
most coloured one for the gain change, where the white estimate fails and detection is
hardest; the benchmark runs 0.5 as well.  The false-fail rate is at most 5 % by
construction (1 % lag-wise Wald test + 4 % on the windows' gains, Bonferroni; issue 32
added the gain part) — binomial at 5 %: P(more than 7 of 40) < 0.3 %.  The gain-change detection needs 90 % and the agreement test is built
for 90 % power at the chosen N_d (measured 100 % on 80 records; at a power of 0.99,
P(fewer than 18 of 20) < 0.2 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.estimation.estimate import estimate_step_responses
from pipeline.identification.search import search
from tests.plants import arx_bic_step, open_loop_record, open_loop_truth

N = 10_000
RECORDS = 40  # the CI sample; the benchmark runs 80 (module notes)
CHANGE_RECORDS = 20  # detection is measured at 100 %: P(< 90 % of 20 | power 0.99) < 0.2 %
MIN_COVERAGE = 0.88  # the CI sample's lower bound below 95.4 % (module notes)
MAX_FALSE_FAILS = 7  # of RECORDS at the 5 % rate: P(more) < 0.3 % (module notes)
HORIZON = 90  # lags compared: twice the 98 % settling time
ARX_MAX_ORDER = 40
TRUTH = open_loop_truth(400)


def _errors(step: np.ndarray) -> tuple[float, float]:
    """Largest and RMS error over the horizon, the estimate continued by its last value
    (what the FIR model says beyond its N_p)."""
    n = step.size
    ext = np.concatenate([step, np.full(max(0, HORIZON - n), step[-1])])[:HORIZON]
    e = ext - TRUTH[:HORIZON]
    return float(np.max(np.abs(e))), float(np.sqrt(np.mean(e**2)))


def _run(phi: float, seed0: int, records: int = RECORDS) -> dict:
    cover, fails, insufficient, err_auto, err_white, err_arx = [], 0, 0, [], [], []
    rms_auto, rms_arx = [], []
    for k in range(records):
        u, y = open_loop_record(N, phi, seed0 + k)
        sr = search(u, y, dt=1.0, noise="auto")
        est = estimate_step_responses(u, y, n_p=sr.n_p, dt=1.0, noise="auto")
        n = int(est.n_p[0, 0])
        s, sd = est.step[0, 0, :n], est.step_std[0, 0, :n]
        cover.append(np.mean(np.abs(s - TRUTH[:n]) <= 2 * sd))
        verdict = sr.agreement[0][0].verdict
        fails += verdict == "fail"
        insufficient += verdict == "insufficient_data"
        e_max, e_rms = _errors(s)
        err_auto.append(e_max)
        rms_auto.append(e_rms)
        srw = search(u, y, dt=1.0, noise="white")
        w = estimate_step_responses(u, y, n_p=srw.n_p, dt=1.0)
        err_white.append(_errors(w.step[0, 0, : int(w.n_p[0, 0])])[0])
        a_max, a_rms = _errors(arx_bic_step(u, y, ARX_MAX_ORDER, HORIZON)[1])
        err_arx.append(a_max)
        rms_arx.append(a_rms)
    return {"coverage": float(np.mean(cover)), "false_fail": fails / records,
            "insufficient": insufficient / records,
            "ratio_white": float(np.median(np.array(err_auto) / np.array(err_white))),
            "ratio_arx_max": float(np.median(err_auto) / np.median(err_arx)),
            "ratio_arx": float(np.median(rms_auto) / np.median(rms_arx)),
            "err_auto": float(np.median(err_auto)), "err_white": float(np.median(err_white)),
            "err_arx": float(np.median(err_arx))}


@pytest.mark.statistical
@pytest.mark.parametrize("phi,seed0", [(0.9, 2_200_000), (0.97, 2_300_000)])
def test_auto_bands_cover_the_truth_and_windows_agree(phi, seed0):
    r = _run(phi, seed0)
    print(f"phi={phi}: {r}")
    assert r["coverage"] >= MIN_COVERAGE
    assert r["false_fail"] <= MAX_FALSE_FAILS / RECORDS
    # never less accurate than the thesis' white least squares (largest error), and as
    # accurate as the peer ARX over the whole response (RMS error; the largest error of
    # a long FIR is the random walk of its late lags, ~1.0-1.25x the ARX's, printed)
    assert r["ratio_white"] <= 1.0
    assert r["ratio_arx"] <= 1.2


@pytest.mark.statistical
@pytest.mark.parametrize("phi,seed0", [(0.97, 2_600_000)])
def test_a_30_percent_gain_change_fails_the_window_agreement(phi, seed0):
    rate = change_detection(phi, seed0)
    assert rate >= 0.90


def change_detection(phi: float, seed0: int, records: int = CHANGE_RECORDS) -> float:
    """Share of ``records`` records with a 30 % gain change between their windows whose
    window agreement fails."""
    verdicts = []
    for k in range(records):
        u, y = open_loop_record(N, phi, seed0 + k, gain_change=1.3)
        verdicts.append(search(u, y, dt=1.0, noise="auto").agreement[0][0].verdict)
    rate = np.mean([v == "fail" for v in verdicts])
    print(f"phi={phi}: 30 % gain change fails in {rate:.0%} of {records} records")
    return float(rate)


def test_white_noise_bands_are_what_the_thesis_promised_and_coloured_ones_are_not():
    """The problem the noise model solves, measured on the same records: the thesis'
    white-noise band covers the truth on white noise but not on AR(1) 0.97 noise."""
    cov = {}
    for phi in (0.0, 0.97):
        c = []
        for k in range(20):
            u, y = open_loop_record(N, phi, 2_700_000 + k)
            e = estimate_step_responses(u, y, n_p=70, dt=1.0)
            c.append(np.mean(np.abs(e.step[0, 0] - TRUTH[:70]) <= 2 * e.step_std[0, 0]))
        cov[phi] = np.mean(c)
    print(cov)
    assert cov[0.0] >= 0.88
    assert cov[0.97] <= 0.75
