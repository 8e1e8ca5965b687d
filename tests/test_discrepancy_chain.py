"""The chain's masked-pair search (``pipeline.discrepancy.chain.Chain._masked``), driven
through ``Chain.run`` with a scripted search in place of the real one.

The real search is exercised end to end by the pairs suite (``tests/test_hidden_effects.py``
CI sample, ``tests/benchmarks/bench_discrepancy.py --suite pairs``); here the decision
logic alone is checked against known answers: which searches run, with which effects in
the model and which candidates forced into the search, and what is kept.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pipeline.demo import boiler_model
from pipeline.discrepancy.chain import Chain
from pipeline.discrepancy.config import DiscrepancyConfig
from pipeline.discrepancy.results import Candidate
from pipeline.effects import Effect

N = 600


def _cand(effect: Effect, *, passed: bool, delta_bic: float) -> Candidate:
    return Candidate(effect=effect, criterion=-delta_bic, delta_bic=delta_bic,
                     n_parameters=1, holdout_rms={}, holdout_z=0.0, holdout_gap=1.0,
                     screening_score=0.0, passed=passed, gap_reduction=0.0,
                     holdout_rms_p=1.0, passed_by="")


def _result(verdict: str, candidates=(), effect=None, gap_after=1.0, revised=()):
    return SimpleNamespace(
        verdict=verdict, effect=effect, candidates=tuple(candidates),
        gap={"holdout_rms_before": 1.0, "holdout_rms_after": gap_after},
        revised_prior=tuple(revised), minor_effects=(),
        series=SimpleNamespace(fit_start=0, holdout_start=400))


def _chain(script):
    """A chain on the boiler model whose searches answer from `script(prior, also)`;
    returns the chain and the log of (prior effect names, forced candidate names)."""
    model = boiler_model()
    rng = np.random.default_rng(0)
    inputs = {k: rng.standard_normal(N) for k in model.inputs}
    measured = {o: rng.standard_normal(N) for o in model.outputs}
    log = []

    def step(prior, _model, _measured, also):
        log.append((tuple(e.name for e in prior), tuple(c.effect.name for c in also)))
        return script(prior, also)

    chain = Chain(model, inputs, measured, 1.0, DiscrepancyConfig(), (), step,
                  lambda *_: None)
    return chain, log


SAT = Effect("saturation", "drum", {"low": -0.2, "high": 0.4})
OPG = Effect("operating_point_gain", "fuel", {"slope": -0.04, "signal": "steam_flow"})


def _masked_script(confirm: bool):
    sat_failing = _cand(SAT, passed=False, delta_bic=7000.0)

    def script(prior, also):
        names = tuple(e.name for e in prior)
        if names == ():
            return _result("no_significant_effect", [sat_failing])
        if names == ("saturation",):
            opg = _cand(OPG, passed=True, delta_bic=350.0)
            return _result("effect_found", [opg], OPG, revised=prior)
        if names == ("operating_point_gain",) and also:
            if not confirm:
                return _result("no_significant_effect", [also[0]])
            again = _cand(Effect("saturation", "drum", {"low": -0.21, "high": 0.42}),
                          passed=True, delta_bic=180.0)
            return _result("effect_found", [again], again.effect, gap_after=0.6,
                           revised=prior)
        return _result("no_significant_effect")
    return script


def test_a_masked_pair_is_kept_when_each_passes_given_the_other():
    chain, log = _chain(_masked_script(confirm=True))
    links, _ = chain.run()
    assert [lk.effect.name for lk in links] == ["saturation", "operating_point_gain"]
    assert links[0].effect.parameters["high"] == 0.42  # as refitted given the other
    # first search; the provisional saturation in the model; the gain alone with the
    # saturation forced among the candidates; then the usual search for a third effect
    assert log[:3] == [((), ()), (("saturation",), ()),
                       (("operating_point_gain",), ("saturation",))]
    assert log[3][0] == ("saturation", "operating_point_gain")


def test_an_unconfirmed_masked_pair_is_dropped():
    chain, log = _chain(_masked_script(confirm=False))
    links, _ = chain.run()
    assert links == []
    assert len(log) == 3  # nothing kept: no search for a third effect


def test_no_masked_search_without_a_strong_failing_candidate():
    weak = _cand(SAT, passed=False, delta_bic=5.0)  # below bic_margin (10)
    chain, log = _chain(lambda prior, also: _result("no_significant_effect", [weak]))
    links, _ = chain.run()
    assert links == [] and log == [((), ())]
