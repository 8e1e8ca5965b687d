"""The compiled many-limit saturation pass (pipeline.discrepancy.lure) against exact,
independent computations: each limit pair simulated on its own by the block-diagram
simulator's per-sample path (``predict_outputs``), and the whitened sum of squares of
its error computed by ``Problem.whiten_split`` -- no code shared with the pass."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.discrepancy.analyse import discrepancy_problem
from pipeline.discrepancy.config import DiscrepancyConfig
from pipeline.discrepancy.lure import StaticMapPath, first_crossing
from pipeline.discrepancy.effects import Effect, predict_outputs
from tests.benchmarks.bench_discrepancy import load_model
from pipeline.progress import quiet
from pipeline.simulated.synthetic import make_discrepancy_demo


@pytest.fixture(scope="module")
def problem():
    model = load_model("boiler_pressure")
    inputs, measured, dt_s = make_discrepancy_demo(model, seed=5, hours=1.0, dt_s=1.0)
    P, _, _ = discrepancy_problem(model, inputs, measured, dt_s, DiscrepancyConfig(), quiet)
    # a coloured-noise whitening filter per output (AR(2)), as the analysis fits one
    P.ar = [np.array([1.0, -0.9, 0.2])] * P.n_y
    P.sigma = np.array([0.01 * float(np.std(P.y[:, i])) + 1e-9 for i in range(P.n_y)])
    return P


# limits inside the controller's range (a wound-up PI loop), one-sided and two-sided,
# and no limit at all
def _pairs(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = np.quantile(v, [0.1, 0.3, 0.7, 0.9])
    lows = np.array([q[0], -np.inf, q[1], -np.inf, q[0]])
    highs = np.array([np.inf, q[3], q[2], np.inf, q[3]])
    return lows, highs


@pytest.mark.parametrize("loc", ["controller", "fuel"])
def test_each_column_equals_its_own_exact_simulation(problem, loc):
    P = problem
    stop = P.holdout_start
    v = P.nominal_signals[loc][:stop]
    lows, highs = _pairs(v)
    path = StaticMapPath(P, loc, P.nominal_signals[loc], stop)
    first = first_crossing(v, lows, highs)
    assert first < stop  # the limits act
    change = path.clip_corrections(P, lows, highs, first=first)
    sse = path.clip_sse(P, lows, highs, first=first)
    inputs = {k: v_[:stop] for k, v_ in P.inputs.items()}
    for j, (lo, hi) in enumerate(zip(lows, highs, strict=True)):
        effect = None if np.isinf(lo) and np.isinf(hi) else Effect(
            "saturation", loc, {"low": float(lo), "high": float(hi)})
        pred = predict_outputs(P.model, effect, inputs, dt_s=P.dt_s, outputs=P.outputs)
        y_exact = np.column_stack([pred[o] for o in P.outputs])
        scale = float(np.max(np.abs(y_exact)))
        np.testing.assert_allclose(P.y_nominal[:stop] + change[:, :, j], y_exact,
                                   rtol=0, atol=1e-9 * scale)
        whitened = P.whiten_split(P.y[:stop] - y_exact, P.fit_start, stop)
        expected = sum(float(w @ w) for w in whitened)
        assert sse[j] == pytest.approx(expected, rel=1e-9)
    # the clips change the outputs (the comparison above is not between zeros)
    assert np.max(np.abs(change[:, :, 0])) > 1e-3 * float(np.max(np.abs(P.y_nominal)))
    assert len(set(np.round(sse, 6))) == lows.size  # every pair gives its own fit


def test_no_limit_column_is_the_nominal_fit(problem):
    P = problem
    stop = P.holdout_start
    path = StaticMapPath(P, "controller", P.nominal_signals["controller"], stop)
    sse = path.clip_sse(P, np.array([-np.inf]), np.array([np.inf]), first=0)
    whitened = P.whiten_split(P.y[:stop] - P.y_nominal[:stop], P.fit_start, stop)
    assert sse[0] == pytest.approx(sum(float(w @ w) for w in whitened), rel=1e-12)


def test_the_fir_residual_rms_is_over_the_samples_the_fir_fit_predicts(problem):
    """``localization[out]["fir_residual_rms"]`` is the RMS of the FIR regression's
    residual over the samples it predicts: the warm-up of ``n_p`` lags (zeros in the
    residual ``localise`` hands on) is not part of it."""
    from pipeline.discrepancy.localise import localise

    P = problem
    resid = P.y - P.y_nominal
    loc, fir_out, _ = localise(P, resid, np.random.default_rng(0))
    for i, out in enumerate(P.outputs):
        f = fir_out[i]
        predicted = f[f != 0.0]
        assert 0 < predicted.size < f.size  # a warm-up was left out
        assert loc[out]["fir_residual_rms"] == pytest.approx(
            float(np.sqrt(np.mean(predicted ** 2))), rel=1e-12)
