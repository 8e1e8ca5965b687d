"""The discrepancy effect catalogue: what can be missing from a simulation model.

Each effect is nested in the nominal model at a null value (design.md, "Effect
catalogue"; names and parameter keys are fixed).  :func:`apply_effect` builds the model
with the effect added; :func:`output_offsets` gives the part that lives outside the block
diagram (a sensor bias and drift is added to the *measured* output, it is not a block);
:func:`predict_outputs` combines both, which is what "re-simulating an augmented model"
means for every effect.

How each effect enters the model (``B`` is the block at the location; "after B" uses
:func:`pipeline.model.insert_after`, so consumers and outputs of ``B`` read the effect
without rewiring and the original block is renamed ``B__<effect>_upstream``):

=====================  =========================================================  ======
effect                 realisation                                                null
=====================  =========================================================  ======
gain                   :func:`~pipeline.model.scale_gain` (``k``; ``kp`` of        1
                       pi/pid; numerator of transfer; every term of a sum)
dead_time              ``delay_s`` added to ``B.delay_s`` (whole samples)          0
extra_lag              ``first_order`` (k = 1, ``tau_s``) after B                  0
inverse_response       ``transfer`` ``(1 - magnitude tau_s s)/(tau_s s + 1)``     tau 0
                       after B: unit DC gain, the step response starts at
                       ``-magnitude`` (wrong way) and relaxes with ``tau_s``; an
                       RHP zero at ``1/(magnitude tau_s)``.  ``magnitude = 0`` is
                       an extra lag, so the catalogue's parsimony decides between
                       them (extra_lag has one parameter fewer)
sensor_bias_drift      ``bias + drift_per_h * t_h`` added to the measured          0, 0
                       output (``t_h`` hours since the first sample); the
                       controller does not see it
operating_point_gain   ``operating_point_gain`` block after B:                     slope 0
                       ``v (1 + slope * signal)``
deadband               ``deadband`` block (``width``) on B's summed input          0
saturation             ``saturation`` block (``low``, ``high``) after B: limits    ±inf
                       on B's output (an actuator or controller-output limit)
unmodelled_input       ``first_order`` (``k``, ``tau_s``, ``delay_s``) from the    k 0
                       measured signal, added to the output block through a
                       ``sum`` after it: a disturbance entering the plant output,
                       so a controller reading that output reacts to it
=====================  =========================================================  ======

Locations: a block name; an output name (``sensor_bias_drift``); ``"signal->output"``
(``unmodelled_input``).

This module is core (numpy/scipy and :mod:`pipeline.model`/:mod:`pipeline.simulate`).
It also holds the hidden-effect trial generator used by the test suite and the demo
(:func:`make_hidden_effect_trial`): data simulated from a shipped model with one hidden
effect, which the discrepancy workflow must find seeing only the data and the nominal
model.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.signal

from pipeline.errors import ConfigError, ModelError
from pipeline.blocks import (
    Block,
    Deadband,
    FirstOrder,
    Gain,
    OperatingPointGain,
    Saturation,
    Sum,
    Term,
    Transfer,
)
from pipeline.model import Model, insert_after, insert_before, scale_gain
from pipeline.simulate import discrete_state_space, simulate

__all__ = [
    "EFFECT_NAMES",
    "EFFECT_PARAMETERS",
    "Effect",
    "HiddenEffectTrial",
    "apply_effect",
    "applicable_locations",
    "make_hidden_effect_trial",
    "output_offsets",
    "predict_outputs",
    "trial_inputs",
]

#: The catalogue (design.md), in the order candidates are listed.
EFFECT_NAMES: tuple[str, ...] = (
    "gain",
    "dead_time",
    "extra_lag",
    "inverse_response",
    "sensor_bias_drift",
    "operating_point_gain",
    "deadband",
    "saturation",
    "unmodelled_input",
)

#: Parameter keys per effect (fixed by design.md) with their null values.
EFFECT_PARAMETERS: dict[str, dict[str, Any]] = {
    "gain": {"factor": 1.0},
    "dead_time": {"delay_s": 0.0},
    "extra_lag": {"tau_s": 0.0},
    "inverse_response": {"tau_s": 0.0, "magnitude": 0.0},
    "sensor_bias_drift": {"bias": 0.0, "drift_per_h": 0.0},
    "operating_point_gain": {"slope": 0.0, "signal": None},
    "deadband": {"width": 0.0},
    "saturation": {"low": -math.inf, "high": math.inf},
    "unmodelled_input": {"k": 0.0, "tau_s": 0.0, "delay_s": 0.0},
}

#: Below this time constant (as a fraction of a sample) a lag is simulated as a gain: its
#: ZOH discretisation differs from 1 by less than exp(-1/1e-3).
_TAU_AS_GAIN_FRACTION = 1e-3


@dataclass(frozen=True)
class Effect:
    """One catalogue effect at one location with its parameter values.

    Parameters
    ----------
    name : str
        One of :data:`EFFECT_NAMES`.
    location : str
        A block name, an output name (``sensor_bias_drift``) or ``"signal->output"``
        (``unmodelled_input``).
    parameters : mapping
        The keys of :data:`EFFECT_PARAMETERS` for `name` (numbers; ``signal`` a name).
    equivalent_locations : tuple of str
        Locations where the same effect changes the measured outputs identically (e.g.
        a gain on a sum block feeding a single gain block); empty when unknown.
    """

    name: str
    location: str
    parameters: Mapping[str, Any]
    equivalent_locations: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.name not in EFFECT_PARAMETERS:
            raise ConfigError(
                f"effect {self.name!r} is not in the catalogue; allowed: "
                f"{', '.join(EFFECT_NAMES)}"
            )
        expected = set(EFFECT_PARAMETERS[self.name])
        given = set(self.parameters)
        if given != expected:
            raise ConfigError(
                f"effect {self.name!r} at {self.location!r}: parameters {sorted(given)} "
                f"but the catalogue defines {sorted(expected)}; give exactly those keys"
            )
        object.__setattr__(self, "parameters", dict(self.parameters))
        object.__setattr__(self, "equivalent_locations", tuple(self.equivalent_locations))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{name, location, parameters, equivalent_locations}``.

        Infinite saturation limits are written as the strings ``"-inf"``/``"inf"``
        (JSON has no infinity).
        """
        return {
            "name": self.name,
            "location": self.location,
            "parameters": {k: _json_number(v) for k, v in self.parameters.items()},
            "equivalent_locations": list(self.equivalent_locations),
        }

    def describe(self) -> str:
        """One line, e.g. ``gain at controller: factor=1.2``."""
        params = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in self.parameters.items()
        )
        return f"{self.name} at {self.location}: {params}"


