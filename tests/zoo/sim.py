"""The zoo's own plant simulator: continuous time, a DCS, actuators, sensors, a historian.

Independent of the code under test: nothing here imports ``pipeline.models.simulate``,
``pipeline.models.model`` or ``pipeline.discrepancy.effects``.  A family (:class:`Family`) writes its plant
as ordinary differential equations in ABSOLUTE engineering units (°C, m, kg/s, % OP);
:func:`simulate_plant` integrates them and plays the plant's surroundings:

* **integration**: classical fixed-step RK4 at ``Family.fine_s`` (0.2 s; the fastest
  plant time constant is 4 s, so the step error is < 1e-7 relative); actuator values are
  held over a fine step (a valve moves at the DCS scan anyway);
* **warm-up**: :data:`WARMUP_S` of plant time with every exogenous signal held at its
  first value before the record starts, so an injected effect's own steady state (a
  wound-up controller, a shifted OP) is reached before the historian writes;
* **a DCS**: each PI loop (:class:`Loop`) runs once per ``scan_s`` (1 s) on the
  measurement of the PREVIOUS scan (the scan delay the model does not have),
  positional form ``OP = OP_0 + kp (e + I / ti_s)``, rectangle integration, OP clamped
  to 0-100 % with conditional integration (the clamp is never reached by a nominal
  record), and the OP written to the actuator quantised to ``Loop.quantum`` (0.1 %: a
  10-bit output card);
* **actuators**: one loop per family (``Family.valve_loop``) carries the injected actuator
  effects, in the order a valve has them: OP -> deadband or backlash (on the stem) ->
  valve characteristic ``Family.valve`` -> gain change about the operating point ->
  saturation (a mechanical stop or a pump's maximum flow; the controller does not know,
  so it winds up) -> dead time -> extra first-order lag -> the plant;
* **sensors**: white noise of ``rel_noise`` (1-3 %, drawn per trial) of each output's
  ``Family.scales`` on every scan; controllers read the noisy value; the historian
  snapshots at every ``dt_s`` what the DCS read at that instant; measured exogenous
  inputs get white noise of the same relative size of their own std; setpoints are exact;
* **a slow unmeasured disturbance** (``"disturbance"`` column: AR(1), correlation time
  :data:`DISTURBANCE_TAU_S`) that the family adds to one of its balances.

Effects injected here (the known answers: :class:`TrueEffect`) are :data:`ZOO_EFFECTS`:
the catalogue's ``gain``, ``dead_time``, ``extra_lag``, ``saturation``, ``deadband``,
``sensor_bias_drift`` and ``unmodelled_input``, and ``backlash`` (design.md turn 3: the
input must reverse by ``width`` before the output follows; a worn valve).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.signal

#: Effects the zoo can inject (catalogue names and parameter keys; ``backlash`` as in
#: design.md's turn-3 additions).
ZOO_EFFECTS: tuple[str, ...] = (
    "gain", "dead_time", "extra_lag", "saturation", "deadband", "backlash",
    "sensor_bias_drift", "unmodelled_input",
)
#: Effects that act in the actuator chain of ``Family.valve_loop``.
ACTUATOR_EFFECTS = ("gain", "dead_time", "extra_lag", "saturation", "deadband", "backlash")
#: Plant time simulated before the record with the exogenous signals held (s).
WARMUP_S = 1800.0
#: Correlation time of the slow unmeasured disturbance (s).
DISTURBANCE_TAU_S = 1800.0


@dataclass(frozen=True)
class TrueEffect:
    """The known answer of a trial: one effect, where, and its parameters.

    Parameters
    ----------
    name : str
        One of :data:`ZOO_EFFECTS`.
    location : str
        A block of the nominal model, an output (``sensor_bias_drift``) or
        ``"signal->output"`` (``unmodelled_input``).
    parameters : mapping
        The catalogue's keys; saturation limits and deadband/backlash widths in the
        model's deviation units at `location`.
    """

    name: str
    location: str
    parameters: Mapping[str, Any]

    def describe(self) -> str:
        """One line, e.g. ``gain at steam: factor=1.2``."""
        params = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in self.parameters.items())
        return f"{self.name} at {self.location}: {params}"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{name, location, parameters}`` (infinite limits as strings)."""
        def plain(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return "inf" if v > 0 else "-inf"
            return v
        return {"name": self.name, "location": self.location,
                "parameters": {k: plain(v) for k, v in self.parameters.items()}}


@dataclass(frozen=True)
class Loop:
    """One DCS PI loop.

    Parameters
    ----------
    op : str
        The controller's block name in the model; its output is the OP (% of span).
    pv : str
        The measured output it controls.
    sp : str
        The exogenous setpoint signal.
    kp : float
        Proportional gain, % OP per unit of error.
    ti_s : float
        Integral time, s.
    reverse : bool
        True: error = pv - sp (more OP lowers the pv); False: error = sp - pv.
    quantum : float
        OP resolution written to the actuator, %.
    """

    op: str
    pv: str
    sp: str
    kp: float
    ti_s: float
    reverse: bool = False
    quantum: float = 0.1


@dataclass
class Family:
    """A plant family: its physics, loops, signals and nominal model.

    Subclasses set the attributes and implement :meth:`model`, :meth:`exogenous`,
    :meth:`steady_state`, :meth:`valve`, :meth:`deriv`, :meth:`measure` and
    :meth:`unmodelled`.  ``exo_names`` fixes the column order of the exogenous table
    that :meth:`deriv` and :meth:`measure` receive as ``e`` (a list of floats).
    """

    name: str = ""
    dt_s: float = 2.0
    scan_s: float = 1.0
    fine_s: float = 0.2
    hours: float = 4.0
    loops: tuple[Loop, ...] = ()
    valve_loop: int = 0
    #: model inputs that are measured plant signals (get input noise) -> tag
    loads: dict[str, str] = field(default_factory=dict)
    #: setpoints -> tag (exact DCS values)
    setpoints: dict[str, str] = field(default_factory=dict)
    #: the measured signal the model ignores (source of unmodelled_input) and its tag
    extra: tuple[str, str] = ("", "")
    #: measured outputs (plant outputs from measure(), then OPs) -> tag
    outputs: dict[str, str] = field(default_factory=dict)
    #: typical std of each output in nominal operation (noise and drift sizes)
    scales: dict[str, float] = field(default_factory=dict)
    #: where each effect is injected (a model block, an output, or signal->output)
    sites: dict[str, str] = field(default_factory=dict)
    #: parameter ranges of the draws (tests.zoo.trial.draw_effect)
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)
    #: signals whose operating point the nominal model is written about (the job's
    #: ``discrepancy.operating_point``; the others are measured from their mean): a
    #: model that is nonlinear in a signal is linearised at a stated point, not at
    #: whatever mean one record has
    operating_point: dict[str, float] = field(default_factory=dict)

    @property
    def exo_names(self) -> tuple[str, ...]:
        """Columns of the exogenous table: setpoints, loads, the extra signal, then
        ``disturbance`` and ``extra_in`` (the extra signal's delayed deviation)."""
        return (*self.setpoints, *self.loads, self.extra[0], "disturbance", "extra_in")

    @property
    def plant_outputs(self) -> tuple[str, ...]:
        """Outputs :meth:`measure` returns (every output that is not an OP)."""
        ops = {lp.op for lp in self.loops}
        return tuple(o for o in self.outputs if o not in ops)

    def model(self) -> dict[str, Any]:  # pragma: no cover - abstract
        """The nominal model YAML mapping (``{"model": {...}}``)."""
        raise NotImplementedError

    def exogenous(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        """Setpoints, loads, the extra signal and the unit disturbance on the fine grid.

        Parameters
        ----------
        rng : numpy.random.Generator
        n : int
            Fine steps (warm-up included).
        """
        raise NotImplementedError  # pragma: no cover

    def steady_state(self, e: Sequence[float], p: Mapping[str, float]
                     ) -> tuple[list[float], list[float]]:
        """Plant state and OPs at rest for exogenous values `e` (nominal actuators).

        Parameters
        ----------
        e : sequence of float
            One row of the exogenous table.
        p : mapping
            Plant parameters.
        """
        raise NotImplementedError  # pragma: no cover

    def calibrate(self, p: Mapping[str, float], e_mean: Sequence[float]) -> dict[str, float]:
        """Plant parameters set from the record's mean exogenous row (default: none).

        Parameters
        ----------
        p : mapping
        e_mean : sequence of float
        """
        return dict(p)

    def valve(self, loop: int, op: float, p: Mapping[str, float]) -> float:
        """Actuator characteristic: the plant input of loop `loop` at OP `op` (%).

        Parameters
        ----------
        loop : int
        op : float
        p : mapping
        """
        raise NotImplementedError  # pragma: no cover

    def deriv(self, x: list[float], a: list[float], e: list[float],
              p: Mapping[str, float]) -> list[float]:
        """State derivatives for actuator values `a` (one per loop) and exogenous `e`.

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        raise NotImplementedError  # pragma: no cover

    def measure(self, x: list[float], a: list[float], e: list[float],
                p: Mapping[str, float]) -> list[float]:
        """Noise-free values of :attr:`plant_outputs` (``a``: the actuator values
        applied now, for flow meters).

        Parameters
        ----------
        x, a, e : list of float
        p : mapping
        """
        raise NotImplementedError  # pragma: no cover

    def unmodelled(self, rng: np.random.Generator, extra_std: float
                   ) -> tuple[dict[str, float], dict[str, float]]:
        """Draw an unmodelled input: plant parameter updates and the known answer's
        ``k`` and ``tau_s`` (``delay_s`` is drawn by the caller).

        Parameters
        ----------
        rng : numpy.random.Generator
        extra_std : float
            Std of the extra signal over the record.
        """
        raise NotImplementedError  # pragma: no cover


def unit_ar1(rng: np.random.Generator, n: int, tau_s: float, h: float) -> np.ndarray:
    """Unit-std AR(1) on a grid of step `h` with correlation time `tau_s`, stationary.

    Parameters
    ----------
    rng : numpy.random.Generator
    n : int
    tau_s, h : float
        Correlation time and grid step, s.
    """
    phi = math.exp(-h / tau_s)
    out, _ = scipy.signal.lfilter([math.sqrt(1 - phi * phi)], [1.0, -phi],
                                  rng.standard_normal(n), zi=[phi * rng.standard_normal()])
    return out


def random_steps(rng: np.random.Generator, n: int, h: float, *, start: float,
                 every_s: tuple[float, float], size: tuple[float, float],
                 bounds: tuple[float, float], first_s: float = WARMUP_S) -> np.ndarray:
    """Piecewise-constant signal: steps of random size and sign at random intervals,
    kept inside `bounds` (a step that would leave them goes the other way).

    Parameters
    ----------
    rng : numpy.random.Generator
    n : int
        Fine steps.
    h : float
        Fine step, s.
    start : float
        Value before the first step.
    every_s, size, bounds : tuple of float
        Interval range (s), step-size range and the allowed band.
    first_s : float
        No step before this time (the warm-up).
    """
    out = np.full(n, float(start))
    t = first_s + rng.uniform(0.2, 1.0) * every_s[0]
    value = float(start)
    while t < n * h:
        step = rng.uniform(*size) * rng.choice([-1.0, 1.0])
        if not bounds[0] <= value + step <= bounds[1]:
            step = -step
        value = min(max(value + step, bounds[0]), bounds[1])
        out[int(t / h):] = value
        t += rng.uniform(*every_s)
    return out


class _Actuator:
    """The actuator chain of one loop (module docstring), with its memory."""

    def __init__(self, family: Family, loop: int, p: Mapping[str, float],
                 effect: TrueEffect | None, op_ref: float, physical: Mapping[str, float]):
        self.family, self.loop, self.p = family, loop, p
        self.op_ref = op_ref
        self.a_ref = family.valve(loop, op_ref, p)
        on = effect is not None and loop == family.valve_loop \
            and effect.name in ACTUATOR_EFFECTS
        self.name = effect.name if on else None
        self.phys = dict(physical) if on else {}
        self.stem: float | None = None
        n_delay = round(self.phys.get("delay_s", 0.0) / family.fine_s)
        self.line: deque[float] | None = deque() if n_delay else None
        self.n_delay = n_delay
        tau = self.phys.get("tau_s", 0.0)
        self.alpha = 1.0 - math.exp(-family.fine_s / tau) if tau > 0 else 1.0
        self.lagged: float | None = None

    def static(self, op: float) -> tuple[float, float]:
        """(plant input before dead time and lag, valve output before saturation)."""
        stem = op
        if self.name == "deadband":
            half, d = 0.5 * self.phys["width"], op - self.op_ref
            stem = self.op_ref + (0.0 if abs(d) <= half else d - math.copysign(half, d))
        elif self.name == "backlash":
            half = 0.5 * self.phys["width"]
            if self.stem is None:
                self.stem = op
            elif op > self.stem + half:
                self.stem = op - half
            elif op < self.stem - half:
                self.stem = op + half
            stem = self.stem
        a = self.family.valve(self.loop, stem, self.p)
        if self.name == "gain":
            a = self.a_ref + self.phys["factor"] * (a - self.a_ref)
        free = a
        if self.name == "saturation":
            a = min(max(a, self.a_ref + self.phys["low"]), self.a_ref + self.phys["high"])
        return a, free

    def dynamic(self, a: float) -> float:
        """One fine step through the dead time and the lag."""
        if self.line is not None:
            if not self.line:
                self.line.extend([a] * self.n_delay)
            self.line.append(a)
            a = self.line.popleft()
        if self.alpha < 1.0:
            self.lagged = a if self.lagged is None else self.lagged + self.alpha * (a - self.lagged)
            a = self.lagged
        return a


def _rk4(f: Callable, x: list[float], a: list[float], e: list[float],
         p: Mapping[str, float], h: float) -> list[float]:
    k1 = f(x, a, e, p)
    k2 = f([xi + 0.5 * h * ki for xi, ki in zip(x, k1)], a, e, p)
    k3 = f([xi + 0.5 * h * ki for xi, ki in zip(x, k2)], a, e, p)
    k4 = f([xi + h * ki for xi, ki in zip(x, k3)], a, e, p)
    return [xi + h / 6.0 * (q1 + 2.0 * q2 + 2.0 * q3 + q4)
            for xi, q1, q2, q3, q4 in zip(x, k1, k2, k3, k4)]


@dataclass(frozen=True)
class PlantRecord:
    """What the historian holds, and the noise-free truth behind it.

    Attributes
    ----------
    t_s : ndarray (N,)
        Sample times from the start of the record, s.
    measured : dict of str -> ndarray (N,)
        Every signal as exported (absolute units; noise, quantised OPs).
    truth : dict of str -> ndarray (N,)
        Noise-free plant outputs and OPs at the samples.
    valve_free : ndarray (N,)
        The effect loop's valve output before any saturation, minus its operating
        point (the model's deviation units at the valve block).
    op_ref, a_ref : float
        OP and valve output of the effect loop at rest under the mean exogenous signals.
    """

    t_s: np.ndarray
    measured: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    valve_free: np.ndarray
    op_ref: float
    a_ref: float


def simulate_plant(family: Family, exo: Mapping[str, np.ndarray], *, p: Mapping[str, float],
                   effect: TrueEffect | None, physical: Mapping[str, float],
                   rel_noise: float, rng: np.random.Generator) -> PlantRecord:
    """Integrate `family` over the fine grid of `exo` (warm-up first, module docstring).

    Parameters
    ----------
    family : Family
    exo : mapping of str -> ndarray (n_fine,)
        Every column of ``family.exo_names``; ``extra_in`` is already the delayed
        deviation of the extra signal.
    p : mapping
        Plant parameters (the family's, with an unmodelled input's updates).
    effect : TrueEffect or None
        The injected effect (actuator effects act here; the trial adds a drift).
    physical : mapping
        The actuator effect in plant units: ``factor``, ``delay_s``, ``tau_s``,
        ``low``/``high`` (deviations of the valve output), ``width`` (% OP).
    rel_noise : float
        Sensor noise std as a fraction of ``family.scales``.
    rng : numpy.random.Generator
        Draws the sensor noise.
    """
    h = family.fine_s
    per_scan, per_sample = round(family.scan_s / h), round(family.dt_s / h)
    warm = round(WARMUP_S / h)
    table = np.column_stack([np.asarray(exo[k], dtype=float) for k in family.exo_names])
    n_fine = table.shape[0]
    rows = table.tolist()
    x, ops = family.steady_state(table[warm:].mean(axis=0).tolist(), p)
    op_ref = ops[family.valve_loop]
    x, ops = family.steady_state(rows[0], p)
    acts = [_Actuator(family, j, p, effect, op_ref if j == family.valve_loop else ops[j],
                      physical) for j in range(len(family.loops))]
    names = family.plant_outputs
    index = {name: i for i, name in enumerate(names)}
    noise_std = [rel_noise * family.scales[o] for o in names]
    sp_col = [family.exo_names.index(lp.sp) for lp in family.loops]
    integral = [0.0] * len(family.loops)
    bias = list(ops)
    n_rec = (n_fine - warm) // per_sample
    truth = np.empty((n_rec, len(names) + len(family.loops)))
    meas = np.empty((n_rec, len(names)))
    free = np.empty(n_rec)
    statics = [acts[j].static(ops[j]) for j in range(len(acts))]
    op_out = list(ops)
    clean = family.measure(x, [s[0] for s in statics], rows[0], p)
    noisy = [c + s * rng.standard_normal() for c, s in zip(clean, noise_std)]
    for i in range(n_fine):
        e = rows[i]
        scan = i % per_scan == 0
        if scan:  # the DCS acts on the previous scan's reading
            for j, lp in enumerate(family.loops):
                pv = noisy[index[lp.pv]]
                err = (pv - e[sp_col[j]]) if lp.reverse else (e[sp_col[j]] - pv)
                trial_i = integral[j] + family.scan_s * err
                op = bias[j] + lp.kp * (err + trial_i / lp.ti_s)
                if 0.0 <= op <= 100.0:
                    integral[j] = trial_i
                else:
                    op = min(max(bias[j] + lp.kp * (err + integral[j] / lp.ti_s), 0.0), 100.0)
                op_out[j] = round(op / lp.quantum) * lp.quantum
                statics[j] = acts[j].static(op_out[j])
        a = [acts[j].dynamic(statics[j][0]) for j in range(len(acts))]
        if scan:
            clean = family.measure(x, a, e, p)
            noisy = [c + s * rng.standard_normal() for c, s in zip(clean, noise_std)]
        k = i - warm
        if k >= 0 and k % per_sample == 0 and k // per_sample < n_rec:
            r = k // per_sample
            truth[r] = [*clean, *op_out]
            meas[r] = noisy
            free[r] = statics[family.valve_loop][1] - acts[family.valve_loop].a_ref
        x = _rk4(family.deriv, x, a, e, p, h)
    measured = {o: meas[:, i] for i, o in enumerate(names)}
    measured.update({lp.op: truth[:, len(names) + j] for j, lp in enumerate(family.loops)})
    truth_d = {o: truth[:, i] for i, o in enumerate((*names, *(lp.op for lp in family.loops)))}
    return PlantRecord(t_s=np.arange(n_rec) * family.dt_s, measured=measured, truth=truth_d,
                       valve_free=free, op_ref=op_ref, a_ref=acts[family.valve_loop].a_ref)
