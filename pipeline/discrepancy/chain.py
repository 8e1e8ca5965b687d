"""Several effects: the chain of searches and its backfitting (discrepancy.max_effects).

A plant usually misses more than one effect (the thesis needed a controller gain and a
more oscillatory small-amplitude response).  After the first search accepts an effect,
the same search -- held to the same statistical and practical tests -- runs on the model
augmented so far, up to ``max_effects``.  A greedy chain alone goes wrong when the
first accepted effect is a compromise between two true ones (a controller gain of
+20 % with a 15 s extra fuel lag was first taken for one 16 s dead time, after which
nothing else passed).  So after each newly accepted effect every earlier one is
*backfitted*: removed, and the search rerun on the model with all the others; what
that search accepts replaces it (the same effect refitted, or another one that the
others now explain better), and when that search accepts nothing the effect is dropped
as no longer needed.  One backfitting sweep per accepted effect (backfitting in the
sense of Hastie and Tibshirani's additive models: each term refitted to the partial
residual of the others).  Later searches also refit jointly the first search's best
candidates at other locations (:data:`N_CARRIED`); a chain that stays at one effect while
some of those remain significant but minor tries them as the first of a confirmed pair
(:data:`N_REPLACED`); a first search that accepts nothing tries its strong candidates --
failed on held-out data, or too small alone -- the same way (:data:`N_MASKED`).

Effects are kept with locations in the NOMINAL model's names
(:func:`pipeline.discrepancy.effects.original_location`) and applied to it in order; a later
effect at a block an earlier one wrapped acts on the outermost block of that name,
which for the linear effects (gain, dead time, lag, inverse response in series) is the
same plant.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from pipeline.discrepancy.config import DiscrepancyConfig
from pipeline.discrepancy.problem import SCALE_FACTOR_HINT
from pipeline.discrepancy.results import Candidate, DiscrepancyResult, EffectStep
from pipeline.discrepancy.practical import carrying_gaps, gap_values
from pipeline.discrepancy.select import holdout_gap, same_class
from pipeline.discrepancy.effects import Effect, apply_effect, original_location, output_offsets
from pipeline.errors import DivergenceError
from pipeline.models.model import Model
from pipeline.models.simulate import simulate

#: One search of the chain: (effects already in the model, the model, measured outputs as
#: adjusted, candidates it must also fit and test) -> result.
StepFn = Callable[[tuple[Effect, ...], Model, Mapping[str, np.ndarray], tuple[Candidate, ...]],
                  DiscrepancyResult]


#: Masked pairs: when the first search names nothing, its best candidates (at most this
#: many, criterion order) that fit the fit part significantly (``bic_margin``) are each
#: tried as a provisional first effect -- whether they failed on held-out data, passed but
#: closed too little of the gap to be named, or passed behind a better fit that failed.
#: Two effects can mask each other on held-out data -- a hidden saturation fitted to its
#: true limits left 9 % MORE of the held-out gap while the hidden operating-point gain
#: beside it was not in the model (their errors cancel where the record ends) -- and each
#: of two effects can be too small alone: on a noisy pair trial (pairs seed 2 000 012) the
#: hidden controller gain closed 10.4 % of the gap with a lower bound of 4.7 % (below the
#: 5 % bar), the hidden operating-point gain 7.7 % (3.7 %), yet given the gain the
#: operating-point gain closed 19 % (13 %).  The provisional effect is kept only when the
#: search on the model with it accepts an effect of another class AND the search on the
#: model with that one alone accepts the provisional class again: each of the two then
#: passed every held-out test, at its practical size, given the other, and together they
#: must close ``min_gap_reduction`` of the nominal model's held-out gap.
N_MASKED = 2

#: Carried candidates: a later search also refits jointly (with the chain's effects) the
#: first search's best candidates -- at most this many, criterion order -- that fitted the
#: nominal model significantly (``bic_margin``), share no location with an accepted
#: effect.  When the first accepted effect is a compromise of
#: both hidden ones (an inverse response whose tau grew from 16 to 21 s to take in an 8.7 s
#: extra lag downstream), the other effect fitted on top of the compromise with it held
#: fixed closes too little to rank among the later search's best, while on the nominal
#: model it was a significant candidate of its own (the lag: 5.4 % of the gap).  Another
#: location only: at an accepted effect's location the first search's other candidates
#: are that effect's look-alikes, and a jointly refitted look-alike pair would grow
#: spurious second effects on single-effect plants.
N_CARRIED = 3

#: Replaced compromises: when the chain ends with one effect while some of the carried
#: candidates (:data:`N_CARRIED`) remain statistically significant but practically minor
#: given it, the single effect may be a compromise of two hidden ones that neither
#: candidate can undo on top of it (a 16 s inverse response at the feedforward, 12 % of
#: the gap, for a hidden x1.39 drum-mass gain plus an inverse response at the feedwater
#: flow: given it the gain still passed every statistical test but closed 2.4 %).  Each of
#: at most this many such candidates (first-search order) is tried as the first effect of
#: a pair, confirmed as the masked pairs are (:data:`N_MASKED`), and the pair replaces the
#: single effect only when it closes ``min_gap_reduction`` of the nominal model's
#: held-out gap more than the single effect did.
N_REPLACED = 2


#: Dynamic look-alikes: a dead time, an extra lag and an inverse response at one block
#: stand in for one another (a first-order Pade approximant of a delay is an inverse
#: response of magnitude 1; a lag of a few samples is a delay).  A chain of two dynamic
#: effects each fitted given the other settles in the wrong pair of classes: both
#: locations right but a hidden inverse response and extra lag named two dead times
#: (pairs tuning trial 800 007), or the classes swapped between the two locations
#: (800 009) -- each effect the best given the other's compromise, which
#: backfitting one effect at a time (its re-search screens the others held fixed)
#: cannot leave.  So every re-search of a dynamic effect also fits its look-alikes at
#: its location, refitted jointly with the others (:func:`_lookalikes`), and the final
#: chain's dynamic effects are re-searched so once more, the newest included.  On the
#: spent pair seeds 1 700 000 that named both effects in four dead-time misses (a 16 s
#: fuel delay beside a controller saturation had been a 13.6 s lag; an inverse response
#: plus a 26 s delay two inverse responses); 800 007 and 800 009 stay wrong (the
#: inverse response of magnitude 1.15 is within the Pade rule of a delay).
_DYNAMIC = ("dead_time", "extra_lag", "inverse_response")


class OutOfTime(Exception):
    """The next search would end after ``discrepancy.max_time_s``: the chain stops."""


def _signature(links: Sequence[Link]) -> tuple:
    """The chain as a set of (effect class, location): what a repeat is judged by."""
    return tuple(sorted((lk.effect.name, lk.effect.location) for lk in links))


@dataclasses.dataclass(frozen=True)
class Link:
    """One accepted effect of the chain: the effect (nominal-model location) and its
    candidate as fitted and tested at the search that accepted it last."""

    effect: Effect
    candidate: Candidate


def _lookalikes(link: Link, dt_s: float) -> tuple[Candidate, ...]:
    """The other dynamic classes (:data:`_DYNAMIC`) at `link`'s location, started at the
    same time scale: a delay L, a lag of tau L and an inverse response of magnitude 1
    and tau L/2 (its Pade form); an inverse response (tau, m) counts as L = (1 + m) tau,
    the delay of its step response's zero crossing-and-settling scale.  Empty for
    other effects."""
    e = link.effect
    if e.name not in _DYNAMIC:
        return ()
    p = e.parameters
    if e.name == "dead_time":
        length = float(p["delay_s"])
    elif e.name == "extra_lag":
        length = float(p["tau_s"])
    else:
        length = (1.0 + abs(float(p["magnitude"]))) * float(p["tau_s"])
    length = max(length, dt_s)
    starts = {"dead_time": ({"delay_s": max(1, round(length / dt_s)) * dt_s}, 1),
              "extra_lag": ({"tau_s": length}, 1),
              "inverse_response": ({"tau_s": length / 2.0, "magnitude": 1.0}, 2)}
    return tuple(
        dataclasses.replace(link.candidate, n_parameters=n_par,
                            effect=dataclasses.replace(e, name=name, parameters=params))
        for name, (params, n_par) in starts.items() if name != e.name)


def simulate_with(augmented: Model, effects: Sequence[Effect], inputs: Mapping[str, Any],
                  **kwargs: Any):
    """:func:`~pipeline.models.simulate.simulate` of a model augmented with ``effects``; a
    divergence names the effects that caused it (the nominal model was checked stable)
    and, for a gain factor beyond :data:`SCALE_FACTOR_HINT`, the likely unit mismatch.

    Parameters
    ----------
    augmented : Model
        The nominal model with ``effects`` applied.
    effects : sequence of Effect
        The effects applied.
    inputs : mapping of str -> array
        The model inputs.
    **kwargs
        Passed to :func:`~pipeline.models.simulate.simulate` (``dt_s``, ``initial``).
    """
    try:
        return simulate(augmented, inputs, **kwargs)
    except DivergenceError as exc:
        scaled = [e for e in effects if e.name == "gain" and isinstance(
            e.parameters.get("factor"), float) and e.parameters["factor"] != 0.0 and max(
            abs(e.parameters["factor"]), 1.0 / abs(e.parameters["factor"])) >= SCALE_FACTOR_HINT]
        hint = "" if not scaled else (
            f"; a gain factor of {scaled[0].parameters['factor']:.3g} at "
            f"{scaled[0].location!r} usually means a signal's scale differs from the model's "
            "(an OP exported as a fraction 0-1 where the model expects %, or another unit): "
            "check the units of the job's signals against the model's")
        raise DivergenceError(
            f"the discrepancy search's model with "
            f"{'; '.join(e.describe() for e in effects) or 'no effect'} diverges: {exc}{hint}"
        ) from None


def predict_with_effects(model: Model, effects: Sequence[Effect],
                         inputs: Mapping[str, np.ndarray], *, dt_s: float, initial: str,
                         outputs: Sequence[str]) -> dict[str, np.ndarray]:
    """The measured outputs the nominal model with `effects` predicts: the augmented
    model simulated (:func:`simulate_with`) plus the effects' measurement offsets
    (:func:`pipeline.discrepancy.effects.output_offsets`); no re-centred constant.

    Parameters
    ----------
    model : Model
        The nominal model.
    effects : sequence of Effect
        Effects with locations in the nominal model's names, added in order.
    inputs : mapping of str -> array
        Every model input (and the extra signals an unmodelled input reads).
    dt_s : float
        Sample period, s.
    initial : str
        Initial state of the simulation (``DiscrepancyConfig.initial``).
    outputs : sequence of str
        The outputs to return.
    """
    augmented = build(model, effects, dt_s)
    sim = simulate_with(augmented, effects, {k: inputs[k] for k in augmented.inputs},
                        dt_s=dt_s, initial=initial)
    pred = {o: np.array(sim.signals[o], dtype=float) for o in outputs}
    n = next(iter(pred.values())).size if pred else 0
    for effect in effects:
        offsets = output_offsets(effect, n=n, dt_s=dt_s, outputs=outputs)
        pred = {o: pred[o] + offsets[o] for o in outputs}
    return pred


def build(model: Model, effects: Sequence[Effect], dt_s: float) -> Model:
    """`model` with `effects` added in order.

    Parameters
    ----------
    model : Model
        The nominal model.
    effects : sequence of Effect
        Effects with locations in the nominal model's names.
    dt_s : float
        Sample period, s (short lags become gains, :func:`pipeline.discrepancy.effects.apply_effect`).
    """
    for effect in effects:
        model = apply_effect(model, effect, dt_s=dt_s)
    return model


def _accepted(result: DiscrepancyResult, nominal: Model) -> Link | None:
    """The step's accepted effect with its location mapped to nominal names (None if the
    location has no nominal counterpart)."""
    return _link(next(c for c in result.candidates if c.effect is result.effect), nominal)


def _link(cand: Candidate, nominal: Model) -> Link | None:
    """A candidate's effect as a link in nominal names (None: no counterpart)."""
    effect = cand.effect
    names = (*nominal.block_names, *nominal.outputs)
    loc = original_location(effect.location, names)
    if loc is None:
        return None
    equivalent = tuple(dict.fromkeys(
        m for m in (original_location(e, names) for e in effect.equivalent_locations)
        if m is not None and m != loc))
    if loc == effect.location and equivalent == tuple(effect.equivalent_locations):
        return Link(effect, cand)  # names of the nominal model already: the same object
    mapped = dataclasses.replace(effect, location=loc, equivalent_locations=equivalent)
    return Link(mapped, dataclasses.replace(cand, effect=mapped))


