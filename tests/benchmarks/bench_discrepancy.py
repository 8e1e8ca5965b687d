"""Hidden-effect suites and timing of the discrepancy workflow (one run, printed).

Run::

    .venv/bin/python -m tests.benchmarks.bench_discrepancy                    # every suite
    .venv/bin/python -m tests.benchmarks.bench_discrepancy --suite nuisance   # one suite
    .venv/bin/python -m tests.benchmarks.bench_discrepancy --trials 10        # smaller
    .venv/bin/python -m tests.benchmarks.bench_discrepancy --tune             # tuning seeds
    .venv/bin/python -m tests.benchmarks.bench_discrepancy --timing-only
    nice .venv/bin/python -m tests.benchmarks.bench_discrepancy --suite zoo --trials 3 --nulls 5

Suites (each trial: a shipped model -- ``boiler_pressure`` for even seeds, ``drum_level``
for odd -- with hidden effects of random size and location, white or AR(1) (phi
0.5-0.9) sensor noise at 10-30 % of each output's std, 1e4 samples at 2 s; the workflow
sees only the data and the nominal model):

1. ``clean``: one hidden effect per trial, ``--trials`` per catalogue effect plus
   ``--nulls`` null trials, simulated by ``pipeline.models.simulate`` with the model's own
   block structure (:func:`pipeline.simulated.effect_trials.make_hidden_effect_trial`).
2. ``nuisance``: the same kind of trials re-simulated as a real plant differs from its
   model (:func:`tests.nuisance_trials.make_nuisance_trial`: continuous-time plant, DCS
   controllers acting on the previous scan, actuator quantisation, a slow unmeasured
   disturbance, input noise).
3. ``pairs``: two simultaneous hidden effects at different locations, a random pair of
   catalogue effects per trial (clean simulation).
4. ``zoo``: the plant zoo (:mod:`tests.zoo`: a heat-exchanger loop with its OP measured,
   two tanks with an integrating level loop, an interacting 2 x 2 blend, a cooler with an
   equal-percentage valve), each simulated by its own continuous-time physics, written
   as a historian export with its model and job YAML and run through
   ``plantdyn discrepancy --no-prefect`` (:mod:`tests.benchmarks.zoo_suite`); per-family
   confusion tables, null verdicts, parameter errors, times.  ``--families``,
   ``--hours``, ``--keep DIR`` (keep every trial's folder) and ``--closed-loops`` (every
   job with ``discrepancy.open_loops: false``; the default opens them) apply to it.

Printed: the confusion matrices (markdown), correct name and location per effect, the
null false-positive rate, the median parameter error, the noise-free error removed,
spurious extra effects, for pairs both-named rate and the gap reduction of each step;
then the timing of the whole workflow on 1e5 samples (the demo plant, 1 s, 27.8 h).

Seeds: suite ``S`` uses ``SEED0[S] + 1000 * effect_index + trial``; thresholds were
tuned on ``TUNE_SEED0[S] + ...`` only (``--tune``); the CI tests use ``CI_SEED0[S]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections import Counter
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from pipeline.adapters.progress import bar as progress_bar
from pipeline.discrepancy import analyse_discrepancy
from pipeline.simulated.synthetic import make_discrepancy_demo
from pipeline.simulated.effect_trials import HIDDEN_EFFECTS, make_hidden_effects_trial
from pipeline.discrepancy.effects import Effect
from pipeline.errors import ConfigError
from pipeline.models.model import Model, model_from_dict

MODELS = Path(__file__).resolve().parents[2] / "configs" / "models"
SUITES = ("clean", "nuisance", "pairs", "zoo")
#: Seeds the thresholds were tuned on (never used for the published numbers or CI).
TUNE_SEED0 = {"clean": 1000, "nuisance": 700_000, "pairs": 800_000}
#: The published suites.  Nuisance seeds from 300 000 gave the first published run (IR
#: 32/50: renamed dead times and lags, which led to ``analyse._distinct_inverse_response``);
#: they are spent, the run after that change uses fresh seeds from 900 000.  Pair seeds
#: from 400 000 gave the 100-trial run of 2026-12-03 (45/100); reading its log led to
#: ``analyse._nested_lags``, so they are spent too and the run after it uses 1 100 000
#: (49/100).  Its log was read to classify the misses before the masked-pair search
#: (``chain.N_MASKED``, diagnosed on tuning seeds), so the run after that uses 1 200 000
#: (66/100); after the joint refits of dead times (diagnosed on tuning seeds only) the
#: run uses 1 300 000 (62/100); after the carried candidates, the weakened joint-refit
#: starts and the replaced compromises (``chain.N_CARRIED``, ``joint._WEAKER_STARTS``,
#: ``chain.N_REPLACED``; diagnosed on tuning seeds only) the run uses 1 400 000 (59/100);
#: after the trajectory screening (``screen._TRAJECTORY_STEP``, tuning seeds only) the
#: runs use 1 500 000 (64/100).  Its log was read to find that a later effect's
#: practical-significance bar should take the accepted sensor corrections off the
#: nominal gap (``analyse.gap_reference``), so those seeds are spent and the run after
#: it uses 1 600 000 (65/100).  The nuisance saturation row of 900 000 was read to find
#: that the final chain must be pruned (``chain.prune``) and that a replacing pair is not
#: led by the single effect's own kind (``chain.Chain._replaced``), so the nuisance suite
#: after those moves to 2 000 000 (438/450, saturation 44/50) and the pairs to 1 700 000
#: (64/100).  Both logs were read (the pairs' to find trials whose effect the chain's
#: rule must call minor -- ``effect_trials.each_needed`` -- and to try the dynamic
#: look-alike sweep, ``chain._DYNAMIC``, on its dead-time misses), so the runs after
#: those use nuisance 2 100 000 and pairs 1 800 000.  Both of those logs were read to
#: find trials no estimate can name (a saturation limit met only in the held-out third,
#: inverse responses in the Padé band, gains in series that one refitted gain absorbs:
#: the generator rules of ``effect_trials``), so the runs after those use nuisance
#: 2 200 000 and pairs 1 900 000.  The nuisance run of 2 200 000 was stopped after 103
#: trials, its dead-time misses read (the Padé rule's one-sample tolerance,
#: ``analyse._PADE_DELAY``): the nuisance suite after it uses 2 300 000.  The pairs run of
#: 1 900 000 (75/100) was read: three misses were lags named lag-like inverse responses
#: (``analyse._lag_like``, ``joint._NONNEGATIVE``), so pairs after it use 2 000 000.
#: Session 6 replaced ``_distinct_inverse_response``, ``_PADE_DELAY``, ``_lag_like`` and
#: the rest of the look-alike special cases by the catalogue's nesting
#: (``select.decide``); the first 15 dead-time, lag and inverse-response trials of
#: nuisance 2 300 000 were read to choose its margin (design notes, "Session 6"), so the
#: nuisance suite after it uses 2 400 000.  Session 7 diagnosed pairs 2 000 012 (a pair
#: whose effects are each too small alone: ``chain.N_MASKED``), so pairs move to 2 100 000,
#: whose first 20 were run once after that change, as its out-of-sample check (design
#: notes, "Session 7").
SUITE_SEED0 = {"clean": 100_000, "nuisance": 2_400_000, "pairs": 2_100_000}
#: The CI samples (tests/discrepancy/test_hidden_effects.py).
CI_SEED0 = {"clean": 200_000, "nuisance": 500_000, "pairs": 600_000}
#: Row/column label of the null case in the confusion matrix.
NONE = "none"


def load_model(name: str) -> Model:
    with (MODELS / f"{name}.yaml").open(encoding="utf-8") as fh:
        return model_from_dict(yaml.safe_load(fh))


def trial_seed(seed0: int, effect: str | None, k: int) -> int:
    index = len(HIDDEN_EFFECTS) if effect is None else HIDDEN_EFFECTS.index(effect)
    return seed0 + 1000 * index + k


def parameter_error(truth: Effect, found: Effect) -> float:
    """Largest relative parameter error (|found - true| / |true|) over the effect's
    numeric parameters; for ``gain`` the relative error of the factor.  A saturation
    limit reported absent (inf) where the truth has one counts as error 1."""
    errors = []
    for key, value in truth.parameters.items():
        if isinstance(value, str) or value is None:
            continue
        est = found.parameters[key]
        if not math.isfinite(est):
            errors.append(1.0 if math.isfinite(value) else 0.0)
            continue
        errors.append(abs(est - value) / abs(value))
    return max(errors) if errors else 0.0


def is_correct(truth: Effect | None, found: Effect | None) -> bool:
    """Name and location (or an exactly equivalent location) agree; for
    operating_point_gain the scheduling signal too."""
    if truth is None or found is None:
        return truth is None and found is None
    if truth.name != found.name:
        return False
    if truth.location != found.location and truth.location not in found.equivalent_locations:
        return False
    if truth.name == "operating_point_gain":
        return truth.parameters["signal"] == found.parameters["signal"]
    return True


def pair_names(seed: int) -> tuple[str, str]:
    """The random pair of catalogue effects of pair trial `seed` (a repeat is allowed:
    the two then sit at different locations)."""
    rng = np.random.default_rng([seed, 2])
    a, b = rng.choice(len(HIDDEN_EFFECTS), 2)
    return HIDDEN_EFFECTS[int(a)], HIDDEN_EFFECTS[int(b)]


#: Derived seeds of a trial whose draw is impossible: ``seed + SEED_STRIDE * attempt``.
SEED_STRIDE = 7_919_000


def make_trial(suite: str, effect: str | None, seed: int, n: int = 10_000):
    """The trial of `suite` (``clean``, ``nuisance`` or ``pairs``) for `seed`.

    Some draws are impossible: at the drawn noise level no gain of 15-60 % at any
    location of the drum-level loop closes 7.5 % of the held-out gap, or a pair's second
    effect has no free location left.  Then the next derived seed is drawn (up to 10;
    the trial's ``seed_used`` says which) -- the suites count them."""
    from tests.nuisance_trials import make_nuisance_trial

    model = load_model("boiler_pressure" if seed % 2 == 0 else "drum_level")
    for attempt in range(10):
        s = seed + SEED_STRIDE * attempt
        try:
            if suite == "pairs":
                names = pair_names(s)
            else:
                names = () if effect is None else (effect,)
            if suite == "nuisance":
                return make_nuisance_trial(model, names, seed=s, n=n), s
            return make_hidden_effects_trial(model, names, seed=s, n=n), s
        except ConfigError:
            continue
    raise ConfigError(f"no possible {suite} trial in 10 derived seeds of {seed}")


def _noise_free_removed(trial, result) -> float:
    """Share of the nominal model's noise-free held-out error that the augmented model
    removes (relative to each output's true std, pooled)."""
    h = slice(result.series.holdout_start, None)
    num = den = 0.0
    for name in result.series.measured:
        scale = float(np.std(trial.truth[name]))
        aug = result.series.augmented[name][h]
        nom = result.series.nominal[name][h]
        num += float(np.mean((trial.truth[name][h] - aug) ** 2)) / scale**2
        den += float(np.mean((trial.truth[name][h] - nom) ** 2)) / scale**2
    return 1.0 - math.sqrt(num / den) if den > 0 else float("nan")


def run_trial(effect: str | None, seed: int, n: int = 10_000, suite: str = "clean"
              ) -> dict[str, Any]:
    """One trial; returns what the suite tabulates."""
    trial, seed_used = make_trial(suite, effect, seed, n)
    model = trial.model
    start = time.perf_counter()
    try:
        result = analyse_discrepancy(model, inputs=trial.inputs, measured=trial.measured,
                                     dt_s=trial.dt_s, seed=seed)
    except Exception as exc:  # an internal error is a result of the suite, not its end
        return _error_result(suite, effect, seed, seed_used, trial, exc,
                             time.perf_counter() - start)
    elapsed = time.perf_counter() - start
    found = result.effect
    chain = [step.candidate.effect for step in result.effects]
    label = NONE if result.verdict == "no_significant_effect" else (
        "inconclusive" if result.verdict == "inconclusive" else found.name)
    truths = list(trial.effects)
    matched = [next((f for f in chain if is_correct(t, f)), None) for t in truths]
    out: dict[str, Any] = {
        "suite": suite, "seed": seed, "seed_used": seed_used, "model": model.name,
        "label": label,
        "effect": "+".join(t.name for t in truths) if suite == "pairs" else (effect or NONE),
        "verdict": result.verdict,
        "correct": (all(m is not None for m in matched) if suite == "pairs"
                    else is_correct(trial.effect, found)),
        "truth": "; ".join(t.describe() for t in truths) or None,
        "found": "; ".join(f.describe() for f in chain) or None,
        "noise": trial.noise, "visibility": trial.visibility, "time_s": elapsed,
        "param_error": float("nan"), "noise_free_removed": float("nan"),
        "lookalikes": [c.effect.describe() for c in result.lookalikes],
        "n_effects": len(result.effects),
        "step_reductions": [step.candidate.gap_reduction for step in result.effects],
        "n_matched": sum(m is not None for m in matched),
        "truth_named": [(t.name, m is not None) for t, m in zip(truths, matched)],
    }
    errors = []
    for t, f in zip(truths, matched):
        if f is None:
            continue
        if t.name == "saturation" and t.location != f.location:
            # an equivalent location behind a static gain: the limits are in other
            # units, so no parameter error is scored (counted in the summary)
            out["param_error_skipped"] = True
        else:
            errors.append(parameter_error(t, f))
    if errors:
        out["param_error"] = max(errors)
    if truths and chain:
        out["noise_free_removed"] = _noise_free_removed(trial, result)
    return out


def _error_result(suite: str, effect: str | None, seed: int, seed_used: int, trial,
                  exc: Exception, elapsed: float) -> dict[str, Any]:
    """The row of a trial whose analysis raised (counted as wrong; printed)."""
    truths = list(trial.effects)
    return {"suite": suite, "seed": seed, "seed_used": seed_used, "model": trial.model.name,
            "label": "error", "verdict": f"error: {type(exc).__name__}: {exc}",
            "effect": "+".join(t.name for t in truths) if suite == "pairs" else (effect or NONE),
            "correct": False, "truth": "; ".join(t.describe() for t in truths) or None,
            "found": None, "noise": trial.noise, "visibility": trial.visibility,
            "time_s": elapsed, "param_error": float("nan"), "noise_free_removed": float("nan"),
            "lookalikes": [], "n_effects": 0, "step_reductions": [], "n_matched": 0,
            "truth_named": [(t.name, False) for t in truths]}


def _run(args: tuple) -> dict[str, Any]:
    return run_trial(*args)


def suite_jobs(suite: str, trials: int, nulls: int, seed0: int,
               effects: tuple[str, ...] = HIDDEN_EFFECTS, n: int = 10_000) -> list[tuple]:
    """The ``(effect, seed, n, suite)`` jobs of a suite (pairs: ``trials`` pair trials
    and no nulls; the others: ``trials`` per effect and ``nulls`` nulls)."""
    if suite == "pairs":
        return [(None, seed0 + k, n, suite) for k in range(trials)]
    jobs = [(e, trial_seed(seed0, e, k), n, suite) for e in effects for k in range(trials)]
    return jobs + [(None, trial_seed(seed0, None, k), n, suite) for k in range(nulls)]


def _run_zoo(args: tuple) -> dict[str, Any]:
    from tests.benchmarks.zoo_suite import run_zoo_trial

    return run_zoo_trial(*args)


def run_zoo(jobs: list[tuple], *, workers: int = 2, jsonl: str | None = None,
            redraws: Any = None) -> list[dict[str, Any]]:
    """Run zoo trials on a process pool, one printed line per trial (and one JSON line
    per trial appended to `jsonl`, which ``python -m tests.benchmarks.zoo_suite`` tabulates
    again, several files together).  `redraws` (:class:`tests.benchmarks.zoo_suite.Redraws`):
    an invisible draw is followed by the job it names, run in the same pool."""
    import json

    results: list[dict[str, Any]] = []
    total = len(jobs)
    with ProcessPoolExecutor(max_workers=workers) as pool, \
            progress_bar("zoo suite", "trials") as tick:
        tick(0, total)
        pending = {pool.submit(_run_zoo, job): job for job in jobs}
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                job, res = pending.pop(future), future.result()
                results.append(res)
                if redraws is not None and (again := redraws.after(job, res)) is not None:
                    pending[pool.submit(_run_zoo, again)] = again
                    total += 1
                tick(len(results), total)
                if jsonl:
                    with open(jsonl, "a", encoding="utf-8") as fh:
                        fh.write(json.dumps(res) + "\n")
                _print_zoo_row(res)
    return results


def _mark(res: dict[str, Any]) -> str:
    """A printed row's first column: right, invisible (not run) or wrong."""
    return "ok " if res["correct"] else "-- " if res["label"] == "invisible" else "BAD"


def _print_zoo_row(res: dict[str, Any]) -> None:
    print(f"{_mark(res)} {res['family']:>14} {res['effect']:>18} seed {res['seed']} -> "
          f"{res['label']:>20} {res.get('time_s', float('nan')):5.0f}s | truth "
          f"{res['truth']} | found {res['found']} | chain {res.get('chain')} | "
          f"noise {res['noise']:.3f} | ideal gap reduction "
          f"{res.get('ideal_gap_reduction', float('nan')):.3f}", flush=True)


def main_zoo(args: argparse.Namespace) -> None:
    """The zoo suite (module docstring, suite 4)."""
    from tests.benchmarks.zoo_suite import (
        MAX_DRAWS_FACTOR,
        SEEDS_PER_EFFECT,
        ZOO_SEED0,
        Redraws,
        issue_bars,
        summarise_zoo,
        zoo_jobs,
    )
    from tests.zoo import FAMILIES, ZOO_EFFECTS

    trials = 20 if args.trials is None else args.trials
    nulls = 30 if args.nulls is None else args.nulls
    families = tuple(args.families or FAMILIES)
    effects = tuple(e for e in args.effects if e in ZOO_EFFECTS) \
        if args.effects != list(HIDDEN_EFFECTS) else ZOO_EFFECTS
    start = time.perf_counter()
    seed0 = ZOO_SEED0 if args.seed0 is None else args.seed0
    max_draws = min(MAX_DRAWS_FACTOR * trials, SEEDS_PER_EFFECT) \
        if args.max_draws is None else args.max_draws
    try:  # more trials, nulls or draws than an effect's seeds: one message, exit 2
        jobs = zoo_jobs(trials, nulls, families=families, effects=effects,
                        hours=args.hours, seed0=seed0)
        redraws = Redraws(trials, max_draws, seed0)
    except ValueError as exc:
        print(f"bench_discrepancy --suite zoo: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    extra = {"open_loops": False} if args.closed_loops else None
    jobs = [(*j, args.keep, extra) for j in jobs]
    results = run_zoo(jobs, workers=args.workers, jsonl=args.jsonl, redraws=redraws)
    print(f"\n## Zoo suite: {trials} visible trials per (family, effect) (at most "
          f"{max_draws} draws) + {nulls} nulls per family, seeds from {seed0}, "
          f"{time.perf_counter() - start:.0f} s wall on {args.workers} workers\n")
    print(summarise_zoo(results))
    print("\n".join(["", "Issue 34's bars:", ""] + issue_bars(results)))


def run_jobs(jobs: list[tuple], *, workers: int = 2, verbose: bool = True,
             label: str = "hidden-effect suite") -> list[dict[str, Any]]:
    """Run trials on a process pool (terminal: a progress bar with rate and ETA)."""
    results = []
    with ProcessPoolExecutor(max_workers=workers) as pool, \
            progress_bar(label, "trials") as tick:
        tick(0, len(jobs))
        for res in pool.map(_run, jobs, chunksize=1):
            results.append(res)
            tick(len(results), len(jobs))
            if verbose:
                print(f"{_mark(res)} {res['suite']:>8} {res['effect']:>28} seed {res['seed']} "
                      f"{res['model']:>15} -> {res['label']:>20} {res['time_s']:5.1f}s | "
                      f"truth {res['truth']} | found {res['found']} | "
                      f"{res['noise']['kind']} {res['noise']['relative_std']:.2f} | "
                      f"{res['lookalikes']}", flush=True)
    return results


def summarise(results: list[dict[str, Any]]) -> str:
    """Confusion matrix (markdown) and the target numbers."""
    rows = [*HIDDEN_EFFECTS, NONE]
    cols = [*HIDDEN_EFFECTS, "inconclusive", NONE]
    if any(r["label"] == "error" for r in results):
        cols.append("error")
    counts = Counter((r["effect"], r["label"]) for r in results)
    lines = ["| hidden \\ named | " + " | ".join(cols) + " | correct name+location |",
             "|---" * (len(cols) + 2) + "|"]
    for row in rows:
        sub = [r for r in results if r["effect"] == row]
        if not sub:
            continue
        correct = sum(r["correct"] for r in sub)
        lines.append(f"| {row} | " + " | ".join(str(counts[(row, c)]) for c in cols)
                     + f" | {correct}/{len(sub)} |")
    effect_trials = [r for r in results if r["effect"] != NONE]
    nulls = [r for r in results if r["effect"] == NONE]
    lines.append("")
    if effect_trials:
        rate = np.mean([r["correct"] for r in effect_trials])
        lines.append(f"correct name and location: {rate:.3f} over {len(effect_trials)} effect trials")
    if nulls:
        fp = np.mean([r["verdict"] != "no_significant_effect" for r in nulls])
        lines.append(f"null false positives (any verdict but no_significant_effect): {fp:.3f} "
                     f"over {len(nulls)} null trials")
    lines.append("")
    lines.append("| effect | correct | median parameter error | 90th pct | median noise-free error "
                 "removed | 10th pct | median time s |")
    lines.append("|---|---|---|---|---|---|---|")
    for e in HIDDEN_EFFECTS:
        sub = [r for r in effect_trials if r["effect"] == e]
        if not sub:
            continue
        pe = np.array([r["param_error"] for r in sub
                       if r["correct"] and math.isfinite(r["param_error"])])
        rm = np.array([r["noise_free_removed"] for r in sub if math.isfinite(r["noise_free_removed"])])
        lines.append(
            f"| {e} | {sum(r['correct'] for r in sub)}/{len(sub)} | "
            f"{np.median(pe) if pe.size else float('nan'):.3f} | "
            f"{np.quantile(pe, 0.9) if pe.size else float('nan'):.3f} | "
            f"{np.median(rm) if rm.size else float('nan'):.3f} | "
            f"{np.quantile(rm, 0.1) if rm.size else float('nan'):.3f} | "
            f"{np.median([r['time_s'] for r in sub]):.1f} |")
    skipped = sum(bool(r.get("param_error_skipped")) for r in effect_trials)
    if skipped:
        lines.append(f"\n(parameter error not scored for {skipped} saturation trial(s) found at an "
                     "equivalent location behind a static gain: limits in other units)")
    pe_all = np.array([r["param_error"] for r in effect_trials
                       if r["correct"] and math.isfinite(r["param_error"])])
    rm_all = np.array([r["noise_free_removed"] for r in effect_trials
                       if math.isfinite(r["noise_free_removed"])])
    if pe_all.size:
        lines.append(f"\nmedian parameter error (correct trials): {np.median(pe_all):.4f}")
    if rm_all.size:
        lines.append(f"median noise-free error removed (trials with an effect named): "
                     f"{np.median(rm_all):.3f}; fraction >= 0.8: {np.mean(rm_all >= 0.8):.3f}")
    found = [r for r in effect_trials if r["verdict"] == "effect_found"]
    if found:
        extra = sum(r["n_effects"] > 1 for r in found)
        lines.append(f"single-effect trials that grew a second effect: {extra}/{len(found)}")
    errors = [r for r in results if r["label"] == "error"]
    if errors:
        lines.append(f"internal errors: {len(errors)} ("
                     + "; ".join(f"seed {r['seed']}: {r['verdict']}" for r in errors[:5]) + ")")
    derived = sum(r["seed_used"] != r["seed"] for r in results)
    lines.append(f"trials drawn from a derived seed (the first draw impossible): {derived}")
    times = [r["time_s"] for r in results]
    lines.append(f"analysis time per trial: median {np.median(times):.2f} s, max {max(times):.2f} s")
    return "\n".join(lines)


def summarise_pairs(results: list[dict[str, Any]]) -> str:
    """Pairs suite: both named with location, one of them, the gap reduction of each
    step of the chain, per pair of effects and overall."""
    n = len(results)
    both = sum(r["correct"] for r in results)
    one = sum(r["n_matched"] == 1 for r in results)
    lines = [f"both effects named with location: {both}/{n} ({both / max(n, 1):.3f}); "
             f"exactly one: {one}; none: {n - both - one}"]
    first = [r["step_reductions"][0] for r in results if r["step_reductions"]]
    second = [r["step_reductions"][1] for r in results if len(r["step_reductions"]) > 1]
    if first:
        lines.append(f"held-out gap reduction of step 1: median {np.median(first):.3f} "
                     f"({len(first)} trials); step 2: "
                     + (f"median {np.median(second):.3f} ({len(second)} trials)" if second
                        else "none"))
    pe = np.array([r["param_error"] for r in results
                   if r["correct"] and math.isfinite(r["param_error"])])
    if pe.size:
        lines.append(f"median parameter error (both named; the larger of the two): "
                     f"{np.median(pe):.4f}")
    lines += ["", "| effect | in pairs | named with location |", "|---|---|---|"]
    for e in HIDDEN_EFFECTS:
        flags = [ok for r in results for name, ok in r["truth_named"] if name == e]
        if flags:
            lines.append(f"| {e} | {len(flags)} | {sum(flags)} |")
    derived = sum(r["seed_used"] != r["seed"] for r in results)
    lines.append(f"\ntrials drawn from a derived seed (the first draw impossible): {derived}")
    times = [r["time_s"] for r in results]
    lines.append(f"analysis time per trial: median {np.median(times):.2f} s, "
                 f"max {max(times):.2f} s")
    return "\n".join(lines)


def timing_1e5() -> str:
    model = load_model("boiler_pressure")
    inputs, measured, dt_s = make_discrepancy_demo(model, seed=3, hours=100_000 / 3600.0,
                                                   dt_s=1.0)
    start = time.perf_counter()
    result = analyse_discrepancy(model, inputs=inputs, measured=measured, dt_s=dt_s,
                                 clock=time.perf_counter)
    elapsed = time.perf_counter() - start
    stages = ", ".join(f"{k} {v:.1f}" for k, v in result.timings_s.items())
    return (f"1e5 samples ({measured['turbine_pressure'].size}): whole workflow {elapsed:.1f} s "
            f"({stages}); verdict {result.verdict}: "
            f"{result.effect.describe() if result.effect else '-'}; held-out RMS "
            f"{result.gap['holdout_rms_before']:.4g} -> {result.gap['holdout_rms_after']:.4g}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--suite", choices=[*SUITES, "all"], default="all")
    parser.add_argument("--trials", type=int, default=None,
                        help="trials per effect (clean, nuisance: 50) or pair trials (100)")
    parser.add_argument("--nulls", type=int, default=None,
                        help="null trials (clean: 50, nuisance: 100)")
    parser.add_argument("--tune", action="store_true", help="use the tuning seeds")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--effects", nargs="*", default=list(HIDDEN_EFFECTS))
    parser.add_argument("--timing-only", action="store_true")
    parser.add_argument("--families", nargs="*", default=None, help="zoo: families to run")
    parser.add_argument("--hours", type=float, default=None,
                        help="zoo: record length (default per family)")
    parser.add_argument("--keep", default=None, help="zoo: keep every trial's folder here")
    parser.add_argument("--closed-loops", action="store_true",
                        help="zoo: run every trial with discrepancy.open_loops: false")
    parser.add_argument("--jsonl", default=None, help="zoo: append each trial's row here")
    parser.add_argument("--max-draws", type=int, default=None,
                        help="zoo: draws per (family, effect) at most; an invisible draw is "
                             "replaced by the next seed until --trials are visible "
                             "(default: MAX_DRAWS_FACTOR x --trials, at most SEEDS_PER_EFFECT; "
                             "--trials: no redraws)")
    parser.add_argument("--seed0", type=int, default=None,
                        help="first seed (default: the suite's SUITE_SEED0 or ZOO_SEED0; "
                        "fresh seeds for a new run)")
    args = parser.parse_args(argv)
    defaults = {"clean": (50, 50), "nuisance": (50, 100), "pairs": (100, 0)}
    for suite in ([] if args.timing_only else SUITES if args.suite == "all" else [args.suite]):
        if suite == "zoo":
            main_zoo(args)
            continue
        trials, nulls = defaults[suite]
        trials = trials if args.trials is None else args.trials
        nulls = nulls if args.nulls is None else args.nulls
        seed0 = (args.seed0 if args.seed0 is not None
                 else (TUNE_SEED0 if args.tune else SUITE_SEED0)[suite])
        start = time.perf_counter()
        jobs = suite_jobs(suite, trials, nulls, seed0, tuple(args.effects))
        results = run_jobs(jobs, workers=args.workers, label=f"{suite} suite")
        what = (f"{trials} pair trials" if suite == "pairs"
                else f"{trials} trials per effect + {nulls} null")
        print(f"\n## Hidden-effect suite `{suite}`: {what}, seeds from {seed0}, "
              f"{time.perf_counter() - start:.0f} s wall on {args.workers} workers\n")
        print(summarise_pairs(results) if suite == "pairs" else summarise(results))
    if args.suite != "zoo":
        print("\n## Timing\n")
        print(timing_1e5())
    return 0


if __name__ == "__main__":
    sys.exit(main())
