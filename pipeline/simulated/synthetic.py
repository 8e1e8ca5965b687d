"""Synthetic plant records for the demos (core: the models come in as arguments).

Every generator here takes the plant's :class:`~pipeline.models.model.Model` and returns
arrays; reading the shipped model files and writing exports is the composition's
(:mod:`pipeline.jobs.demo`).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.signal

from pipeline.simulated.effect_trials import trial_inputs
from pipeline.discrepancy.effects import Effect, apply_effect
from pipeline.models.model import Model
from pipeline.models.simulate import simulate

#: the demo's setpoint moves (uniform within ± this, bar) and the setpoint filter, s
SP_MOVE_BAR, SP_RAMP_S = 1.0, 30.0

__all__ = ["boiler_demo_plant", "boiler_demo_signals", "make_discrepancy_demo"]


def boiler_demo_plant(model: dict) -> dict:
    """The estimation demo's plant: the boiler pressure loop of `model` (the shipped
    ``boiler_pressure`` model as a dict, design.md "Model YAML") with the pressure
    setpoint ``pressure_sp`` the operators move: the controller acts on
    ``turbine_pressure - pressure_sp``.  Returns a new model dict (`model` is not
    changed).

    Parameters
    ----------
    model : dict
        The boiler model's ``model:`` mapping (blocks ``controller`` and ``drum``).
    """
    m = {**model, "inputs": [*model["inputs"], "pressure_sp"]}
    blocks = []
    for b in model["blocks"]:
        b = dict(b)
        if b["name"] == "controller":
            blocks.append({"name": "pressure_error", "type": "sum",
                           "inputs": [b["input"], "-pressure_sp"]})
            b["input"] = "pressure_error"
        blocks.append(b)
    m["blocks"] = blocks
    return m


def boiler_demo_signals(plant: Model, operating_point: dict[str, float], *,
                        hours: float = 12.0, dt_s: float = 1.0, seed: int = 7) -> dict:
    """The estimation demo's plant signals: ``{"t_s", "steam_flow", "turbine_pressure",
    "fuel_flow", "pressure_sp"}`` (absolute engineering values, sensor noise included).

    The load (steam flow) wanders like a real unit's: slow moves (correlation time
    ~20 min) plus turbulence (~40 s).  The operators move the pressure setpoint now and
    then (a new value every 15-45 min, within ±1 bar, ramped by a 30 s setpoint filter).
    ``plant`` (:func:`boiler_demo_plant`) is simulated from them, and each measured
    signal gets white sensor noise.

    Parameters
    ----------
    plant : Model
        The demo plant (inputs ``steam_flow`` and ``pressure_sp``; blocks
        ``turbine_pressure`` and ``fuel``).
    operating_point : dict of str to float
        ``steam_flow``, ``turbine_pressure`` and ``fuel_flow`` values the deviations are
        added to.
    hours : float
        Length of the record, h.
    dt_s : float
        Sample period of the simulation, s.
    seed : int
        Seeds the load, the setpoint moves and the sensor noise.
    """
    rng = np.random.default_rng(seed)
    n = int(hours * 3600 / dt_s)
    slow = scipy.signal.lfilter([1 - np.exp(-dt_s / 1200)], [1, -np.exp(-dt_s / 1200)],
                                rng.standard_normal(n)) * 40.0
    fast = scipy.signal.lfilter([np.sqrt(1 - np.exp(-2 * dt_s / 40))], [1, -np.exp(-dt_s / 40)],
                                rng.standard_normal(n)) * 1.5
    steam = slow + fast
    sp = np.zeros(n)
    k = int(rng.integers(0, int(1800 / dt_s)))
    while k < n:
        hold = int(rng.integers(int(900 / dt_s), int(2700 / dt_s)))
        sp[k:k + hold] = rng.uniform(-SP_MOVE_BAR, SP_MOVE_BAR)
        k += hold
    b = np.exp(-dt_s / SP_RAMP_S)  # the setpoint ramps (a setpoint filter)
    sp = scipy.signal.lfilter([1 - b], [1, -b], sp)
    sim = simulate(plant, {"steam_flow": steam, "pressure_sp": sp}, dt_s=dt_s)
    pressure = sim.outputs[:, 0]
    fuel = np.asarray(sim.signals["fuel"])
    op = operating_point
    return {
        "t_s": np.arange(n) * dt_s,
        "steam_flow": op["steam_flow"] + steam + 0.05 * rng.standard_normal(n),
        "turbine_pressure": op["turbine_pressure"] + pressure + 0.001 * rng.standard_normal(n),
        "fuel_flow": op["fuel_flow"] + fuel + 0.05 * rng.standard_normal(n),
        "pressure_sp": op["turbine_pressure"] + sp,
    }


#: The discrepancy demo's plant: the controller gain 20 % above the model's (method.md §9).
DEMO_EFFECTS = (Effect("gain", "controller", {"factor": 1.2}),)
#: The two-effect demo's plant: that, and the auxiliary flow (an attemperator spray the
#: model ignores) acting on the turbine pressure through a 60 s lag after 10 s.
TWO_EFFECT_DEMO_EFFECTS = (
    Effect("gain", "controller", {"factor": 1.2}),
    Effect("unmodelled_input", "aux_flow->turbine_pressure",
           {"k": 0.02, "tau_s": 60.0, "delay_s": 10.0}),
)


def make_discrepancy_demo(model: Model, seed: int = 0, *, hours: float = 8.0, dt_s: float = 1.0,
                          effects: tuple[Effect, ...] = DEMO_EFFECTS
                          ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Plant data for the discrepancy demos: the model with hidden `effects`.

    The plant is ``model`` (the shipped boiler steam-pressure loop, design.md "Model
    YAML") with `effects` added -- by default the PI controller's ``kp`` multiplied by
    1.2 (method.md §9: the thesis' simulation matched the plant only after raising the
    controller gain by about 20 %); :data:`TWO_EFFECT_DEMO_EFFECTS` adds an unmodelled
    auxiliary flow.  Steam flow
    (the load, kg/s deviation) wanders slowly (20 min), with turbulence (40 s) and a few
    load steps; the measured turbine pressure carries AR(1) sensor noise (phi 0.7) at
    15 % of the pressure's std.  Also measured: ``aux_flow``, an unrelated flow.

    Parameters
    ----------
    model : Model
        The nominal boiler pressure loop (a ``pi`` block ``controller``, input
        ``steam_flow``, output ``turbine_pressure``).
    seed : int
        Seed of the random generator (load signals and sensor noise).
    hours : float
        Record length, h.
    dt_s : float
        Sample period, s (must divide the model's 8 s fuel dead time).
    effects : tuple of Effect
        The plant's differences from `model`, added in order.

    Returns
    -------
    inputs : dict of str -> ndarray (N,)
        ``steam_flow`` and ``aux_flow`` (deviations).
    measured : dict of str -> ndarray (N,)
        ``turbine_pressure`` (deviation, bar).
    dt_s : float
    """
    rng = np.random.default_rng(seed)
    n = int(round(hours * 3600.0 / dt_s))
    inputs = trial_inputs(model.name, n=n, dt_s=dt_s, rng=rng)
    plant = model
    for effect in effects:
        plant = apply_effect(plant, effect, dt_s=dt_s)
    truth = simulate(plant, {k: inputs[k] for k in plant.inputs}, dt_s=dt_s).signals[
        "turbine_pressure"]
    phi = 0.7
    e = scipy.signal.lfilter([math.sqrt(1 - phi**2)], [1.0, -phi], rng.standard_normal(n))
    measured = {"turbine_pressure": truth + 0.15 * float(np.std(truth)) * e}
    return inputs, measured, dt_s
