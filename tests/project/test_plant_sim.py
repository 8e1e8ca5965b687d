"""The independent plant simulator (``tests/plant_sim.py``) against independent answers.

References, none of them the simulator's code path nor the pipeline's:

* python-control ``forced_response`` of the continuous transfer function (and, for the
  drum-level loop, of the ``interconnect``-ed closed loop).  For a continuous system it
  integrates exactly with the input linearly interpolated between its time points (a
  matrix exponential of the augmented system), i.e. exactly the plant's input model, so
  the reference is exact up to rounding; it runs on a grid 10x finer than the plant's
  fine step so that dead times are exact shifts;
* scipy ``solve_ivp`` (DOP853, rtol 1e-11) by the method of steps for the boiler loop,
  whose 8 s dead time python-control cannot represent exactly;
* closed forms (static nonlinearities, the DCS recursion written out with numpy, the
  trapezoid integral of a piecewise-linear signal, steady states).

Tolerances.  The plant integrates by Heun's method (second order) at ``h = dt_s /
substeps``: its global error on a mode of rate ``w`` is about ``(h w)^2 / 6`` of the
response amplitude, so the tolerance is ``(h w)^2 * max|y|`` (a 6x margin) with ``w`` the
fastest block pole or the input's bandwidth, whichever is larger; the measured errors are
2.4-20x below it and halve-the-step convergence (ratio 4) is checked separately.  A
fractional dead time adds the buffer's linear-interpolation error ``h^2/8 max|y''|``.
Integrators and PI blocks of a piecewise-linear input are integrated exactly (the
trapezoid rule), so they and the DCS recursion are checked to rounding (1e-10).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import ClassVar

import control as ct
import numpy as np
import pytest
import scipy.signal as ss
import yaml
from scipy.integrate import cumulative_trapezoid, solve_ivp

from pipeline.models.blocks import (
    Block,
    Deadband,
    FirstOrder,
    OperatingPointGain,
    Saturation,
    Term,
    Transfer,
)
from pipeline.models.model import Model, insert_after, insert_before, model_from_dict
from tests.plant_sim import MAX_STEP_POLE, simulate_plant

MODELS = Path(__file__).resolve().parents[2] / "configs" / "models"
DT = 2.0
N = 600  # 20 min at 2 s: many time constants of every test block
POLE = 0.9  # input AR(1) pole per sample
INPUT_RATE = -math.log(POLE) / DT  # the input's bandwidth, rad/s
REFINE = 10  # reference grid = plant fine step / REFINE
TK = np.arange(N) * DT


def load(name: str) -> Model:
    with (MODELS / f"{name}.yaml").open(encoding="utf-8") as fh:
        return model_from_dict(yaml.safe_load(fh))


def one_block(spec: dict, inputs: tuple[str, ...] = ("u",)) -> Model:
    return model_from_dict({"model": {"name": "one", "inputs": list(inputs), "outputs": ["y"],
                                      "blocks": [{"name": "y", "input": "u", **spec}]}})


def smooth_input(n: int, seed: int, pole: float = POLE, scale: float = 0.1) -> np.ndarray:
    """A slowly wandering process variable that starts at rest (0)."""
    u = ss.lfilter([scale], [1.0, -pole], np.random.default_rng(seed).standard_normal(n))
    return u - u[0]


def ct_reference(G, u: np.ndarray, *, delay_s: float, hr: float
                 ) -> tuple[np.ndarray, float]:
    """``G`` driven by the linearly interpolated ``u`` (exact), delayed, at the samples;
    and ``max|y''|`` on the fine grid ``hr``."""
    per = round(DT / hr)
    t = np.arange((u.size - 1) * per + 1) * hr
    y = ct.forced_response(G, T=t, U=np.interp(t, TK[: u.size], u)).outputs
    shift = round(delay_s / hr)
    assert abs(shift * hr - delay_s) < 1e-9  # the shift must be an exact dead time
    y = np.concatenate([np.zeros(shift), y[: y.size - shift]])
    return y[::per], float(np.max(np.abs(np.diff(y, 2)))) / hr**2


# ---------------------------------------------------------------- linear open loop
_TF = 10.0 / 10.0  # pid derivative filter td/n_filter, s
LINEAR = [
    # id, block spec, continuous G without the delay, fastest pole (rad/s), exact?
    ("lag+delay", dict(type="first_order", k=2.0, tau_s=12.0, delay_s=5.0),
     ct.tf([2.0], [12.0, 1.0]), 1 / 12, False),
    ("lag+fractional_delay", dict(type="first_order", k=2.0, tau_s=12.0, delay_s=5.06),
     ct.tf([2.0], [12.0, 1.0]), 1 / 12, False),
    ("second_order", dict(type="second_order", k=1.5, wn=0.3, zeta=0.4),
     ct.tf([1.5 * 0.09], [1.0, 0.24, 0.09]), 0.3, False),
    ("inverse_response", dict(type="transfer", num=[-10.0, 1.0], den=[20.0, 1.0]),
     ct.tf([-10.0, 1.0], [20.0, 1.0]), 1 / 20, False),
    ("rhp_zero_2nd+delay", dict(type="transfer", num=[-8.0, 1.0], den=[60.0, 17.0, 1.0],
                                delay_s=3.0),
     ct.tf([-8.0, 1.0], [60.0, 17.0, 1.0]), 1 / 5, False),
    ("pid", dict(type="pid", kp=0.8, ti_s=30.0, td_s=10.0, n_filter=10.0),
     0.8 * (1 + ct.tf([1.0], [30.0, 0.0]) + ct.tf([10.0, 0.0], [_TF, 1.0])), 1 / _TF, False),
    ("integrator+delay", dict(type="integrator", k=0.05, delay_s=4.0),
     ct.tf([0.05], [1.0, 0.0]), 0.0, True),
    ("pi", dict(type="pi", kp=0.8, ti_s=30.0), ct.tf([0.8 * 30.0, 0.8], [30.0, 0.0]), 0.0, True),
    ("gain+delay", dict(type="gain", k=-1.7, delay_s=7.2), ct.tf([-1.7], [1.0]), 0.0, True),
]


@pytest.mark.parametrize(("spec", "G", "rate", "exact"), [c[1:] for c in LINEAR],
                         ids=[c[0] for c in LINEAR])
def test_linear_block_matches_python_control(spec, G, rate, exact):
    substeps = 10
    h = DT / substeps
    u = smooth_input(N, seed=11)
    y = simulate_plant(one_block(spec), {"u": u}, dt_s=DT, substeps=substeps)["y"]
    ref, curvature = ct_reference(G, u, delay_s=spec.get("delay_s", 0.0), hr=h / REFINE)
    scale = np.max(np.abs(ref))
    if exact:  # trapezoid rule on a piecewise-linear integrand: rounding only (~1e-13)
        tol = 1e-10 * scale
    else:
        tol = (h * max(rate, INPUT_RATE)) ** 2 * scale
        steps = spec.get("delay_s", 0.0) / h
        if abs(steps - round(steps)) > 1e-9:  # buffer read between two slots
            tol += h**2 / 8 * curvature
    err = np.max(np.abs(y - ref))
    assert err <= tol, (err, tol)
    assert scale > 0.1  # the record excites the block


@pytest.mark.parametrize("case", ["lag+delay", "second_order", "rhp_zero_2nd+delay"])
def test_error_is_second_order_in_the_fine_step(case):
    """Halving h divides the error by 4 (Heun), so the tolerances above are the method's
    error, not a bug hiding under a loose bound."""
    spec, G = next(c[1:3] for c in LINEAR if c[0] == case)
    u = smooth_input(N, seed=12)
    ref, _ = ct_reference(G, u, delay_s=spec.get("delay_s", 0.0), hr=DT / 200)
    err = [np.max(np.abs(simulate_plant(one_block(spec), {"u": u}, dt_s=DT,
                                        substeps=s)["y"] - ref)) for s in (10, 20)]
    assert 3.5 < err[0] / err[1] < 4.6, err


# ---------------------------------------------------------------- closed loops
def drum_reference(m: Model, steam: np.ndarray, sp: np.ndarray) -> tuple[np.ndarray, ...]:
    """The drum-level loop wired by hand with python-control (no dead time: exact)."""
    c, ff, fw = m.block("controller"), m.block("feedforward"), m.block("feedwater_flow")
    dm, sw = m.block("drum_mass"), m.block("swell")
    loop = ct.interconnect([
        ct.summing_junction(inputs=["sp", "-lvl"], output="e"),
        ct.tf([c.kp * c.ti_s, c.kp], [c.ti_s, 0.0], inputs="e", outputs="c"),
        ct.tf([ff.k], [1.0], inputs="steam", outputs="ff"),
        ct.summing_junction(inputs=["c", "ff"], output="fwd"),
        ct.tf([fw.k], [fw.tau_s, 1.0], inputs="fwd", outputs="fw"),
        ct.summing_junction(inputs=["fw", "-steam"], output="imb"),
        ct.tf([dm.k], [1.0, 0.0], inputs="imb", outputs="dm"),
        ct.tf([sw.k], [sw.tau_s, 1.0], inputs="steam", outputs="sw"),
        ct.summing_junction(inputs=["dm", "sw"], output="lvl"),
    ], inplist=["steam", "sp"], outlist=["lvl", "fw", "c"])
    per = 10 * REFINE
    t = np.arange((N - 1) * per + 1) * (DT / per)
    U = np.vstack([np.interp(t, TK, steam), np.interp(t, TK, sp)])
    y = ct.forced_response(loop, T=t, U=U).outputs[:, ::per]
    return y[0], y[1], y[2]


def test_drum_level_loop_matches_python_control():
    m = load("drum_level")
    steam = smooth_input(N, seed=21, pole=0.95, scale=0.2)
    sp = np.repeat(np.random.default_rng(22).standard_normal(N // 100), 100)
    sp -= sp[0]
    lvl, fw, c = drum_reference(m, steam, sp)
    substeps = 10
    out = simulate_plant(m, {"steam_flow": steam, "level_setpoint": sp}, dt_s=DT,
                         substeps=substeps)
    # fastest mode: the 15 s swell lag (the 20 s valve lag and the loop are slower)
    w = 1 / 15
    for got, ref in ((out["drum_level"], lvl), (out["feedwater_flow"], fw),
                     (out["controller"], c)):
        tol = (DT / substeps * w) ** 2 * np.max(np.abs(ref))
        assert np.max(np.abs(got - ref)) <= tol
    # and the halved step is 4x closer (second order)
    fine = simulate_plant(m, {"steam_flow": steam, "level_setpoint": sp}, dt_s=DT,
                          substeps=20)
    ratio = np.max(np.abs(out["drum_level"] - lvl)) / np.max(np.abs(fine["drum_level"] - lvl))
    assert 3.5 < ratio < 4.6


def boiler_reference(m: Model, steam: np.ndarray) -> dict[str, np.ndarray]:
    """The boiler loop as two ODEs, integrated by solve_ivp one sample at a time (the
    input's kinks are interval ends) with the 8 s dead time read from the dense output
    of earlier intervals (method of steps: 8 s >= one interval)."""
    kp, ti = m.block("controller").kp, m.block("controller").ti_s
    kff, kfuel, dead = m.block("feedforward").k, m.block("fuel").k, m.block("fuel").delay_s
    kdrum = m.block("drum").k
    kps = next(t.k for t in m.block("turbine_pressure").inputs if t.signal == "steam_flow")
    assert dead >= DT

    def steam_at(t):
        return float(np.interp(t, TK, steam))

    def demand(t, x):
        p = x[1] + kps * steam_at(t)
        return kp * (p + x[0] / ti) + kff * steam_at(t)

    sols = []

    def rhs(t, x):  # x = (integral of the controller input, drum output)
        past = t - dead
        fuel = 0.0 if past <= 0.0 else kfuel * demand(
            past, sols[min(int(past // DT), len(sols) - 1)](past))
        return [x[1] + kps * steam_at(t), kdrum * (fuel - steam_at(t))]

    x = np.zeros(2)
    states = [x]
    for k in range(N - 1):
        r = solve_ivp(rhs, (TK[k], TK[k + 1]), x, method="DOP853", rtol=1e-11, atol=1e-13,
                      dense_output=True)
        sols.append(r.sol)
        x = r.y[:, -1]
        states.append(x)
    X = np.array(states)
    pressure = X[:, 1] + kps * steam
    return {"turbine_pressure": pressure, "drum": X[:, 1],
            "controller": kp * (pressure + X[:, 0] / ti)}


def test_boiler_loop_with_dead_time_matches_solve_ivp():
    m = load("boiler_pressure")
    steam = smooth_input(N, seed=31, pole=0.95, scale=0.2)
    ref = boiler_reference(m, steam)
    substeps = 10
    out = simulate_plant(m, {"steam_flow": steam}, dt_s=DT, substeps=substeps)
    # no block poles but 0; the fastest rate is the loop crossover, ~0.032 rad/s
    # (0.554*65*0.000883 per s), or the input's 0.026 rad/s: take 0.05 rad/s
    w = 0.05
    for name, r in ref.items():
        tol = (DT / substeps * w) ** 2 * np.max(np.abs(r))
        assert np.max(np.abs(out[name] - r)) <= tol, name


# ---------------------------------------------------------------- static nonlinear
class TestStaticNonlinear:
    def test_deadband_saturation_and_scheduled_gain_are_their_closed_forms(self):
        u = smooth_input(N, seed=41, scale=0.3)
        r = smooth_input(N, seed=42, scale=0.3)
        m = Model(name="nl", inputs=("u", "r"), outputs=("db",), blocks=(
            Deadband(name="db", inputs=(Term("u"),), width=0.6),
            Saturation(name="sat", inputs=(Term("u", 2.0),), low=-0.5, high=0.8),
            Saturation(name="cap", inputs=(Term("u"),), low=-math.inf, high=0.2),
            OperatingPointGain(name="opg", inputs=(Term("u"),), slope=0.4, signal="r"),
        ))
        out = simulate_plant(m, {"u": u, "r": r}, dt_s=DT)
        # static blocks at the sample instants see the samples themselves: exact
        assert np.array_equal(out["db"], np.where(np.abs(u) <= 0.3, 0.0,
                                                  u - np.sign(u) * 0.3))
        np.testing.assert_allclose(out["sat"], np.clip(2.0 * u, -0.5, 0.8), rtol=0, atol=1e-15)
        np.testing.assert_allclose(out["cap"], np.minimum(u, 0.2), rtol=0, atol=1e-15)
        np.testing.assert_allclose(out["opg"], u * (1 + 0.4 * r), rtol=1e-14, atol=1e-15)
        # every branch of the nonlinearities is visited
        assert np.mean(out["db"] == 0.0) > 0.2 and np.mean(out["db"] != 0.0) > 0.2
        assert np.mean(out["sat"] == 0.8) > 0.05 and np.mean(out["sat"] == -0.5) > 0.05

    def test_a_chain_listed_backwards_is_evaluated_in_signal_order(self):
        """Blocks listed downstream first; a scheduled gain reads a lag's output."""
        u = smooth_input(N, seed=43, scale=0.3)
        m = Model(name="chain", inputs=("u",), outputs=("out",), blocks=(
            OperatingPointGain(name="out", inputs=(Term("db"),), slope=-0.5, signal="lag"),
            Deadband(name="db", inputs=(Term("sat"),), width=0.2),
            Saturation(name="sat", inputs=(Term("u"),), low=-0.4, high=0.4),
            FirstOrder(name="lag", inputs=(Term("u"),), k=1.0, tau_s=10.0),
        ))
        out = simulate_plant(m, {"u": u}, dt_s=DT)
        s = np.clip(u, -0.4, 0.4)
        d = np.where(np.abs(s) <= 0.1, 0.0, s - np.sign(s) * 0.1)
        np.testing.assert_allclose(out["out"], d * (1 - 0.5 * out["lag"]), rtol=0, atol=1e-15)
        assert np.std(out["lag"]) > 0.01 and np.mean(d != 0.0) > 0.2


# ---------------------------------------------------------------- DCS and nuisances
SCAN = 0.4
PER = round(DT / SCAN)


def scan_errors(u: np.ndarray) -> np.ndarray:
    """What the controller acts on at scan j: the input sampled at scan j-1 (0 at j=0)."""
    sampled = np.interp(np.arange((u.size - 1) * PER + 1) * SCAN, TK[: u.size], u)
    return np.concatenate([[0.0], sampled[:-1]])


def pi_recursion(e: np.ndarray, kp: float, ti: float) -> np.ndarray:
    return kp * (e + np.cumsum(SCAN * e) / ti)  # rectangles of the scan period


def test_dcs_pi_is_the_scan_recursion():
    kp, ti = 0.7, 25.0
    u = smooth_input(300, seed=51)
    y = simulate_plant(one_block(dict(type="pi", kp=kp, ti_s=ti)), {"u": u}, dt_s=DT,
                       dcs_scan_s=SCAN)["y"]
    want = pi_recursion(scan_errors(u), kp, ti)[::PER]  # held: the scan at t_k
    np.testing.assert_allclose(y, want, rtol=0, atol=1e-10 * np.max(np.abs(want)))
    continuous = simulate_plant(one_block(dict(type="pi", kp=kp, ti_s=ti)), {"u": u},
                                dt_s=DT)["y"]
    assert np.max(np.abs(continuous - y)) > 1e-3  # the scan delay is visible


def test_dcs_pid_adds_the_backward_euler_filtered_derivative():
    kp, ti, td, n = 0.7, 25.0, 8.0, 8.0
    tf = td / n
    u = smooth_input(300, seed=52)
    y = simulate_plant(one_block(dict(type="pid", kp=kp, ti_s=ti, td_s=td, n_filter=n)),
                       {"u": u}, dt_s=DT, dcs_scan_s=SCAN)["y"]
    e = scan_errors(u)
    b = kp * td / (tf + SCAN)
    d = ss.lfilter([b, -b], [1.0, -tf / (tf + SCAN)], e)
    want = (pi_recursion(e, kp, ti) + d)[::PER]
    np.testing.assert_allclose(y, want, rtol=0, atol=1e-10 * np.max(np.abs(want)))
    assert np.max(np.abs(d)) > 0.1 * np.max(np.abs(want))


def test_quanta_round_dcs_and_continuous_outputs():
    q = 0.05
    u = smooth_input(300, seed=53, scale=0.3)
    y = simulate_plant(one_block(dict(type="pi", kp=0.7, ti_s=25.0)), {"u": u}, dt_s=DT,
                       dcs_scan_s=SCAN, quanta={"y": q})["y"]
    exact = pi_recursion(scan_errors(u), 0.7, 25.0)[::PER]  # the integral is not rounded
    np.testing.assert_allclose(y, np.round(exact / q) * q, rtol=0, atol=1e-12)
    assert len(np.unique(y)) > 5
    g = simulate_plant(one_block(dict(type="gain", k=3.0)), {"u": u}, dt_s=DT,
                       quanta={"y": 0.1})["y"]
    np.testing.assert_allclose(g, np.round(3.0 * u / 0.1) * 0.1, rtol=0, atol=1e-12)


def test_quanta_inside_a_dcs_loop_hold_their_resolution():
    m = load("drum_level")
    steam = smooth_input(N, seed=54, pole=0.95, scale=0.2)
    inputs = {"steam_flow": steam, "level_setpoint": np.zeros(N)}
    out = simulate_plant(m, inputs, dt_s=DT, dcs_scan_s=1.0,
                         quanta={"controller": 0.02, "feedwater_flow": 0.01})
    for name, q in (("controller", 0.02), ("feedwater_flow", 0.01)):
        np.testing.assert_allclose(out[name] / q, np.round(out[name] / q), atol=1e-9)
    plain = simulate_plant(m, inputs, dt_s=DT, dcs_scan_s=1.0)
    assert 0 < np.max(np.abs(out["drum_level"] - plain["drum_level"])) < 1.0  # mm


def test_dcs_loop_approaches_the_continuous_loop_as_the_scan_shrinks():
    """The scan adds ~1.5 scans of delay (previous sample + hold): first order in T."""
    m = load("boiler_pressure")
    steam = smooth_input(N, seed=55, pole=0.95, scale=0.2)
    cont = simulate_plant(m, {"steam_flow": steam}, dt_s=DT)["turbine_pressure"]
    diff = [np.max(np.abs(simulate_plant(m, {"steam_flow": steam}, dt_s=DT, dcs_scan_s=T)
                          ["turbine_pressure"] - cont)) for T in (2.0, 0.4)]
    assert 3.0 < diff[0] / diff[1] < 7.0, diff


def test_a_disturbance_on_an_integrator_adds_its_integral():
    u = smooth_input(N, seed=61)
    w = np.where(TK >= 200.0, 0.3, 0.0) + 0.05 * np.sin(TK / 50.0)
    m = one_block(dict(type="integrator", k=0.02))
    base = simulate_plant(m, {"u": u}, dt_s=DT)["y"]
    moved = simulate_plant(m, {"u": u}, dt_s=DT, disturbances={"y": w})["y"]
    # exact: the trapezoid of the interpolated (piecewise-linear) disturbance
    want = 0.02 * cumulative_trapezoid(w, TK, initial=0.0)
    np.testing.assert_allclose(moved - base, want, rtol=0, atol=1e-10 * np.max(np.abs(want)))


def test_a_step_disturbance_in_the_boiler_loop_is_taken_by_the_controller():
    """Integral action: the pressure returns to 0 and the controller makes up the energy,
    fuel = -d, i.e. controller = -d / fuel.k (steam flow at 0)."""
    m = load("boiler_pressure")
    n, d = 2000, 0.5
    w = np.where(np.arange(n) * DT >= 100.0, d, 0.0)
    out = simulate_plant(m, {"steam_flow": np.zeros(n)}, dt_s=DT, disturbances={"drum": w})
    # the slowest closed-loop mode (~ti = 60 s) has decayed e^-60 after 3800 s
    assert abs(out["controller"][-1] + d / m.block("fuel").k) < 1e-6
    assert abs(out["turbine_pressure"][-1]) < 1e-6
    assert np.max(np.abs(out["turbine_pressure"])) > 1e-2  # it was disturbed


# ---------------------------------------------------------------- errors
@dataclasses.dataclass(frozen=True, kw_only=True)
class _Lookup(Block):
    TYPE: ClassVar[str] = "lookup_table"
    LINEAR: ClassVar[bool] = False


@pytest.mark.parametrize(("model", "kwargs", "match"), [
    (one_block(dict(type="pi", kp=1.0, ti_s=10.0)), dict(dcs_scan_s=0.3),
     r"dcs_scan_s=0.3 must be a whole number of fine steps h=0.2 s that divides dt_s=2"),
    (one_block(dict(type="pi", kp=1.0, ti_s=10.0)), dict(dcs_scan_s=0.6),
     r"dcs_scan_s=0.6 must be a whole number of fine steps"),
    (one_block(dict(type="gain", k=1.0, delay_s=0.1)), {},
     r"block 'y': delay_s=0.1 is shorter than the fine step h=0.2 s"),
    (one_block(dict(type="first_order", k=1.0, tau_s=0.5)), {},
     rf"block 'y': pole of 2 rad/s is too fast .* > {MAX_STEP_POLE}\); multiply substeps"),
    (one_block(dict(type="gain", k=1.0)), dict(quanta={"nope": 0.1}),
     r"quanta: \['nope'\] not in the model; allowed: \['y'\]"),
    (one_block(dict(type="gain", k=1.0)), dict(quanta={"y": -1.0}),
     r"quanta\['y'\]=-1.0 must be a finite number > 0"),
    (one_block(dict(type="gain", k=1.0)), dict(disturbances={"y": np.zeros(5)}),
     r"disturbance 'y': shape \(5,\), expected \(600,\)"),
    (one_block(dict(type="gain", k=1.0)), dict(substeps=0), r"substeps=0 must be an integer"),
    (Model(name="lut", inputs=("u",), outputs=("t",),
           blocks=(_Lookup(name="t", inputs=(Term("u"),)),)), {},
     r"block 't': type 'lookup_table' is not supported .* supported: gain, sum"),
])
def test_bad_arguments_name_the_culprit(model, kwargs, match):
    with pytest.raises(ValueError, match=match):
        simulate_plant(model, {"u": np.zeros(N)}, dt_s=DT, **kwargs)


def test_bad_inputs_name_the_signal():
    m = one_block(dict(type="gain", k=1.0))
    with pytest.raises(ValueError, match=r"inputs: missing model inputs \['u'\]"):
        simulate_plant(m, {"v": np.zeros(10)}, dt_s=DT)
    with pytest.raises(ValueError, match=r"inputs: \['v'\] not in the model"):
        simulate_plant(m, {"u": np.zeros(10), "v": np.zeros(10)}, dt_s=DT)
    with pytest.raises(ValueError, match=r"input 'u': non-finite value at sample 3"):
        simulate_plant(m, {"u": np.array([0, 1, 2, np.nan, 4.0])}, dt_s=DT)


# ---------------------------------------------------------------- speed
def test_long_records_of_the_shipped_loops_with_an_effect_block_stay_finite():
    """10 000 samples at 2 s, 10 substeps (1e5 fine steps) of each shipped loop with an
    effect block and every nuisance: every block's output has the record's length and
    is finite (the time is printed; its ratio to pipeline.models.simulate is in
    ``tests/benchmarks/bench_simulate.py``, not asserted here)."""
    boiler = load("boiler_pressure")
    boiler = insert_after(boiler, "fuel", upstream_name="fuel_raw", block=Transfer(
        name="fuel", inputs=(Term("fuel_raw"),), num=(-0.3 * 20.0, 1.0), den=(20.0, 1.0)))
    drum = insert_before(load("drum_level"), "controller",
                         block=Deadband(name="controller_deadband", width=0.2))
    n = 10_000
    steam = smooth_input(n, seed=71, pole=0.95, scale=0.2)
    cases = [
        ("boiler_pressure+inverse_response", boiler, {"steam_flow": steam}, {}),
        ("drum_level+deadband", drum, {"steam_flow": steam, "level_setpoint": np.zeros(n)}, {}),
        ("drum_level+deadband, DCS+quanta+disturbance", drum,
         {"steam_flow": steam, "level_setpoint": np.zeros(n)},
         dict(dcs_scan_s=0.4, quanta={"controller": 0.01}, disturbances={"drum_mass": steam})),
    ]
    for label, model, inputs, extra in cases:
        start = time.perf_counter()
        out = simulate_plant(model, inputs, dt_s=DT, substeps=10, **extra)
        elapsed = time.perf_counter() - start
        print(f"\nplant_sim {label}: {n} samples x 10 substeps in {elapsed:.3f} s")
        assert set(out) == set(model.block_names)
        assert all(v.shape == (n,) and np.all(np.isfinite(v)) for v in out.values())
