"""Plant data for the discrepancy demo (controller gain 20 % above the model's)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.fft
import scipy.optimize
import scipy.signal

from pipeline.effects import Effect, apply_effect
from pipeline.simulate import simulate


def make_discrepancy_demo(seed: int = 0, *, hours: float = 8.0, dt_s: float = 1.0
                          ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Plant data for the discrepancy demo: controller gain 20 % above the model's.

    The plant is the shipped boiler steam-pressure loop (design.md "Model YAML") with the
    PI controller's ``kp`` multiplied by 1.2 (method.md §9: the thesis' simulation
    matched the plant only after raising the controller gain by about 20 %).  Steam flow
    (the load, kg/s deviation) wanders slowly (20 min), with turbulence (40 s) and a few
    load steps; the measured turbine pressure carries AR(1) sensor noise (phi 0.7) at
    15 % of the pressure's std.  Also measured: ``aux_flow``, an unrelated flow.

    Parameters
    ----------
    seed : int
        Seed of the random generator (load signals and sensor noise).
    hours : float
        Record length, h.
    dt_s : float
        Sample period, s (must divide the model's 8 s fuel dead time).

    Returns
    -------
    inputs : dict of str -> ndarray (N,)
        ``steam_flow`` and ``aux_flow`` (deviations).
    measured : dict of str -> ndarray (N,)
        ``turbine_pressure`` (deviation, bar).
    dt_s : float
    """
    from pipeline.effects import trial_inputs
    from pipeline.model import model_from_dict

    model = model_from_dict(_BOILER_MODEL)
    rng = np.random.default_rng(seed)
    n = int(round(hours * 3600.0 / dt_s))
    inputs = trial_inputs(model.name, n=n, dt_s=dt_s, rng=rng)
    plant = apply_effect(model, Effect("gain", "controller", {"factor": 1.2}), dt_s=dt_s)
    truth = simulate(plant, {"steam_flow": inputs["steam_flow"]}, dt_s=dt_s).signals[
        "turbine_pressure"]
    phi = 0.7
    e = scipy.signal.lfilter([math.sqrt(1 - phi**2)], [1.0, -phi], rng.standard_normal(n))
    measured = {"turbine_pressure": truth + 0.15 * float(np.std(truth)) * e}
    return inputs, measured, dt_s


#: The shipped boiler model (configs/models/boiler_pressure.yaml), inline so that the
#: core module reads no files; tests check that both agree.
_BOILER_MODEL: dict[str, Any] = {
    "model": {
        "name": "boiler_pressure",
        "inputs": ["steam_flow"],
        "outputs": ["turbine_pressure"],
        "blocks": [
            {"name": "feedforward", "type": "gain", "input": "steam_flow", "k": 0.019},
            {"name": "controller", "type": "pi", "input": "turbine_pressure", "kp": -0.554,
             "ti_s": 60},
            {"name": "demand", "type": "sum", "inputs": ["controller", "feedforward"]},
            {"name": "fuel", "type": "gain", "input": "demand", "k": 65, "delay_s": 8},
            {"name": "drum", "type": "integrator", "inputs": ["fuel", "-steam_flow"],
             "k": 0.000883},
            {"name": "turbine_pressure", "type": "sum",
             "inputs": ["drum", {"signal": "steam_flow", "k": -0.045}]},
        ],
    }
}
