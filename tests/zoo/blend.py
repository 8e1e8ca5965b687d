"""Family ``blend``: an interacting 2 × 2 blend, total flow and composition, two PI loops.

A concentrate A (c_A ≈ 50 %) and a diluent B (c_B ≈ 0 %) are blended into a mixing
drum; the total flow is controlled with the diluent valve, the composition with the
concentrate valve.  Plant (flows kg/s, concentrations %)::

    valves       a_A = 0.04 OP_A,  a_B = 0.16 OP_B            kg/s per %
    flows        τ_v dF_A/dt = a_A − F_A,  τ_v dF_B/dt = a_B − F_B      τ_v 10 s
    mixer        τ_m dC/dt = C_0 + 4 (F_A − 2) − (F_B − 8)
                             + 0.2 (c_A − 50) + 0.8 d + g − C             τ_m 120 s
    analyser     τ_q dC_m/dt = C − C_m                                    τ_q 15 s
    recycle      τ_x dg/dt = k_x (r(t − δ) − r̄) − g                      (k_x 0 nominal)
    measured     total_flow = F_A + F_B, flow_a = F_A, composition = C_m, comp_pi = OP_A

The mixer is the component balance ``V dC/dt = F_A c_A + F_B c_B − (F_A + F_B) C``
linearised about the design point F_A = 2, F_B = 8, C_0 = 10 %, c_A = 50 %, c_B = 0:
``∂/∂F_A = (c_A − C_0)/F = 4``, ``∂/∂F_B = (c_B − C_0)/F = −1``, ``∂/∂c_A = F_A/F = 0.2``,
``∂/∂c_B = 0.8``; ``τ_m = V/F = 120 s``.  The bilinear terms are left out ON PURPOSE so
that a null trial is exactly the nominal model's structure (with flows within ±10 % they
would change the composition response by up to ~10 % -- a structural mismatch this
family is not meant to test).  ``c_A`` (``feed_conc``) is measured (50 %, 1.5 % wander);
``d`` is the unmeasured diluent-quality drift (0.25 % std, 30 min); ``r`` a measured
recycle flow that the model ignores.

Loops: flow PI on the diluent valve ``kp = 3 %/(kg/s), ti = 12 s`` (process
0.16/(10 s + 1): crossover ≈ 0.06 rad/s, PM > 60°); composition PI on the concentrate
valve ``kp = 12 %/%, ti = 120 s`` (with the flow loop closed the concentrate moves the
composition by 0.04 · 5 = 0.2 %/%: the diluent valve takes back the added flow;
crossover ≈ 0.02 rad/s, PM ≈ 55°).  The relative gain of the pairing is 0.8: the loops
interact.  Setpoint moves: flow 0.4-1.0 kg/s every 15-40 min in 9-11 kg/s; composition
0.5-1.5 % every 20-50 min in 8-12 %.  Historian: 2 s, 4 h.

Nominal model: ``flow_error``, ``flow_pi``, ``comp_error``, ``comp_pi``, ``valve_a``,
``flow_a``, ``valve_b``, ``flow_b``, ``total_flow``, ``mixer``, ``composition``; outputs
``total_flow``, ``composition``, ``flow_a`` (stream A's flow meter), ``comp_pi`` (its OP).

Effect sites: actuator effects at ``valve_a`` (the concentrate valve: saturation at its
travel stop with the composition controller winding up); ``sensor_bias_drift`` on the
``flow_a`` meter (no loop reads it); ``unmodelled_input`` ``recycle_flow->composition``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.zoo.sim import Family, Loop, random_steps, unit_ar1

KV_A, KV_B = 0.04, 0.16
FA0, FB0, C0, CA0 = 2.0, 8.0, 10.0, 50.0
G_A, G_B, G_CA, G_CB = 4.0, -1.0, 0.2, 0.8
TAU_V, TAU_M, TAU_Q = 10.0, 120.0, 15.0


@dataclass
class Blend(Family):
    """The blend family (module docstring)."""

    name: str = "blend"
    dt_s: float = 2.0
    hours: float = 4.0
    loops: tuple[Loop, ...] = (
        Loop(op="flow_pi", pv="total_flow", sp="flow_sp", kp=3.0, ti_s=12.0),
        Loop(op="comp_pi", pv="composition", sp="comp_sp", kp=12.0, ti_s=120.0))
    valve_loop: int = 1
    loads: dict[str, str] = field(default_factory=lambda: {"feed_conc": "AI-501.PV"})
    setpoints: dict[str, str] = field(default_factory=lambda: {
        "flow_sp": "FIC-510.SP", "comp_sp": "AIC-520.SP"})
    extra: tuple[str, str] = ("recycle_flow", "FI-530.PV")
    outputs: dict[str, str] = field(default_factory=lambda: {
        "total_flow": "FIC-510.PV", "composition": "AIC-520.PV", "flow_a": "FI-511.PV",
        "comp_pi": "AIC-520.OP"})
    scales: dict[str, float] = field(default_factory=lambda: {
        "total_flow": 0.4, "composition": 0.6, "flow_a": 0.15, "comp_pi": 4.0})
    sites: dict[str, str] = field(default_factory=lambda: {
        **{e: "valve_a" for e in ("gain", "dead_time", "extra_lag", "saturation",
                                  "deadband", "backlash")},
        "sensor_bias_drift": "flow_a", "unmodelled_input": "recycle_flow->composition"})
    ranges: dict[str, tuple[float, float]] = field(default_factory=lambda: {
        "gain": (0.2, 0.4), "dead_time": (4.0, 20.0), "extra_lag": (10.0, 40.0),
        "deadband": (1.0, 3.0), "backlash": (1.0, 3.0), "drift": (1.0, 2.0),
        "unmodelled_delay": (0.0, 10.0)})
    params: dict[str, float] = field(default_factory=lambda: {
        "extra_k": 0.0, "extra_tau": 60.0, "dist_std": 0.25})

    def model(self) -> dict[str, Any]:
        """The nominal model YAML mapping."""
        fl, cl = self.loops
        return {"model": {
            "name": "blend",
            "inputs": ["flow_sp", "comp_sp", "feed_conc"],
            "outputs": ["total_flow", "composition", "flow_a", "comp_pi"],
            "blocks": [
                {"name": "flow_error", "type": "sum", "inputs": ["flow_sp", "-total_flow"]},
                {"name": "flow_pi", "type": "pi", "input": "flow_error",
                 "kp": fl.kp, "ti_s": fl.ti_s},
                {"name": "comp_error", "type": "sum", "inputs": ["comp_sp", "-composition"]},
                {"name": "comp_pi", "type": "pi", "input": "comp_error",
                 "kp": cl.kp, "ti_s": cl.ti_s},
                {"name": "valve_a", "type": "gain", "input": "comp_pi", "k": KV_A},
                {"name": "flow_a", "type": "first_order", "input": "valve_a",
                 "k": 1.0, "tau_s": TAU_V},
                {"name": "valve_b", "type": "gain", "input": "flow_pi", "k": KV_B},
                {"name": "flow_b", "type": "first_order", "input": "valve_b",
                 "k": 1.0, "tau_s": TAU_V},
                {"name": "total_flow", "type": "sum", "inputs": ["flow_a", "flow_b"]},
                {"name": "mixer", "type": "first_order",
                 "inputs": [{"signal": "flow_a", "k": G_A}, {"signal": "flow_b", "k": G_B},
                            {"signal": "feed_conc", "k": G_CA}],
                 "k": 1.0, "tau_s": TAU_M},
                {"name": "composition", "type": "first_order", "input": "mixer",
                 "k": 1.0, "tau_s": TAU_Q},
            ]}}

    def exogenous(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        """Setpoint steps, feed concentration, recycle flow and the unit disturbance.

        Parameters
        ----------
        rng : numpy.random.Generator
        n : int
            Fine steps.
        """
        h = self.fine_s
        flow_sp = random_steps(rng, n, h, start=10.0, every_s=(900.0, 2400.0),
                               size=(0.4, 1.0), bounds=(9.0, 11.0))
        comp_sp = random_steps(rng, n, h, start=10.0, every_s=(1200.0, 3000.0),
                               size=(0.5, 1.5), bounds=(8.0, 12.0))
        feed = CA0 + 1.5 * unit_ar1(rng, n, 1200.0, h)
        recycle = 1.0 + 0.1 * unit_ar1(rng, n, 600.0, h) + random_steps(
            rng, n, h, start=0.0, every_s=(900.0, 2400.0), size=(0.1, 0.2), bounds=(-0.3, 0.3))
        return {"flow_sp": flow_sp, "comp_sp": comp_sp, "feed_conc": feed,
                "recycle_flow": recycle, "disturbance": unit_ar1(rng, n, 1800.0, h)}

    def _mixer_input(self, fa: float, fb: float, e: Sequence[float],
                     p: Mapping[str, float]) -> float:
        return (C0 + G_A * (fa - FA0) + G_B * (fb - FB0) + G_CA * (e[2] - CA0)
                + G_CB * p["dist_std"] * e[4])

    def steady_state(self, e: Sequence[float], p: Mapping[str, float]
                     ) -> tuple[list[float], list[float]]:
        """State ``[F_A, F_B, C, C_m, g]`` and OPs at rest on both setpoints.

        Parameters
        ----------
        e : sequence of float
        p : mapping
        """
        flow_sp, comp_sp = e[0], e[1]
        g = p["extra_k"] * e[5]
        # C = comp_sp and F_A + F_B = flow_sp: two linear equations in F_A, F_B
        rest = comp_sp - g - self._mixer_input(0.0, 0.0, e, p)
        fa = (rest - G_B * flow_sp) / (G_A - G_B)
        fb = flow_sp - fa
        return [fa, fb, comp_sp - g, comp_sp - g, g], [fb / KV_B, fa / KV_A]

    def valve(self, loop: int, op: float, p: Mapping[str, float]) -> float:
        """Valve flow demand (kg/s) of loop `loop` (0: diluent B, 1: concentrate A).

        Parameters
        ----------
        loop : int
        op : float
        p : mapping
        """
        return (KV_B if loop == 0 else KV_A) * op

    def deriv(self, x: list[float], a: list[float], e: list[float],
              p: Mapping[str, float]) -> list[float]:
        """Flow lags, the linearised component balance, the analyser and the recycle.

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        fa, fb, c, cm, g = x
        return [(a[1] - fa) / TAU_V, (a[0] - fb) / TAU_V,
                (self._mixer_input(fa, fb, e, p) - c) / TAU_M,
                (c - cm) / TAU_Q,
                (p["extra_k"] * e[5] - g) / p["extra_tau"]]

    def measure(self, x: list[float], a: list[float], e: list[float],
                p: Mapping[str, float]) -> list[float]:
        """``[total_flow, composition, flow_a]``.

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        return [x[0] + x[1], x[3] + x[4], x[0]]

    def unmodelled(self, rng: np.random.Generator, extra_std: float
                   ) -> tuple[dict[str, float], dict[str, float]]:
        """A recycle path of 0.3-0.7 composition scales.

        Parameters
        ----------
        rng : numpy.random.Generator
        extra_std : float
        """
        k = rng.uniform(0.3, 0.7) * self.scales["composition"] / extra_std
        tau = float(rng.uniform(20.0, 90.0))
        return {"extra_k": k, "extra_tau": tau}, {"k": k, "tau_s": tau}
