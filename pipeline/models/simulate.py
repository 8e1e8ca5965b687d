"""Discrete-time simulation of block-diagram models (:mod:`pipeline.models.model`).

Discretisation
    Every linear block's continuous transfer function is converted to state space
    (``scipy.signal.tf2ss``) and discretised *exactly* for piecewise-constant inputs
    with a zero-order hold (``scipy.signal.cont2discrete(method="zoh")``, the same as
    ``control.sample_system(sys, dt_s, "zoh")``).  Signals are therefore exact at the
    sample instants when the inputs are held between samples; every block of a loop is
    discretised on its own, i.e. the signals between blocks are sampled-and-held too
    (as in a DCS executing the blocks once per scan).

Dead time
    A block's ``delay_s`` is an integer number of samples.  ``delay_s / dt_s`` must lie
    within 1e-9 of an integer; otherwise :class:`~pipeline.errors.ModelError` names the
    block and suggests sample periods that divide every delay.  Rounding silently would
    shift a fitted dead time by up to half a sample without anybody noticing.

Loops
    Blocks are evaluated per sample in a topological order of the *feedthrough* graph:
    a block with ``delay_s > 0`` or a strictly proper transfer function (whose ZOH
    discretisation has ``D = 0``) emits its output from its state before its input is
    known, which is what breaks a loop.  Algebraic loops are rejected by
    :class:`~pipeline.models.model.Model` itself.

Two exact paths
    ``"linear"`` (models without deadband/saturation/operating-point gain): the whole
    interconnection is assembled into ONE discrete state-space system
    (:func:`discrete_state_space`) and simulated in lifted form, ``chunk`` samples per
    matrix product (see :func:`_lifted_response`), which is vectorised.
    ``"per_sample"`` (any model): one compiled kernel runs the blocks sample by sample
    (:mod:`pipeline.models.sample_program`).  ``"auto"`` picks ``"linear"``
    when possible.  Both give the same numbers to rounding (tests check 1e-9).

Initial condition
    ``initial="rest"`` (default): every state zero, i.e. the inputs are deviations from
    a steady operating point and every signal starts at 0.  ``initial="steady"``: the
    steady state for the first input sample held constant (linear models only; needs a
    unique equilibrium, i.e. no integrator outside a feedback loop).  Or an explicit
    state vector in the layout of :func:`state_names`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Literal

import numpy as np
import scipy.signal

from pipeline.errors import ConfigError, DataQualityError, DivergenceError, ModelError
from pipeline.models.blocks import Block
from pipeline.models.model import Model
from pipeline.models.sample_program import DiscreteBlock, per_sample_response

__all__ = [
    "DiscreteStateSpace",
    "SimulationResult",
    "discrete_state_space",
    "loop_state_matrix",
    "simulate",
    "state_names",
]

#: Tolerance on ``delay_s / dt_s`` being an integer.
DELAY_INTEGER_TOL = 1e-9
#: Above this many states (long delays at short dt_s make delay chains long), the
#: dense lifted matrices cost more than the per-sample path, which keeps delays in
#: ring buffers; ``method="auto"`` then uses the per-sample path.
MAX_LIFTED_STATES = 1500
#: A dead time longer than both the simulated record and this many samples is refused
#: (its register holds one float per sample: ``delay_s: 1e12`` at 1 s asked for 7 TiB).
MAX_DELAY_SAMPLES = 10**6
#: Largest system :func:`discrete_state_space` assembles as dense matrices (8 n_x² bytes
#: each: 20 000 states are 3.2 GB).
MAX_DENSE_STATES = 20_000
#: Samples per lifted step: the boundary recursion runs N/chunk Python iterations and
#: the Toeplitz product costs ~chunk·n_signals·n_inputs·N flops; 64 balances both.
_CHUNK = 64


@dataclass(frozen=True)
class DiscreteStateSpace:
    """The whole model as one discrete system ``x+ = a x + b u``, ``y = c x + d u``.

    Attributes
    ----------
    a : ndarray, shape (n_x, n_x)
    b : ndarray, shape (n_x, n_u)
    c : ndarray, shape (n_blocks, n_x)
        Rows in ``signal_names`` order (every block's output).
    d : ndarray, shape (n_blocks, n_u)
    dt_s : float
        Sample period, s.
    input_names : tuple of str
        Model inputs (columns of ``b``, ``d``).
    signal_names : tuple of str
        Block names (rows of ``c``, ``d``).
    state_names : tuple of str
        ``"block.x0"``... for block states, ``"block.delay1"``... for dead-time
        samples (``delay1`` is the most recent).
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    d: np.ndarray
    dt_s: float
    input_names: tuple[str, ...]
    signal_names: tuple[str, ...]
    state_names: tuple[str, ...]


@dataclass(frozen=True)
class SimulationResult:
    """Simulated signals.

    Attributes
    ----------
    t_s : ndarray, shape (N,)
        Sample times ``k * dt_s``, s.
    outputs : ndarray, shape (N, n_out)
        Model outputs in ``output_names`` (= ``model.outputs``) order.
    signals : dict of str -> ndarray, shape (N,)
        Every block's output.
    output_names : tuple of str
    dt_s : float
    method : str
        ``"linear"`` or ``"per_sample"``: the path that produced the numbers.
    """

    t_s: np.ndarray
    outputs: np.ndarray
    signals: dict[str, np.ndarray]
    output_names: tuple[str, ...]
    dt_s: float
    method: str


# -- discretisation ------------------------------------------------------------------
def _check_dt(dt_s: Any) -> float:
    if isinstance(dt_s, bool) or not isinstance(dt_s, (int, float, np.floating, np.integer)):
        raise ConfigError(f"dt_s={dt_s!r} must be a positive number of seconds")
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s={dt_s!r} must be a positive finite number of seconds")
    return float(dt_s)


def _suggest_dt(delays_s: Sequence[float], dt_s: float) -> list[float]:
    """Up to three sample periods <= dt_s that divide every delay exactly."""
    common = Fraction(0)
    for delay in delays_s:
        frac = Fraction(delay).limit_denominator(10**6)
        common = Fraction(math.gcd(common.numerator * frac.denominator,
                                   frac.numerator * common.denominator),
                          common.denominator * frac.denominator)
    if common == 0:
        return []
    first = max(1, math.ceil(common / Fraction(dt_s)))
    return [float(common / m) for m in range(first, first + 3)]


def _delay_samples(model: Model, dt_s: float) -> dict[str, int]:
    counts: dict[str, int] = {}
    delayed = [b for b in model.blocks if b.dead_time_s > 0]
    for block in model.blocks:
        ratio = block.dead_time_s / dt_s
        n = round(ratio)
        if abs(ratio - n) > DELAY_INTEGER_TOL or (block.dead_time_s > 0 and n == 0):
            hints = _suggest_dt([b.dead_time_s for b in delayed], dt_s)
            hint = ", ".join(f"{h:g}" for h in hints)
            raise ModelError(
                f"block {block.name!r}: delay_s={block.dead_time_s:g} is not a whole number "
                f"of samples at dt_s={dt_s:g} (ratio {ratio:.6g}); dead time is simulated "
                f"in whole samples: choose a dt_s that divides every delay_s"
                + (f", e.g. {hint}" if hint else "")
                + " or round the delay_s in the model"
            )
        counts[block.name] = n
    return counts


# Cached: the discrepancy search simulates a model thousands of times with all but one
# block unchanged, and each linear block's ZOH discretisation (tf2ss + expm) cost more
# than the per-sample loop itself.  Blocks are frozen (hashable by value); the cached
# arrays are read-only.
@functools.lru_cache(maxsize=4096)
def _discretise_block(block: Block, dt_s: float, n_delay: int) -> DiscreteBlock:
    db = _discretised(block, dt_s, n_delay)
    for arr in (db.a, db.b, db.c):
        arr.flags.writeable = False
    return db


def _discretised(block: Block, dt_s: float, n_delay: int) -> DiscreteBlock:
    if not block.LINEAR:
        empty = np.zeros((0, 0))
        return DiscreteBlock(block, empty, np.zeros(0), np.zeros(0), 0.0, 0)
    num, den = block.transfer_function()
    scale = float(np.abs(num).max())
    if len(den) == 1 or scale == 0.0:
        # Static (or identically zero): tf2ss/cont2discrete need at least one state.
        d = float(num[-1] / den[-1]) if len(den) == 1 and len(num) == 1 else 0.0
        return DiscreteBlock(block, np.zeros((0, 0)), np.zeros(0), np.zeros(0), d, n_delay)
    # scipy's normalize() treats numerator coefficients below 1e-14 as zeros, so a
    # block with a tiny gain would lose it: convert the unit-scaled numerator, then
    # scale C and D (the output map only, so the system is unchanged).
    a, b, c, d = scipy.signal.tf2ss(num / scale, den)
    ad, bd, cd, dd, _ = scipy.signal.cont2discrete((a, b, c, d), dt_s, method="zoh")
    return DiscreteBlock(
        block,
        np.asarray(ad),
        np.asarray(bd)[:, 0],
        scale * np.asarray(cd)[0],
        scale * float(dd[0, 0]),
        n_delay,
    )


def _check_delay_length(model: Model, dt_s: float, n_samples: int) -> None:
    """Refuse a dead time longer than the record and than :data:`MAX_DELAY_SAMPLES`."""
    from pipeline.models.stability import check_delays

    limit_s = max(n_samples, MAX_DELAY_SAMPLES) * dt_s
    if any(b.dead_time_s > limit_s for b in model.blocks):
        check_delays(model, record_s=n_samples * dt_s,
                     where=f"the record ({n_samples} samples at dt_s={dt_s:g})")


def _discretise(model: Model, dt_s: float) -> list[DiscreteBlock]:
    delays = _delay_samples(model, dt_s)
    return [_discretise_block(b, dt_s, delays[b.name]) for b in model.blocks]


def _augmented(db: DiscreteBlock) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Block dynamics with its dead time as a shift register of ``n_delay`` states."""
    n, m = len(db.b), db.n_delay
    if m == 0:
        return db.a, db.b, db.c, db.d
    a = np.zeros((n + m, n + m))
    a[:n, :n] = db.a
    a[n, :n] = db.c  # delay1+ = c x + d u (undelayed output)
    for j in range(1, m):
        a[n + j, n + j - 1] = 1.0  # delay(j+1)+ = delay(j)
    b = np.zeros(n + m)
    b[:n] = db.b
    b[n] = db.d
    c = np.zeros(n + m)
    c[-1] = 1.0
    return a, b, c, 0.0


def _state_names(blocks: Sequence[DiscreteBlock]) -> list[str]:
    names = []
    for db in blocks:
        names += [f"{db.block.name}.x{j}" for j in range(len(db.b))]
        names += [f"{db.block.name}.delay{j + 1}" for j in range(db.n_delay)]
    return names


def state_names(model: Model, *, dt_s: float) -> tuple[str, ...]:
    """Names of the simulation state in the layout `initial` arrays use (any model).

    Parameters
    ----------
    model : Model
    dt_s : float
        Sample period, s (sets the number of dead-time states).

    Returns
    -------
    tuple of str
        ``"block.x0"``... per block state (model block order), then that block's
        ``"block.delay1"`` (newest) ... ``"block.delayN"`` (oldest, output next).
    """
    return tuple(_state_names(_discretise(model, _check_dt(dt_s))))


def _wiring(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """``u_blocks = m @ y_blocks + n @ u_model`` (term weights summed per source)."""
    names = model.block_names
    block_index = {name: i for i, name in enumerate(names)}
    input_index = {name: i for i, name in enumerate(model.inputs)}
    m = np.zeros((len(names), len(names)))
    n = np.zeros((len(names), len(model.inputs)))
    for i, block in enumerate(model.blocks):
        for term in block.inputs:
            if term.signal in block_index:
                m[i, block_index[term.signal]] += term.k
            else:
                n[i, input_index[term.signal]] += term.k
    return m, n


def _require_linear(model: Model, what: str) -> None:
    nonlinear = [b.name for b in model.blocks if not b.LINEAR]
    if nonlinear:
        raise ModelError(
            f"model {model.name!r}: {what} needs a linear model, but blocks {nonlinear} are "
            "nonlinear (deadband/backlash/saturation/operating_point_gain); use method='per_sample' "
            "and initial='rest' or an explicit state vector"
        )


def discrete_state_space(model: Model, *, dt_s: float) -> DiscreteStateSpace:
    """Assemble a linear model into one exact discrete state-space system.

    Parameters
    ----------
    model : Model
        Must be linear.
    dt_s : float
        Sample period, s; every ``delay_s`` must be a whole number of samples.

    Returns
    -------
    DiscreteStateSpace
        Outputs are all block signals; poles are ``eig(a)``.

    Raises
    ------
    ModelError
        Nonlinear blocks, or a delay that is not a whole number of samples.
    """
    dt_s = _check_dt(dt_s)
    _require_linear(model, "discrete_state_space")
    n_x = sum(len(b.transfer_function()[1]) - 1 + round(b.dead_time_s / dt_s)
              for b in model.blocks)
    if n_x > MAX_DENSE_STATES:
        raise ModelError(
            f"model {model.name!r}: {n_x} states at dt_s={dt_s:g} (dead times count one state "
            f"per sample); at most {MAX_DENSE_STATES} fit dense matrices -- shorten the "
            "delay_s values or use a longer dt_s")
    return _assemble(model, _discretise(model, dt_s), dt_s)


def loop_state_matrix(model: Model, names: Sequence[str], *, dt_s: float,
                      max_states: int) -> np.ndarray | None:
    """State matrix of the linear blocks ``names`` alone (signals from outside them held
    at zero; dead times as shift registers): its eigenvalues are the loop's poles.

    Parameters
    ----------
    model : Model
    names : sequence of str
        Linear blocks of ``model``.
    dt_s : float
        Sample period, s.
    max_states : int
        None is returned above this many states (dense eigenvalues cost n_x³).
    """
    dt_s = _check_dt(dt_s)
    delays = _delay_samples(model, dt_s)
    blocks = [model.block(n) for n in names]
    sizes = [len(b.transfer_function()[1]) - 1 + delays[b.name] for b in blocks]
    if not 0 < sum(sizes) <= max_states:
        return None
    sub = [_discretise_block(b, dt_s, delays[b.name]) for b in blocks]
    local = {name: j for j, name in enumerate(names)}
    m = np.zeros((len(blocks), len(blocks)))
    for j, block in enumerate(blocks):
        for term in block.inputs:
            if term.signal in local:
                m[j, local[term.signal]] += term.k
    parts = [_augmented(db) for db in sub]
    n_x, n_b = sum(len(p[1]) for p in parts), len(parts)
    a_blk, b_blk = np.zeros((n_x, n_x)), np.zeros((n_x, n_b))
    c_blk, d_blk = np.zeros((n_b, n_x)), np.zeros(n_b)
    offset = 0
    for j, (a, b, c, d) in enumerate(parts):
        sl = slice(offset, offset + len(b))
        a_blk[sl, sl], b_blk[sl, j], c_blk[j, sl], d_blk[j] = a, b, c, d
        offset += len(b)
    c_sys = np.linalg.solve(np.eye(n_b) - d_blk[:, None] * m, c_blk)
    return a_blk + b_blk @ m @ c_sys


def _assemble(model: Model, blocks: Sequence[DiscreteBlock], dt_s: float) -> DiscreteStateSpace:
    parts = [_augmented(db) for db in blocks]
    sizes = [len(p[1]) for p in parts]
    n_x, n_b = sum(sizes), len(blocks)
    a_blk = np.zeros((n_x, n_x))
    b_blk = np.zeros((n_x, n_b))
    c_blk = np.zeros((n_b, n_x))
    d_blk = np.zeros(n_b)
    offset = 0
    for i, (a, b, c, d) in enumerate(parts):
        sl = slice(offset, offset + sizes[i])
        a_blk[sl, sl] = a
        b_blk[sl, i] = b
        c_blk[i, sl] = c
        d_blk[i] = d
        offset += sizes[i]
    m, n = _wiring(model)
    # y = C x + D (M y + N u)  =>  (I - D M) y = C x + D N u.  D M is nilpotent because
    # the model has no algebraic loop, so the solve is exact up to rounding.
    lhs = np.eye(n_b) - d_blk[:, None] * m
    c_sys = np.linalg.solve(lhs, c_blk)
    d_sys = np.linalg.solve(lhs, d_blk[:, None] * n)
    a_sys = a_blk + b_blk @ m @ c_sys
    b_sys = b_blk @ (m @ d_sys + n)
    return DiscreteStateSpace(
        a=a_sys,
        b=b_sys,
        c=c_sys,
        d=d_sys,
        dt_s=dt_s,
        input_names=model.inputs,
        signal_names=model.block_names,
        state_names=tuple(_state_names(blocks)),
    )


# -- linear path ---------------------------------------------------------------------
def _lifted_response(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, u: np.ndarray, x0: np.ndarray
) -> np.ndarray:
    """``y`` of ``x+ = a x + b u, y = c x + d u`` for ``u`` (N, n_u), in lifted form.

    Hand-written because scipy.signal.dlsim and control.forced_response step through
    the samples in a Python loop (~5 µs per sample).  Lifting: over a chunk of L samples
    starting in state x, ``y_chunk = O x + G u_chunk`` and ``x_next = a^L x + R u_chunk``
    with O = [c; c a; ...; c a^(L-1)], G the block-Toeplitz Markov matrix and
    R = [a^(L-1) b, ..., b].  Only the chunk-boundary states need a Python loop
    (N/L iterations); everything else is matrix products.  Exact up to rounding.
    """
    n_samples, n_u = u.shape
    n_y, n_x = c.shape
    chunk = max(1, min(_CHUNK, n_samples))
    n_chunks = -(-n_samples // chunk)
    powers = [np.eye(n_x)]
    for _ in range(chunk):
        powers.append(a @ powers[-1])
    obs = np.concatenate([c @ powers[j] for j in range(chunk)], axis=0)  # (L n_y, n_x)
    markov = [d] + [c @ powers[j] @ b for j in range(chunk - 1)]  # h_0..h_{L-1}
    toeplitz = np.zeros((chunk * n_y, chunk * n_u))
    for row in range(chunk):
        for col in range(row + 1):
            toeplitz[row * n_y:(row + 1) * n_y, col * n_u:(col + 1) * n_u] = markov[row - col]
    reach = np.concatenate([powers[chunk - 1 - j] @ b for j in range(chunk)], axis=1)
    a_chunk = powers[chunk]
    u_pad = np.zeros((n_chunks * chunk, n_u))
    u_pad[:n_samples] = u
    u_lift = u_pad.reshape(n_chunks, chunk * n_u).T  # column = one chunk's inputs
    drive = reach @ u_lift  # (n_x, n_chunks)
    x_start = np.empty((n_x, n_chunks))
    x = np.asarray(x0, dtype=float).copy()
    for k in range(n_chunks):
        x_start[:, k] = x
        x = a_chunk @ x + drive[:, k]
    y_lift = obs @ x_start + toeplitz @ u_lift  # (L n_y, n_chunks)
    return y_lift.T.reshape(n_chunks * chunk, n_y)[:n_samples]


# -- public entry point --------------------------------------------------------------
def _input_matrix(model: Model, inputs: Any) -> np.ndarray:
    n_u = len(model.inputs)
    if isinstance(inputs, Mapping):
        unknown = sorted(set(inputs) - set(model.inputs))
        missing = [name for name in model.inputs if name not in inputs]
        if unknown or missing:
            raise ConfigError(
                f"model {model.name!r}: inputs given {sorted(inputs)} but the model needs "
                f"{list(model.inputs)} (missing {missing}, unknown {unknown}); pass exactly "
                "the model inputs"
            )
        columns = []
        for name in model.inputs:
            column = np.asarray(inputs[name], dtype=float)
            if column.ndim != 1:
                raise ConfigError(
                    f"input {name!r}: shape {column.shape}; each input must be 1-D (N,)"
                )
            columns.append(column)
        lengths = {len(col) for col in columns}
        if len(lengths) > 1:
            raise ConfigError(
                f"model {model.name!r}: inputs have different lengths "
                f"{ {name: len(col) for name, col in zip(model.inputs, columns, strict=True)} }; "
                "give every input the same number of samples"
            )
        if not columns:
            raise ConfigError(
                f"model {model.name!r} has no inputs; pass a (N, 0) array to set the length"
            )
        u = np.column_stack(columns)
    else:
        u = np.asarray(inputs, dtype=float)
        if u.ndim == 1 and n_u == 1:
            u = u[:, None]
        if u.ndim != 2 or u.shape[1] != n_u:
            raise ConfigError(
                f"model {model.name!r}: inputs array has shape {u.shape}; expected (N, {n_u}) "
                f"with columns {list(model.inputs)}"
            )
    if u.shape[0] == 0:
        raise ConfigError(f"model {model.name!r}: inputs have no samples")
    if not np.all(np.isfinite(u)):
        bad = np.argwhere(~np.isfinite(u))
        row, col = bad[0]
        raise DataQualityError(
            f"model {model.name!r}: input {model.inputs[col]!r} is not finite at sample "
            f"{row} ({bad.shape[0]} non-finite values in total); fill or cut the gaps "
            "before simulating"
        )
    return u


def simulate(
    model: Model,
    inputs: Mapping[str, Any] | np.ndarray,
    *,
    dt_s: float,
    initial: Literal["rest", "steady"] | np.ndarray = "rest",
    method: Literal["auto", "linear", "per_sample"] = "auto",
) -> SimulationResult:
    """Simulate `model` driven by sampled `inputs` (held constant between samples).

    Parameters
    ----------
    model : Model
    inputs : mapping of str -> array (N,), or array (N, n_u)
        Input deviations; a mapping must have exactly ``model.inputs`` as keys, an
        array has its columns in ``model.inputs`` order ((N,) allowed for one input).
    dt_s : float
        Sample period, s.  Every ``delay_s`` must be a whole number of samples.
    initial : {"rest", "steady"} or array (n_x,)
        ``"rest"``: all states zero (signals start at 0; inputs are deviations).
        ``"steady"``: equilibrium for ``inputs[0]`` held constant (linear models).
        An array: the state in the layout of :func:`state_names`.
    method : {"auto", "linear", "per_sample"}
        ``"linear"``: one assembled state-space system, lifted (vectorised) simulation;
        linear models only.  ``"per_sample"``: the compiled per-sample kernel (:mod:`pipeline.models.sample_program`); any model.
        ``"auto"``: ``"linear"`` for linear models with at most
        :data:`MAX_LIFTED_STATES` states, else ``"per_sample"``.

    Returns
    -------
    SimulationResult

    Raises
    ------
    ModelError
        A delay not a whole number of samples, or longer than both the record and
        :data:`MAX_DELAY_SAMPLES`; ``"linear"``/``"steady"`` on a nonlinear model; no
        unique steady state; a wrongly sized initial state.
    ConfigError
        Bad `dt_s`, `method`, `initial` or input names/shapes.
    DataQualityError
        Non-finite input values.
    DivergenceError
        A signal overflowed although every input is finite: the model (or a loop of it)
        is unstable; the message names the part and its pole.
    """
    dt_s = _check_dt(dt_s)
    if method not in ("auto", "linear", "per_sample"):
        raise ConfigError(f"method={method!r}; allowed: 'auto', 'linear', 'per_sample'")
    u = _input_matrix(model, inputs)
    _check_delay_length(model, dt_s, u.shape[0])
    blocks = _discretise(model, dt_s)
    n_x = sum(len(db.b) + db.n_delay for db in blocks)

    steady = isinstance(initial, str) and initial == "steady"
    if method == "linear":
        _require_linear(model, "method='linear'")
    if steady:
        _require_linear(model, "initial='steady'")
    if method == "auto":
        method = "linear" if model.is_linear and n_x <= MAX_LIFTED_STATES else "per_sample"
    system = _assemble(model, blocks, dt_s) if method == "linear" or steady else None

    x0 = _initial_state(model, initial, system, u, n_x)

    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is reported below
        if method == "linear":
            assert system is not None
            y = _lifted_response(system.a, system.b, system.c, system.d, u, x0)
        else:
            y = per_sample_response(model, blocks, u, x0)
    if not np.isfinite(y).all():  # the inputs are finite (checked above): the model grew
        from pipeline.models.stability import divergence_message

        raise DivergenceError(divergence_message(model, y, dt_s=dt_s))

    names = model.block_names
    signals = {name: np.ascontiguousarray(y[:, i]) for i, name in enumerate(names)}
    out_index = [names.index(name) for name in model.outputs]
    return SimulationResult(
        t_s=np.arange(u.shape[0]) * dt_s,
        outputs=y[:, out_index].copy(),
        signals=signals,
        output_names=model.outputs,
        dt_s=dt_s,
        method=method,
    )


def _initial_state(model: Model, initial: Any, system: DiscreteStateSpace | None,
                   u: np.ndarray, n_x: int) -> np.ndarray:
    """The state at sample 0 for :func:`simulate`'s ``initial``."""
    if isinstance(initial, str):
        if initial == "rest":
            return np.zeros(n_x)
        if initial == "steady":
            assert system is not None
            return _steady_state(model, system, u[0])
        raise ConfigError(f"initial={initial!r}; allowed: 'rest', 'steady' or a state vector")
    x0 = np.asarray(initial, dtype=float)
    if x0.shape != (n_x,) or not np.all(np.isfinite(x0)):
        raise ModelError(
            f"model {model.name!r}: initial state has shape {x0.shape} (finite: "
            f"{bool(np.all(np.isfinite(x0)))}); expected {n_x} finite values in the "
            "layout of state_names(model, dt_s=...)"
        )
    return x0


def _steady_state(model: Model, system: DiscreteStateSpace, u0: np.ndarray) -> np.ndarray:
    """Solve ``x = a x + b u0`` (unique equilibrium required)."""
    lhs = np.eye(system.a.shape[0]) - system.a
    if lhs.size and np.linalg.cond(lhs) > 1e12:
        poles = np.linalg.eigvals(system.a)
        at_one = int(np.sum(np.abs(poles - 1.0) < 1e-9))
        raise ModelError(
            f"model {model.name!r}: initial='steady' has no unique steady state "
            f"({at_one} pole(s) at z=1: an integrator outside a feedback loop drifts for "
            "any nonzero net input); use initial='rest' with inputs as deviations"
        )
    return np.linalg.solve(lhs, system.b @ u0) if lhs.size else np.zeros(0)
