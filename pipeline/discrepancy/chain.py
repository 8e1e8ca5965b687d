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
residual of the others).

Effects are kept with locations in the NOMINAL model's names
(:func:`pipeline.effects.original_location`) and applied to it in order; a later
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
from pipeline.discrepancy.results import Candidate, DiscrepancyResult, EffectStep
from pipeline.discrepancy.select import same_class
from pipeline.effects import Effect, apply_effect, original_location, output_offsets
from pipeline.model import Model
from pipeline.simulate import simulate

#: One search of the chain: (effects already in the model, the model, measured outputs as
#: adjusted, candidates it must also fit and test) -> result.
StepFn = Callable[[tuple[Effect, ...], Model, Mapping[str, np.ndarray], tuple[Candidate, ...]],
                  DiscrepancyResult]


#: Masked pairs: when the first search finds nothing, its best candidates (at most this
#: many, criterion order) that fit the fit part significantly (``bic_margin``) but fail on
#: held-out data are each tried as a provisional first effect.  Two effects can mask each
#: other on held-out data -- a hidden saturation fitted to its true limits left 9 % MORE of
#: the held-out gap while the hidden operating-point gain beside it was not in the model
#: (their errors cancel where the record ends).  The provisional effect is kept only when
#: the search on the model with it accepts an effect of another class AND the search on
#: the model with that one alone accepts the provisional class again: each of the two then
#: passed every held-out test given the other, and together they must close
#: ``min_gap_reduction`` of the nominal model's held-out gap.
N_MASKED = 2


@dataclasses.dataclass(frozen=True)
class Link:
    """One accepted effect of the chain: the effect (nominal-model location) and its
    candidate as fitted and tested at the search that accepted it last."""

    effect: Effect
    candidate: Candidate


