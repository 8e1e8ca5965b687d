"""Model parameters bounded before simulation (issue 33, build 4): a dead time longer than
the record, a model with too many blocks, an unstable block or loop, a simulation that
overflows -- each one message naming the block or loop and the numbers (exit 2 in the
CLI), never an allocation of terabytes, a MemoryError or a blame on the data.

Known answers: ``den: [-20, 1]`` has its pole at s = +1/20 = +0.05 1/s (e-fold every
20 s).  The loop ``f = u + 1.5 y``, ``y = 2 / (20 s + 1) f`` at dt_s = 1 s: the ZOH
discretisation of the lag is ``y+ = a y + 2 (1 - a) f`` with a = exp(-1/20), so the loop
alone is ``y+ = (a + 3 (1 - a)) y``: its pole is z = 3 - 2 exp(-1/20) = 1.097541, its
static loop gain 1.5 * 2 = +3.
"""

from __future__ import annotations

import contextlib
import io
import math
import time

import numpy as np
import pytest

from flows.cli import main
from pipeline.errors import DivergenceError, ModelError
from pipeline.models.model import MAX_BLOCKS, model_from_dict
from pipeline.models.simulate import discrete_state_space, simulate
from pipeline.models.stability import GROWTH_LIMIT, check_simulable, unstable_parts
from tests.conftest import PLANT_GAIN, PLANT_TAU_S


def _model(*blocks: dict, outputs=("y",)) -> dict:
    return {"name": "plant", "inputs": ["u"], "outputs": list(outputs), "blocks": list(blocks)}


LAG = {"name": "y", "type": "first_order", "input": "u", "k": PLANT_GAIN, "tau_s": PLANT_TAU_S}
NEGATIVE_TAU = {"name": "y", "type": "transfer", "input": "u", "num": [2.0], "den": [-20.0, 1.0]}
POSITIVE_LOOP = ({"name": "f", "type": "sum", "inputs": ["u", {"signal": "y", "k": 1.5}]},
                 {"name": "y", "type": "first_order", "input": "f", "k": 2.0, "tau_s": 20.0})
LOOP_POLE = 3.0 - 2.0 * math.exp(-1.0 / 20.0)


def discrepancy(make_job, model: dict) -> tuple[int, str, str]:
    job = make_job(1, hours=1.0, model=model)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["discrepancy", str(job), "--no-prefect"])
    return rc, out.getvalue(), err.getvalue()


def refused(rc: int, err: str, *needles: str) -> None:
    assert rc == 2, err[-3000:]
    assert "Traceback" not in err and err.count("plantdyn: error:") == 1, err[-3000:]
    for needle in needles:
        assert needle in err, err[-3000:]
    assert "fill" not in err and "non-finite" not in err, err  # the data is fine


# ----------------------------------------------------------------------- dead time
def test_delay_longer_than_the_record_is_one_message(make_job):
    t0 = time.perf_counter()
    rc, out, err = discrepancy(make_job, _model({**LAG, "delay_s": 1e12}))
    refused(rc, err, "block 'y' (model.blocks[0]): delay 1e+12 s is longer than the record, "
                     "3600 s; set delay_s below 3600 s in the model")
    assert out == "" and time.perf_counter() - t0 < 60


def test_simulate_refuses_a_delay_register_larger_than_record_and_bound():
    model = model_from_dict(_model({**LAG, "delay_s": 1e12}))
    with pytest.raises(ModelError, match=r"delay 1e\+12 s is longer than the record \(100 "
                                         r"samples at dt_s=1\), 100 s; set delay_s below"):
        simulate(model, {"u": np.ones(100)}, dt_s=1.0)
    with pytest.raises(ModelError, match=r"1000000000001 states at dt_s=1 .* at most 20000"):
        discrete_state_space(model, dt_s=1.0)
    # a delay longer than a short simulation but of bounded size still simulates (the
    # discrepancy workflow's step responses are shorter than the record)
    short = model_from_dict(_model({**LAG, "delay_s": 500}))
    assert np.all(simulate(short, {"u": np.ones(100)}, dt_s=1.0).outputs == 0.0)


