"""Model specification: parsing, validation messages, round trip, modification helpers."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline.errors import ConfigError, ModelError
from pipeline.models.blocks import (
    BLOCK_TYPES,
    PI,
    PID,
    Deadband,
    FirstOrder,
    Gain,
    Saturation,
    Sum,
    Term,
    Transfer,
)
from pipeline.models.model import (
    Model,
    insert_after,
    insert_before,
    model_from_dict,
    model_to_dict,
    scale_gain,
)

MODELS = Path(__file__).resolve().parents[2] / "configs" / "models"

BOILER = {
    "model": {
        "name": "boiler_pressure",
        "inputs": ["steam_flow"],
        "outputs": ["turbine_pressure"],
        "blocks": [
            {"name": "feedforward", "type": "gain", "input": "steam_flow", "k": 0.019},
            {"name": "controller", "type": "pi", "input": "turbine_pressure",
             "kp": -0.554, "ti_s": 60},
            {"name": "demand", "type": "sum", "inputs": ["controller", "feedforward"]},
            {"name": "fuel", "type": "gain", "input": "demand", "k": 65, "delay_s": 8},
            {"name": "drum", "type": "integrator", "inputs": ["fuel", "-steam_flow"],
             "k": 0.000883},
            {"name": "turbine_pressure", "type": "sum",
             "inputs": ["drum", {"signal": "steam_flow", "k": -0.045}]},
        ],
    }
}

# Every block type once, with non-default optional parameters, infinite limits and a
# description: the round trip must keep all of it.
EVERY_TYPE = {
    "model": {
        "name": "every_type",
        "description": "one block of each type",
        "inputs": ["u", "w"],
        "outputs": ["out", "sat"],
        "blocks": [
            {"name": "g", "type": "gain", "input": "u", "k": 2, "delay_s": 3},
            {"name": "f", "type": "first_order", "input": "g", "k": 1.5, "tau_s": 20},
            {"name": "s2", "type": "second_order", "input": "u", "k": 1, "wn": 0.3,
             "zeta": 0.4, "delay_s": 1},
            {"name": "tr", "type": "transfer", "input": "w", "num": [-4, 1],
             "den": [10, 7, 1]},
            {"name": "i", "type": "integrator", "input": "-w", "k": 0.01},
            {"name": "pi", "type": "pi", "input": "out", "kp": -0.5, "ti_s": 50},
            {"name": "pid", "type": "pid", "input": "out", "kp": 0.2, "ti_s": 40,
             "td_s": 5, "n_filter": 8},
            {"name": "db", "type": "deadband", "input": "pid", "width": 0.5},
            {"name": "bl", "type": "backlash", "input": "db", "width": 0.3},
            {"name": "sat", "type": "saturation", "input": "bl", "low": -math.inf,
             "high": 2.0},
            {"name": "opg", "type": "operating_point_gain", "input": "f", "slope": 0.02,
             "signal": "w"},
            {"name": "out", "type": "sum",
             "inputs": ["opg", "s2", "tr", "i", {"signal": "pi", "k": 0.5}, "sat"],
             "delay_s": 2},
        ],
    }
}


def load(path: Path) -> dict:
    """Test-only YAML loader (the config adapter owns YAML in the package)."""
    with path.open(encoding="utf-8") as fh:
        return yaml.safe_load(fh)


def mutated(base: dict, edit) -> dict:
    d = copy.deepcopy(base)
    edit(d["model"])
    return d


# -- parsing and round trip ---------------------------------------------------------
def test_boiler_parses_to_the_expected_blocks():
    model = model_from_dict(BOILER)
    assert model.inputs == ("steam_flow",)
    assert model.outputs == ("turbine_pressure",)
    assert model.block("fuel") == Gain(name="fuel", inputs=(Term("demand"),), k=65.0, delay_s=8.0)
    assert model.block("drum").inputs == (Term("fuel"), Term("steam_flow", -1.0))
    assert model.block("turbine_pressure").inputs == (Term("drum"), Term("steam_flow", -0.045))
    assert model.is_linear


@pytest.mark.parametrize("spec", [BOILER, EVERY_TYPE], ids=["boiler", "every_type"])
def test_round_trip_through_dict_and_yaml_is_equal(spec):
    model = model_from_dict(spec)
    again = model_from_dict(model_to_dict(model))
    assert again == model
    # The dict is plain YAML: dump and reload (as model_augmented.yaml will be) too.
    text = yaml.safe_dump(model_to_dict(model), sort_keys=False)
    assert model_from_dict(yaml.safe_load(text)) == model


def test_every_block_type_is_covered_by_the_round_trip_fixture():
    used = {b["type"] for b in EVERY_TYPE["model"]["blocks"]}
    assert used == set(BLOCK_TYPES)


def test_inner_mapping_is_accepted_as_inline_model():
    assert model_from_dict(BOILER["model"]) == model_from_dict(BOILER)


def test_to_dict_omits_defaults_and_keeps_non_defaults():
    d = model_to_dict(model_from_dict(EVERY_TYPE))["model"]
    by_name = {b["name"]: b for b in d["blocks"]}
    assert "delay_s" not in by_name["f"]
    assert by_name["g"]["delay_s"] == 3.0
    assert by_name["pid"]["n_filter"] == 8.0
    assert by_name["sat"]["low"] == -math.inf
    assert by_name["i"]["input"] == "-w"
    assert by_name["out"]["inputs"][4] == {"signal": "pi", "k": 0.5}


@pytest.mark.parametrize("filename", ["boiler_pressure.yaml", "drum_level.yaml"])
def test_shipped_models_validate_and_round_trip(filename):
    model = model_from_dict(load(MODELS / filename))
    assert model.name == filename.removesuffix(".yaml")
    assert model_from_dict(model_to_dict(model)) == model


def test_shipped_boiler_is_the_design_model_verbatim():
    assert model_from_dict(load(MODELS / "boiler_pressure.yaml")) == model_from_dict(BOILER)


def test_shipped_drum_level_interface():
    model = model_from_dict(load(MODELS / "drum_level.yaml"))
    assert model.inputs == ("steam_flow", "level_setpoint")
    assert model.outputs == ("drum_level", "feedwater_flow")
    assert model.block("controller").TYPE == "pi"
    assert 100 <= model.block("controller").ti_s <= 200


# -- feedthrough and algebraic loops --------------------------------------------------
@pytest.mark.parametrize(
    ("block", "feedthrough"),
    [
        (Gain(name="b", inputs=(Term("u"),), k=2), True),
        (Gain(name="b", inputs=(Term("u"),), k=2, delay_s=1), False),
        (FirstOrder(name="b", inputs=(Term("u"),), k=1, tau_s=5), False),
        (PI(name="b", inputs=(Term("u"),), kp=1, ti_s=5), True),
        (PID(name="b", inputs=(Term("u"),), kp=1, ti_s=5, td_s=1), True),
        (Transfer(name="b", inputs=(Term("u"),), num=(0, 0, 1), den=(1, 2, 1)), False),
        (Transfer(name="b", inputs=(Term("u"),), num=(1, 0), den=(1, 2)), True),
        (Sum(name="b", inputs=(Term("u"),)), True),
        (Deadband(name="b", inputs=(Term("u"),), width=1), True),
    ],
)
def test_feedthrough_classification(block, feedthrough):
    assert block.has_feedthrough is feedthrough


def _loop(second: dict) -> dict:
    return {
        "name": "loop",
        "inputs": ["u"],
        "outputs": ["first"],
        "blocks": [
            {"name": "first", "type": "gain", "inputs": ["u", "-second"], "k": 2.0},
            {"name": "second", "input": "first", **second},
        ],
    }


def test_algebraic_loop_of_two_gains_names_both_blocks():
    with pytest.raises(ModelError, match=r"algebraic loop through blocks .*'first'.*'second'|"
                                         r"algebraic loop through blocks .*'second'.*'first'"):
        model_from_dict(_loop({"type": "gain", "k": 0.5}))


def test_algebraic_loop_through_pi_and_sum_is_detected():
    spec = _loop({"type": "pi", "kp": 1.0, "ti_s": 10.0})
    with pytest.raises(ModelError, match=r"put a delay_s > 0 or a lag/integrator in the loop"):
        model_from_dict(spec)


@pytest.mark.parametrize(
    "second",
    [
        {"type": "gain", "k": 0.5, "delay_s": 1.0},
        {"type": "integrator", "k": 0.1},
        {"type": "first_order", "k": 1.0, "tau_s": 3.0},
        {"type": "transfer", "num": [1.0], "den": [1.0, 1.0, 1.0]},
    ],
    ids=["delay", "integrator", "lag", "strictly_proper_transfer"],
)
def test_loop_through_a_non_feedthrough_block_is_legal(second):
    model = model_from_dict(_loop(second))
    assert model.block("second").has_feedthrough is False


# -- validation messages (key path, bad value, what is allowed) --------------------
INVALID = [
    (lambda m: m["blocks"][3].update(type="gian"),
     r"model\.blocks\[3\]\.type: unknown block type 'gian' \(did you mean 'gain'\?\); "
     r"allowed: gain, first_order"),
    (lambda m: m["blocks"][3].update(kk=1),
     r"model\.blocks\[3\]\.kk: unknown parameter for block type gain \(did you mean 'k'\?\); "
     r"allowed: k, delay_s"),
    (lambda m: m["blocks"][1].pop("ti_s"),
     r"model\.blocks\[1\]\.ti_s: missing; block type pi requires kp, ti_s"),
    (lambda m: m["blocks"][4].update(inputs=["fuel", "-stem_flow"]),
     r"model\.blocks\[4\]\.inputs\[1\]: unknown signal 'stem_flow' in block 'drum' "
     r"\(did you mean 'steam_flow'\?\)"),
    (lambda m: m["blocks"][2].update(name="fuel"),
     r"model\.blocks\[3\]\.name: duplicate block name 'fuel' \(also model\.blocks\[2\]\)"),
    (lambda m: m.update(outputs=["pressure"]),
     r"model\.outputs\[0\]: 'pressure' is not a block \(did you mean 'turbine_pressure'\?\); "
     r"outputs must name blocks: \['feedforward', 'controller'"),
    (lambda m: m["blocks"][3].update(delay_s=-8),
     r"model\.blocks\[3\]\.delay_s: -8 is invalid for block 'fuel' \(type gain\); "
     r"delay_s must be a finite number >= 0"),
    (lambda m: m["blocks"].append(
        {"name": "lag", "type": "first_order", "input": "fuel", "k": 1, "tau_s": 0}),
     r"model\.blocks\[6\]\.tau_s: 0 is invalid .* tau_s must be a finite number > 0"),
    (lambda m: m["blocks"][0].update(k=float("nan")),
     r"model\.blocks\[0\]\.k: nan is invalid .* k must be a finite number"),
    (lambda m: m["blocks"][0].update(k=True),
     r"model\.blocks\[0\]\.k: True is invalid"),
    (lambda m: m["blocks"][0].update(k="0.019"),
     r"model\.blocks\[0\]\.k: '0\.019' is invalid"),
    (lambda m: m["blocks"][0].update(inputs=["steam_flow"]),
     r"model\.blocks\[0\]: block 'feedforward' needs exactly one of 'input: name' or 'inputs:"),
    (lambda m: m["blocks"][0].pop("input"),
     r"model\.blocks\[0\]: block 'feedforward' needs exactly one of"),
    (lambda m: m["blocks"][5].update(inputs=["drum", {"signal": "steam_flow", "gain": 2}]),
     r"model\.blocks\[5\]\.inputs\[1\]\.gain: 2 is invalid; keys 'signal' and 'k'"),
    (lambda m: m["blocks"][5].update(inputs=["drum", 3]),
     r"model\.blocks\[5\]\.inputs\[1\]: 3 is invalid; 'name', '-name'"),
    (lambda m: m["blocks"][2].update(inputs=[]),
     r"model\.blocks\[2\]\.inputs: \[\] must be a non-empty list"),
    (lambda m: m.update(inputs=["steam_flow", "steam_flow"]),
     r"model\.inputs\[1\]: duplicate input name 'steam_flow'"),
    (lambda m: m["blocks"][0].update(name="steam_flow"),
     r"model\.blocks\[0\]\.name: 'steam_flow' is also a model input"),
    (lambda m: m.update(solver="rk4"),
     r"model\.solver: unknown key; allowed: name, description, inputs, outputs, blocks"),
    (lambda m: m.pop("outputs"),
     r"model\.outputs: missing; a model needs name, inputs, outputs, blocks"),
    (lambda m: m["blocks"].append(
        {"name": "db", "type": "deadband", "input": "fuel", "width": 1, "delay_s": 2}),
     r"model\.blocks\[6\]\.delay_s: unknown parameter for block type deadband; allowed: "
     r"width; nonlinear blocks take no delay_s"),
    (lambda m: m["blocks"].append(
        {"name": "sat", "type": "saturation", "input": "fuel", "low": 5, "high": 5}),
     r"model\.blocks\[6\]\.high: 5\.0 is invalid .* high must be greater than low=5\.0"),
    (lambda m: m["blocks"].append(
        {"name": "d", "type": "transfer", "input": "fuel", "num": [1, 0, 0], "den": [1, 1]}),
     r"model\.blocks\[6\]\.num: .* improper \(numerator degree 2 > denominator degree 1\)"),
    (lambda m: m["blocks"].append(
        {"name": "p", "type": "pid", "input": "fuel", "kp": 1, "ti_s": 10, "td_s": -1}),
     r"model\.blocks\[6\]\.td_s: -1 is invalid .* td_s must be a finite number >= 0"),
    (lambda m: m["blocks"].append(
        {"name": "o", "type": "operating_point_gain", "input": "fuel", "slope": 0.1,
         "signal": "lod"}),
     r"model\.blocks\[6\]\.signal: unknown signal 'lod' in block 'o'"),
    (lambda m: m["blocks"][3].update(input="-"),
     r"model\.blocks\[3\]\.input\.signal: '' is invalid"),
]


@pytest.mark.parametrize(("edit", "message"), INVALID)
def test_validation_errors_name_path_value_and_what_is_allowed(edit, message):
    with pytest.raises(ModelError, match=message):
        model_from_dict(mutated(BOILER, edit))


def test_model_error_is_a_config_error_and_value_error():
    with pytest.raises(ConfigError, match=r"model\.blocks\[0\]\.k"):
        model_from_dict(mutated(BOILER, lambda m: m["blocks"][0].update(k=None)))
    with pytest.raises(ValueError, match=r"model: expected a mapping, got list"):
        model_from_dict([1, 2])


def test_constructors_validate_without_the_dict_path():
    # A modified model built with dataclasses.replace is validated the same way.
    block = model_from_dict(BOILER).block("controller")
    with pytest.raises(ModelError, match=r"block 'controller' \(type pi\): ti_s=-1 is invalid"):
        dataclasses.replace(block, ti_s=-1)
    model = model_from_dict(BOILER)
    with pytest.raises(ModelError, match=r"model\.outputs\[0\]: 'nope' is not a block"):
        dataclasses.replace(model, outputs=("nope",))


# -- modification helpers ----------------------------------------------------------
def test_scale_gain_multiplies_the_documented_parameter():
    model = model_from_dict(EVERY_TYPE)
    assert scale_gain(model.block("g"), 1.2).k == pytest.approx(2.4, rel=1e-15)
    assert scale_gain(model.block("pi"), 1.2).kp == pytest.approx(-0.6, rel=1e-15)
    assert scale_gain(model.block("pid"), 2.0).kp == pytest.approx(0.4, rel=1e-15)
    assert scale_gain(model.block("tr"), 2.0).num == (-8.0, 2.0)
    assert [t.k for t in scale_gain(model.block("out"), 2.0).inputs] == [2, 2, 2, 2, 1, 2]
    with pytest.raises(ModelError, match=r"block 'db' \(type deadband\): nonlinear block has no"):
        scale_gain(model.block("db"), 2.0)


def test_insert_after_keeps_the_name_downstream_and_outputs_unchanged():
    model = model_from_dict(BOILER)
    lag = FirstOrder(name="turbine_pressure", inputs=(Term("tp_raw"),), k=1.0, tau_s=20.0)
    new = insert_after(model, "turbine_pressure", block=lag, upstream_name="tp_raw")
    assert new.outputs == model.outputs
    assert new.block("tp_raw") == dataclasses.replace(model.block("turbine_pressure"),
                                                      name="tp_raw")
    assert new.block("turbine_pressure") == lag
    assert new.block("controller").inputs == (Term("turbine_pressure"),)
    assert model_from_dict(model_to_dict(new)) == new
    with pytest.raises(ModelError, match=r"insert_after: the inserted block is called 'x'"):
        insert_after(model, "fuel", block=dataclasses.replace(lag, name="x"),
                     upstream_name="tp_raw")


def test_insert_before_moves_the_inputs_to_the_new_block():
    model = model_from_dict(BOILER)
    new = insert_before(model, "fuel", block=Deadband(name="fuel_db", width=0.2))
    assert new.block("fuel_db").inputs == (Term("demand"),)
    assert new.block("fuel").inputs == (Term("fuel_db"),)
    assert not new.is_linear
    with pytest.raises(ModelError, match=r"insert_before: block 'x' already has inputs"):
        insert_before(model, "fuel", block=Saturation(name="x", inputs=(Term("drum"),),
                                                      low=-1, high=1))


def test_with_block_replaces_or_appends():
    model = model_from_dict(BOILER)
    faster = dataclasses.replace(model.block("controller"), ti_s=30.0)
    assert model.with_block(faster).block("controller").ti_s == 30.0
    extra = Gain(name="spy", inputs=(Term("drum"),), k=1.0)
    assert model.with_block(extra).block_names[-1] == "spy"
    with pytest.raises(ModelError, match=r"no block 'drun' \(did you mean 'drum'\?\)"):
        model.block("drun")


def test_pid_transfer_function_matches_the_documented_form():
    pid = PID(name="c", inputs=(Term("e"),), kp=2.0, ti_s=30.0, td_s=6.0, n_filter=10.0)
    num, den = pid.transfer_function()
    s = 1j * np.array([0.001, 0.03, 0.5, 7.0])
    tf_s = 6.0 / 10.0
    expected = 2.0 * (1 + 1 / (30.0 * s) + 6.0 * s / (tf_s * s + 1))
    np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s), expected, rtol=1e-12)


def test_model_requires_blocks_with_inputs():
    with pytest.raises(ModelError, match=r"model\.blocks\[0\]\.inputs: block 'g' reads no signal"):
        Model(name="m", inputs=("u",), outputs=("g",), blocks=(Gain(name="g", k=1.0),))
