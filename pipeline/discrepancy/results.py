"""What the discrepancy analysis returns: candidates, series and the result."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.discrepancy.config import DiscrepancyConfig
from pipeline.discrepancy.effects import Effect
from pipeline.models.model import Model


VERDICTS = ("effect_found", "inconclusive", "no_significant_effect")


@dataclass(frozen=True)
class Candidate:
    """One fitted candidate effect (ranked in :attr:`DiscrepancyResult.candidates`).

    Attributes
    ----------
    effect : Effect
        Name, location, fitted parameters, equivalent locations.
    criterion : float
        Whitened BIC on the fit part (lower is better; the nominal model's is
        ``DiscrepancyResult.noise["bic_nominal"]``).
    delta_bic : float
        Nominal BIC minus this BIC (> ``bic_margin`` needed).
    n_parameters : int
    holdout_rms : dict of str -> float
        Held-out output-error RMS per output (engineering units).
    holdout_z : float
        Held-out z statistic: whitened SSE drop against the nominal model over its
        null standard deviation.
    holdout_gap : float
        Held-out output-error RMS in the units of ``DiscrepancyResult.gap`` (one
        output: its units; several: each divided by its held-out std, pooled); must be
        below the nominal model's (``gap["holdout_rms_before"]``).
    screening_score : float
        Approximate whitened sum of squares explained at screening, minus the BIC penalty.
    passed : bool
        The statistical acceptance passed: the whitened tests (BIC margin, held-out z,
        held-out gap below the model's) or the plain held-out RMS test.
    gap_reduction : float
        ``1 - holdout_gap / (the model's held-out gap)``: how much of the gap of the model
        it was added to the candidate closes on held-out data (practical significance:
        at least ``min_gap_reduction`` for a finding).
    holdout_rms_p : float
        p-value of "no held-out RMS reduction" against the noise model's surrogate
        disturbances (:func:`pipeline.discrepancy.select.holdout_rms_noise_test`).
    passed_by : str
        Which acceptance passed: ``"whitened"``, ``"held-out RMS"``, ``"both"`` or ``""``.
    gap_reduction_low : float
        The share of the reference held-out gap the candidate closes where it closes the
        most -- on one output, or pooled -- at the one-sided 95 % lower confidence bound
        (each bound at 5 % over the gaps judged, free outputs' held-out levels left out),
        from surrogate disturbances of the candidate's own residual's noise model: what
        practical significance is judged on
        (:func:`pipeline.discrepancy.practical.practical_share`).  NaN for a candidate that
        failed the held-out tests (not computed: it would decide nothing).
    gap_reduction_low_output : str or None
        Where `gap_reduction_low` is measured: an output's name, or
        :data:`pipeline.discrepancy.practical.POOLED_GAP` for the pooled gap (None with it NaN).
    worse_on : tuple of str
        Outputs whose held-out errors the candidate makes larger than the model it was
        added to, beyond chance (:func:`pipeline.discrepancy.select.worse_outputs`): such
        a candidate fails.
    closed_loop_prediction_error_reduction : float
        With loops opened: the share of the closed loop's held-out one-step prediction
        error the candidate removes
        (:meth:`pipeline.discrepancy.closed_loop.ClosedLoop.prediction_error_reduction`;
        a checked candidate that does not narrow it fails); NaN when not checked (no
        loop opened, a sensor correction, an actuator nonlinearity seen outside the
        controlled variables).
    """

    effect: Effect
    criterion: float
    delta_bic: float
    n_parameters: int
    holdout_rms: dict[str, float]
    holdout_z: float
    holdout_gap: float
    screening_score: float
    passed: bool
    gap_reduction: float = math.nan
    holdout_rms_p: float = math.nan
    passed_by: str = ""
    gap_reduction_low: float = math.nan
    gap_reduction_low_output: str | None = None
    worse_on: tuple[str, ...] = ()
    closed_loop_prediction_error_reduction: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping (``name``, ``location``, ``parameters``, ``criterion``, ...)."""
        out = self.effect.to_dict()
        out.update(
            criterion=json_float(self.criterion),
            delta_bic=json_float(self.delta_bic),
            n_parameters=self.n_parameters,
            holdout_rms={k: json_float(v) for k, v in self.holdout_rms.items()},
            holdout_z=json_float(self.holdout_z),
            holdout_gap=json_float(self.holdout_gap),
            screening_score=json_float(self.screening_score),
            passed=self.passed,
            gap_reduction=json_float(self.gap_reduction),
            holdout_rms_p=json_float(self.holdout_rms_p),
            passed_by=self.passed_by,
            gap_reduction_low=json_float(self.gap_reduction_low),
            gap_reduction_low_output=self.gap_reduction_low_output,
            worse_on=list(self.worse_on),
            closed_loop_prediction_error_reduction=json_float(self.closed_loop_prediction_error_reduction),
        )
        return out


@dataclass(frozen=True)
class EffectStep:
    """One accepted effect of the chain (:attr:`DiscrepancyResult.effects`).

    Attributes
    ----------
    candidate : Candidate
        The effect as fitted and tested on the model it was added to.
    gap_before, gap_after : float
        Held-out gap (units of ``DiscrepancyResult.gap``) of that model and of the model
        with the effect.
    holdout_rms_after : dict of str -> float
        Held-out RMS per output after the effect (engineering units).
    """

    candidate: Candidate
    gap_before: float
    gap_after: float
    holdout_rms_after: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the candidate's fields plus the gap before and after this step."""
        return {**self.candidate.to_dict(), "gap_before": json_float(self.gap_before),
                "gap_after": json_float(self.gap_after),
                "holdout_rms_after": {k: json_float(v) for k, v in self.holdout_rms_after.items()}}


@dataclass(frozen=True)
class DiscrepancySeries:
    """Signals for plots (full record; arrays of shape (N,)).

    Attributes
    ----------
    t_s : ndarray
        Time since the first sample, s.
    measured, nominal, augmented : dict of str -> ndarray
        Measured outputs, nominal simulation, augmented simulation (with measurement
        offsets of a sensor_bias_drift effect) per measured output.
    residual_before, residual_after : dict of str -> ndarray
        ``measured - nominal`` and ``measured - augmented``.
    rolling_rms : dict of str -> ndarray
        Residual RMS in centred windows (``localization[out]["time_windows"]["window_s"]``).
    fit_start, holdout_start : int
        Sample indices: criteria use ``[fit_start, holdout_start)`` for fitting and
        ``[holdout_start, N)`` for judging.
    """

    t_s: np.ndarray
    measured: dict[str, np.ndarray]
    nominal: dict[str, np.ndarray]
    augmented: dict[str, np.ndarray]
    residual_before: dict[str, np.ndarray]
    residual_after: dict[str, np.ndarray]
    rolling_rms: dict[str, np.ndarray]
    fit_start: int
    holdout_start: int


@dataclass(frozen=True)
class DiscrepancyResult:
    """What :func:`analyse_discrepancy` found.

    Attributes
    ----------
    verdict : str
        ``"effect_found"``, ``"inconclusive"`` or ``"no_significant_effect"`` (of the
        first step: the nominal model).
    effect : Effect or None
        The first accepted effect (None unless ``effect_found``).
    candidates : tuple of Candidate
        Every exactly fitted candidate, best (lowest criterion) first.
    lookalikes : tuple of Candidate
        For ``inconclusive``: the accepted candidates too close to tell apart.
    localization : dict
        Per measured output (JSON-ready): see the module docstring, step 1.
    gap : dict
        ``holdout_rms_before``, ``holdout_rms_after``, ``reduction`` (= 1 - after/before)
        and ``per_output``; for one measured output in its units, for several the RMS
        over outputs of each output's RMS divided by its measured std (``units``).
    augmented_model : Model
        The nominal model with the accepted effect (the nominal model otherwise).  With
        a ``sensor_bias_drift`` effect the blocks are unchanged and the measured-side
        offsets are in :attr:`output_offsets`.
    output_offsets : dict of str -> ndarray
        Added to the augmented model's simulated outputs (zeros unless
        sensor_bias_drift).  :func:`pipeline.discrepancy.effects.predict_outputs` with the nominal
        model and :attr:`effect` reproduces :attr:`series` ``.augmented``.
    noise : dict
        Noise model per output (AR coefficients, innovation std) and the nominal BIC.
    screening : tuple of dict
        Screening score per candidate class (best first), also in ``localization``.
    series : DiscrepancySeries
    dt_s : float
    config : DiscrepancyConfig
    timings_s : dict of str -> float
        Wall time per stage.
    n_fit_simulations : int
        Exact simulations run by the fits (a cost measure).
    effects : tuple of EffectStep
        The accepted chain in order (the first is :attr:`effect`), each with the held-out
        gap after it; :attr:`augmented_model` holds all of them.
    minor_effects : tuple of Candidate
        Candidates that passed every statistical test but shrink the held-out gap by less
        than ``min_gap_reduction`` (at the step where the chain stopped).
    operating_point_shift : dict of str -> float
        With effects: the constant by which each free output's operating point moved for the final augmented model (``free_offsets``); :attr:`series`
        ``.augmented`` includes it.  Empty otherwise.
    equivalent_effects : tuple of Candidate
        With ``effect_found``: look-alikes of :attr:`effect` the data cannot tell apart
        (within ``lookalike_margin`` of its BIC, each passing every test); the simplest
        of the tie is :attr:`effect` (``discrepancy.json`` ``equivalent_effects``).
    rejected : tuple of Candidate
        With ``no_significant_effect``: the best-BIC candidate, which failed on held-out
        data while a weaker one passed -- the fit part's discrepancy is not a stable
        plant effect.
    diverged : tuple of Effect
        Fitted candidates whose simulation over the record diverged (an effect that
        destabilises a loop): dropped from the selection, listed with their parameters.
    opened_loops : tuple of str
        Controllers whose loops the analysis opened at their measured OP
        (:func:`pipeline.discrepancy.problem.loops_to_open`): their OPs were inputs, not
        compared outputs; :attr:`augmented_model` has the loops closed.
    notes : tuple of str
        How the search ended when not by its own rules: the time budget
        (``max_time_s``) ran out, or the chain returned to one it had held.
    revised_prior : tuple of Effect
        Internal to the chain: for a search on a model that already holds effects, those
        effects as refitted jointly with this search's :attr:`effect` (unchanged when it
        was not a joint refit).
    """

    verdict: str
    effect: Effect | None
    candidates: tuple[Candidate, ...]
    lookalikes: tuple[Candidate, ...]
    localization: dict[str, Any]
    gap: dict[str, Any]
    augmented_model: Model
    output_offsets: dict[str, np.ndarray]
    noise: dict[str, Any]
    screening: tuple[dict[str, Any], ...]
    series: DiscrepancySeries
    dt_s: float
    config: DiscrepancyConfig
    timings_s: dict[str, float] = field(default_factory=dict)
    n_fit_simulations: int = 0
    effects: tuple[EffectStep, ...] = ()
    minor_effects: tuple[Candidate, ...] = ()
    operating_point_shift: dict[str, float] = field(default_factory=dict)
    revised_prior: tuple[Effect, ...] = ()
    equivalent_effects: tuple[Candidate, ...] = ()
    rejected: tuple[Candidate, ...] = ()
    diverged: tuple[Effect, ...] = ()
    notes: tuple[str, ...] = ()
    opened_loops: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no long arrays): what ``discrepancy.json`` holds."""
        return {
            "verdict": self.verdict,
            "effect": None if self.effect is None else self.effect.to_dict(),
            "candidates": [c.to_dict() for c in self.candidates],
            "lookalikes": [c.to_dict() for c in self.lookalikes],
            "localization": self.localization,
            "gap": self.gap,
            "noise": self.noise,
            "screening": list(self.screening),
            "dt_s": self.dt_s,
            "n_samples": int(self.series.t_s.size),
            "fit_samples": [self.series.fit_start, self.series.holdout_start],
            "holdout_samples": [self.series.holdout_start, int(self.series.t_s.size)],
            "config": {
                k: (list(v) if isinstance(v, tuple) else v)
                for k, v in dataclasses.asdict(self.config).items()
            },
            "timings_s": {k: round(v, 4) for k, v in self.timings_s.items()},
            "n_fit_simulations": self.n_fit_simulations,
            "effects": [e.to_dict() for e in self.effects],
            "minor_effects": [c.to_dict() for c in self.minor_effects],
            "operating_point_shift": {k: float(v) for k, v in self.operating_point_shift.items()},
            "equivalent_effects": [c.to_dict() for c in self.equivalent_effects],
            "rejected": [c.to_dict() for c in self.rejected],
            "diverged": [e.to_dict() for e in self.diverged],
            "notes": list(self.notes),
            "opened_loops": list(self.opened_loops),
        }

    def __str__(self) -> str:
        lines = [f"discrepancy verdict: {self.verdict}"]
        if self.effect is not None:
            lines.append(f"  effect: {self.effect.describe()}")
        for c in self.lookalikes:
            lines.append(f"  look-alike: {c.effect.describe()} (criterion {c.criterion:.1f})")
        for c in self.equivalent_effects:
            lines.append(f"  equivalent: {c.effect.describe()} (criterion {c.criterion:.1f})")
        for c in self.rejected:
            lines.append(f"  rejected (fails on held-out data): {c.effect.describe()}")
        g = self.gap
        lines.append(
            f"  held-out RMS {g['holdout_rms_before']:.4g} -> {g['holdout_rms_after']:.4g} "
            f"({100 * g['reduction']:.1f} % smaller)"
        )
        lines += [f"  note: {n}" for n in self.notes]
        for c in self.candidates[:5]:
            lines.append(
                f"  candidate {c.effect.describe()}: dBIC {c.delta_bic:.1f}, held-out z "
                f"{c.holdout_z:.1f}{' (passed)' if c.passed else ''}"
            )
        return "\n".join(lines)


def json_float(value: Any) -> Any:
    """Float for JSON (non-finite as string).

    Parameters
    ----------
    value : float or numpy scalar
        Number to convert (``float(value)``); inf, -inf and nan become
        ``"inf"``, ``"-inf"`` and ``"nan"``.
    """
    value = float(value)
    if math.isfinite(value):
        return value
    return "inf" if value > 0 else ("-inf" if value < 0 else "nan")
