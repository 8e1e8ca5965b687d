"""Integrating outputs with a noisy level sensor (issue 9, must-show 4).

Drum level with shrink and swell (tests/plants.py: steam flow -> -0.01/s + 0.59/(10 s+1),
wrong-way peak 0.312; feedwater -> 0.008/(s (3 s+1)) with 2 s dead time), simulated with
python-control's exact ZOH, white level-sensor noise of s.d. 1 (the swell of a unit steam
step is 0.59).  Differencing that noise (eq. 3.15) leaves MA(1) noise with a unit root:
the thesis' estimate is unbiased but its wrong-way peak has σ ≈ 0.2 for a peak of 0.31.
``noise="auto"`` must pick the level form (level on cumulated inputs, exact for white
measurement noise) from the data and recover the peak and the rates.

Tolerances: 30 records of 2e4 samples.  "Within 20 % / 3 %" is asked of 90 % of the
records (the estimate's own σ at the peak is ~7 % of it, so 20 % is ~3σ; the rates' σ
are ~0.4 %, so 3 % is many σ — the tolerance is the must-show's).
"""

from __future__ import annotations

import numpy as np
import pytest


from pipeline.readouts.characteristics import integrating_characteristics
from pipeline.estimation.estimate import estimate_step_responses
from tests.plants import DRUM_RATES, ar1, drum_plant, drum_record, drum_truth, zoh_response

N = 20_000
N_P = 80
RECORDS = 30
H_STEAM, H_FEED = drum_truth(N_P)
PEAK = float(H_STEAM.max())


@pytest.mark.statistical
def test_auto_recovers_the_wrong_way_peak_and_the_rates_with_calibrated_bands():
    peak_ok, rate_ok, cover, rate_cover, forms, sd_white = [], [], [], [], set(), []
    for k in range(RECORDS):
        x, level = drum_record(N, 4_100_000 + k)
        est = estimate_step_responses(x, level, n_p=N_P, dt=1.0, integrating=True,
                                      noise="auto")
        forms.add(est.noise_model[0].form)
        ch = integrating_characteristics(est.step[0, 0], dt_s=1.0, step_std=est.step_std[0, 0],
                                         rate=float(est.rate[0, 0]))
        peak_ok.append(abs(ch.inverse_peak / PEAK - 1) <= 0.20)
        rate_ok.append(all(abs(est.rate[0, j] / DRUM_RATES[j] - 1) <= 0.03 for j in range(2)))
        cover.append(np.mean(np.concatenate([
            np.abs(est.step[0, 0] - H_STEAM) <= 2 * est.step_std[0, 0],
            np.abs(est.step[0, 1] - H_FEED) <= 2 * est.step_std[0, 1]])))
        rate_cover += [abs(est.rate[0, j] - DRUM_RATES[j]) <= 2 * est.rate_std[0, j]
                       for j in range(2)]
        if k < 5:
            w = estimate_step_responses(x, level, n_p=N_P, dt=1.0, integrating=True)
            sd_white.append(w.step_std[0, 0, int(np.argmax(H_STEAM))])
    print(f"peak within 20 %: {np.mean(peak_ok):.0%}, rates within 3 %: {np.mean(rate_ok):.0%},"
          f" coverage {np.mean(cover):.1%}, rate coverage {np.mean(rate_cover):.0%}, forms "
          f"{forms}, white sigma at the peak {np.mean(sd_white):.3f} for a peak of {PEAK:.3f}")
    assert forms == {"level"}
    assert np.mean(peak_ok) >= 0.9
    assert np.mean(rate_ok) >= 0.9
    assert 0.90 <= np.mean(cover) <= 0.99
    assert np.mean(rate_cover) >= 0.85
    # the problem it solves: differenced white least squares is honest but useless here
    assert np.mean(sd_white) > 0.5 * PEAK


def test_a_random_walk_disturbance_keeps_the_differenced_form():
    """Process noise that integrates (a level disturbance that is a random walk, no
    sensor noise) is white after differencing: auto must keep eq. 3.15's form."""
    Gs, Gf, dly = drum_plant()
    forms = set()
    for k in range(5):
        rng = np.random.default_rng(4_200_000 + k)
        us, uf = ar1(N, 0.95, rng), ar1(N, 0.95, rng)
        level = zoh_response(Gs, us, 1.0) + zoh_response(Gf, uf, 1.0, dly)
        level = level + np.cumsum(0.05 * rng.standard_normal(N))
        est = estimate_step_responses(np.column_stack([us, uf]), level, n_p=N_P, dt=1.0,
                                      integrating=True, noise="auto")
        forms.add(est.noise_model[0].form)
        assert abs(est.rate[0, 0] - DRUM_RATES[0]) < 3 * est.rate_std[0, 0]
    assert forms == {"differenced"}

