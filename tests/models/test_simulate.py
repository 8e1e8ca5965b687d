"""Simulation of block-diagram models against independent references.

References: python-control (``control.sample_system`` + ``step_response`` /
``interconnect`` + ``forced_response``), ``scipy.signal.dlsim``/``lfilter``, closed-form
answers.  Tolerances: ZOH discretisation is exact at the sample instants, so the only
differences are floating-point rounding in two different algorithms; 1e-9 (1e-8 for the
closed loop, whose states pass ~1e5 recursions) is many orders above rounding
(~1e-13 here) and far below any modelling effect.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import control as ct
import numpy as np
import pytest
import scipy.signal
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.errors import ConfigError, DataQualityError, ModelError
from pipeline.models.blocks import Deadband, FirstOrder, Gain, Saturation, Term
from pipeline.models.model import Model, insert_after, insert_before, model_from_dict
from pipeline.models.simulate import (
    MAX_LIFTED_STATES,
    discrete_state_space,
    simulate,
    state_names,
)

MODELS = Path(__file__).resolve().parents[2] / "configs" / "models"
METHODS = ["linear", "per_sample"]


def load_model(name: str) -> Model:
    with (MODELS / f"{name}.yaml").open(encoding="utf-8") as fh:
        return model_from_dict(yaml.safe_load(fh))


def single_block(spec: dict, n_inputs: int = 1) -> Model:
    inputs = ["u", "w", "v"][:n_inputs]
    block = {"name": "y", "input": "u", **spec}
    return model_from_dict({"name": "one", "inputs": inputs, "outputs": ["y"],
                            "blocks": [block]})


# -- single linear blocks vs python-control ------------------------------------------
LINEAR_BLOCKS = [
    ({"type": "gain", "k": -2.5}, ct.tf([-2.5], [1])),
    ({"type": "first_order", "k": 1.7, "tau_s": 12.0}, ct.tf([1.7], [12.0, 1])),
    ({"type": "second_order", "k": 0.8, "wn": 0.35, "zeta": 0.2},
     ct.tf([0.8 * 0.35**2], [1, 2 * 0.2 * 0.35, 0.35**2])),
    ({"type": "transfer", "num": [-6.0, 1.0], "den": [40.0, 14.0, 1.0]},
     ct.tf([-6.0, 1.0], [40.0, 14.0, 1.0])),
    ({"type": "transfer", "num": [3.0, 1.0], "den": [5.0, 1.0]},
     ct.tf([3.0, 1.0], [5.0, 1.0])),
    ({"type": "integrator", "k": 0.004}, ct.tf([0.004], [1, 0])),
    ({"type": "pi", "kp": -0.554, "ti_s": 60.0}, ct.tf([-0.554 * 60, -0.554], [60, 0])),
    # PID built from its three documented terms by python-control's own algebra.
    ({"type": "pid", "kp": 1.5, "ti_s": 30.0, "td_s": 8.0},
     1.5 * (1 + ct.tf([1], [30.0, 0]) + ct.tf([8.0, 0], [0.8, 1]))),
    ({"type": "pid", "kp": 1.5, "ti_s": 30.0, "td_s": 8.0, "n_filter": 4},
     1.5 * (1 + ct.tf([1], [30.0, 0]) + ct.tf([8.0, 0], [2.0, 1]))),
]
LINEAR_IDS = ["gain", "first_order", "second_order", "transfer_rhp_zero",
              "transfer_biproper", "integrator", "pi", "pid", "pid_n4"]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(("spec", "reference"), LINEAR_BLOCKS, ids=LINEAR_IDS)
def test_block_step_response_equals_python_control_zoh(spec, reference, method):
    dt_s, n = 2.0, 300
    t = np.arange(n) * dt_s
    expected = ct.step_response(ct.sample_system(reference, dt_s, method="zoh"), T=t).outputs
    got = simulate(single_block(spec), {"u": np.ones(n)}, dt_s=dt_s, method=method)
    assert got.method == method
    np.testing.assert_allclose(got.outputs[:, 0], expected, rtol=0, atol=1e-9 * max(
        1.0, np.abs(expected).max()))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(("spec", "reference"), LINEAR_BLOCKS[:4], ids=LINEAR_IDS[:4])
def test_delay_shifts_by_exactly_the_number_of_samples(spec, reference, method):
    dt_s, n, delay_samples = 0.5, 200, 7
    u = np.random.default_rng(1).standard_normal(n)
    plain = simulate(single_block(spec), {"u": u}, dt_s=dt_s, method=method).outputs[:, 0]
    delayed_model = single_block({**spec, "delay_s": delay_samples * dt_s})
    delayed = simulate(delayed_model, {"u": u}, dt_s=dt_s, method=method).outputs[:, 0]
    np.testing.assert_array_equal(delayed[:delay_samples], 0.0)
    np.testing.assert_allclose(delayed[delay_samples:], plain[:-delay_samples], rtol=0,
                               atol=1e-12 * np.abs(plain).max())


@settings(max_examples=25, deadline=None)
@given(
    k=st.floats(-5, 5),
    tau_s=st.floats(0.1, 100),
    delay_samples=st.integers(1, 30),
    dt_s=st.sampled_from([0.1, 0.25, 1.0, 2.0]),
)
def test_property_dead_time_is_a_time_shift(k, tau_s, delay_samples, dt_s):
    u = np.sin(np.arange(120) * 0.37) + 0.1 * np.arange(120) % 3
    spec = {"type": "first_order", "k": k, "tau_s": tau_s}
    plain = simulate(single_block(spec), {"u": u}, dt_s=dt_s).outputs[:, 0]
    delayed = simulate(single_block({**spec, "delay_s": delay_samples * dt_s}), {"u": u},
                       dt_s=dt_s).outputs[:, 0]
    np.testing.assert_allclose(delayed[delay_samples:], plain[:-delay_samples], rtol=0,
                               atol=1e-12 * max(1.0, np.abs(plain).max()))


@settings(max_examples=15, deadline=None)
@given(a=st.floats(-3, 3), b=st.floats(-3, 3), seed=st.integers(0, 2**16))
def test_property_superposition_on_the_drum_loop(a, b, seed):
    model = load_model("drum_level")
    rng = np.random.default_rng(seed)
    u1, u2 = rng.standard_normal((2, 400, 2))

    def run(u):
        return simulate(model, u, dt_s=1.0).outputs

    combined = run(a * u1 + b * u2)
    np.testing.assert_allclose(combined, a * run(u1) + b * run(u2), rtol=0,
                               atol=1e-10 * max(1.0, np.abs(combined).max()))


@pytest.mark.parametrize("method", METHODS)
def test_sum_signs_and_scales(method):
    model = model_from_dict({
        "name": "sum", "inputs": ["a", "b", "c"], "outputs": ["y"],
        "blocks": [{"name": "y", "type": "sum", "delay_s": 2.0,
                    "inputs": ["a", "-b", {"signal": "c", "k": 2.5}, {"signal": "a", "k": -0.5}]}],
    })
    a, b, c = np.random.default_rng(2).standard_normal((3, 50))
    y = simulate(model, {"a": a, "b": b, "c": c}, dt_s=1.0, method=method).outputs[:, 0]
    np.testing.assert_allclose(y[2:], (0.5 * a - b + 2.5 * c)[:-2], rtol=0, atol=1e-14)
    np.testing.assert_array_equal(y[:2], 0.0)


# -- nonlinear static blocks -------------------------------------------------------
def test_deadband_static_map():
    u = np.linspace(-3, 3, 601)
    y = simulate(single_block({"type": "deadband", "width": 1.6}), {"u": u}, dt_s=1.0)
    assert y.method == "per_sample"
    expected = np.sign(u) * np.maximum(np.abs(u) - 0.8, 0.0)
    np.testing.assert_allclose(y.outputs[:, 0], expected, rtol=0, atol=1e-15)


def test_backlash_follows_the_input_a_half_width_behind_after_each_reversal():
    # a triangle 0 -> 3 -> -3 -> 0 through play of width 1 (memory at rest, 0): the
    # output holds until the input is 0.5 away, then trails it by 0.5 in the direction
    # of travel; after the reversal at 3 it holds 2.5 until the input is down to 2.0
    u = np.concatenate([np.linspace(0, 3, 301), np.linspace(3, -3, 601)[1:],
                        np.linspace(-3, 0, 301)[1:]])
    y = simulate(single_block({"type": "backlash", "width": 1.0}), {"u": u}, dt_s=1.0)
    assert y.method == "per_sample"
    up1, down, up2 = slice(0, 301), slice(301, 901), slice(901, None)
    expected = np.empty_like(u)
    expected[up1] = np.maximum(u[up1] - 0.5, 0.0)
    expected[down] = np.minimum(u[down] + 0.5, 2.5)
    expected[up2] = np.maximum(u[up2] - 0.5, -2.5)
    np.testing.assert_allclose(y.outputs[:, 0], expected, rtol=0, atol=1e-12)


def test_saturation_static_map_with_an_infinite_limit():
    u = np.linspace(-3, 3, 601)
    for low, high in [(-1.0, 2.0), (-np.inf, 0.5)]:
        y = simulate(single_block({"type": "saturation", "low": low, "high": high}),
                     {"u": u}, dt_s=1.0)
        np.testing.assert_array_equal(y.outputs[:, 0], np.clip(u, low, high))


def test_operating_point_gain_static_map():
    model = single_block({"type": "operating_point_gain", "slope": 0.3, "signal": "w"},
                         n_inputs=2)
    u, w = np.random.default_rng(3).standard_normal((2, 100))
    y = simulate(model, {"u": u, "w": w}, dt_s=1.0).outputs[:, 0]
    np.testing.assert_allclose(y, u * (1 + 0.3 * w), rtol=1e-15, atol=0)


def test_nonlinear_path_equals_linear_path_at_zero_width_and_infinite_limits():
    boiler = load_model("boiler_pressure")
    model = insert_before(boiler, "fuel", block=Deadband(name="fuel_db", width=0.0))
    model = insert_after(
        model, "controller", upstream_name="controller_raw",
        block=Saturation(name="controller", inputs=(Term("controller_raw"),),
                         low=-np.inf, high=np.inf),
    )
    assert not model.is_linear
    u = np.random.default_rng(4).standard_normal(3000)
    nonlinear = simulate(model, {"steam_flow": u}, dt_s=1.0)
    linear = simulate(boiler, {"steam_flow": u}, dt_s=1.0)
    assert (nonlinear.method, linear.method) == ("per_sample", "linear")
    np.testing.assert_allclose(nonlinear.outputs, linear.outputs, rtol=0,
                               atol=1e-9 * np.abs(linear.outputs).max())
    # ...and the saturation really acts when its limits are finite.
    limited = dataclasses.replace(model.block("controller"), low=-0.005, high=0.005)
    clipped = simulate(model.with_block(limited), {"steam_flow": u}, dt_s=1.0)
    assert np.abs(clipped.signals["controller"]).max() == pytest.approx(0.005, rel=1e-12)
    assert np.abs(clipped.outputs - linear.outputs).max() > 1e-3


# -- loops -----------------------------------------------------------------------
def _boiler_reference(dt_s: float) -> ct.StateSpace:
    """The boiler loop assembled by python-control from independently sampled blocks."""

    def zoh(sys, inputs, outputs):
        return ct.sample_system(sys, dt_s, method="zoh", inputs=inputs, outputs=outputs)

    delay = round(8.0 / dt_s)
    parts = [
        ct.tf([0.019], [1], dt_s, inputs="steam_flow", outputs="feedforward"),
        zoh(ct.tf([-0.554 * 60, -0.554], [60, 0]), "turbine_pressure", "controller"),
        ct.summing_junction(["controller", "feedforward"], "demand", dt=dt_s),
        ct.tf([65.0], [1.0] + [0.0] * delay, dt_s, inputs="demand", outputs="fuel"),
        ct.summing_junction(["fuel", "-steam_flow"], "drum_in", dt=dt_s),
        zoh(ct.tf([0.000883], [1, 0]), "drum_in", "drum"),
        ct.tf([-0.045], [1], dt_s, inputs="steam_flow", outputs="steam_term"),
        ct.summing_junction(["drum", "steam_term"], "turbine_pressure", dt=dt_s),
    ]
    return ct.interconnect(parts, inplist=["steam_flow"], outlist=["turbine_pressure"],
                           inputs="steam_flow", outputs="turbine_pressure")


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dt_s", [1.0, 0.5])
def test_boiler_loop_equals_python_control_interconnection(dt_s, method):
    n = 4000
    u = np.random.default_rng(5).standard_normal(n)
    t = np.arange(n) * dt_s
    expected = ct.forced_response(_boiler_reference(dt_s), T=t, U=u).outputs
    got = simulate(load_model("boiler_pressure"), {"steam_flow": u}, dt_s=dt_s, method=method)
    np.testing.assert_allclose(got.outputs[:, 0], expected, rtol=0, atol=1e-8)
    np.testing.assert_allclose(got.t_s, t)


def test_loop_through_a_delay_is_a_known_recursion():
    # y[k] = u[k] + 0.6 y[k-1]  ->  lfilter([1], [1, -0.6])
    model = model_from_dict({
        "name": "echo", "inputs": ["u"], "outputs": ["y"],
        "blocks": [{"name": "y", "type": "sum", "inputs": ["u", "fb"]},
                   {"name": "fb", "type": "gain", "input": "y", "k": 0.6, "delay_s": 1.0}],
    })
    u = np.random.default_rng(6).standard_normal(500)
    for method in METHODS:
        y = simulate(model, {"u": u}, dt_s=1.0, method=method).outputs[:, 0]
        np.testing.assert_allclose(y, scipy.signal.lfilter([1.0], [1.0, -0.6], u), atol=1e-12)


def test_loop_through_an_integrator_is_a_known_recursion():
    # y = integrator(k)(u - y), ZOH: y[k+1] = y[k] + k dt (u[k] - y[k])
    k, dt_s = 0.05, 2.0
    model = model_from_dict({
        "name": "int_loop", "inputs": ["u"], "outputs": ["y"],
        "blocks": [{"name": "y", "type": "integrator", "inputs": ["u", "-y"], "k": k}],
    })
    u = np.random.default_rng(7).standard_normal(500)
    expected = scipy.signal.lfilter([0.0, k * dt_s], [1.0, -(1.0 - k * dt_s)], u)
    for method in METHODS:
        y = simulate(model, {"u": u}, dt_s=dt_s, method=method).outputs[:, 0]
        np.testing.assert_allclose(y, expected, atol=1e-12)


# -- the two paths and the initial state -------------------------------------------
def test_paths_agree_with_dlsim_from_a_random_initial_state():
    model = load_model("drum_level")
    system = discrete_state_space(model, dt_s=1.0)
    rng = np.random.default_rng(8)
    x0 = rng.standard_normal(len(system.state_names))
    u = rng.standard_normal((700, 2))
    _, expected, _ = scipy.signal.dlsim((system.a, system.b, system.c, system.d, 1.0), u, x0=x0)
    for method in METHODS:
        got = simulate(model, u, dt_s=1.0, initial=x0, method=method)
        for i, name in enumerate(system.signal_names):
            np.testing.assert_allclose(got.signals[name], expected[:, i], rtol=0, atol=1e-9)


def test_state_layout_names_blocks_and_delay_samples():
    system = discrete_state_space(load_model("boiler_pressure"), dt_s=2.0)
    assert system.state_names == ("controller.x0", "fuel.delay1", "fuel.delay2",
                                  "fuel.delay3", "fuel.delay4", "drum.x0")
    assert system.signal_names[-1] == "turbine_pressure"


def test_delayed_block_initial_register_is_read_oldest_first():
    # x0 = [delay1 (newest), delay2, delay3 (oldest)]: the output reads delay3 first.
    model = single_block({"type": "gain", "k": 1.0, "delay_s": 3.0})
    for method in METHODS:
        y = simulate(model, {"u": np.zeros(5)}, dt_s=1.0, initial=np.array([1.0, 2.0, 3.0]),
                     method=method).outputs[:, 0]
        np.testing.assert_array_equal(y, [3.0, 2.0, 1.0, 0.0, 0.0])


def test_steady_initial_state_of_the_boiler_is_the_balance_point():
    # Constant steam flow 1: the PI integral drives the pressure back to 0, so
    # drum = 0.045, fuel = 1 (fuel balances steam), demand = 1/65.
    n = 300
    result = simulate(load_model("boiler_pressure"), {"steam_flow": np.ones(n)}, dt_s=1.0,
                      initial="steady")
    expected = {"turbine_pressure": 0.0, "drum": 0.045, "fuel": 1.0, "demand": 1 / 65,
                "feedforward": 0.019, "controller": 1 / 65 - 0.019}
    for name, value in expected.items():
        np.testing.assert_allclose(result.signals[name], value, rtol=0, atol=1e-10)


def test_steady_without_an_equilibrium_is_refused():
    with pytest.raises(ModelError, match=r"initial='steady' has no unique steady state "
                                         r"\(1 pole\(s\) at z=1"):
        simulate(single_block({"type": "integrator", "k": 1.0}), {"u": np.ones(3)}, dt_s=1.0,
                 initial="steady")


def test_rest_start_gives_zero_signals_for_zero_inputs():
    result = simulate(load_model("drum_level"), np.zeros((50, 2)), dt_s=1.0)
    assert set(result.signals) == set(load_model("drum_level").block_names)
    assert not np.any(result.outputs)


def test_auto_uses_per_sample_path_for_very_long_delay_chains():
    delay = MAX_LIFTED_STATES + 10
    model = single_block({"type": "gain", "k": 2.0, "delay_s": float(delay)})
    u = np.random.default_rng(9).standard_normal(delay + 300)
    result = simulate(model, {"u": u}, dt_s=1.0)
    assert result.method == "per_sample"
    np.testing.assert_array_equal(result.outputs[delay:, 0], 2.0 * u[:-delay])


# -- the drum-level model --------------------------------------------------------
def _drum_open_loop() -> Model:
    model = load_model("drum_level")
    model = model.with_block(dataclasses.replace(model.block("controller"), kp=0.0))
    return model.with_block(dataclasses.replace(model.block("feedforward"), k=0.0))


def test_drum_level_open_loop_inverse_response_matches_closed_form():
    # Open loop (no feedwater), steam step 1 kg/s: level = -0.071 t + 3 (1 - exp(-t/15)).
    n, dt_s = 200, 1.0
    t = np.arange(n) * dt_s
    result = simulate(_drum_open_loop(), {"steam_flow": np.ones(n),
                                          "level_setpoint": np.zeros(n)}, dt_s=dt_s)
    level = result.signals["drum_level"]
    np.testing.assert_allclose(level, -0.071 * t + 3.0 * (1 - np.exp(-t / 15.0)), atol=1e-9)
    assert np.all(np.diff(level[:10]) > 0)  # wrong way first: the level rises...
    assert level[-1] < -5.0  # ...then the mass loss wins


def test_drum_level_closed_loop_shows_shrink_swell_and_settles():
    n = 2000
    result = simulate(load_model("drum_level"),
                      {"steam_flow": np.ones(n), "level_setpoint": np.zeros(n)}, dt_s=1.0)
    level = result.signals["drum_level"]
    assert level[1] > 0 and level[5] > level[1]  # rises first after a steam increase
    assert level.min() < -0.1  # then dips below while feedwater catches up
    assert abs(level[-1]) < 1e-4  # PI integral action removes the offset
    assert result.signals["feedwater_flow"][-1] == pytest.approx(1.0, abs=1e-4)  # mass balance


def test_drum_level_closed_loop_is_stable_in_continuous_and_discrete_time():
    model = load_model("drum_level")
    poles_z = np.linalg.eigvals(discrete_state_space(model, dt_s=1.0).a)
    assert np.abs(poles_z).max() < 0.995
    # Independent continuous-time check: python-control interconnection of the blocks.
    parts = [
        ct.summing_junction(["level_setpoint", "-drum_level"], "level_error"),
        ct.tf([0.3 * 150, 0.3], [150, 0], inputs="level_error", outputs="controller"),
        ct.tf([1.0], [1], inputs="steam_flow", outputs="feedforward"),
        ct.summing_junction(["controller", "feedforward"], "feedwater_demand"),
        ct.tf([1.0], [20.0, 1], inputs="feedwater_demand", outputs="feedwater_flow"),
        ct.summing_junction(["feedwater_flow", "-steam_flow"], "mass_in"),
        ct.tf([0.071], [1, 0], inputs="mass_in", outputs="drum_mass"),
        ct.tf([3.0], [15.0, 1], inputs="steam_flow", outputs="swell"),
        ct.summing_junction(["drum_mass", "swell"], "drum_level"),
    ]
    closed = ct.interconnect(parts, inputs=["steam_flow", "level_setpoint"],
                             outputs=["drum_level", "feedwater_flow"])
    assert np.real(closed.poles()).max() < -1e-3


# -- errors ------------------------------------------------------------------------
def test_fractional_delay_is_refused_with_suggested_sample_periods():
    with pytest.raises(ModelError, match=r"block 'fuel': delay_s=8 is not a whole number of "
                                         r"samples at dt_s=3 \(ratio 2\.66667\).*e\.g\. "
                                         r"2\.66667, 2, 1\.6"):
        simulate(load_model("boiler_pressure"), {"steam_flow": np.zeros(10)}, dt_s=3.0)


def test_delay_shorter_than_one_sample_is_refused():
    model = single_block({"type": "gain", "k": 1.0, "delay_s": 1e-12})
    with pytest.raises(ModelError, match=r"delay_s=1e-12 is not a whole number of samples"):
        simulate(model, {"u": np.zeros(4)}, dt_s=1.0)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"inputs": {"steam": np.zeros(5)}}, ConfigError,
         r"inputs given \['steam'\] but the model needs \['steam_flow'\] "
         r"\(missing \['steam_flow'\], unknown \['steam'\]\)"),
        ({"inputs": np.zeros((5, 2))}, ConfigError,
         r"inputs array has shape \(5, 2\); expected \(N, 1\)"),
        ({"inputs": {"steam_flow": np.array([0.0, np.nan, 1.0])}}, DataQualityError,
         r"input 'steam_flow' is not finite at sample 1"),
        ({"dt_s": 0.0}, ConfigError, r"dt_s=0\.0 must be a positive finite number"),
        ({"method": "fast"}, ConfigError, r"method='fast'; allowed: 'auto', 'linear'"),
        ({"initial": "cold"}, ConfigError, r"initial='cold'; allowed: 'rest', 'steady'"),
        ({"initial": np.zeros(3)}, ModelError,
         r"initial state has shape \(3,\).*expected 10 finite values"),
    ],
)
def test_simulate_argument_errors(kwargs, error, message):
    call = {"inputs": {"steam_flow": np.zeros(5)}, "dt_s": 1.0, **kwargs}
    with pytest.raises(error, match=message):
        simulate(load_model("boiler_pressure"), call.pop("inputs"), **call)


def test_linear_method_on_a_nonlinear_model_is_refused():
    model = single_block({"type": "deadband", "width": 1.0})
    with pytest.raises(ModelError, match=r"method='linear' needs a linear model, but blocks "
                                         r"\['y'\] are nonlinear"):
        simulate(model, {"u": np.zeros(3)}, dt_s=1.0, method="linear")
    with pytest.raises(ModelError, match=r"discrete_state_space needs a linear model"):
        discrete_state_space(model, dt_s=1.0)


def test_gain_block_objects_can_be_simulated_without_yaml():
    model = Model(name="m", inputs=("u",), outputs=("lag",), blocks=(
        Gain(name="g", inputs=(Term("u"),), k=2.0),
        FirstOrder(name="lag", inputs=(Term("g"),), k=1.0, tau_s=10.0),
    ))
    y = simulate(model, np.ones(30), dt_s=1.0).outputs[:, 0]
    np.testing.assert_allclose(y, 2.0 * (1 - np.exp(-np.arange(30) / 10.0)), atol=1e-12)


def test_state_names_cover_nonlinear_models_too():
    model = insert_before(load_model("boiler_pressure"), "fuel",
                          block=Deadband(name="fuel_db", width=0.1))
    names = state_names(model, dt_s=4.0)
    assert names == ("controller.x0", "fuel.delay1", "fuel.delay2", "drum.x0")
    x0 = np.zeros(len(names))
    x0[names.index("fuel.delay2")] = 1.0  # the fuel pulse that arrives first
    result = simulate(model, np.zeros(3), dt_s=4.0, initial=x0)
    np.testing.assert_array_equal(result.signals["fuel"], [1.0, 0.0, 0.0])
    # it reaches the drum integrator one sample later: 0.000883 * 4 s * 1
    np.testing.assert_allclose(result.signals["drum"], [0.0, 0.000883 * 4.0, 0.000883 * 4.0],
                               rtol=1e-14)