# --------------------------------------------------------------------- block count
def _chain(n: int) -> dict:
    blocks = [{"name": "b0", "type": "first_order", "input": "u", "k": 1, "tau_s": 5}]
    blocks += [{"name": f"b{i}", "type": "gain", "input": f"b{i - 1}", "k": 1}
               for i in range(1, n)]
    return _model(*blocks, outputs=[f"b{n - 1}"])


def test_block_count_is_bounded_at_load():
    assert model_from_dict(_chain(MAX_BLOCKS)).block_names[-1] == f"b{MAX_BLOCKS - 1}"
    t0 = time.perf_counter()
    with pytest.raises(ModelError, match=rf"model.blocks: 10000 blocks; a model may have at "
                                         rf"most {MAX_BLOCKS} .* lump chains of blocks"):
        model_from_dict(_chain(10_000))
    assert time.perf_counter() - t0 < 1.0  # refused before any block is built
    # the workflow's own augmented models are not bounded
    assert len(model_from_dict(_chain(MAX_BLOCKS + 3), max_blocks=None).blocks) == \
        MAX_BLOCKS + 3


def test_ten_thousand_blocks_in_a_discrepancy_job(make_job):
    chain = _chain(10_000)
    chain["blocks"][-1]["name"] = "y"
    chain["outputs"] = ["y"]
    rc, _, err = discrepancy(make_job, chain)
    refused(rc, err, f"10000 blocks; a model may have at most {MAX_BLOCKS}")


# ----------------------------------------------------------------------- stability
def test_negative_time_constant_is_named_unstable(make_job):
    rc, _, err = discrepancy(make_job, _model(NEGATIVE_TAU))
    refused(rc, err, "model 'plant' is unstable: block 'y' is unstable: its pole at "
                     "s = +0.05 1/s grows e-fold every 20 s", "over the 3600 s record")


def test_positive_feedback_loop_is_named_with_its_pole_and_gain(make_job):
    rc, _, err = discrepancy(make_job, _model(*POSITIVE_LOOP))
    refused(rc, err, "the loop 'f' -> 'y' -> 'f' (steady-state loop gain +3) is unstable",
            f"pole at z = {LOOP_POLE:+.6g}")
    part, = unstable_parts(model_from_dict(_model(*POSITIVE_LOOP)), dt_s=1.0)
    assert part.pole.real == pytest.approx(LOOP_POLE, rel=1e-12)
    assert part.growth_per_s == pytest.approx(math.log(LOOP_POLE), rel=1e-12)


def test_stable_models_and_slow_growth_pass():
    from pipeline.jobs.demo import boiler_model

    check_simulable(boiler_model(), dt_s=1.0, n_samples=86_400)  # PI loop round an integrator
    # a pole at +1e-5 1/s grows e^0.036 over an hour: a drift, not an instability
    slow = model_from_dict(_model({**NEGATIVE_TAU, "den": [-1e5, 1.0]}))
    check_simulable(slow, dt_s=1.0, n_samples=3600)
    # ... but more than GROWTH_LIMIT times over ten days
    with pytest.raises(ModelError, match="block 'y' is unstable: its pole at s = \\+1e-05"):
        check_simulable(slow, dt_s=1.0, n_samples=864_000)
    assert math.exp(1e-5 * 864_000) > GROWTH_LIMIT > math.exp(1e-5 * 3600)


@pytest.mark.parametrize("method", ["linear", "per_sample"])
def test_overflowing_simulation_is_a_divergence_not_bad_data(method):
    model = model_from_dict(_model({**NEGATIVE_TAU, "den": [-1.0, 1.0]}))  # e-fold per s
    with pytest.raises(DivergenceError, match=r"model 'plant' diverged: block 'y' overflowed "
                                              r"to (inf|-inf|nan) at sample \d+ .* although "
                                              r"every input is finite; block 'y' is unstable: "
                                              r"its pole at s = \+1 1/s"):
        simulate(model, {"u": np.ones(2000)}, dt_s=1.0, method=method)