def build(model: Model, effects: Sequence[Effect], dt_s: float) -> Model:
    """`model` with `effects` added in order.

    Parameters
    ----------
    model : Model
        The nominal model.
    effects : sequence of Effect
        Effects with locations in the nominal model's names.
    dt_s : float
        Sample period, s (short lags become gains, :func:`pipeline.effects.apply_effect`).
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
    """

    def __init__(self, model: Model, inputs: Mapping[str, np.ndarray],
                 measured: Mapping[str, np.ndarray], dt_s: float, config: DiscrepancyConfig,
                 free_offsets: tuple[str, ...], step: StepFn,
                 say: Callable[[str, str], None]) -> None:
        self.model, self.inputs, self.dt_s, self.config = model, inputs, dt_s, config
        self.measured = {o: np.asarray(v, dtype=float) for o, v in measured.items()}
        self.outputs = list(self.measured)
        self.free_offsets, self.step, self.say = free_offsets, step, say
        self.fit = slice(0, 0)  # the fit part, known after the first search
        self.n = next(iter(self.measured.values())).size
        self.steps: list[DiscrepancyResult] = []

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
            Re-estimate the free outputs' constant (every search after the first does;
            the reported result does when the chain holds two or more effects).
        """
        augmented = build(self.model, effects, self.dt_s)
        sim = simulate(augmented, {k: self.inputs[k] for k in augmented.inputs},
                       dt_s=self.dt_s, initial=self.config.initial)
        pred = {o: np.array(sim.signals[o], dtype=float) for o in self.outputs}
        for effect in effects:
            offsets = output_offsets(effect, n=self.n, dt_s=self.dt_s, outputs=self.outputs)
            pred = {o: pred[o] + offsets[o] for o in self.outputs}
        shift = {}
        if effects and recentre:
            for o in self.free_offsets:  # their constant follows the model ("mean")
                shift[o] = float(np.mean((self.measured[o] - pred[o])[self.fit]))
                pred[o] = pred[o] + shift[o]
        return pred, shift

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
        augmented = build(self.model, effects, self.dt_s)
        adjusted = dict(self.measured)
        if effects:
            pred, _ = self.prediction(effects)
            sim = simulate(augmented, {k: self.inputs[k] for k in augmented.inputs},
                           dt_s=self.dt_s, initial=self.config.initial)
            # what the prediction adds to the simulation is taken off the measurement
            adjusted = {o: self.measured[o] - (pred[o] - sim.signals[o]) for o in self.outputs}
        result = self.step(tuple(effects), augmented, adjusted, tuple(also))
        if not self.steps:
            self.fit = slice(result.series.fit_start, result.series.holdout_start)
        self.steps.append(result)
        return result

    def run(self) -> tuple[list[Link], tuple[Candidate, ...]]:
        """Search, accept, backfit, search again: the accepted chain and the minor
        effects of the search that ended it."""
        first = self.search([])
        links: list[Link] = []
        dropped: list[Effect] = []
        last = first
        budget = 3 * self.config.max_effects  # searches after the first, at most
        if first.verdict == "effect_found" and (link := _accepted(first, self.model)):
            links.append(link)
        elif self.config.max_effects >= 2:
            links, last, budget = self._masked(first, budget)
        while links and len(links) < self.config.max_effects and budget > 0:
            self.say("chain", f"{len(links)} effect(s) accepted; searching again on the "
                     "augmented model")
            last = self.search([lk.effect for lk in links])
            budget -= 1
            if last.verdict != "effect_found":
                break
            link = _accepted(last, self.model)
            if link is None or any(same_class(link.effect, e)
                                   for e in [*(lk.effect for lk in links), *dropped]):
                break
            links = _revise(links, last.revised_prior) + [link]
            links, budget = self._backfit(links, dropped, budget)
        names = (*self.model.block_names, *self.model.outputs)
        minor = []
        for c in last.minor_effects:  # in nominal names; none that has no counterpart
            loc = original_location(c.effect.location, names)
            if loc is not None:
                minor.append(dataclasses.replace(
                    c, effect=dataclasses.replace(c.effect, location=loc)))
        return links, tuple(minor)

    def _masked(self, first: DiscrepancyResult, budget: int
                ) -> tuple[list[Link], DiscrepancyResult, int]:
        """Two effects that mask each other on held-out data (see :data:`N_MASKED`): the
        confirmed pair as links (none: ``[]``), the search that ended and the budget
        left."""
        ref = first.gap["holdout_rms_before"]
        bar = self.config.min_gap_reduction
        masked = [c for c in first.candidates if not c.passed
                  and c.delta_bic >= self.config.bic_margin][:N_MASKED]
        for cand in masked:
            if budget < 2:
                break
            link0 = _link(cand, self.model)
            if link0 is None:
                continue
            self.say("chain", f"{cand.effect.describe()} fits but fails on held-out data: "
                     "searching for an effect that masks it")
            second = self.search([link0.effect])
            budget -= 1
            link1 = _accepted(second, self.model) if second.verdict == "effect_found" else None
            if link1 is None or same_class(link1.effect, link0.effect):
                continue
            [link0] = _revise([link0], second.revised_prior)
            self.say("chain", f"confirming {link0.effect.describe()} given "
                     f"{link1.effect.describe()}")
            alt = self.search([link1.effect], also=[link0.candidate])
            budget -= 1
            again = _accepted(alt, self.model) if alt.verdict == "effect_found" else None
            total = 1.0 - alt.gap["holdout_rms_after"] / ref if ref > 0 else 0.0
            if again is not None and same_class(again.effect, link0.effect) and total >= bar:
                return [again, *_revise([link1], alt.revised_prior)], alt, budget
        return [], first, budget

    def _backfit(self, links: list[Link], dropped: list[Effect], budget: int
                 ) -> tuple[list[Link], int]:
        """Refit every effect but the newest given the others (see module docstring)."""
        j = 0
        while j < len(links) - 1 and budget > 0:
            others = links[:j] + links[j + 1:]
            self.say("backfit", f"re-searching {links[j].effect.describe()} given the "
                     f"{len(others)} other effect(s)")
            alt = self.search([lk.effect for lk in others])
            budget -= 1
            if alt.verdict == "no_significant_effect":
                dropped.append(links[j].effect)  # the others explain it now
                links = others
                continue
            if alt.verdict == "effect_found" and (link := _accepted(alt, self.model)) and \
                    not any(same_class(link.effect, lk.effect) for lk in others):
                others = _revise(others, alt.revised_prior)
                links = others[:j] + [link] + others[j:]
            j += 1
        return links, budget


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
        pred, shift = chain.prediction([lk.effect for lk in links[:k]],
                                       recentre=len(links) > 1)
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
