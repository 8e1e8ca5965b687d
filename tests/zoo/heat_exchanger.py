"""Family ``heat_exchanger``: a steam-heated exchanger's outlet-temperature loop, OP measured.

Plant (absolute units; a steam valve, a condensing shell, the tube-side fluid, a sensor)::

    steam flow       a  = c_v · OP                                  kg/s  (c_v 0.012 /%)
    shell heat       τ_s dQ/dt  = K_q a − Q                         K-equivalent, τ_s 15 s
    fluid            τ_f dT1/dt = T_in + Q + d − T1                 °C, τ_f 60 s
    sensor           τ_m dT/dt  = T1 − T                            °C, τ_m 8 s
    bypass mixing    τ_x dw/dt  = k_x (b(t − δ) − b̄) − w           (k_x 0 in the nominal)
    measured         outlet_temp = T + w,  steam = a,  controller = OP

``K_q = λ / (F_p c_p) = 2100 / (5 · 4.18) = 100.48`` K per kg/s of steam (latent heat
2100 kJ/kg, process flow 5 kg/s of water).  ``T_in`` is the measured inlet temperature
(a load: 20 °C, slow wander of 1.5 K and steps of 1-3 K); ``d`` the unmeasured
disturbance (steam-header pressure and fouling, 0.8 K std, 30 min correlation time);
``b`` a measured bypass flow (0.5 kg/s, 0.1 kg/s wander) that the model ignores.

Loop: PI ``kp = 2.5 %/K, ti = 70 s`` on ``temp_sp − outlet_temp``.  Process gain
``c_v K_q = 1.206 K/%``; with the 60/15/8 s lags, the 1 s scan and half a scan of
sample-and-hold, crossover ≈ 0.038 rad/s with ≈ 43° phase margin and ≈ 3.4 gain margin:
a firm but ordinary temperature loop.  Setpoint moves of 2-5 K every 20-45 min in
70-90 °C (operating point 80 °C, OP ≈ 50 %).  Historian: 2 s.

Nominal model: the same equations in deviation variables (blocks ``temp_error``,
``controller``, ``steam``, ``shell``, ``exchanger``, ``outlet_temp``), outputs
``outlet_temp``, ``controller`` (the OP) and ``steam`` (the steam flow meter).

Effect sites: every actuator effect at ``steam`` (the valve; saturation = the valve's
travel stop with the controller winding up); ``sensor_bias_drift`` on the steam flow
meter (an uncontrolled output: the catalogue's drift is not seen by a controller);
``unmodelled_input`` ``bypass_flow->outlet_temp`` (the mixing lag above: exactly the
catalogue's first-order path).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.zoo.sim import Family, Loop, random_steps, unit_ar1

CV = 0.012
KQ = 2100.0 / (5.0 * 4.18)
TAU_SHELL, TAU_FLUID, TAU_SENSOR = 15.0, 60.0, 8.0


@dataclass
class HeatExchanger(Family):
    """The heat-exchanger family (module docstring)."""

    name: str = "heat_exchanger"
    dt_s: float = 2.0
    hours: float = 4.0
    loops: tuple[Loop, ...] = (Loop(op="controller", pv="outlet_temp", sp="temp_sp",
                                    kp=2.5, ti_s=70.0),)
    loads: dict[str, str] = field(default_factory=lambda: {"inlet_temp": "TI-300.PV"})
    setpoints: dict[str, str] = field(default_factory=lambda: {"temp_sp": "TIC-301.SP"})
    extra: tuple[str, str] = ("bypass_flow", "FI-305.PV")
    outputs: dict[str, str] = field(default_factory=lambda: {
        "outlet_temp": "TI-301.PV", "steam": "FI-302.PV", "controller": "TIC-301.OP"})
    scales: dict[str, float] = field(default_factory=lambda: {
        "outlet_temp": 3.0, "steam": 0.033, "controller": 2.8})
    sites: dict[str, str] = field(default_factory=lambda: {
        **{e: "steam" for e in ("gain", "dead_time", "extra_lag", "saturation",
                                "deadband", "backlash")},
        "sensor_bias_drift": "steam", "unmodelled_input": "bypass_flow->outlet_temp"})
    ranges: dict[str, tuple[float, float]] = field(default_factory=lambda: {
        "gain": (0.2, 0.4), "dead_time": (4.0, 16.0), "extra_lag": (10.0, 40.0),
        "deadband": (1.0, 3.0), "backlash": (1.0, 3.0), "drift": (1.0, 2.0),
        "unmodelled_delay": (0.0, 10.0)})
    params: dict[str, float] = field(default_factory=lambda: {
        "extra_k": 0.0, "extra_tau": 30.0, "dist_std": 0.8})

    def model(self) -> dict[str, Any]:
        """The nominal model YAML mapping."""
        return {"model": {
            "name": "heat_exchanger",
            "inputs": ["temp_sp", "inlet_temp"],
            "outputs": ["outlet_temp", "controller", "steam"],
            "blocks": [
                {"name": "temp_error", "type": "sum", "inputs": ["temp_sp", "-outlet_temp"]},
                {"name": "controller", "type": "pi", "input": "temp_error",
                 "kp": self.loops[0].kp, "ti_s": self.loops[0].ti_s},
                {"name": "steam", "type": "gain", "input": "controller", "k": CV},
                {"name": "shell", "type": "first_order", "input": "steam",
                 "k": round(KQ, 4), "tau_s": TAU_SHELL},
                {"name": "exchanger", "type": "first_order", "inputs": ["shell", "inlet_temp"],
                 "k": 1.0, "tau_s": TAU_FLUID},
                {"name": "outlet_temp", "type": "first_order", "input": "exchanger",
                 "k": 1.0, "tau_s": TAU_SENSOR},
            ]}}

    def exogenous(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        """Setpoint steps, inlet temperature, bypass flow and the unit disturbance.

        Parameters
        ----------
        rng : numpy.random.Generator
        n : int
            Fine steps.
        """
        h = self.fine_s
        sp = random_steps(rng, n, h, start=80.0, every_s=(1200.0, 2700.0), size=(2.0, 5.0),
                          bounds=(70.0, 90.0))
        inlet = 20.0 + 1.5 * unit_ar1(rng, n, 1200.0, h) + random_steps(
            rng, n, h, start=0.0, every_s=(1800.0, 3600.0), size=(1.0, 3.0), bounds=(-3, 3))
        bypass = 0.5 + 0.08 * unit_ar1(rng, n, 600.0, h) + random_steps(
            rng, n, h, start=0.0, every_s=(900.0, 2400.0), size=(0.05, 0.15),
            bounds=(-0.2, 0.2))
        return {"temp_sp": sp, "inlet_temp": inlet, "bypass_flow": bypass,
                "disturbance": unit_ar1(rng, n, 1800.0, h)}

    def steady_state(self, e: Sequence[float], p: Mapping[str, float]
                     ) -> tuple[list[float], list[float]]:
        """State ``[Q, T1, T, w]`` and OP at rest with ``T = temp_sp`` (see
        :meth:`tests.zoo.sim.Family.steady_state`).

        Parameters
        ----------
        e : sequence of float
        p : mapping
        """
        sp, t_in, _, dist, extra_in = e
        w = p["extra_k"] * extra_in
        temp = sp - w
        q = temp - t_in - p["dist_std"] * dist
        return [q, temp, temp, w], [q / KQ / CV]

    def valve(self, loop: int, op: float, p: Mapping[str, float]) -> float:
        """Steam flow (kg/s) at OP `op` (%): linear valve.

        Parameters
        ----------
        loop : int
        op : float
        p : mapping
        """
        return CV * op

    def deriv(self, x: list[float], a: list[float], e: list[float],
              p: Mapping[str, float]) -> list[float]:
        """Energy balances (module docstring).

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        q, t1, t, w = x
        return [(KQ * a[0] - q) / TAU_SHELL,
                (e[1] + q + p["dist_std"] * e[3] - t1) / TAU_FLUID,
                (t1 - t) / TAU_SENSOR,
                (p["extra_k"] * e[4] - w) / p["extra_tau"]]

    def measure(self, x: list[float], a: list[float], e: list[float],
                p: Mapping[str, float]) -> list[float]:
        """``[outlet_temp, steam]``; the steam meter reads the valve's flow.

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        return [x[2] + x[3], a[0]]

    def unmodelled(self, rng: np.random.Generator, extra_std: float
                   ) -> tuple[dict[str, float], dict[str, float]]:
        """A bypass mixing path of 0.3-0.7 outlet scales (module docstring).

        Parameters
        ----------
        rng : numpy.random.Generator
        extra_std : float
        """
        k = -rng.uniform(0.3, 0.7) * self.scales["outlet_temp"] / extra_std
        tau = float(rng.uniform(20.0, 90.0))
        return {"extra_k": k, "extra_tau": tau}, {"k": k, "tau_s": tau}