def test_divergence_through_a_nonlinear_loop_names_the_loop():
    blocks = (POSITIVE_LOOP[0],
              {"name": "g", "type": "deadband", "input": "f", "width": 0.1},
              {**POSITIVE_LOOP[1], "input": "g", "k": 200.0})
    model = model_from_dict(_model(*blocks))
    with pytest.raises(DivergenceError, match=r"diverged: .* look at the loop\(s\) "
                                              r"\['f', 'g', 'y'\]"):
        simulate(model, {"u": np.ones(5000)}, dt_s=1.0)


#: A PI loop through the gain ``c (1 + 0.1 c)`` of its own output ``c``: the incremental
#: gain ``1 + 0.2 c`` turns negative below ``c = -5``, and ``c (1 + 0.1 c)`` is never
#: below -2.5, so a setpoint 10 above the output winds the controller past -5 and the
#: feedback turns positive (a quadratic valve characteristic beyond its range).
CURVED_LOOP = ({"name": "err", "type": "sum", "inputs": ["y", "-u"]},
               {"name": "controller", "type": "pi", "input": "err", "kp": 1.0, "ti_s": 10.0},
               {"name": "flow", "type": "operating_point_gain", "input": "controller",
                "slope": 0.1, "signal": "controller"},
               {"name": "y", "type": "first_order", "input": "flow", "k": -1.0, "tau_s": 10.0})


def test_divergence_of_an_unlimited_controller_names_the_saturation_to_add():
    """The model's PI winds on past the range of the curved gain and the loop runs away;
    the message says to limit the controller in YAML terms, and the model so limited
    (here at +-4, inside the range where the gain keeps its sign) simulates finitely."""
    with pytest.raises(DivergenceError, match=r"the loop's controller 'controller' has no "
                                              r"output limits in the model.* 'flow' "
                                              r"\(operating_point_gain\) can turn the feedback "
                                              r"positive there: add a block \{name: "
                                              r"controller_limited, type: saturation, input: "
                                              r"controller, low: \.\.\., high: \.\.\.\}"):
        simulate(model_from_dict(_model(*CURVED_LOOP)), {"u": np.full(2000, 10.0)}, dt_s=1.0)
    err, pi, flow, y = CURVED_LOOP
    limited = model_from_dict(_model(
        err, pi, {"name": "controller_limited", "type": "saturation", "input": "controller",
                  "low": -4.0, "high": 4.0},
        {**flow, "input": "controller_limited", "signal": "controller_limited"}, y))
    out = simulate(limited, {"u": np.full(2000, 10.0)}, dt_s=1.0).signals["y"]
    assert np.all(np.isfinite(out))
    assert out[-1] == pytest.approx(-(-4.0 * (1 + 0.1 * -4.0)), rel=1e-6)  # y = -flow at -4


def test_a_candidate_that_diverges_is_named_with_the_scale_hint():
    """The OP-as-fraction case: the search fits ``gain`` with a factor near 100 in the
    boiler's pressure loop (PI kp -0.554 x 100 through 8 s of dead time): the augmented
    model overflows, and the message names the effect and the likely unit mismatch."""
    from pipeline.jobs.demo import boiler_model
    from pipeline.discrepancy.chain import build, simulate_with
    from pipeline.discrepancy.effects import Effect

    model = boiler_model()
    check_simulable(model, dt_s=1.0, n_samples=20_000)  # the nominal model is stable
    effect = Effect(name="gain", location="controller", parameters={"factor": 100.0})
    augmented = build(model, [effect], 1.0)
    steam = np.sin(np.arange(20_000) / 300.0)
    with pytest.raises(DivergenceError, match=r"the discrepancy search's model with gain at "
                                              r"controller: factor=100 diverges: model "
                                              r"'boiler_pressure' diverged: .* loop .* a gain "
                                              r"factor of 100 at 'controller' usually means a "
                                              r"signal's scale differs from the model's \(an OP "
                                              r"exported as a fraction 0-1"):
        simulate_with(augmented, [effect], {"steam_flow": steam}, dt_s=1.0)