def _revise(links: list[Link], effects: Sequence[Effect]) -> list[Link]:
    """`links` with their effects' parameters as a joint refit left them."""
    if len(effects) != len(links):
        return list(links)
    return [Link(e, dataclasses.replace(lk.candidate, effect=e))
            for lk, e in zip(links, effects, strict=True)]


class Chain:
    """The measured outputs as each later search sees them, and the chain's searches.

    Parameters
    ----------
    model : Model
        The nominal model.
    inputs : mapping of str -> ndarray
        Validated measured signals.
    measured : mapping of str -> ndarray
        Measured outputs.
    dt_s : float
        Sample period, s.
    config : DiscrepancyConfig
    free_offsets : tuple of str
        Outputs whose constant follows the model (re-centred on the fit part).
    step : StepFn
        One search.
    say : callable (stage, message)
        Progress.
    clock : callable () -> float, optional
        A monotonic clock in seconds: with it, no search starts that would end after
        ``config.max_time_s`` (judged by the longest search so far); the chain so far is
        then the result and :attr:`notes` says so.  None: no time budget.
    """

    def __init__(self, model: Model, inputs: Mapping[str, np.ndarray],
                 measured: Mapping[str, np.ndarray], dt_s: float, config: DiscrepancyConfig,
                 free_offsets: tuple[str, ...], step: StepFn,
                 say: Callable[[str, str], None],
                 clock: Callable[[], float] | None = None) -> None:
        self.clock = clock
        self.t0 = clock() if clock is not None else 0.0
        self.longest_s = 0.0  # the longest search so far, s
        self.so_far: list[Link] = []  # the chain as last consistently fitted
        self.notes: list[str] = []  # what the result must say (time budget, repeats)
        self._seen: set[tuple] = set()  # chains held so far (no alternating re-searches)
        self.model, self.inputs, self.dt_s, self.config = model, inputs, dt_s, config
        self.measured = {o: np.asarray(v, dtype=float) for o, v in measured.items()}
        self.outputs = list(self.measured)
        self.free_offsets, self.step, self.say = free_offsets, step, say
        self.fit = slice(0, 0)  # the fit part, known after the first search
        self.n = next(iter(self.measured.values())).size
        self.steps: list[DiscrepancyResult] = []
        self._held: dict[tuple, float] = {}  # held_out's cache

    def prediction(self, effects: Sequence[Effect], recentre: bool = True
                   ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """Predicted measured outputs of the nominal model with `effects` (their
        measurement offsets and the free outputs' re-centred constant included) and
        that constant per free output.

        Parameters
        ----------
        effects : sequence of Effect
            Effects with nominal locations.
        recentre : bool
            Re-estimate the free outputs' constant on the fit part (as every search
            profiles it out of each candidate's prediction; the reported chain does).
        """
        pred = predict_with_effects(self.model, effects, self.inputs, dt_s=self.dt_s,
                                    initial=self.config.initial, outputs=self.outputs)
        shift = {}
        if effects and recentre:
            for o in self.free_offsets:  # their constant follows the model ("mean")
                shift[o] = float(np.mean((self.measured[o] - pred[o])[self.fit]))
                pred[o] = pred[o] + shift[o]
        return pred, shift

    def held_out(self, effects: Sequence[Effect]) -> dict[str, Any]:
        """Held-out gap (the result's ``gap``: pooled, and ``per_output``) of the
        nominal model with `effects` (:meth:`prediction`; the nominal model's own when
        there are none).

        Parameters
        ----------
        effects : sequence of Effect
            Effects with nominal locations (cached by name, location and values).
        """
        key = tuple((e.name, e.location, tuple(sorted(e.parameters.items())))
                    for e in effects)
        if key not in self._held:  # prune asks for the same chains repeatedly
            s0 = self.steps[0].series
            pred = self.prediction(effects)[0] if effects else s0.nominal
            y, y_nom, y_aug = (np.column_stack([sig[o] for o in self.outputs])
                               for sig in (s0.measured, s0.nominal, pred))
            self._held[key] = holdout_gap(y, self.outputs, s0.holdout_start, y - y_nom,
                                          y_aug)
        return self._held[key]

    def needed(self, links: Sequence[Link], k: int) -> tuple[bool, float, float, float]:
        """Whether the chain `links` as fitted needs its `k`-th effect: on some output,
        or pooled, the held-out gap without it, less that with all, must be at least
        ``min_gap_reduction`` of that gap with the chain's sensor corrections only (the
        nominal model's when there are none: the reference of
        :func:`pipeline.discrepancy.analyse.gap_reference`; the gaps
        :func:`pipeline.discrepancy.practical.practical_share` judges a candidate on,
        those that may carry a finding, :func:`~pipeline.discrepancy.practical.carrying_gaps`).
        Returns (needed, that share where it is largest, pooled gap without it, pooled
        gap with all).

        Parameters
        ----------
        links : sequence of Link
            The chain, as fitted.
        k : int
            Index of the effect in question.
        """
        effects = [lk.effect for lk in links]
        gaps = [self.held_out(e) for e in (
            [e for e in effects if e.is_sensor_correction], effects[:k] + effects[k + 1:],
            effects)]
        ref, without, full = (gap_values(g, self.outputs, "holdout_rms_after") for g in gaps)
        carrying = carrying_gaps(ref, [gaps[0]["per_output"][o]["holdout_std"]
                                       for o in self.outputs], self.config.min_gap_reduction)
        share = max((w - f) / r if r > 0 else 0.0
                    for w, f, r, c in zip(without, full, ref, carrying, strict=True) if c)
        return share >= self.config.min_gap_reduction, share, without[-1], full[-1]

    def search(self, effects: Sequence[Effect], also: Sequence[Candidate] = ()
               ) -> DiscrepancyResult:
        """One search on the model with `effects`, the measured outputs less what the
        model does not simulate (measurement offsets, re-centred constants).

        Parameters
        ----------
        effects : sequence of Effect
            Effects already in the model (nominal locations).
        also : sequence of Candidate
            Effects (nominal locations) the search fits and tests among its own
            candidates whatever its screening ranks (refitted jointly with `effects`).
        """
        if self.steps:
            self._check_time()
        t_start = self.clock() if self.clock is not None else 0.0
        augmented = build(self.model, effects, self.dt_s)
        adjusted = dict(self.measured)
        if effects:
            pred, _ = self.prediction(effects)
            sim = simulate_with(augmented, effects,
                                {k: self.inputs[k] for k in augmented.inputs},
                                dt_s=self.dt_s, initial=self.config.initial)
            # what the prediction adds to the simulation is taken off the measurement
            adjusted = {o: self.measured[o] - (pred[o] - sim.signals[o]) for o in self.outputs}
        result = self.step(tuple(effects), augmented, adjusted, tuple(also))
        if not self.steps:
            self.fit = slice(result.series.fit_start, result.series.holdout_start)
        self.steps.append(result)
        if self.clock is not None:
            self.longest_s = max(self.longest_s, self.clock() - t_start)
        return result

    def _check_time(self) -> None:
        """Raise :class:`OutOfTime` when the next search, as long as the longest so far,
        would end after ``max_time_s`` (the first search always runs)."""
        limit = self.config.max_time_s
        if limit is None or self.clock is None:
            return
        elapsed = self.clock() - self.t0
        if elapsed + self.longest_s > limit:
            raise OutOfTime(
                f"time budget: discrepancy.max_time_s is {limit:g} s and {elapsed:.0f} s "
                f"have gone on {len(self.steps)} search(es); the next one (up to "
                f"{self.longest_s:.0f} s, the longest so far) would end after it, so the "
                "chain found so far is reported; raise max_time_s in the job's "
                "discrepancy: section to search further")

    def _keep(self, links: list[Link]) -> list[Link]:
        """Record `links` as the chain so far (what a stop on time reports) and as a chain
        held (:meth:`_returns_to`)."""
        self.so_far = list(links)
        self._seen.add(_signature(links))
        return links

    def _returns_to(self, links: Sequence[Link]) -> bool:
        """Whether `links` is a chain held before: a backfit that swaps an effect for a
        look-alike and back would only alternate (a 19 s dead time in the zoo's blend
        went dead time -> inverse response -> dead time until the run was killed); a
        note says so."""
        sig = _signature(links)
        if sig not in self._seen:
            return False
        note = (f"the chain returned to {', '.join(f'{n} at {loc}' for n, loc in sig)}, "
                "which it had held before: re-searching would only alternate, so the "
                "backfit stops there")
        self.notes.append(note)
        self.say("chain", note)
        return True

    def run(self) -> tuple[list[Link], tuple[Candidate, ...]]:
        """Search, accept, backfit, search again: the accepted chain and the minor
        effects of the search that ended it.  Out of time (:meth:`_check_time`): the
        chain as last consistently fitted, no minor effects, and a note."""
        try:
            return self._run()
        except OutOfTime as exc:
            self.notes.append(str(exc))
            self.say("chain", str(exc))
            return list(self.so_far), ()

    def _run(self) -> tuple[list[Link], tuple[Candidate, ...]]:
        """:meth:`run` without the time budget's stop."""
        first = self.search([])
        links: list[Link] = []
        dropped: list[Effect] = []
        last = first
        budget = 3 * self.config.max_effects  # searches after the first, at most
        if first.verdict == "effect_found" and (link := _accepted(first, self.model)):
            links.append(link)
        elif self.config.max_effects >= 2:
            links, last, budget = self._masked(first, budget)
        self._keep(links)
        links, last, budget = self._grow(links, dropped, last, budget)
        if len(links) == 1 and self.config.max_effects >= 2:
            pair = self._replaced(links[0], last, budget)
            if pair is not None:
                links, last, budget = pair
                self._keep(links)
                links, last, budget = self._grow(links, dropped, last, budget)
        if len(links) >= 2 and any(lk.effect.name in _DYNAMIC for lk in links):
            # the newest effect was never re-searched with its look-alikes
            links, _ = self._backfit(links, dropped, len(links), newest=True)
        names = (*self.model.block_names, *self.model.outputs)
        minor = []
        for c in last.minor_effects:  # in nominal names; none that has no counterpart
            loc = original_location(c.effect.location, names)
            if loc is not None:
                minor.append(dataclasses.replace(
                    c, effect=dataclasses.replace(c.effect, location=loc)))
        return links, tuple(minor)

    def _grow(self, links: list[Link], dropped: list[Effect], last: DiscrepancyResult,
              budget: int) -> tuple[list[Link], DiscrepancyResult, int]:
        """Search again on the augmented model and backfit while searches accept new
        effects: the chain, the search that ended it and the budget left."""
        while links and len(links) < self.config.max_effects and budget > 0:
            self.say("chain", f"{len(links)} effect(s) accepted; searching again on the "
                     "augmented model")
            last = self.search([lk.effect for lk in links], also=self._carried(links))
            budget -= 1
            if last.verdict != "effect_found":
                break
            link = _accepted(last, self.model)
            if link is None or any(same_class(link.effect, e)
                                   for e in [*(lk.effect for lk in links), *dropped]):
                break
            links = self._keep(_revise(links, last.revised_prior) + [link])
            links, budget = self._backfit(links, dropped, budget)
        return links, last, budget

    def _carried(self, links: Sequence[Link]) -> tuple[Candidate, ...]:
        """The first search's candidates a later search refits too (:data:`N_CARRIED`)."""
        taken = frozenset().union(*(lk.effect.places for lk in links))
        out = []
        for c in self.steps[0].candidates:
            if len(out) == N_CARRIED:
                break
            if c.delta_bic >= self.config.bic_margin and not c.effect.places & taken \
                    and (link := _link(c, self.model)) is not None:
                out.append(link.candidate)
        return tuple(out)

    def _search_or_none(self, effects: Sequence[Effect], also: Sequence[Candidate] = ()
                        ) -> DiscrepancyResult | None:
        """:meth:`search`, or None when the model with `effects` diverges.  The chain
        proposes models no search has simulated -- a pair's second effect without the
        first, one effect left out for backfitting -- and an effect held bounded by
        another can destabilise a loop alone (zoo null 8 108 023: an operating-point gain
        accepted given a saturation diverged without it, and ended the analysis as
        exit 2).  Such a model is not an explanation; the chain goes on without it."""
        try:
            return self.search(effects, also)
        except DivergenceError as exc:
            self.say("chain", f"not pursued: {exc}")
            return None

    def _pair(self, cand: Candidate, budget: int, must_close: float
              ) -> tuple[tuple[list[Link], DiscrepancyResult] | None, int]:
        """`cand` (a first-search candidate) as a provisional first effect, confirmed by
        a second one: the search on the model with it must accept an effect of another
        class, the search on the model with that one alone (`cand` refitted jointly
        among its candidates) must accept `cand`'s class again, and the pair must leave
        a held-out gap of at most `must_close`.  Returns (the pair as links and the
        confirming search, or None) and the budget left."""
        link0 = _link(cand, self.model)
        if link0 is None or budget < 2:
            return None, budget
        second = self._search_or_none([link0.effect])
        budget -= 1
        link1 = _accepted(second, self.model) if second is not None and \
            second.verdict == "effect_found" else None
        if link1 is None or same_class(link1.effect, link0.effect):
            return None, budget
        [link0] = _revise([link0], second.revised_prior)
        self.say("chain", f"confirming {link0.effect.describe()} given "
                 f"{link1.effect.describe()}")
        alt = self._search_or_none([link1.effect], also=[link0.candidate])
        budget -= 1
        if alt is None:
            return None, budget
        again = _accepted(alt, self.model) if alt.verdict == "effect_found" else None
        if again is None or not same_class(again.effect, link0.effect) or \
                alt.gap["holdout_rms_after"] > must_close:
            return None, budget
        return ([again, *_revise([link1], alt.revised_prior)], alt), budget

    def _masked(self, first: DiscrepancyResult, budget: int
                ) -> tuple[list[Link], DiscrepancyResult, int]:
        """Two effects that mask each other or are too small alone (see
        :data:`N_MASKED`): the confirmed pair as links (none: ``[]``), the search that
        ended and the budget left.  Together they must close ``min_gap_reduction`` of the
        nominal gap."""
        ref = first.gap["holdout_rms_before"]
        masked = [c for c in first.candidates
                  if c.delta_bic >= self.config.bic_margin][:N_MASKED]
        for cand in masked:
            self.say("chain", f"{cand.effect.describe()} fits but is not named alone: "
                     "searching for an effect that masks it")
            pair, budget = self._pair(cand, budget,
                                      (1.0 - self.config.min_gap_reduction) * ref)
            if pair is not None:
                return *pair, budget
        return [], first, budget

    def _replaced(self, only: Link, last: DiscrepancyResult, budget: int
                  ) -> tuple[list[Link], DiscrepancyResult, int] | None:
        """A compromise single effect replaced by a confirmed pair (see
        :data:`N_REPLACED`): the pair, the search that confirmed it and the budget left,
        or None.  `last` is the search that ended the chain, on the model with `only`."""
        if tuple(last.revised_prior) != (only.effect,):
            return None  # not a search on the model with exactly `only`
        ref = self.steps[0].gap["holdout_rms_before"]
        # the pair must close min_gap_reduction of the nominal gap more than `only`
        must_close = last.gap["holdout_rms_before"] - self.config.min_gap_reduction * ref
        # not `only`'s own effect at another place: that is its location look-alike (a
        # saturation one block upstream, still significant given the one accepted), and
        # a pair it leads puts the effect in the wrong place plus a correction for that
        # (nuisance trial 907037: the hidden feedwater-flow saturation was replaced by
        # one on the demand and an operating-point gain at the feedforward)
        tried = [c for c in self._carried([only]) if c.effect.name != only.effect.name
                 and any(same_class(c.effect, m.effect) for m in last.minor_effects)]
        for cand in tried[:N_REPLACED]:
            self.say("chain", f"{cand.effect.describe()} stays significant given "
                     f"{only.effect.describe()}: trying it as the first of a pair")
            pair, budget = self._pair(cand, budget, must_close)
            if pair is not None:
                return *pair, budget
        return None

    def _backfit(self, links: list[Link], dropped: list[Effect], budget: int,
                 newest: bool = False) -> tuple[list[Link], int]:
        """Refit every effect but the newest (`newest`: every dynamic one, the newest
        included) given the others (see module docstring); a dynamic effect's
        re-search fits its look-alikes too (:data:`_DYNAMIC`)."""
        j = 0
        while j < len(links) - (0 if newest else 1) and budget > 0:
            if newest and links[j].effect.name not in _DYNAMIC:
                j += 1
                continue
            others = links[:j] + links[j + 1:]
            self.say("backfit", f"re-searching {links[j].effect.describe()} given the "
                     f"{len(others)} other effect(s)")
            alt = self._search_or_none([lk.effect for lk in others],
                                       also=_lookalikes(links[j], self.dt_s))
            budget -= 1
            if alt is None:  # the others diverge without it: it stays as it was
                j += 1
                continue
            if alt.verdict == "no_significant_effect":
                if not self.needed(links, j)[0]:
                    dropped.append(links[j].effect)  # the others explain it now
                    links = self._keep(others)
                    continue
                # the others do not: its refit failed (a saturation's upper limit, met
                # mostly in the held-out third, went to inf given a deadband; pairs
                # tuning trial 800039) -- it stays as it was
            if alt.verdict == "effect_found" and (link := _accepted(alt, self.model)) and \
                    not any(same_class(link.effect, lk.effect) for lk in others):
                others = _revise(others, alt.revised_prior)
                swapped = others[:j] + [link] + others[j:]
                if link.effect.name != links[j].effect.name and self._returns_to(swapped):
                    break  # back to a chain held before: the re-searches would alternate
                links = self._keep(swapped)
            j += 1
        return links, budget


def prune(chain: Chain, links: Sequence[Link]) -> tuple[list[Link], list[Candidate]]:
    """The chain without the effects it does not need as finally fitted, and those
    effects as minor candidates.

    Each search held its finding to ``min_gap_reduction`` of the reference gap
    (:func:`pipeline.discrepancy.analyse.gap_reference`) on the model of that moment,
    with the earlier effects refitted jointly.  That joint refit can be what closed the
    gap: after a saturation (accepted first, its limits fitted on the static-map path) a
    controller gain of x1.017 and an operating-point gain of slope -0.003 passed, while
    in the final chain -- the saturation as refitted with them -- they closed -0.3 % and
    -45 % of the gap (nuisance trials 907030, 907012).  So, once the chain is final,
    every effect must still be needed (:meth:`Chain.needed`): the held-out gap of the
    chain without it, less that of the whole chain, at least ``min_gap_reduction`` of
    the gap with the chain's sensor corrections only.  Backfitting drops an effect by
    the same rule.  The least needed effect under the bar is dropped and the rest
    checked again; the last effect always stays (the first search held it to the bar
    on its own).  Leave-one-out, not the step-by-step reduction of
    :func:`chain_steps`: two effects that mask each other on held-out data
    (:data:`N_MASKED`) each close little alone but much together.

    Parameters
    ----------
    chain : Chain
    links : sequence of Link
        The accepted effects in order.
    """
    links, dropped = list(links), []
    while len(links) >= 2:
        checks = [chain.needed(links, k) for k in range(len(links))]
        k = int(np.argmin([share for _, share, _, _ in checks]))  # the least needed
        needed, _, without, full = checks[k]
        if needed:
            break
        lk = links.pop(k)
        chain.say("chain", f"{lk.effect.describe()} closes {without - full:.3g} of the "
                  "held-out gap in the final chain: a minor effect")
        dropped.append(dataclasses.replace(
            lk.candidate, holdout_gap=full,
            gap_reduction=1.0 - full / without if without > 0 else 0.0))
    return links, dropped


def chain_steps(chain: Chain, links: Sequence[Link],
                gap: Callable[[dict[str, np.ndarray] | None], dict[str, Any]]
                ) -> tuple[tuple[EffectStep, ...], dict[str, np.ndarray], dict[str, float]]:
    """The chain as reported: each effect with the held-out gap of the model with the
    effects up to it (final parameters); the final prediction and free-output shift.

    Parameters
    ----------
    chain : Chain
    links : sequence of Link
        The accepted effects in order (at least one).
    gap : callable (prediction or None) -> gap dict
        The held-out gap of a prediction (None: the nominal model), with
        ``holdout_rms_after`` and ``per_output``.
    """
    steps = []
    before = gap(None)
    pred: dict[str, np.ndarray] = {}
    shift: dict[str, float] = {}
    for k in range(1, len(links) + 1):
        # the free outputs' constants as every search profiled them (also for one effect)
        pred, shift = chain.prediction([lk.effect for lk in links[:k]])
        after = gap(pred)
        g0, g1 = before["holdout_rms_after"], after["holdout_rms_after"]
        # the reduction this effect brings to the chain as finally fitted (the search
        # that accepted it measured it against the model of that moment)
        cand = dataclasses.replace(links[k - 1].candidate, holdout_gap=g1,
                                   gap_reduction=1.0 - g1 / g0 if g0 > 0 else 0.0)
        steps.append(EffectStep(cand, before["holdout_rms_after"],
                                after["holdout_rms_after"],
                                {o: g["holdout_rms_after"] for o, g in after["per_output"].items()}))
        before = after
    return tuple(steps), pred, shift
