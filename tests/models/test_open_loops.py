"""Opening a loop at its measured controller output (``open_at``) and which loops the
discrepancy analysis opens (``loops_to_open``)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from pipeline.discrepancy.problem import loops_to_open
from pipeline.errors import ModelError
from pipeline.models.model import model_from_dict, open_at
from pipeline.models.simulate import simulate


def _loop(process: dict, *, controller: str = "pi") -> dict:
    """A temperature-style loop: setpoint, PI, valve gain, the given process block
    (named ``plant``), a sensor lag; OP and valve flow measured."""
    return {"model": {
        "name": "loop", "inputs": ["sp", "load"],
        "outputs": ["temp", "controller", "valve"],
        "blocks": [
            {"name": "error", "type": "sum", "inputs": ["sp", "-temp"]},
            {"name": "controller", "type": controller, "input": "error", "kp": 2.0,
             "ti_s": 60.0},
            {"name": "valve", "type": "gain", "input": "controller", "k": 0.5},
            {"name": "plant", "inputs": ["valve", "load"], **process},
            {"name": "temp", "type": "first_order", "input": "plant", "k": 1.0,
             "tau_s": 5.0},
        ]}}


LAG = {"type": "first_order", "k": 1.0, "tau_s": 40.0}


def test_the_opened_model_driven_by_the_loops_own_op_reproduces_the_closed_loop():
    """Known answer: fed the OP the closed loop produced, the blocks after the
    controller see exactly what they saw in the loop, so every other output is the
    closed loop's (the controller and its error sum are gone, the OP is an input)."""
    closed = model_from_dict(_loop(LAG))
    rng = np.random.default_rng(5)
    n, dt = 2000, 1.0
    sp = np.repeat(rng.normal(0, 1, n // 200), 200)
    load = np.cumsum(rng.normal(0, 0.05, n))
    ref = simulate(closed, {"sp": sp, "load": load}, dt_s=dt)
    opened = open_at(closed, ["controller"])
    assert opened.inputs == ("sp", "load", "controller")
    assert opened.outputs == ("temp", "valve")
    assert "controller" not in opened.block_names and "error" not in opened.block_names
    out = simulate(opened, {"sp": sp, "load": load,
                            "controller": ref.signals["controller"]}, dt_s=dt)
    for name in ("temp", "valve"):
        np.testing.assert_allclose(out.signals[name], ref.signals[name], atol=1e-9)


def test_opening_a_block_that_is_not_an_output_or_everything_is_refused():
    closed = model_from_dict(_loop(LAG))
    with pytest.raises(ModelError, match="not one of the outputs"):
        open_at(closed, ["valve_missing"])
    only = model_from_dict({"model": {**_loop(LAG)["model"], "outputs": ["controller"]}})
    with pytest.raises(ModelError, match="no output to compare"):
        open_at(only, ["controller"])


def _record(model, n, dt=1.0, seed=5):
    """Setpoint steps and a wandering load; the loop's own signals as 'measured'."""
    rng = np.random.default_rng(seed)
    sp = np.repeat(rng.normal(0, 1, n // 200 + 1), 200)[:n]
    load = np.cumsum(rng.normal(0, 0.02, n))
    sim = simulate(model, {"sp": sp, "load": load}, dt_s=dt)
    return {"sp": sp, "load": load}, {o: sim.signals[o] for o in model.outputs}


@pytest.mark.parametrize(("process", "controller", "measured", "n", "opened"), [
    (LAG, "pi", ("temp", "controller"), 3600, ("controller",)),
    (LAG, "pid", ("temp", "controller"), 3600, ("controller",)),
    # the OP not measured: nothing to drive the path with
    (LAG, "pi", ("temp", "valve"), 3600, ()),
    # an integrating process: opened, it would accumulate the unmeasured disturbance
    ({"type": "integrator", "k": 0.01}, "pi", ("temp", "controller"), 3600, ()),
    # the 40 s lag settles to 2 % in 160 s: not within a 120 s hold-out (360 s record)
    (LAG, "pi", ("temp", "controller"), 360, ()),
    (LAG, "pi", ("temp", "controller"), 720, ("controller",)),
])
def test_a_loop_is_opened_only_at_a_measured_op_whose_path_settles_in_the_holdout(
        process, controller, measured, n, opened):
    spec = _loop(process, controller=controller)
    if controller == "pid":
        spec["model"]["blocks"][1]["td_s"] = 2.0
    model = model_from_dict(spec)
    _, signals = _record(model, n)
    got = loops_to_open(model, {o: signals[o] for o in measured}, dt_s=1.0,
                        holdout_fraction=1 / 3)
    assert got == opened


@pytest.mark.parametrize("extra", [0.0, 0.8, 1.2, 3.0])
def test_a_loop_is_opened_however_much_of_its_op_answers_a_disturbance(extra):
    """The measured OP is the model's own OP plus an independent slow signal `extra`
    times its std (what the real controller did against a disturbance the model does
    not know: the model explains ``1 / (1 + extra^2)`` of its variance, 1 to 0.1).  The
    loop is opened all the same: that share biases only the paths the controller
    reads, and their candidates are checked closed (pipeline.discrepancy.closed_loop);
    a settling path is what decides (the test above)."""
    model = model_from_dict(_loop(LAG))
    _, signals = _record(model, 6000)
    rng = np.random.default_rng(9)
    slow = scipy.signal.detrend(np.cumsum(rng.normal(0, 1, 6000)))
    op = signals["controller"]
    slow *= extra * np.std(op[600:4000]) / np.std(slow[600:4000])
    measured = {"temp": signals["temp"], "controller": op + slow}
    assert loops_to_open(model, measured, dt_s=1.0, holdout_fraction=1 / 3) == ("controller",)


def test_a_loop_whose_closed_model_diverges_stays_closed():
    """The closed check of an opened analysis needs the user's model to run closed;
    with the error sum's sign flipped (sp + temp: positive feedback through the PI's
    integral, growing without bound) it cannot, so the loop stays closed and the
    analysis gets the model as given (it then names the divergence).  The same record
    with the right sign is opened."""
    from pipeline.discrepancy.config import DiscrepancyConfig
    from pipeline.discrepancy.problem import opened_view

    spec = _loop(LAG)
    model = model_from_dict(spec)
    inputs, signals = _record(model, 6000)
    measured = {"temp": signals["temp"], "controller": signals["controller"]}
    config = DiscrepancyConfig()
    assert opened_view(model, inputs, measured, 1.0, config)[4] == ("controller",)
    spec["model"]["blocks"][0]["inputs"] = ["sp", "temp"]
    flipped = model_from_dict(spec)
    got = opened_view(flipped, inputs, measured, 1.0, config)
    assert got[4] == () and got[0] is flipped and set(got[2]) == {"temp", "controller"}
