"""Family ``two_tanks``: two tanks in series, a level loop on the integrating second tank.

Plant (levels in m, flows in L/s)::

    tank 1 (gravity outflow, self-regulating)
        A_1 dh_1/dt = 1e-3 (F_in + F_side − h_1 / R_1)      A_1 1.2 m², R_1 0.1 m per L/s
    tank 2 (pumped outflow, integrating)
        A_2 dh_2/dt = 1e-3 (h_1 / R_1 − a − d)               A_2 3 m²
    pump              a = k_p · OP                           k_p 0.2 L/s per %
    measured          tank1_level = h_1, tank2_level = h_2, controller = OP

so tank 1 is a first-order lag ``R_1 / (τ_1 s + 1)``, ``τ_1 = 1e3 A_1 R_1 = 120 s``, and
tank 2 integrates at ``1e-3 / A_2 = 3.33e-4`` m/s per L/s.  ``F_in`` is the measured
inflow (a load: 10 L/s, 0.8 L/s wander of 20 min and steps of 0.5-1.5 L/s);
``F_side = k_side (s(t − δ) − s̄)`` a measured side stream ``s`` into tank 1 that the
model ignores (k_side 0 in the nominal); ``d`` the unmeasured draw from tank 2
(0.3 L/s std, 30 min correlation time).

Loop: PI ``kp = 60 %/m, ti = 600 s`` on ``tank2_level − level_sp`` (more pump lowers the
level).  Integrating gain ``k_p · 3.33e-4 = 6.7e-5`` m/s per %: closed-loop
``s² + K s + K/ti`` with ``K = 4e-3``: ω_n = 2.6e-3 rad/s, ζ = 0.77 — an averaging-level
tuning that lets the level move to keep the pump flow smooth.  Setpoint moves of
0.1-0.25 m every 30-60 min in 1.2-1.8 m (operating point 1.5 m; pump OP ≈ 50 %).
Historian: 5 s (the loop's time scale is minutes), 8 h.

Nominal model: blocks ``tank1_level`` (first_order), ``outflow1`` (gain 1/R_1),
``level_error``, ``controller``, ``pump`` (gain), ``tank2_level`` (integrator);
outputs ``tank1_level``, ``tank2_level``, ``controller``.

Effect sites: actuator effects at ``pump`` (saturation: the pump's maximum or minimum
flow, the level controller winding up); ``sensor_bias_drift`` on ``tank1_level`` (not
controlled); ``unmodelled_input`` ``side_flow->tank1_level``: the side stream enters tank
1, so its path is exactly the catalogue's first-order lag, ``k = R_1 k_side`` and
``tau_s = τ_1`` (and it flows on into tank 2, as the catalogue's augmented model has it).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.zoo.sim import Family, Loop, random_steps, unit_ar1

A1, A2, R1, KP_PUMP = 1.2, 3.0, 0.1, 0.2
TAU1 = 1e3 * A1 * R1


@dataclass
class TwoTanks(Family):
    """The two-tank family (module docstring)."""

    name: str = "two_tanks"
    dt_s: float = 5.0
    hours: float = 8.0
    loops: tuple[Loop, ...] = (Loop(op="controller", pv="tank2_level", sp="level_sp",
                                    kp=60.0, ti_s=600.0, reverse=True),)
    loads: dict[str, str] = field(default_factory=lambda: {"inflow": "FI-401.PV"})
    setpoints: dict[str, str] = field(default_factory=lambda: {"level_sp": "LIC-402.SP"})
    extra: tuple[str, str] = ("side_flow", "FI-405.PV")
    outputs: dict[str, str] = field(default_factory=lambda: {
        "tank1_level": "LI-401.PV", "tank2_level": "LI-402.PV", "controller": "LIC-402.OP"})
    scales: dict[str, float] = field(default_factory=lambda: {
        "tank1_level": 0.1, "tank2_level": 0.1, "controller": 5.0})
    sites: dict[str, str] = field(default_factory=lambda: {
        **{e: "pump" for e in ("gain", "dead_time", "extra_lag", "saturation",
                               "deadband", "backlash")},
        "sensor_bias_drift": "tank1_level", "unmodelled_input": "side_flow->tank1_level"})
    ranges: dict[str, tuple[float, float]] = field(default_factory=lambda: {
        "gain": (0.2, 0.4), "dead_time": (20.0, 60.0), "extra_lag": (30.0, 120.0),
        "deadband": (1.0, 3.0), "backlash": (1.0, 3.0), "drift": (1.0, 2.0),
        "unmodelled_delay": (0.0, 30.0)})
    params: dict[str, float] = field(default_factory=lambda: {
        "extra_k": 0.0, "dist_std": 0.3})

    def model(self) -> dict[str, Any]:
        """The nominal model YAML mapping."""
        lp = self.loops[0]
        return {"model": {
            "name": "two_tanks",
            "inputs": ["level_sp", "inflow"],
            "outputs": ["tank1_level", "tank2_level", "controller"],
            "blocks": [
                {"name": "tank1_level", "type": "first_order", "input": "inflow",
                 "k": R1, "tau_s": TAU1},
                {"name": "outflow1", "type": "gain", "input": "tank1_level", "k": 1.0 / R1},
                {"name": "level_error", "type": "sum", "inputs": ["tank2_level", "-level_sp"]},
                {"name": "controller", "type": "pi", "input": "level_error",
                 "kp": lp.kp, "ti_s": lp.ti_s},
                {"name": "pump", "type": "gain", "input": "controller", "k": KP_PUMP},
                {"name": "tank2_level", "type": "integrator", "inputs": ["outflow1", "-pump"],
                 "k": round(1e-3 / A2, 10)},
            ]}}

    def exogenous(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        """Level setpoint steps, inflow, side stream and the unit disturbance.

        Parameters
        ----------
        rng : numpy.random.Generator
        n : int
            Fine steps.
        """
        h = self.fine_s
        sp = random_steps(rng, n, h, start=1.5, every_s=(1800.0, 3600.0), size=(0.1, 0.25),
                          bounds=(1.2, 1.8))
        inflow = 10.0 + 0.8 * unit_ar1(rng, n, 1200.0, h) + random_steps(
            rng, n, h, start=0.0, every_s=(1800.0, 3600.0), size=(0.5, 1.5), bounds=(-2, 2))
        side = 1.5 + 0.3 * unit_ar1(rng, n, 900.0, h) + random_steps(
            rng, n, h, start=0.0, every_s=(1200.0, 3000.0), size=(0.2, 0.5),
            bounds=(-0.6, 0.6))
        return {"level_sp": sp, "inflow": inflow, "side_flow": side,
                "disturbance": unit_ar1(rng, n, 1800.0, h)}

    def steady_state(self, e: Sequence[float], p: Mapping[str, float]
                     ) -> tuple[list[float], list[float]]:
        """State ``[h_1, h_2]`` and OP at rest with ``h_2 = level_sp``.

        Parameters
        ----------
        e : sequence of float
        p : mapping
        """
        sp, inflow, _, dist, extra_in = e
        f1 = inflow + p["extra_k"] * extra_in
        pump = f1 - p["dist_std"] * dist
        return [R1 * f1, sp], [pump / KP_PUMP]

    def valve(self, loop: int, op: float, p: Mapping[str, float]) -> float:
        """Pump flow (L/s) at OP `op` (%).

        Parameters
        ----------
        loop : int
        op : float
        p : mapping
        """
        return KP_PUMP * op

    def deriv(self, x: list[float], a: list[float], e: list[float],
              p: Mapping[str, float]) -> list[float]:
        """Mass balances (module docstring).

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        h1, _ = x
        out1 = h1 / R1
        return [1e-3 * (e[1] + p["extra_k"] * e[4] - out1) / A1,
                1e-3 * (out1 - a[0] - p["dist_std"] * e[3]) / A2]

    def measure(self, x: list[float], a: list[float], e: list[float],
                p: Mapping[str, float]) -> list[float]:
        """``[tank1_level, tank2_level]``.

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        return [x[0], x[1]]

    def unmodelled(self, rng: np.random.Generator, extra_std: float
                   ) -> tuple[dict[str, float], dict[str, float]]:
        """A side stream whose level effect is 0.3-0.7 tank-1 scales.

        Parameters
        ----------
        rng : numpy.random.Generator
        extra_std : float
        """
        k_side = rng.uniform(0.3, 0.7) * self.scales["tank1_level"] / (R1 * extra_std)
        return {"extra_k": k_side}, {"k": R1 * k_side, "tau_s": TAU1}
