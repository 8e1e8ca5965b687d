"""The analysis problem: validated signals, the nominal simulation, the data split and the whitening."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.discrepancy.config import DiscrepancyConfig
from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError, ModelError
from pipeline.models.blocks import CONTROLLER_TYPES
from pipeline.models.model import Model, open_at
from pipeline.models.simulate import simulate
from pipeline.models.stability import unstable_parts


#: Innovation stds are floored at this fraction of the output's std (:func:`sigma_floor`).
_SIGMA_FLOOR_RTOL = 1e-6

#: A factor this far from 1 (or its inverse) between a measured output and the nominal
#: model's simulation of it -- or a fitted gain factor -- is more likely a unit or scale
#: mismatch between the export and the model than a plant change: the catalogue's effects
#: change a gain by tens of percent, a unit error by a power of ten (an OP exported as a
#: fraction 0-1 where the model expects %: 100).
SCALE_FACTOR_HINT = 30.0
#: The measured output must follow the scaled simulation this closely (correlation over
#: the fit part) for the factor to be read as a scale: a quarter of its variance explained.
SCALE_MIN_CORRELATION = 0.5


def check_scales(y: np.ndarray, y_nominal: np.ndarray, outputs: tuple[str, ...],
                 part: slice) -> None:
    """Refuse a measured output whose scale differs from the model's by a unit factor.

    The least-squares factor ``b = <m, s> / <s, s>`` between the measured output ``m`` and
    the nominal simulation ``s`` (both less their means over `part`) is the gain that
    maps the model's output onto the measurement.  When the two are correlated
    (:data:`SCALE_MIN_CORRELATION`) and ``b`` is :data:`SCALE_FACTOR_HINT` or more away
    from 1, no catalogue effect is the explanation: the search would fit a saturation
    or a gain of ``b`` to a unit error (an OP exported as a fraction was named a
    controller saturation closing 98 % of the gap), so the analysis stops with the
    factor named.

    Parameters
    ----------
    y, y_nominal : ndarray (N, n_y)
        Measured outputs and the nominal model's simulation of them.
    outputs : tuple of str
        Their names.
    part : slice
        Samples compared (the fit part).

    Raises
    ------
    ConfigError
        An output whose scale is off by a factor beyond :data:`SCALE_FACTOR_HINT`.
    """
    for i, name in enumerate(outputs):
        m, sim = y[part, i] - np.mean(y[part, i]), y_nominal[part, i] - np.mean(y_nominal[part, i])
        ss, mm = float(sim @ sim), float(m @ m)
        if ss <= 0.0 or mm <= 0.0:
            continue
        b = float(m @ sim) / ss
        corr = float(m @ sim) / math.sqrt(ss * mm)
        if corr < SCALE_MIN_CORRELATION or 1.0 / SCALE_FACTOR_HINT < b < SCALE_FACTOR_HINT:
            continue
        factor = 1.0 / b
        decade = 10.0 ** round(math.log10(factor))
        near = abs(factor / decade - 1.0) <= 0.15  # a power of ten: a unit's factor
        likely, suggest = (f" ≈ {decade:g}", f"{decade:g}") if near else ("", f"{factor:.3g}")
        raise ConfigError(
            f"output {name!r}: the measurement is {b:.3g} × the nominal model's simulation "
            f"of it (correlation {corr:.2f} over the fit part), so its scale differs from "
            f"the model's by a factor of {factor:.3g}{likely}: a unit mismatch, not a plant "
            "effect (e.g. an OP exported as a fraction 0-1 where the model expects %).  Put "
            f"the signal in the model's units with 'scale: {suggest}' under "
            f"signals.outputs.{name} in the job YAML, or fix the model's units"
        )


@dataclass
class Problem:
    """Everything the stages share (internal, mutable while the analysis runs)."""

    model: Model
    inputs: dict[str, np.ndarray]
    outputs: tuple[str, ...]
    y: np.ndarray  # (N, n_y) measured
    dt_s: float
    n: int
    fit_start: int
    holdout_start: int
    config: DiscrepancyConfig
    settling_s: float
    n_p: int
    max_delay: int
    nominal_signals: dict[str, np.ndarray]
    y_nominal: np.ndarray  # (N, n_y)
    ar: list[np.ndarray] = field(default_factory=list)  # per output [1, -phi_1, ...]
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: block and output names of the nominal model: a later search of the chain screens
    #: only locations with a counterpart there (:func:`pipeline.discrepancy.effects.original_location`)
    location_names: tuple[str, ...] | None = None
    #: fitted candidates whose simulation over the whole record diverged: dropped from
    #: the selection, listed in the result with their parameters (shared by the copies
    #: the white-weighted screening makes)
    diverged: list = field(default_factory=list)
    #: indices of the outputs whose constant is not known (``free_offsets``): every
    #: prediction has it profiled out on the fit part (:meth:`with_free_offsets`)
    free: tuple[int, ...] = ()
    #: controllers whose loops the analysis opened (:func:`loops_to_open`; the result's
    #: ``opened_loops``): their measured OPs are inputs that carry the noise's past, so
    #: the noise model's residual regression leaves them out
    #: (:func:`pipeline.discrepancy.localise.localise`)
    opened_loops: tuple[str, ...] = ()
    #: with loops opened, the user's model closed and the record as measured, with the
    #: chain's effects so far: every candidate must narrow its held-out gap too
    #: (:class:`pipeline.discrepancy.closed_loop.ClosedLoop`); None when nothing is opened
    closed: Any = None

    def with_free_offsets(self, y: np.ndarray) -> np.ndarray:
        """`y` (predicted outputs from sample 0, at least to the hold-out) with each free
        output moved by the constant that makes its fit-part residual zero-mean.

        An output measured from its mean has no known constant: the nominal model's is
        set that way, and every candidate gets the same treatment (the constant profiled
        out, as a least-squares intercept is), so an effect that moves an output's mean
        -- a saturation with the controller winding up moves its measured OP's -- is
        compared on equal terms instead of carrying the nominal model's constant.

        Parameters
        ----------
        y : ndarray (M, n_y)
            Predicted outputs from sample 0; returned as it is when shorter than the
            fit part's end (``holdout_start``) or when no output is free.
        """
        if not self.free or y.shape[0] < self.holdout_start:
            return y
        part = slice(self.fit_start, self.holdout_start)
        y = np.array(y, dtype=float, copy=True)
        for i in self.free:
            y[:, i] += float(np.mean(self.y[part, i] - y[part, i]))
        return y

    @property
    def n_y(self) -> int:
        return len(self.outputs)

    @property
    def extra_signals(self) -> list[str]:
        return [s for s in self.inputs if s not in self.model.inputs]

    def whiten(self, z: np.ndarray, start: int, stop: int) -> np.ndarray:
        """Whitened, noise-normalised ``z`` (N', n_y) on samples ``[start+p, stop)``.

        Returns the per-output vectors concatenated (length ~ n_y (stop-start)).

        Parameters
        ----------
        z : ndarray (N', n_y)
            Output errors or changes from sample 0 on (N' >= `stop`); filtered from
            sample 0 so that the first whitened samples have their past.
        start, stop : int
            Sample indices of the span (``stop`` exclusive), e.g. ``fit_start`` and
            ``holdout_start`` for the fit part; the first ``p`` (the highest AR order
            over the outputs) samples after ``start`` are dropped.
        """
        return np.concatenate(self.whiten_split(z, start, stop))

    def whiten_split(self, z: np.ndarray, start: int, stop: int) -> list[np.ndarray]:
        """Per-output whitened vectors, all on samples ``[start + p_max, stop)``.

        Parameters
        ----------
        z : ndarray (N', n_y)
            Output errors or changes from sample 0 on (N' >= `stop`).
        start, stop : int
            Sample indices of the span (``stop`` exclusive); ``p_max`` is the highest
            AR order over the outputs.
        """
        first = start + max(len(a) for a in self.ar) - 1
        out = []
        for i in range(self.n_y):
            w = fir_from(self.ar[i], z[:stop, i], first)
            out.append(w / self.sigma[i])
        return out


#: Longest automatic warm-up, as a share of the record: the analysis skips three times
#: the model's settling time but never more than this (:func:`pipeline.discrepancy.analyse.
#: discrepancy_problem`); what runs before the warm-up is known (the operating point,
#: :func:`loops_to_open`) skips this share, conservatively.
AUTO_WARMUP_MAX_SHARE = 0.10


def first_holdout_sample(n: int, holdout_fraction: float) -> int:
    """First sample of the held-out last `holdout_fraction` of `n` samples.

    Parameters
    ----------
    n : int
        Samples in the record.
    holdout_fraction : float
        ``DiscrepancyConfig.holdout_fraction``.
    """
    return int(round(n * (1.0 - holdout_fraction)))


def opened_signals(inputs: Mapping[str, Any], measured: Mapping[str, Any],
                   opened: tuple[str, ...]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The inputs and measured outputs with each opened loop's measured OP moved from
    the outputs to the inputs (:func:`pipeline.models.model.open_at`'s signals).

    Parameters
    ----------
    inputs, measured : mapping of str -> array
        As the analysis takes them.
    opened : tuple of str
        Controllers whose loops are opened (:func:`loops_to_open`).
    """
    return ({**inputs, **{c: measured[c] for c in opened}},
            {k: v for k, v in measured.items() if k not in opened})


def downstream(model: Model, start: str) -> set[str]:
    """Blocks of `model` that read `start` directly or through other blocks.

    Parameters
    ----------
    model : Model
    start : str
        A block or input name.
    """
    reached, frontier = set(), {start}
    while frontier:
        frontier = {b.name for b in model.blocks
                    if set(b.references()) & frontier and b.name not in reached}
        reached |= frontier
    return reached


def loops_to_open(model: Model, measured: Mapping[str, np.ndarray], *, dt_s: float,
                  holdout_fraction: float) -> tuple[str, ...]:
    """The controllers whose loops the analysis opens at their measured output.

    A controller block (:data:`CONTROLLER_TYPES`) that is a model output with a measured
    signal qualifies when, with its loop opened (:func:`pipeline.models.model.open_at`),
    every block its OP then drives settles to 2 % within the held-out part
    (:func:`pipeline.models.stability.unstable_parts` with growth ``exp(-4)``: no
    integrator, no time constant above a quarter of it).  The comparison is free-run
    (output error): an opened path that does not settle accumulates the unmeasured
    disturbance the controller was rejecting -- an integrating level driven by its
    measured pump demand drifts without bound -- so the held-out comparison would hinge
    on the state the path reached, not on the effect.  Closed, the controller keeps such
    an output bounded.

    How much of the OP is the controller's answer to the unmeasured disturbance does
    not decide: that share biases the opened fit of the paths whose output the
    controller reads (Forssell & Ljung 1999: ``(H0 - H) Phi_ue / Phi_u``), and those
    candidates are checked closed with the setpoints and loads as instruments
    (:mod:`pipeline.discrepancy.closed_loop`); a path seen outside the loop (a valve's
    flow meter) carries sensor noise only and is fitted without that bias.  Until
    session 21 a loop also stayed closed when the nominal model explained less than
    half of the OP's variance -- a guard from before the closed check, which could not
    tell the disturbance from the missing effect itself: a heat exchanger's 16 s steam
    delay leaves the nominal model 0.28-0.46 of its OP (its loop rings where the model's
    does not), and closed, five of six such delays were named as an inverse response
    or at the shell (spent zoo seeds 8 711 000-019; opened, all six were named with location,
    :mod:`pipeline.discrepancy.closed_loop` on delays that leave the loop ringing).

    Parameters
    ----------
    model : Model
    measured : mapping of str -> ndarray
        The analysis's measured outputs (deviations, one grid).
    dt_s : float
        Sample period, s (loops are judged at it).
    holdout_fraction : float
        The held-out part's share of the record.

    Returns
    -------
    tuple of str
        In model order; empty when no loop qualifies.
    """
    n = min((np.size(v) for v in measured.values()), default=0)
    hold = first_holdout_sample(n, holdout_fraction)
    fit = slice(int(AUTO_WARMUP_MAX_SHARE * n), hold)
    if fit.stop - fit.start < 2:
        return ()
    chosen = []
    for block in model.blocks:
        if block.TYPE not in CONTROLLER_TYPES or block.name not in model.outputs \
                or block.name not in measured:
            continue
        try:
            opened = open_at(model, [block.name])
        except ModelError:  # nothing left to compare
            continue
        driven = downstream(opened, block.name)
        slow = unstable_parts(opened, dt_s=dt_s, record_s=(n - hold) * dt_s,
                              growth_limit=math.exp(-4.0))
        if not any(set(part.blocks) & driven for part in slow):
            chosen.append(block.name)
    return tuple(chosen)


def _closed_ops(model: Model, inputs: Mapping[str, Any], opened: tuple[str, ...], *,
                dt_s: float, config: DiscrepancyConfig) -> np.ndarray | None:
    """The opened controllers' OPs as the closed nominal model simulates them from the
    setpoints and loads (N, len(opened)); None when that simulation fails or does not
    stay finite."""
    try:
        with np.errstate(all="ignore"):
            sim = simulate(model, {k: np.asarray(inputs[k], dtype=float)
                                   for k in model.inputs},
                           dt_s=dt_s, initial=config.initial).signals
    except (ModelError, DataQualityError, ConfigError, KeyError, ValueError):
        return None
    ops = np.column_stack([sim[c] for c in opened])
    return ops if np.all(np.isfinite(ops)) and np.max(np.abs(ops)) < 1e12 else None


def opened_view(model: Model, inputs: Mapping[str, Any], measured: Mapping[str, Any],
                dt_s: float, config: DiscrepancyConfig, free_offsets: tuple[str, ...] = ()
                ) -> tuple[Model, dict[str, Any], dict[str, Any], tuple[str, ...],
                           tuple[str, ...]]:
    """What the analysis compares: the model, inputs, measured outputs and free outputs
    with the loops :func:`loops_to_open` picks opened (each measured OP moved from the
    outputs to the inputs, ``config.open_loops``), and those loops' controller names
    (empty: everything as given).  Loops are opened only when the model runs closed
    from the setpoints and loads (the closed check needs it), and the OPs' scales are
    checked first against that run (:func:`check_scales`; ConfigError).

    Parameters
    ----------
    model : Model
    inputs, measured : mapping of str -> array
        The analysis's inputs and measured outputs (deviations, one grid).
    dt_s : float
        Sample period, s.
    config : DiscrepancyConfig
        ``open_loops`` and ``holdout_fraction`` are read.
    free_offsets : tuple of str
        Outputs whose constant is profiled out.
    """
    if not config.open_loops or not measured:
        return model, dict(inputs), dict(measured), free_offsets, ()
    opened = loops_to_open(model, measured, dt_s=float(dt_s),
                           holdout_fraction=config.holdout_fraction)
    if not opened:
        return model, dict(inputs), dict(measured), free_offsets, ()
    # closed, the nominal model must run: the closed check needs it (without it the
    # opened candidates would go unchecked), and the OPs' scales are judged on it --
    # opened, an OP exported as a fraction would surface as a factor on the outputs it
    # drives and be blamed on them.  A model that diverges closed stays closed, and the
    # analysis names the divergence (with the limit to add).
    ops = _closed_ops(model, inputs, opened, dt_s=float(dt_s), config=config)
    if ops is None:
        return model, dict(inputs), dict(measured), free_offsets, ()
    n = ops.shape[0]
    check_scales(np.column_stack([np.asarray(measured[c], dtype=float)[:n] for c in opened]),
                 ops, opened, slice(int(AUTO_WARMUP_MAX_SHARE * n),
                                    first_holdout_sample(n, config.holdout_fraction)))
    return (open_at(model, opened), *opened_signals(inputs, measured, opened),
            tuple(o for o in free_offsets if o not in opened), opened)


def fir_from(a: np.ndarray, z: np.ndarray, first: int) -> np.ndarray:
    """``(a(q) z)[first:]`` for the short whitening filter ``a`` (zero initial state),
    along the first axis of ``z`` (any trailing shape).

    The same numbers as ``scipy.signal.lfilter(a, [1.0], z, axis=0)[first:]``; written
    out as shifted sums because scipy's FIR path loops in Python over the trailing
    columns (``apply_along_axis`` with ``np.convolve``): 2.5 s of a 10 s analysis went
    there.

    Parameters
    ----------
    a : ndarray (p + 1,)
        Filter coefficients ``[1, -phi_1, ..]``.
    z : ndarray (N, ...)
        Signal(s), from sample 0 (the filter's past).
    first : int
        First sample returned; ``first >= len(a) - 1`` needs no zero past.
    """
    z = np.asarray(z, dtype=float)
    out = a[0] * z[first:]
    for j in range(1, len(a)):
        lo = max(first - j, 0)
        out[lo + j - first:] += a[j] * z[lo:z.shape[0] - j]
    return out


def sigma_floor(y: np.ndarray) -> float:
    """Smallest innovation std used for whitening: :data:`_SIGMA_FLOOR_RTOL` of the
    output's spread.

    Noise-free records (simulations) have a zero FIR residual, and the right candidate
    reproduces them up to the optimiser's tolerance (relative ``_LSQ_TOL`` in the
    parameters); dividing by such a "noise" std would turn every statistic into
    rounding noise.  No sensor resolves a millionth of its signal's spread, so on real
    data the floor never binds.

    Parameters
    ----------
    y : ndarray (N,)
        One measured output.
    """
    return _SIGMA_FLOOR_RTOL * float(np.std(y)) + 1e-300


def validate_signals(model: Model, inputs: Mapping[str, Any], measured: Mapping[str, Any],
              dt_s: float) -> tuple[dict[str, np.ndarray], tuple[str, ...], np.ndarray]:
    """Check the model and the signals; return (inputs, output names, y (N, n_y)).

    The output names are the measured outputs in the model's order, the columns of y.

    Parameters
    ----------
    model : Model
        Nominal model.
    inputs : mapping of str -> array_like (N,)
        Measured signals: every model input, plus any other signals (candidate
        unmodelled inputs); none may have a model block's name.
    measured : mapping of str -> array_like (N,)
        Measured outputs: a non-empty subset of the model's outputs.
    dt_s : float
        Sample period, s.

    Raises
    ------
    ConfigError
        Wrong types, missing model inputs, unknown outputs or name clashes.
    DataQualityError
        Signals not 1-D, with non-finite values or of different lengths.
    InsufficientDataError
        Fewer than 500 samples.
    """
    if not isinstance(model, Model):
        raise ConfigError(f"model: expected a pipeline.models.model.Model, got {type(model).__name__}")
    if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s={dt_s!r} must be a positive number of seconds")
    if not isinstance(inputs, Mapping) or not isinstance(measured, Mapping):
        raise ConfigError("inputs and measured must be mappings of signal name -> array")
    missing = [name for name in model.inputs if name not in inputs]
    if missing:
        raise ConfigError(
            f"model {model.name!r} needs inputs {list(model.inputs)} but {missing} are not "
            f"among the measured signals {sorted(inputs)}; add them to the job's signals"
        )
    unknown = [name for name in measured if name not in model.outputs]
    if unknown or not measured:
        raise ConfigError(
            f"measured outputs {sorted(measured)} must be a non-empty subset of the model "
            f"outputs {list(model.outputs)} (unknown: {unknown})"
        )
    clash = [name for name in inputs if name in model.block_names]
    if clash:
        raise ConfigError(
            f"measured signals {clash} have the names of model blocks; rename the signals"
        )
    arrays: dict[str, np.ndarray] = {}
    for kind, source in (("input", inputs), ("output", measured)):
        for name, values in source.items():
            arr = np.asarray(values, dtype=float)
            if arr.ndim != 1:
                raise DataQualityError(f"{kind} {name!r}: shape {arr.shape}; expected (N,)")
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                raise DataQualityError(
                    f"{kind} {name!r}: {bad.size} non-finite values (first at sample "
                    f"{bad[0]}); fill or cut the gaps before the discrepancy analysis"
                )
            arrays[(kind, name)] = arr  # type: ignore[index]
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) != 1:
        raise DataQualityError(
            f"signals have different lengths { {k[1]: len(a) for k, a in arrays.items()} }; "
            "resample them to one grid first"
        )
    n = lengths.pop()
    if n < 500:
        raise InsufficientDataError(
            f"{n} samples is too few for a discrepancy analysis (fit, hold-out, noise model); "
            "give at least 500 samples, better 20 settling times"
        )
    ins = {name: arrays[("input", name)] for name in inputs}  # type: ignore[index]
    outputs = tuple(name for name in model.outputs if name in measured)
    y = np.column_stack([arrays[("output", name)] for name in outputs])  # type: ignore[index]
    return ins, outputs, y


def settling_time(model: Model, dt_s: float, n_max: int) -> float:
    """Longest 2 % settling time of the model's outputs after a unit step on any input, s.

    An output still moving at the end of the horizon (integrating) gets the horizon.

    Parameters
    ----------
    model : Model
        Nominal model (simulated from rest).
    dt_s : float
        Sample period, s.
    n_max : int
        Longest step simulation, samples (the record length); the horizon is
        ``min(n_max, max(200, 4 h / dt_s))`` samples.
    """
    horizon = int(min(n_max, max(200, 4 * 3600 / dt_s)))
    longest = 0.0
    for name in model.inputs:
        step = {k: (np.ones(horizon) if k == name else np.zeros(horizon)) for k in model.inputs}
        with np.errstate(all="ignore"):
            sim = simulate(model, step, dt_s=dt_s)
        for out in sim.outputs.T:
            scale = float(np.max(np.abs(out)))
            if not math.isfinite(scale) or scale == 0.0:
                continue
            outside = np.flatnonzero(np.abs(out - out[-1]) > 0.02 * scale)
            k = 0 if outside.size == 0 else int(outside[-1]) + 1
            longest = max(longest, k * dt_s)
    return max(longest, 10 * dt_s)