def _json_number(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return "inf" if value > 0 else ("-inf" if value < 0 else "nan")
    if isinstance(value, (np.floating, np.integer)):
        return _json_number(float(value))
    return value


# -- locations ---------------------------------------------------------------------
def applicable_locations(
    model: Model,
    name: str,
    *,
    measured_outputs: Sequence[str] | None = None,
    signals: Sequence[str] = (),
) -> list[str]:
    """Every location where effect `name` can be placed in `model`.

    Parameters
    ----------
    model : Model
    name : str
        Effect name.
    measured_outputs : sequence of str, optional
        Outputs with measurements (default: every model output); locations for
        ``sensor_bias_drift`` and targets of ``unmodelled_input``.
    signals : sequence of str
        Measured signals that are NOT model inputs (sources of ``unmodelled_input``).

    Returns
    -------
    list of str
        Block names in model order, output names, or ``"signal->output"`` strings.
    """
    outputs = list(model.outputs if measured_outputs is None else measured_outputs)
    if name in ("gain", "dead_time", "extra_lag", "inverse_response"):
        # nonlinear blocks have no gain and no delay_s; a lag after them is still
        # meaningful but the catalogue places dynamics effects on linear blocks only.
        return [b.name for b in model.blocks if b.LINEAR]
    if name in ("operating_point_gain", "deadband", "saturation"):
        return [b.name for b in model.blocks if not isinstance(b, (Deadband, Saturation))]
    if name == "sensor_bias_drift":
        return outputs
    if name == "unmodelled_input":
        return [f"{s}->{o}" for s in signals if s not in model.inputs for o in outputs]
    raise ConfigError(f"effect {name!r} is not in the catalogue; allowed: {', '.join(EFFECT_NAMES)}")


def _unique_name(model: Model, base: str) -> str:
    taken = set(model.block_names) | set(model.inputs)
    candidate, n = base, 1
    while candidate in taken:
        n += 1
        candidate = f"{base}{n}"
    return candidate


def _after(model: Model, name: str, effect: str, make: Any) -> Model:
    """Insert ``make(upstream_name)`` after block `name` (see module docstring)."""
    upstream = _unique_name(model, f"{name}__{effect}_upstream")
    return insert_after(model, name, block=make(upstream), upstream_name=upstream)


def _lag_block(name: str, source: str, *, k: float, tau_s: float, delay_s: float,
               dt_s: float | None) -> Block:
    if dt_s is not None and tau_s < _TAU_AS_GAIN_FRACTION * dt_s:
        return Gain(name=name, inputs=(Term(source),), k=k, delay_s=delay_s)
    return FirstOrder(name=name, inputs=(Term(source),), k=k, tau_s=tau_s, delay_s=delay_s)


def apply_effect(model: Model, effect: Effect, *, dt_s: float | None = None) -> Model:
    """`model` with `effect` added (the augmented model).

    Parameters
    ----------
    model : Model
        The nominal model.
    effect : Effect
    dt_s : float, optional
        Sample period, s.  When given, lags shorter than a thousandth of a sample are
        built as gains (a first_order block needs ``tau_s > 0``).

    Returns
    -------
    Model
        A valid model; its ``description`` says which effect was added.  For
        ``sensor_bias_drift`` the blocks are unchanged (the bias is added to the
        measurement: :func:`output_offsets`).  At an effect's null value the model
        simulates exactly like `model`.

    Raises
    ------
    ModelError
        The location does not exist or does not fit the effect (e.g. a gain on a
        deadband block).
    """
    name, loc, p = effect.name, effect.location, effect.parameters
    note = f"augmented by plantdyn discrepancy: {effect.describe()}"
    description = f"{model.description}\n{note}".strip() if model.description else note
    if name == "sensor_bias_drift":
        if loc not in model.outputs:
            raise ModelError(
                f"sensor_bias_drift: location {loc!r} is not a model output "
                f"{list(model.outputs)}; a sensor bias sits on a measured output"
            )
        return dataclasses.replace(model, description=description)
    if name == "unmodelled_input":
        augmented = _with_unmodelled_input(model, loc, p, dt_s)
    else:
        augmented = _with_block_effect(model, name, loc, p, dt_s)
    return dataclasses.replace(augmented, description=description)


def _with_unmodelled_input(model: Model, loc: str, p: Mapping[str, Any],
                           dt_s: float | None) -> Model:
    """`model` with a lag from the measured signal added to the output (``signal->output``)."""
    signal, sep, output = loc.partition("->")
    if not sep or output not in model.outputs:
        raise ModelError(
            f"unmodelled_input: location {loc!r} must be 'signal->output' with output in "
            f"{list(model.outputs)}"
        )
    if signal in model.block_names:
        raise ModelError(
            f"unmodelled_input: {signal!r} is a block of the model, not a measured signal"
        )
    inputs = model.inputs if signal in model.inputs else (*model.inputs, signal)
    path = _unique_name(model, f"{signal}__to__{output}")
    augmented = dataclasses.replace(model, inputs=inputs).with_block(
        _lag_block(path, signal, k=float(p["k"]), tau_s=float(p["tau_s"]),
                   delay_s=float(p["delay_s"]), dt_s=dt_s)
    )
    return _after(
        augmented, output, "unmodelled_input",
        lambda up: Sum(name=output, inputs=(Term(up), Term(path))),
    )


def _with_block_effect(model: Model, name: str, loc: str, p: Mapping[str, Any],
                       dt_s: float | None) -> Model:
    """`model` with effect `name` at block `loc` (every effect but the two above)."""
    block = model.block(loc)
    if name == "gain":
        augmented = model.with_block(scale_gain(block, float(p["factor"])))
    elif name == "dead_time":
        if not block.LINEAR:
            raise ModelError(f"dead_time: block {loc!r} is nonlinear and takes no delay_s")
        augmented = model.with_block(
            dataclasses.replace(block, delay_s=block.dead_time_s + float(p["delay_s"]))
        )
    elif name == "extra_lag":
        tau = float(p["tau_s"])
        augmented = model if tau == 0.0 else _after(
            model, loc, "extra_lag",
            lambda up: _lag_block(loc, up, k=1.0, tau_s=tau, delay_s=0.0, dt_s=dt_s),
        )
    elif name == "inverse_response":
        tau, mag = float(p["tau_s"]), float(p["magnitude"])
        augmented = model if tau == 0.0 else _after(
            model, loc, "inverse_response",
            lambda up: Transfer(name=loc, inputs=(Term(up),), num=(-mag * tau, 1.0),
                                den=(tau, 1.0)),
        )
    elif name == "operating_point_gain":
        slope, signal = float(p["slope"]), p["signal"]
        if not isinstance(signal, str) or not signal:
            raise ModelError(f"operating_point_gain: signal={signal!r} must be a signal name")
        # A measured signal the model does not use yet becomes a model input.
        base = model
        if signal not in (*model.inputs, *model.block_names):
            base = dataclasses.replace(model, inputs=(*model.inputs, signal))
        augmented = _after(
            base, loc, "operating_point_gain",
            lambda up: OperatingPointGain(name=loc, inputs=(Term(up),), slope=slope,
                                          signal=signal),
        )
    elif name == "deadband":
        db_name = _unique_name(model, f"{loc}__deadband")
        augmented = insert_before(model, loc, block=Deadband(name=db_name, width=float(p["width"])))
    elif name == "saturation":
        low, high = float(p["low"]), float(p["high"])
        augmented = _after(
            model, loc, "saturation",
            lambda up: Saturation(name=loc, inputs=(Term(up),), low=low, high=high),
        )
    else:  # pragma: no cover - Effect validates the name
        raise ConfigError(f"effect {name!r} is not in the catalogue")
    return augmented


def output_offsets(effect: Effect | None, *, n: int, dt_s: float,
                   outputs: Sequence[str]) -> dict[str, np.ndarray]:
    """The measurement-side part of `effect`: ``bias + drift_per_h * t_h`` per output.

    Parameters
    ----------
    effect : Effect or None
    n : int
        Number of samples.
    dt_s : float
        Sample period, s; ``t_h = k * dt_s / 3600`` for sample ``k`` (0 at the first
        sample of the record).
    outputs : sequence of str

    Returns
    -------
    dict of str -> ndarray (n,)
        Zeros except the biased output of a ``sensor_bias_drift`` effect.
    """
    out = {name: np.zeros(n) for name in outputs}
    if effect is not None and effect.name == "sensor_bias_drift" and effect.location in out:
        t_h = np.arange(n) * dt_s / 3600.0
        out[effect.location] = (
            float(effect.parameters["bias"]) + float(effect.parameters["drift_per_h"]) * t_h
        )
    return out


def predict_outputs(
    model: Model,
    effect: Effect | None,
    inputs: Mapping[str, Any],
    *,
    dt_s: float,
    outputs: Sequence[str] | None = None,
    initial: str = "rest",
) -> dict[str, np.ndarray]:
    """Simulated outputs of `model` with `effect` added, measurement offsets included.

    Parameters
    ----------
    model : Model
        The nominal model (the effect is applied here) -- or pass an already augmented
        model with ``effect=None`` and no offsets.
    effect : Effect or None
    inputs : mapping of str -> array (N,)
        Measured signals; may hold more than the model needs.
    dt_s : float
        Sample period, s.
    outputs : sequence of str, optional
        Which outputs to return (default every model output).
    initial : {"rest", "steady"}
        As in :func:`pipeline.simulate.simulate`.

    Returns
    -------
    dict of str -> ndarray (N,)
    """
    augmented = model if effect is None else apply_effect(model, effect, dt_s=dt_s)
    try:
        drive = {name: inputs[name] for name in augmented.inputs}
    except KeyError as exc:
        raise ConfigError(
            f"model {augmented.name!r} needs input {exc.args[0]!r}; measured signals given: "
            f"{sorted(inputs)}"
        ) from None
    sim = simulate(augmented, drive, dt_s=dt_s, initial=initial)
    names = list(augmented.outputs if outputs is None else outputs)
    offsets = output_offsets(effect, n=sim.t_s.size, dt_s=dt_s, outputs=names)
    return {name: sim.signals[name] + offsets[name] for name in names}


# -- hidden-effect trials ------------------------------------------------------------
@dataclass(frozen=True)
class HiddenEffectTrial:
    """Data simulated from a nominal model with one hidden effect (or none).

    Attributes
    ----------
    model : Model
        The nominal model (what the workflow is given).
    inputs : dict of str -> ndarray (N,)
        Measured signals: the model inputs plus an extra measured signal ``aux_flow``
        that the model does not use (source of ``unmodelled_input``; a null trial has
        it too).
    measured : dict of str -> ndarray (N,)
        Measured outputs (noisy).
    dt_s : float
        Sample period, s.
    effect : Effect or None
        The hidden truth (None: null trial).
    truth : dict of str -> ndarray (N,)
        Noise-free outputs of the true plant.
    noise : dict
        ``{"kind": "white"|"ar1", "phi": float, "relative_std": float}``; the noise std
        per output is ``relative_std`` times the std of that output's noise-free signal.
    redraws : int
        How many effect draws were rejected (unstable loop, or an effect whose output
        contribution is below :data:`MIN_VISIBILITY` of the noise std, over the whole
        record or over its last :data:`HOLDOUT_FRACTION`).
    seed : int
    visibility : float
        RMS of the effect's contribution over the noise std, on the output where it
        shows most (NaN for a null trial).
    """

    model: Model
    inputs: dict[str, np.ndarray]
    measured: dict[str, np.ndarray]
    dt_s: float
    effect: Effect | None
    truth: dict[str, np.ndarray]
    noise: dict[str, Any]
    redraws: int
    seed: int
    visibility: float = field(default=float("nan"))


#: A drawn effect is redrawn when the RMS of its contribution to the outputs (truth minus
#: nominal, relative to that output's noise std, on the output where it shows most) is
#: below this.  At 0.25 an effect changes the outputs by a quarter of the sensor noise:
#: smaller "effects" are not discrepancies an engineer would act on.
MIN_VISIBILITY = 0.25
#: ... and also when it is below MIN_VISIBILITY on the last third of the record alone
#: (the discrepancy workflow's default held-out part).  An effect can vanish there: a
#: deadband inside a loop with integral action acts only while the block's input
#: crosses zero; once the input stays on one side the deadband is a constant offset
#: that the integrator absorbs *exactly* (truth - nominal ~ 1e-14 for the rest of the
#: record).  No held-out selection can judge such a trial; 4 of the first published
#: run's 50 deadband trials were of this kind, so the generator redraws them.
HOLDOUT_FRACTION = 1.0 / 3.0


def _ar1(rng: np.random.Generator, n: int, tau_samples: float) -> np.ndarray:
    """Unit-variance AR(1) with correlation time `tau_samples` (stationary start)."""
    a = math.exp(-1.0 / tau_samples)
    e = rng.standard_normal(n) * math.sqrt(1 - a * a)
    x, _ = scipy.signal.lfilter([1.0], [1.0, -a], e, zi=[a * rng.standard_normal()])
    return x


def _steps(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """Piecewise constant signal with `count` random steps (unit size scale)."""
    out = np.zeros(n)
    for k in np.sort(rng.integers(n // 20, n, count)):
        out[k:] += rng.normal()
    return out - out.mean()


def trial_inputs(model_name: str, *, n: int, dt_s: float,
                 rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Realistic excitation for the shipped models (deviation units).

    Load (steam flow, kg/s): slow wander (correlation time 20 min) + turbulence (40 s)
    + a few load steps.  Level set point (drum, mm): a few steps.  ``aux_flow``: an
    extra measured signal (e.g. a blowdown or attemperator flow) with its own slow
    wander, turbulence and steps, independent of the load.

    Parameters
    ----------
    model_name : str
        Name of the shipped model; ``"drum_level"`` also gets a ``level_setpoint``.
    n : int
        Number of samples.
    dt_s : float
        Sample period (s); sets the correlation times in samples.
    rng : numpy.random.Generator
        Source of the random wander, turbulence and steps.
    """
    n_tau = lambda s: max(s / dt_s, 1.0)  # noqa: E731 - correlation time in samples
    load = 4.0 * _ar1(rng, n, n_tau(1200)) + 1.0 * _ar1(rng, n, n_tau(40)) + 2.0 * _steps(rng, n, 4)
    aux = 2.0 * _ar1(rng, n, n_tau(600)) + 0.7 * _ar1(rng, n, n_tau(30)) + 1.0 * _steps(rng, n, 3)
    signals = {"steam_flow": load - load[0], "aux_flow": aux - aux[0]}
    if model_name == "drum_level":
        sp = 20.0 * _steps(rng, n, 6) + 3.0 * _ar1(rng, n, n_tau(300))
        signals["level_setpoint"] = sp - sp[0]
    return signals


def _stable(model: Model, dt_s: float) -> bool:
    if not model.is_linear:
        return True  # checked on the simulated trajectory instead
    try:
        system = discrete_state_space(model, dt_s=dt_s)
    except ModelError:
        return False
    return bool(np.max(np.abs(np.linalg.eigvals(system.a)), initial=0.0) < 0.998)


def _draw_effect(name: str, model: Model, nominal: Any, inputs: Mapping[str, np.ndarray],
                 dt_s: float, rng: np.random.Generator) -> Effect:
    """One random effect of catalogue entry `name` (sizes documented in the suite)."""
    measured_outputs = list(model.outputs)
    locations = applicable_locations(model, name, measured_outputs=measured_outputs,
                                     signals=[s for s in inputs if s not in model.inputs])
    loc = str(rng.choice(locations))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    sig = nominal.signals
    n = next(iter(inputs.values())).size
    if name == "gain":
        return Effect(name, loc, {"factor": math.exp(sign * rng.uniform(math.log(1.15), math.log(1.6)))})
    if name == "dead_time":
        return Effect(name, loc, {"delay_s": float(rng.integers(2, 16)) * dt_s})
    if name == "extra_lag":
        return Effect(name, loc, {"tau_s": math.exp(rng.uniform(math.log(3 * dt_s), math.log(40 * dt_s)))})
    if name == "inverse_response":
        return Effect(name, loc, {"tau_s": math.exp(rng.uniform(math.log(4 * dt_s), math.log(30 * dt_s))),
                                  "magnitude": rng.uniform(0.4, 2.0)})
    if name == "sensor_bias_drift":
        std = float(np.std(sig[loc]))
        hours = n * dt_s / 3600.0
        return Effect(name, loc, {"bias": sign * rng.uniform(0.2, 1.0) * std,
                                  "drift_per_h": (1 if rng.random() < 0.5 else -1)
                                  * rng.uniform(0.2, 1.0) * std / hours})
    if name == "operating_point_gain":
        # the gain varies by 20-60 % at the signal's extreme: never changes sign
        signal = str(rng.choice(list(inputs)))
        extreme = float(np.max(np.abs(inputs[signal])))
        return Effect(name, loc, {"slope": sign * rng.uniform(0.2, 0.6) / extreme, "signal": signal})
    if name == "deadband":
        block = model.block(loc)
        u = sum(t.k * (sig[t.signal] if t.signal in sig else inputs[t.signal]) for t in block.inputs)
        return Effect(name, loc, {"width": rng.uniform(0.3, 1.5) * float(np.std(u))})
    if name == "saturation":
        v = sig[loc]
        return Effect(name, loc, {"low": float(np.quantile(v, rng.uniform(0.03, 0.15))),
                                  "high": float(np.quantile(v, rng.uniform(0.85, 0.97)))})
    if name == "unmodelled_input":
        signal, _, output = loc.partition("->")
        std_y = float(np.std(sig[output]))
        return Effect(name, loc, {"k": sign * rng.uniform(0.3, 1.0) * std_y / float(np.std(inputs[signal])),
                                  "tau_s": math.exp(rng.uniform(math.log(2 * dt_s), math.log(30 * dt_s))),
                                  "delay_s": float(rng.integers(1, 11)) * dt_s})
    raise ConfigError(f"effect {name!r} is not in the catalogue")


def make_hidden_effect_trial(
    model: Model,
    effect_name: str | None,
    *,
    seed: int,
    n: int = 10_000,
    dt_s: float = 2.0,
    noise_kind: str | None = None,
    max_redraws: int = 50,
) -> HiddenEffectTrial:
    """Simulate a plant = `model` + one random hidden effect, with sensor noise.

    Parameters
    ----------
    model : Model
        A shipped model (``boiler_pressure`` or ``drum_level``: input names matter).
    effect_name : str or None
        Catalogue effect to hide (random location and size); None for a null trial.
    seed : int
        Seeds everything (inputs, effect, noise).
    n : int
        Samples.
    dt_s : float
        Sample period, s (divides every delay of the shipped models).
    noise_kind : {"white", "ar1"}, optional
        Default: drawn 50/50.  AR(1) has ``phi ~ U(0.5, 0.9)``.  The noise std is
        ``U(0.1, 0.3)`` times the std of each noise-free output.
    max_redraws : int
        Effects drawn until the loop is stable and the effect visible
        (:data:`MIN_VISIBILITY`, on the whole record and on its held-out last third).

    Notes
    -----
    Effect sizes (uniform, random sign where it has one; location uniform over
    :func:`applicable_locations`): gain factor ``exp(±U(ln 1.15, ln 1.6))``; dead time
    2-15 samples; extra lag ``tau_s`` log-uniform 3-40 samples; inverse response
    ``tau_s`` log-uniform 4-30 samples, ``magnitude`` U(0.4, 2); sensor bias
    U(0.2, 1) output std and drift U(0.2, 1) output std per record length;
    operating-point gain: the gain changes by U(0.2, 0.6) at the signal's extreme;
    deadband width U(0.3, 1.5) std of the block's input; saturation limits at the
    U(0.03, 0.15) and U(0.85, 0.97) quantiles of the block's nominal output; unmodelled
    input from ``aux_flow`` with a contribution of U(0.3, 1) output std per signal std,
    ``tau_s`` log-uniform 2-30 samples, delay 1-10 samples.

    Returns
    -------
    HiddenEffectTrial
    """
    rng = np.random.default_rng(seed)
    inputs = trial_inputs(model.name, n=n, dt_s=dt_s, rng=rng)
    drive = {name: inputs[name] for name in model.inputs}
    nominal = simulate(model, drive, dt_s=dt_s)
    kind, phi, rel, noise_unit = _unit_noise(model, n, noise_kind, rng)
    effect, truth, redraws, visibility = None, None, 0, float("nan")
    if effect_name is None:
        truth = {name: nominal.signals[name] for name in model.outputs}
    else:
        effect, truth, redraws, visibility = _visible_effect(
            model, effect_name, nominal, inputs, dt_s=dt_s, rel=rel, n=n, seed=seed,
            max_redraws=max_redraws, rng=rng)
    measured = {
        name: truth[name] + rel * float(np.std(truth[name])) * noise_unit[name]
        for name in model.outputs
    }
    return HiddenEffectTrial(
        model=model, inputs=inputs, measured=measured, dt_s=dt_s, effect=effect,
        truth=truth, noise={"kind": kind, "phi": phi, "relative_std": rel},
        redraws=redraws, seed=seed, visibility=visibility,
    )


def _unit_noise(model: Model, n: int, noise_kind: str | None, rng: np.random.Generator
                ) -> tuple[str, float, float, dict[str, np.ndarray]]:
    """The noise kind, AR(1) ``phi``, relative std and unit-variance noise per output."""
    kind = noise_kind or ("white" if rng.random() < 0.5 else "ar1")
    phi = 0.0 if kind == "white" else float(rng.uniform(0.5, 0.9))
    rel = float(rng.uniform(0.1, 0.3))
    noise_unit = {}
    for name in model.outputs:
        e = rng.standard_normal(n)
        if phi:
            e, _ = scipy.signal.lfilter([math.sqrt(1 - phi * phi)], [1.0, -phi], e,
                                        zi=[phi * rng.standard_normal()])
        noise_unit[name] = e
    return kind, phi, rel, noise_unit


def _visible_effect(model: Model, effect_name: str, nominal: Any,
                    inputs: Mapping[str, np.ndarray], *, dt_s: float, rel: float, n: int,
                    seed: int, max_redraws: int, rng: np.random.Generator
                    ) -> tuple[Effect, dict[str, np.ndarray], int, float]:
    """Draw effects until one is stable and visible: the effect, the true outputs, the
    index of the accepted draw and its visibility."""
    for redraws in range(max_redraws):
        candidate = _draw_effect(effect_name, model, nominal, inputs, dt_s, rng)
        augmented = apply_effect(model, candidate, dt_s=dt_s)
        if not _stable(augmented, dt_s):
            continue
        with np.errstate(all="ignore"):
            out = predict_outputs(model, candidate, inputs, dt_s=dt_s)
        if not all(np.all(np.isfinite(v)) and np.std(v) < 20 * np.std(nominal.signals[k]) + 1e-12
                   for k, v in out.items()):
            continue
        visibility, held_visibility = _visibility(model, out, nominal, rel, n)
        if visibility < MIN_VISIBILITY or held_visibility < MIN_VISIBILITY:
            continue
        return candidate, out, redraws, visibility
    raise ConfigError(
        f"make_hidden_effect_trial: no stable, visible {effect_name} effect in "
        f"{max_redraws} draws for model {model.name!r} (seed {seed})"
    )


def _visibility(model: Model, out: Mapping[str, np.ndarray], nominal: Any, rel: float,
                n: int) -> tuple[float, float]:
    """RMS of the effect's contribution over the noise std, on the output where it shows
    most: over the whole record and over its held-out last part."""
    vis, vis_held = [], []
    held = slice(n - int(round(HOLDOUT_FRACTION * n)), n)
    for name in model.outputs:
        sigma = rel * float(np.std(out[name]))
        diff = out[name] - nominal.signals[name]
        vis.append(float(np.sqrt(np.mean(diff ** 2))) / sigma)
        vis_held.append(float(np.sqrt(np.mean(diff[held] ** 2))) / sigma)
    return max(vis), max(vis_held)
