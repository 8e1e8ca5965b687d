"""Sample period from the signals themselves: the α_T criterion (method.md §3).

α_T of one signal — the relative mean-square error of its half-period hold, the mapping of
a hold of ``m`` record samples to a hold period, the spectral form used above a noise
floor — is measured by :mod:`pipeline.identification.hold_error` (its functions are re-exported here).
Targets: about 5 % on inputs and 1 % on outputs, and the smallest ``T`` over the signals
that set it wins (:func:`choose_sample_period`).

Resampling to ``T`` is average-then-decimate (:func:`resample_average`), which is the
anti-alias filter the thesis' recorders had.

Integrating outputs: α_T of the first difference
-------------------------------------------------
For an integrating output (a drum level, a tank) the estimator regresses the first
difference ``Δy(k) = y(k) - y(k-1)`` (method.md §1, eq. 3.15), so that is the signal whose
reconstruction ``T`` must keep accurate, and α_T is measured on ``Δy`` (``integrating=``).
The level itself is a random-walk-like signal: its spectrum is the rate's divided by
``ω²``, so its slow wander dominates ``mean(y²)`` and α_T on the level tolerates holds
far longer than the fast part of the response (a boiler drum with a 15 s swell/shrink
got ``T = 22 s``, the simulated one in tests/identification/test_sampling_integrating.py 24 s; measured
on ``Δy`` of the noise-free record, 4.4 s).  ``Δy`` is sampled every ``dt`` like the
level, so the hold-period mapping is unchanged; α_T is scale-free, so ``Δy ≈ ẏ·dt``
measures ``ẏ``.

A first difference amplifies sample-to-sample noise: a level sensor's white noise of
half a millimetre already dominates ``Δy`` of that drum at a 1 s record period, and α_T
of ``Δy`` then measures the noise (it misses a 1 % target at every hold).  The record
period is then a poor answer, not a safe one: with slowly moving inputs the per-lag
estimates at 1 s scatter, and the simulated drum's wrong-way peak read off the data came
out 0.51 instead of 0.32 (0.32 at the 5 s chosen here).  α_T is defined on the signal,
not on the sensor's noise, so when an integrating output's ``Δy`` misses its target at
the record period, α_T is measured on the part of ``Δy``'s spectrum that stands above
the noise floor (:func:`pipeline.identification.hold_error.alpha_above_noise_floor`: the spectral form
of the hold error on the Welch spectrum minus a floor of white level noise).  What hides
under the floor is not seen, so ``T`` lengthens as the noise grows — on the drum
simulation (swell time constant 15 s, six records each): 4.4-4.6 s noise-free, 5.5-5.9 s
with 2 mm of noise, 6.4-7.3 s with 1 cm.  A rate that truly changes every sample (a
random-walk level) is not mistaken for noise: its flat spectrum stands above the floor's
rising one, and the record period is used as before.  Self-regulating outputs and inputs
are measured as before (their noise is not amplified by a difference); when one of them
misses its target at the record period and its lag-1 autocorrelation (near +1 for a
signal the record resolves, near 0 for white noise) is below :data:`NOISE_RHO1`, the
note blames the noise rather than the record.

Step-wise (held) signals do not set T
-------------------------------------
A piecewise-constant signal — a held setpoint, an exception-reported tag gridded with
hold — has at least :data:`STEPWISE_UNCHANGED_FRACTION` of its consecutive samples equal.
Its α_T is made by its few step instants alone (a hold is wrong only across a step), so
it measures how often the signal steps, not a frequency content the model could miss:
rare steps give an absurdly long preferred ``T`` (15-46 min for the fractionator
export's setpoints, 99.5 % unchanged, on its 60 s record), frequent steps an absurdly
short one.  The model (3.12) holds such an input exactly apart from where inside a
sample each step falls, which average-then-decimate turns into a one-sample ramp — an
error of one sample of the response, whatever ``T``.  So step-wise signals are measured
and reported but do not set ``T``; the continuously moving signals do.  Only when every
signal is step-wise do they set it (with a note).

A sample period the N_p search can use
--------------------------------------
A ``T`` is not chosen when the record at ``T`` is too short for the default N_p search
(:func:`search_fits`): the largest decimation that still fits is taken instead, and
``SamplePeriodChoice.reduced_reason`` says so (written to ``checks.json`` → ``sampling``).
A shorter ``T`` keeps the α_T targets (α_T rises with ``T``); a longer one with a
search that cannot run gives no result at all.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.signal

from pipeline.errors import ConfigError, DataQualityError
from pipeline.identification.hold_error import (
    alpha_above_noise_floor,
    alpha_t,
    alpha_t_curve,
    alpha_t_first_order,
    as_signal,
    check_hold,
    crossing_hold,
    hold_error_ratio,
    hold_period_s,
)

__all__ = [
    "SamplePeriodChoice",
    "alpha_t",
    "alpha_t_curve",
    "alpha_t_first_order",
    "choose_sample_period",
    "hold_period_s",
    "resample_average",
    "resample_average_masked",
    "sample_period_s",
    "search_fits",
    "NOISE_RHO1",
    "SEARCH_N_P_MIN",
    "SEARCH_OBS_PER_UNKNOWN",
    "STEPWISE_UNCHANGED_FRACTION",
]

ROLES = ("input", "output")

STEPWISE_UNCHANGED_FRACTION = 0.9
"""A signal with at least this fraction of consecutive samples unchanged is step-wise
(held) and does not set ``T`` (module notes).  Held setpoints on the fractionator export
are 99.5-99.7 % unchanged, its continuously moving flows and analysers 0-0.1 %."""

NOISE_RHO1 = 0.5
"""Below this lag-1 autocorrelation the analysed signal is dominated by sample-to-sample
noise (white: 0, differenced white: -0.5; a first-order signal sampled at a tenth of its
time constant: 0.9); a missed α_T target is then blamed on the noise in the note."""

SEARCH_N_P_MIN = 3
"""Shortest horizon (lags) the default N_p search must be able to try (``search.n_p_min``'s
default)."""

SEARCH_OBS_PER_UNKNOWN = 20
"""Observations per unknown the record at ``T`` must hold for the default N_p search
(:func:`search_fits`): two disjoint windows (method.md §5 judges N_d by comparing them) of
10 observations per unknown each (method.md §5: N_d starts around 10·N_p for each of an
output's N_p·N_x unknowns)."""


def search_fits(n_samples: int, n_inputs: int, *, n_p_min: int = SEARCH_N_P_MIN) -> bool:
    """Whether a record of ``n_samples`` at ``T`` can hold the default N_p search.

    The rule (kept simple on purpose; the search's own defaults may change): the record
    must hold ``SEARCH_OBS_PER_UNKNOWN · n_p_min · n_inputs`` observations — two disjoint
    windows of 10 observations per unknown at the shortest horizon ``n_p_min`` — after the
    ``n_p_min`` lead-in samples an observation needs (``n_p_min - 1`` lags and one for the
    first difference of an integrating output).

    Parameters
    ----------
    n_samples : int
        Samples of the record at the sample period ``T``.
    n_inputs : int
        Number of inputs (each output has ``N_p · n_inputs`` unknowns); at least 1 is
        assumed.
    n_p_min : int
        Shortest horizon the search must be able to try (lags), default
        :data:`SEARCH_N_P_MIN`.

    Returns
    -------
    bool
        True when the record is long enough.
    """
    return int(n_samples) - int(n_p_min) >= (
        SEARCH_OBS_PER_UNKNOWN * int(n_p_min) * max(int(n_inputs), 1))


# ------------------------------------------------------------ choosing the period
@dataclass(frozen=True)
class SamplePeriodChoice:
    """The chosen sample period and the α_T evidence behind it.

    Attributes
    ----------
    dt_s : float
        Chosen sample period ``T`` (s): ``decimation * grid_dt_s``.
    decimation : int
        Resampling factor from the record (average-then-decimate by this many samples).
    grid_dt_s : float
        Sample period of the record (s).
    alpha_t : dict[str, float]
        Per signal, α_T at the chosen ``T`` (half-period hold ``T/2``).
    preferred_dt_s : dict[str, float]
        Per signal, the ``T`` at which α_T reaches that signal's target (s); ``inf``
        if not reached within the longest hold measured (then the longest measured
        period is used, see notes).
    targets : dict[str, float]
        Per signal, the α_T target used (by role).
    roles : dict[str, str]
        ``"input"`` or ``"output"`` per signal.
    limiting_signal : str
        The signal whose preferred ``T`` is smallest among those that set ``T`` (step-wise
        signals do not, module notes).
    notes : tuple of str
        Human-readable remarks (record sampled too slowly, target not reached, ...).
    measured_on : dict[str, str]
        Per signal, what α_T was measured on: ``"signal"``, ``"first difference"``
        (integrating outputs) or ``"first difference above the noise floor"`` (module
        notes).
    stepwise : tuple of str
        Signals recognised as step-wise (held); they do not set ``T``.
    alpha_t_dt_s : float or None
        The ``T`` the α_T targets alone chose (s); ``None`` means the same as ``dt_s``.
    reduced_reason : str or None
        Why ``dt_s`` is shorter than ``alpha_t_dt_s`` (the record at that ``T`` could not
        hold the default N_p search, :func:`search_fits`); ``None`` when it is not.
    """

    dt_s: float
    decimation: int
    grid_dt_s: float
    alpha_t: dict[str, float]
    preferred_dt_s: dict[str, float]
    targets: dict[str, float]
    roles: dict[str, str]
    limiting_signal: str
    notes: tuple[str, ...] = field(default_factory=tuple)
    measured_on: dict[str, str] = field(default_factory=dict)
    stepwise: tuple[str, ...] = field(default_factory=tuple)
    alpha_t_dt_s: float | None = None
    reduced_reason: str | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict (``inf`` preferred periods become ``None``)."""
        return {
            "dt_s": self.dt_s,
            "decimation": self.decimation,
            "record_dt_s": self.grid_dt_s,  # the result-file key stays (issue 35)
            "alpha_t": dict(self.alpha_t),
            "preferred_dt_s": {
                k: (v if np.isfinite(v) else None) for k, v in self.preferred_dt_s.items()
            },
            "targets": dict(self.targets),
            "roles": dict(self.roles),
            "measured_on": dict(self.measured_on),
            "stepwise": list(self.stepwise),
            "limiting_signal": self.limiting_signal,
            "alpha_t_dt_s": self.dt_s if self.alpha_t_dt_s is None else self.alpha_t_dt_s,
            "reduced_reason": self.reduced_reason,
            "notes": list(self.notes),
        }

    def __str__(self) -> str:
        lines = [
            f"sample period T = {self.dt_s:g} s (decimation {self.decimation} of "
            f"{self.grid_dt_s:g} s), limited by {self.limiting_signal}"
        ]
        if self.reduced_reason:
            lines.append(f"  shorter than the α_T choice: {self.reduced_reason}")
        for name in self.alpha_t:
            on = self.measured_on.get(name, "signal")
            lines.append(
                f"  {name} ({self.roles[name]}"
                f"{', ' + on if on != 'signal' else ''}"
                f"{', step-wise: does not set T' if name in self.stepwise else ''}): "
                f"alpha_t = {self.alpha_t[name]:.4f} (target {self.targets[name]:.3f}), "
                f"preferred T = {self.preferred_dt_s[name]:g} s"
            )
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)


def _signals_dict(signals, names) -> dict[str, np.ndarray]:
    if isinstance(signals, Mapping):
        if names is not None:
            raise ConfigError("give names only with a 2-D array; a dict already names its signals")
        out = {str(k): np.asarray(v, dtype=float) for k, v in signals.items()}
    else:
        arr = np.asarray(signals, dtype=float)
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2:
            raise DataQualityError(
                f"signals must be a dict of 1-D arrays or a 2-D array (samples x signals); "
                f"got shape {arr.shape}"
            )
        if names is None or len(names) != arr.shape[1]:
            raise ConfigError(
                f"a 2-D signals array with {arr.shape[1]} column(s) needs names= with one "
                f"name per column; got {names!r}"
            )
        out = {str(n): arr[:, i] for i, n in enumerate(names)}
    if not out:
        raise DataQualityError("no signals given; choose_sample_period needs at least one")
    lengths = {k: v.shape for k, v in out.items()}
    if len({v for v in lengths.values()}) != 1 or any(len(s) != 1 for s in lengths.values()):
        raise DataQualityError(
            f"every signal must be 1-D with the same length; got shapes {lengths}"
        )
    return out


def _roles_dict(roles, names: Sequence[str]) -> dict[str, str]:
    if isinstance(roles, Mapping):
        missing = [n for n in names if n not in roles]
        if missing:
            raise ConfigError(
                f"roles has no entry for signal(s) {missing}; give 'input' or 'output'"
            )
        out = {n: str(roles[n]) for n in names}
    else:
        roles = list(roles)
        if len(roles) != len(names):
            raise ConfigError(
                f"roles has {len(roles)} entries for {len(names)} signals {list(names)}; "
                "give one 'input'/'output' per signal"
            )
        out = dict(zip(names, map(str, roles)))
    bad = {n: r for n, r in out.items() if r not in ROLES}
    if bad:
        raise ConfigError(f"unknown role(s) {bad}; each role must be 'input' or 'output'")
    return out


def sample_period_s(decimation: int, grid_dt_s: float) -> float:
    """The estimation sample period ``T`` (s): `decimation` grid periods -- where ``T``
    is computed, for estimation and discrepancy jobs alike.

    Parameters
    ----------
    decimation : int
        Grid samples per estimation sample.
    grid_dt_s : float
        The grid period (s).

    Returns
    -------
    float
    """
    return float(decimation * grid_dt_s)


def choose_sample_period(
    signals,
    *,
    grid_dt_s: float,
    roles,
    names: Sequence[str] | None = None,
    integrating: Mapping[str, bool] | None = None,
    target_input: float = 0.05,
    target_output: float = 0.01,
    max_hold_samples: int | None = None,
    detrend: bool = True,
    n_search_samples: int | None = None,
    n_p_min: int = SEARCH_N_P_MIN,
) -> SamplePeriodChoice:
    """Choose the sample period ``T`` from α_T targets (method.md §3).

    Parameters
    ----------
    signals : dict[str, array (N,)] or array (N, k)
        The record's signals, sampled every ``grid_dt_s`` without gaps.
    grid_dt_s : float
        Sample period of the record: its grid period (s).
    roles : dict[str, str] or sequence of str
        ``"input"`` or ``"output"`` per signal (by name, or in column order).
    names : sequence of str, optional
        Column names when ``signals`` is a 2-D array.
    integrating : mapping of str to bool, optional
        Per output, whether it is integrating (the job's ``signals.outputs.<name>.
        integrating``); α_T of an integrating output is measured on its first difference
        (module notes).  Missing names are not integrating; only outputs may be.
    target_input, target_output : float
        α_T targets (defaults 5 % and 1 %, the thesis' values).
    max_hold_samples : int, optional
        Longest hold examined (record samples); default ``N // 20`` so that at least
        20 holds fit in the record.
    detrend : bool
        Remove each analysed signal's mean and linear trend first (the criterion concerns
        the fluctuations; a trend would dominate mean(x²)).
    n_search_samples : int, optional
        Samples (at ``grid_dt_s``) the N_p search will have — the whole record's usable
        samples when α_T is measured on a clean stretch of it; default ``N``.
    n_p_min : int
        Shortest horizon the search must be able to try at ``T`` (:func:`search_fits`);
        default :data:`SEARCH_N_P_MIN`.

    Returns
    -------
    SamplePeriodChoice

    Notes
    -----
    Per signal, the hold ``T'`` at which α_T reaches its target is found by linear
    interpolation between integer hold lengths (a hold of ``m`` samples measures
    ``T' = (m-1)·grid_dt_s``, see the module notes); its preferred period is ``2 T'``.
    The chosen ``T`` is the smallest preferred period of the signals that set ``T``
    (all but the step-wise ones, module notes), rounded **down** to an integer
    multiple of ``grid_dt_s`` (α_T rises with ``T``, so rounding down keeps every signal at or
    below its target), and never below ``grid_dt_s``: when a signal needs ``T < grid_dt_s`` the
    record is sampled too slowly for its target (or the signal is noise-dominated — the
    note tells which), ``T = grid_dt_s`` and a note says so.  When a signal stays below target
    over every hold examined, its preferred period is ``inf`` and it does not limit
    ``T``; if no signal reaches its target, ``T`` is the longest period examined,
    ``2 (max_hold_samples - 1) grid_dt_s``, with a note.  Finally, when the record at ``T``
    cannot hold the default N_p search (:func:`search_fits` with ``n_search_samples``
    and the number of inputs), ``T`` is lowered to the largest multiple of ``grid_dt_s`` at
    which it can, and ``reduced_reason`` says so.

    Raises
    ------
    ConfigError
        Bad ``grid_dt_s``, roles, targets, names or ``integrating``.
    DataQualityError
        A signal is non-finite, too short or constant after detrending (for an integrating
        output: its first difference is).
    """
    _check_period_and_targets(grid_dt_s, target_input, target_output)
    sig = _signals_dict(signals, names)
    role = _roles_dict(roles, list(sig))
    diff = _integrating_dict(integrating, role)
    n = next(iter(sig.values())).size
    max_hold = _max_hold(n, max_hold_samples)
    targets = {k: (target_input if role[k] == "input" else target_output) for k in sig}
    notes: list[str] = []
    measured, preferred = _measure(sig, diff, targets, max_hold, grid_dt_s, detrend, notes)
    stepwise, setting = _setting_signals(sig, preferred, grid_dt_s, notes)
    limiting, decimation = _decimation({k: preferred[k] for k in setting}, targets, max_hold,
                                       grid_dt_s, notes, measured)
    n_inputs = sum(r == "input" for r in role.values())
    n_search = n if n_search_samples is None else int(n_search_samples)
    final, reason = _search_decimation(decimation, n_search, n_inputs, n_p_min, grid_dt_s)
    return SamplePeriodChoice(
        dt_s=sample_period_s(final, grid_dt_s), decimation=final, grid_dt_s=float(grid_dt_s),
        alpha_t=_alpha_at_decimation(measured, final), preferred_dt_s=preferred,
        targets=targets, roles=role, limiting_signal=limiting, notes=tuple(notes),
        measured_on={k: m.measured_on for k, m in measured.items()}, stepwise=stepwise,
        alpha_t_dt_s=sample_period_s(decimation, grid_dt_s), reduced_reason=reason)


def _max_hold(n: int, max_hold_samples: int | None) -> int:
    """The longest hold α_T examines (a record of at least 40 samples: 20 holds of 2)."""
    if n < 40:
        raise DataQualityError(
            f"record has {n} samples; α_T needs at least 40 (20 holds of 2 samples) to "
            "choose a sample period — supply a longer record"
        )
    return max(n // 20 if max_hold_samples is None else check_hold(max_hold_samples, n), 2)


def _setting_signals(sig: dict, preferred: dict, dt_s: float, notes: list
                     ) -> tuple[tuple, list]:
    """The step-wise signals and the signals that set T (all but the step-wise ones, or
    every signal when all are step-wise; a note says so)."""
    stepwise = tuple(k for k, x in sig.items() if _is_stepwise(as_signal(x, k)))
    setting = [k for k in sig if k not in stepwise] or list(sig)
    if stepwise:
        notes.append(_stepwise_note(stepwise, preferred, dt_s,
                                    all_stepwise=len(setting) == len(sig)))
    return stepwise, setting


def _check_period_and_targets(dt_s, target_input, target_output) -> None:
    """Reject a non-positive record period or a target outside (0, 1)."""
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    for label, tgt in (("target_input", target_input), ("target_output", target_output)):
        if not (0 < tgt < 1):
            raise ConfigError(f"{label} must lie in (0, 1) (a fraction, 0.05 = 5 %); got {tgt!r}")


def _integrating_dict(integrating, role: dict[str, str]) -> dict[str, bool]:
    """Per signal, whether α_T is measured on its first difference (outputs only)."""
    out = {k: False for k in role}
    if integrating is None:
        return out
    if not isinstance(integrating, Mapping):
        raise ConfigError(
            f"integrating must be a mapping of output name to bool; got {integrating!r}")
    unknown = sorted(set(map(str, integrating)) - set(role))
    if unknown:
        raise ConfigError(
            f"integrating names signal(s) {unknown} that are not among the signals; "
            f"allowed: {', '.join(k for k, r in role.items() if r == 'output')}")
    for k, v in integrating.items():
        if not isinstance(v, (bool, np.bool_)):
            raise ConfigError(f"integrating[{k!r}] must be True or False; got {v!r}")
        if v and role[str(k)] != "output":
            raise ConfigError(
                f"integrating[{k!r}] is True but {k!r} is an {role[str(k)]}; only outputs "
                "integrate (their first difference is what the estimator regresses)")
        out[str(k)] = bool(v)
    return out


def _is_stepwise(x: np.ndarray) -> bool:
    """At least :data:`STEPWISE_UNCHANGED_FRACTION` of consecutive samples equal (to
    round-off of the signal's magnitude)."""
    tol = 1e-12 * float(np.max(np.abs(x)))
    return float(np.mean(np.abs(np.diff(x)) <= tol)) >= STEPWISE_UNCHANGED_FRACTION


def _stepwise_note(stepwise: tuple[str, ...], preferred: dict[str, float], dt_s: float,
                   *, all_stepwise: bool) -> str:
    """The note on step-wise signals: they do not set T (or, all step-wise, they do)."""
    pref = ", ".join(f"{k} {preferred[k]:.4g} s" if np.isfinite(preferred[k]) else f"{k} -"
                     for k in stepwise)
    if all_stepwise:
        return (f"every signal is step-wise (held: >= {STEPWISE_UNCHANGED_FRACTION:.0%} of "
                f"samples unchanged; preferred T {pref}); with no continuously moving "
                "signal they set T, though their α_T reflects how often they step, not "
                "the dynamics — set sampling.dt_s in the job YAML if the plant's response "
                "times are known")
    return (f"step-wise signal(s) {', '.join(stepwise)} (held: >= "
            f"{STEPWISE_UNCHANGED_FRACTION:.0%} of samples unchanged) do not set T: their "
            f"α_T reflects how often they step, not the dynamics (preferred T {pref})")


def _analysed(raw: np.ndarray, name: str, integrating: bool, detrend: bool
              ) -> tuple[np.ndarray, float]:
    """The signal α_T is measured on (the first difference of an integrating output),
    detrended or mean-free, with its sum of squares."""
    x = np.diff(raw) if integrating else raw
    x = scipy.signal.detrend(x, type="linear") if detrend else x - x.mean()
    sum_sq = float(x @ x)
    scale = float(raw @ raw) if not integrating else float(np.diff(raw) @ np.diff(raw))
    if sum_sq <= 1e-24 * max(scale, 1e-300):
        what = (" (an integrating output): its first difference" if integrating else "")
        raise DataQualityError(
            f"signal {name!r}{what} is constant (after removing mean"
            f"{' and trend' if detrend else ''}); α_T is undefined: drop it from the job "
            "or pick a window where it moves"
        )
    return x, sum_sq


@dataclass(frozen=True)
class _Measured:
    """How α_T of one signal is measured: ``alpha_of(m)`` for a hold of ``m`` samples."""

    x: np.ndarray  # the analysed signal (mean-free)
    alpha_of: Callable[[int], float]
    measured_on: str


def _measure(sig: dict[str, np.ndarray], diff: dict[str, bool], targets: dict[str, float],
             max_hold: int, dt_s: float, detrend: bool, notes: list[str]
             ) -> tuple[dict[str, _Measured], dict[str, float]]:
    """Per signal, how α_T is measured and the preferred ``T`` (``inf`` with a note when
    the target is not reached).  An integrating output whose first difference misses its
    target at the record period is measured above its noise floor (module notes)."""
    measured: dict[str, _Measured] = {}
    preferred: dict[str, float] = {}
    for name, raw in sig.items():
        x, sum_sq = _analysed(as_signal(raw, name), name, diff[name], detrend)
        m = _Measured(x, lambda k, x=x, s=sum_sq: hold_error_ratio(x, k, s),
                      "first difference" if diff[name] else "signal")
        hold = min(max_hold, x.size)
        t_hold, reached = crossing_hold(m.alpha_of, targets[name], hold)
        if diff[name] and reached and 2.0 * t_hold < 1.0:
            floor = alpha_above_noise_floor(x)
            if floor is not None:
                t2, r2 = crossing_hold(floor[0], targets[name], hold)
                notes.append(
                    f"{name}: α_T of its first difference reaches {targets[name]:g} already "
                    f"at T = {2 * t_hold * dt_s:.3g} s, below the record period; a floor of "
                    f"white level noise (a sensor's, amplified by the difference) holds "
                    f"{floor[1]:.0%} of its variance (lag-1 autocorrelation "
                    f"{_lag1_correlation(x):.2f}), so α_T is measured on the part of its "
                    "spectrum above that floor (dynamics hidden under the floor are not "
                    "seen: the noisier the level, the longer this T)")
                m = _Measured(x, floor[0], "first difference above the noise floor")
                t_hold, reached = t2, r2
        measured[name] = m
        if reached:
            preferred[name] = 2.0 * t_hold * dt_s
        else:
            preferred[name] = float("inf")
            notes.append(
                f"{name}: α_T stays below its target {targets[name]:g} for every hold up to "
                f"{max_hold} samples (T up to {2 * (max_hold - 1) * dt_s:g} s); it does not "
                "limit T"
            )
    return measured, preferred


def _lag1_correlation(x: np.ndarray) -> float:
    """Lag-1 autocorrelation of a mean-free signal."""
    return float(x[1:] @ x[:-1]) / max(float(x @ x), 1e-300)


def _decimation(preferred: dict[str, float], targets: dict[str, float], max_hold: int,
                dt_s: float, notes: list[str],
                measured: dict[str, _Measured]) -> tuple[str, int]:
    """The limiting signal and the decimation: its preferred ``T`` rounded down to whole
    record samples, at least 1 (notes when no target is reached or the record is slow)."""
    limiting = min(preferred, key=preferred.get)
    t_pref = preferred[limiting]
    if not np.isfinite(t_pref):
        t_pref = 2.0 * (max_hold - 1) * dt_s
        notes.append(
            f"no signal reaches its α_T target within holds of {max_hold} samples; T set to "
            f"the longest period examined, {t_pref:g} s (raise max_hold_samples to look further)"
        )
    # Round DOWN (α_T grows with T); the small tolerance keeps exact multiples exact.
    decimation = int(np.floor(t_pref / dt_s * (1 + 1e-9)))
    if decimation < 1:
        decimation = 1
        note = (f"record sampled too slowly for {limiting}: α_T target {targets[limiting]:g} "
                f"needs T = {t_pref:.4g} s but the record has dt_s = {dt_s:g} s; T = dt_s "
                "(the record's own period) is used and α_T there exceeds the target")
        rho = _lag1_correlation(measured[limiting].x)
        if measured[limiting].measured_on.endswith("noise floor"):
            note += (". Even above its noise floor its first difference moves faster than "
                     "the record resolves")
        elif rho < NOISE_RHO1:
            note += (f". Its analysed signal's lag-1 autocorrelation is {rho:.2f} (a signal "
                     "the record resolves has one near +1): sample-to-sample noise dominates "
                     "it, so α_T measures the noise, not the dynamics; set sampling.dt_s in "
                     "the job YAML if the dynamics are known to be slower (a T much shorter "
                     "than the inputs' scatters the per-lag estimates)")
        notes.append(note)
    return limiting, decimation


def _search_decimation(decimation: int, n_search: int, n_inputs: int, n_p_min: int,
                       dt_s: float) -> tuple[int, str | None]:
    """The largest decimation ``<= decimation`` whose record holds the default N_p search
    (:func:`search_fits`), and the reason when it is smaller (None when not)."""
    if search_fits(n_search // decimation, n_inputs, n_p_min=n_p_min):
        return decimation, None
    need = SEARCH_OBS_PER_UNKNOWN * n_p_min * max(n_inputs, 1) + n_p_min
    fits = [d for d in range(decimation - 1, 0, -1)
            if search_fits(n_search // d, n_inputs, n_p_min=n_p_min)]
    final = fits[0] if fits else 1
    why = (f"at the α_T choice T = {decimation * dt_s:g} s the record holds "
           f"{n_search // decimation} samples, fewer than the {need} the N_p search needs "
           f"({SEARCH_OBS_PER_UNKNOWN} observations per unknown x {n_p_min} lags x "
           f"{max(n_inputs, 1)} input(s) + {n_p_min} lead-in: two disjoint windows of 10 "
           "per unknown at the shortest horizon); ")
    if fits:
        why += (f"T = {final * dt_s:g} s, the longest at which it fits "
                f"({n_search // final} samples), is used (α_T is lower there)")
    else:
        why += (f"even the record period {dt_s:g} s gives only {n_search} samples, so T = "
                f"{dt_s:g} s is used and the search will report the shortage — supply a "
                "longer record")
    return final, why


def _alpha_at_decimation(measured: dict[str, _Measured], decimation: int
                         ) -> dict[str, float]:
    """Per signal, α_T at the chosen ``T`` (hold ``T/2``, interpolated between integer holds)."""
    t_hold = 0.5 * decimation  # T' = T/2 in record samples, i.e. m - 1
    alpha_chosen = {}
    for name, m in measured.items():
        lo = int(np.floor(t_hold)) + 1  # hold m with (m-1) <= T' (m>=1)
        a_lo = 0.0 if lo == 1 else m.alpha_of(lo)
        frac = t_hold - (lo - 1)
        if frac > 0 and lo + 1 <= m.x.size:
            alpha_chosen[name] = float(a_lo + frac * (m.alpha_of(lo + 1) - a_lo))
        else:
            alpha_chosen[name] = float(a_lo)
    return alpha_chosen


# -------------------------------------------------------------------- resampling
def resample_average(x, factor: int) -> np.ndarray:
    """Average-then-decimate: means of consecutive blocks of ``factor`` samples.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, k)
        Uniformly sampled signal(s), time along axis 0.
    factor : int
        Decimation factor (>= 1).  The incomplete tail block is dropped.

    Returns
    -------
    ndarray, shape (N // factor,) or (N // factor, k)
        Block ``i`` is the mean of samples ``i*factor .. (i+1)*factor - 1``.  NaN in a
        block propagates (use :func:`resample_average_masked` for masked data).
    """
    arr = np.asarray(x, dtype=float)
    f = _check_factor(factor, arr)
    n_out = arr.shape[0] // f
    return arr[: n_out * f].reshape((n_out, f) + arr.shape[1:]).mean(axis=1)


def _check_factor(factor, arr: np.ndarray) -> int:
    if arr.ndim not in (1, 2):
        raise DataQualityError(f"x must have shape (N,) or (N, k); got {arr.shape}")
    if isinstance(factor, (bool, np.bool_)) or not float(factor).is_integer() or factor < 1:
        raise ConfigError(f"factor must be a positive integer (decimation); got {factor!r}")
    f = int(factor)
    if arr.shape[0] < f:
        raise DataQualityError(
            f"record of {arr.shape[0]} samples is shorter than one block of factor={f}; "
            "use a smaller factor or a longer record"
        )
    return f


def resample_average_masked(
    x, good, factor: int, *, max_bad_fraction: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Average-then-decimate with a quality mask.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, k)
        Signal(s); bad samples may hold NaN.
    good : array_like of bool, shape like ``x`` or (N,)
        ``True`` where a sample is good.  A 1-D mask applies to every column.
    factor : int
        Decimation factor.
    max_bad_fraction : float
        A decimated sample is good when the fraction of bad source samples in its block
        is ``<= max_bad_fraction``; default 0 (any bad source sample makes it bad).
        Good blocks average their good samples only.

    Returns
    -------
    x_dec : ndarray, shape (N // factor,) or (N // factor, k)
        Block means of the good samples; NaN where the block is bad.
    good_dec : ndarray of bool, same shape
    """
    arr = np.asarray(x, dtype=float)
    f = _check_factor(factor, arr)
    g = np.asarray(good, dtype=bool)
    if g.shape != arr.shape:
        if g.ndim == 1 and arr.ndim == 2 and g.shape[0] == arr.shape[0]:
            g = np.broadcast_to(g[:, None], arr.shape)
        else:
            raise DataQualityError(
                f"good has shape {g.shape} but x has {arr.shape}; give one flag per sample "
                "(shape (N,)) or per value (same shape as x)"
            )
    if not (0.0 <= max_bad_fraction < 1.0):
        raise ConfigError(f"max_bad_fraction must lie in [0, 1); got {max_bad_fraction!r}")
    n_out = arr.shape[0] // f
    shape = (n_out, f) + arr.shape[1:]
    gb = g[: n_out * f].reshape(shape)
    xb = np.where(gb, arr[: n_out * f].reshape(shape), 0.0)
    n_good = gb.sum(axis=1)
    good_dec = (f - n_good) <= max_bad_fraction * f + 1e-12
    good_dec &= n_good > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        means = xb.sum(axis=1) / n_good
    return np.where(good_dec, means, np.nan), good_dec
