"""The ``zoo`` suite of :mod:`tests.benchmarks.bench_discrepancy`: the plant zoo as a user runs it.

Each trial (:mod:`tests.zoo.trial`): a family, an injected effect or nothing, a seed;
the historian export, the nominal model YAML and the discrepancy job YAML are written
to a scratch folder and the job is run exactly as a user would,
``plantdyn discrepancy job.yaml --no-prefect`` (in-process ``flows.cli.main``); the
result is read back from the run directory's ``discrepancy.json``.

Trials are visible effects (:mod:`tests.zoo.trial`: a model with the effect exactly
shrinks the held-out gap by at least 7.5 %); one that stays below after every redraw is
not run and is listed apart, and the cell's next seed is drawn in its place until the
cell has ``--trials`` visible trials or ``MAX_DRAWS_FACTOR`` times as many draws
(:class:`Redraws`; ``--max-draws``).  Tabulated per family: the confusion table (true effect × named effect, ``none`` =
``no_significant_effect``), the nulls' verdicts (``no_significant_effect`` /
``inconclusive`` / ``effect_found``), correct name and location per effect (the found
location or one of its ``equivalent_locations``), the median parameter error of the
correct trials (largest relative error over the truth's non-zero numeric parameters;
a saturation's infinite limit is not scored), the median and longest wall time per run and
the runs the time budget stopped (a "time budget" note in discrepancy.json); then issue
34's bars, each with its count, rate and whether it is met (:func:`issue_bars`).

Seeds: trial ``k`` of effect ``e`` uses ``ZOO_SEED0 + 1000 * index(e) + k`` (nulls: the
index after the last effect); each family draws from ``default_rng([seed,
crc32(family)])``, so the families' trials differ for one seed.  Nothing was tuned on
any zoo seed: the first run (this build) is the baseline.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.simulated.effect_trials import TRIAL_GAP_REDUCTION
from tests.zoo import FAMILIES, ZOO_EFFECTS
from tests.zoo.explainable import model_gap_reduction
from tests.zoo.trial import make_trial, write_trial

#: The published zoo seeds: the must-show run of session 8 (fresh when it ran; the
#: baseline of build 1 used 3 000 000).  Unseen runs since: 8 6x0 000 per session, the
#: last 8 680 000 (session 16); 8 690 000 was read by a smoke check of session 17;
#: 8 700 000 is issue 34's must-show run of session 19 (README) and 8 710 000 that of
#: session 20, so the next fresh seeds start at 8 720 000.
ZOO_SEED0 = 8_100_000
#: Row/column label of "nothing named" / "nothing injected".
NONE = "none"
#: Label of a trial whose effect stayed below the visibility bar after every redraw
#: (:mod:`tests.zoo.trial`), or whose plant the zoo could not start (a valve cooler's
#: steady state beyond its valve for one seed's exogenous draws): not run, left out of
#: the rates and counted apart.
INVISIBLE = "invisible"
#: Catalogue names the workflow can report (columns of the confusion tables).
NAMED = ("gain", "dead_time", "extra_lag", "inverse_response", "sensor_bias_drift",
         "operating_point_gain", "deadband", "saturation", "unmodelled_input", "backlash",
         "stiction")


#: Seeds per effect (and for the nulls): trial ``k`` of effect ``e`` is
#: ``seed0 + SEEDS_PER_EFFECT * index(e) + k``, so ``k`` must stay below it, or the
#: draws of one effect would reuse the next effect's seeds.
SEEDS_PER_EFFECT = 1000


def zoo_seed(effect: str | None, k: int, seed0: int = ZOO_SEED0) -> int:
    """Seed of trial `k` of `effect` (None: a null trial); ValueError when `k` would
    reach the next effect's seeds (``k >= SEEDS_PER_EFFECT``)."""
    if not 0 <= k < SEEDS_PER_EFFECT:
        raise ValueError(f"trial {k} of {effect or 'the nulls'}: the zoo has "
                         f"{SEEDS_PER_EFFECT} seeds per effect (trials 0 to "
                         f"{SEEDS_PER_EFFECT - 1}); ask for fewer trials, nulls or draws")
    index = len(ZOO_EFFECTS) if effect is None else ZOO_EFFECTS.index(effect)
    return seed0 + SEEDS_PER_EFFECT * index + k


def _finite(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def parameter_error(truth: dict[str, Any], found: dict[str, Any]) -> float:
    """Largest relative error over the truth's finite non-zero numeric parameters."""
    errors = []
    for key, value in truth["parameters"].items():
        t = _finite(value)
        if t is None or t == 0.0:
            continue
        f = _finite(found["parameters"].get(key))
        errors.append(1.0 if f is None else abs(f - t) / abs(t))
    return max(errors) if errors else float("nan")


def _correct(truth: dict[str, Any] | None, found: dict[str, Any] | None) -> bool:
    if truth is None or found is None:
        return truth is None and found is None
    places = {found["location"], *found.get("equivalent_locations", [])}
    return truth["name"] == found["name"] and truth["location"] in places


def run_zoo_trial(family: str, effect: str | None, seed: int, hours: float | None = None,
                  keep: str | None = None, discrepancy: dict | None = None) -> dict[str, Any]:
    """One zoo trial through ``plantdyn discrepancy``; the row the suite tabulates.
    `discrepancy`: keys added to the job's ``discrepancy:`` section."""
    from flows.cli import main

    try:
        trial = make_trial(FAMILIES[family], effect, seed, hours=hours)
    except (ArithmeticError, ValueError) as exc:  # the zoo's own plant cannot start there
        return {"family": family, "effect": effect or NONE, "seed": seed, "truth": None,
                "noise": float("nan"), "label": INVISIBLE, "verdict": f"not simulated: {exc}",
                "found": None, "correct": False, "param_error": float("nan")}
    truth = None if trial.effect is None else trial.effect.to_dict()
    row: dict[str, Any] = {"family": family, "effect": effect or NONE, "seed": seed,
                           "truth": trial.effect.describe() if trial.effect else None,
                           "noise": trial.rel_noise, "redraws": trial.redraws,
                           "ideal_gap_reduction": trial.gap_reduction}
    if not trial.visible:  # not a finding by definition: not run, counted apart
        return {**row, "label": INVISIBLE, "verdict": INVISIBLE, "found": None,
                "correct": False, "param_error": float("nan")}
    root = Path(tempfile.mkdtemp(prefix=f"zoo_{family}_"))
    try:
        job = write_trial(trial, root, discrepancy=discrepancy)
        # the second bar (tests/zoo/explainable.py), read from the same export
        row["model_gap_reduction"] = model_gap_reduction(trial, job)
        out = io.StringIO()
        start = time.perf_counter()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            rc = main(["discrepancy", "--no-prefect", "--progress", "never", str(job)])
        row["time_s"] = time.perf_counter() - start
        lines = out.getvalue().strip().splitlines()
        if rc != 0 or not lines:
            return {**row, "label": "error", "verdict": f"error: exit {rc}", "found": None,
                    "correct": False, "param_error": float("nan")}
        d = json.loads((Path(lines[-1]) / "discrepancy.json").read_text())
    finally:
        if keep:
            shutil.copytree(root, Path(keep) / f"{family}_{effect or NONE}_{seed}",
                            dirs_exist_ok=True)
        shutil.rmtree(root, ignore_errors=True)
    found = d.get("effect")
    verdict = d["verdict"]
    label = {"no_significant_effect": NONE, "inconclusive": "inconclusive"}.get(
        verdict, found["name"] if found else NONE)
    correct = _correct(truth, found) if verdict == "effect_found" or truth is None else False
    return {**row, "label": label, "verdict": verdict, "correct": correct,
            "found": None if not found else (
                f"{found['name']} at {found['location']}: " + ", ".join(
                    f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                    for k, v in found["parameters"].items())),
            "chain": [f"{e['name']}@{e['location']}" for e in d.get("effects", [])],
            "notes": list(d.get("notes", [])),
            "lookalikes": [f"{e['name']}@{e['location']}" for e in d.get("lookalikes", [])
                           if isinstance(e, dict) and "name" in e],
            "param_error": parameter_error(truth, found) if correct and truth else float("nan")}


def zoo_jobs(trials: int, nulls: int, *, families: tuple[str, ...] = tuple(FAMILIES),
             effects: tuple[str, ...] = ZOO_EFFECTS, seed0: int = ZOO_SEED0,
             hours: float | None = None) -> list[tuple]:
    """``(family, effect, seed, hours)`` for every trial of the suite, interleaved
    (trial k of every effect and family before trial k + 1; the families alternate), so
    a run stopped early still covers every family and effect evenly."""
    rows = [(k, i, family, e) for family in families
            for i, e in enumerate((*effects, None))
            for k in range(trials if e is not None else nulls)]
    return [(family, e, zoo_seed(e, k, seed0), hours)
            for k, _, family, e in sorted(rows, key=lambda r: (r[0], r[1]))]


#: Draws per (family, effect) cell, as a multiple of the trials asked for, up to which an
#: invisible draw is replaced by the cell's next seed (:class:`Redraws`): the issue asks
#: for at least 20 visible trials per cell, and the valve cooler's opened loop rejects
#: small valve faults -- 3 to 20 of 20 draws per cell were visible in the must-show run
#: of seeds 8 700 000 (backlash 3 of 20), so 10 x covers a 1-in-7 cell.
MAX_DRAWS_FACTOR = 10


class Redraws:
    """Which trial to draw next when a draw is invisible: the cell's next seed
    (:func:`zoo_seed`, trial index ``k = trials, trials + 1, ...``) until the cell has
    had `max_draws` draws, so that each cell ends with `trials` visible trials where
    the cap allows.  Null trials are never redrawn (a null has nothing to see).

    Parameters
    ----------
    trials : int
        Draws per cell before any redraw (the suite's ``--trials``).
    max_draws : int
        Draws per cell at most (``trials``: no redraws); ValueError above
        ``SEEDS_PER_EFFECT``, whose seeds would be the next effect's.
    seed0 : int
        The suite's first seed.
    """

    def __init__(self, trials: int, max_draws: int, seed0: int) -> None:
        if max_draws > SEEDS_PER_EFFECT:
            raise ValueError(f"{max_draws} draws per cell: the zoo has {SEEDS_PER_EFFECT} "
                             f"seeds per effect; ask for --max-draws <= {SEEDS_PER_EFFECT}")
        self.max_draws, self.seed0 = max_draws, seed0
        self._next: dict[tuple[str, str], int] = {}
        self._trials = trials

    def after(self, job: tuple, row: dict[str, Any]) -> tuple | None:
        """The job to run in place of `job` (its result `row`), or None.

        Parameters
        ----------
        job : tuple
            ``(family, effect, seed, ...)`` as :func:`zoo_jobs` builds it (more fields
            are carried over).
        row : dict
            Its result (:func:`run_zoo_trial`).
        """
        family, effect = job[0], job[1]
        if effect is None or row.get("label") != INVISIBLE:
            return None
        k = self._next.get((family, effect), self._trials)
        if k >= self.max_draws:
            return None
        self._next[(family, effect)] = k + 1
        return (family, effect, zoo_seed(effect, k, self.seed0), *job[3:])


def summarise_zoo(results: list[dict[str, Any]]) -> str:
    """Per-family confusion tables, null verdicts, per-effect rates, errors and times."""
    lines = []
    for family in dict.fromkeys(r["family"] for r in results):
        hidden = Counter(r["effect"] for r in results
                         if r["family"] == family and r["label"] == INVISIBLE)
        sub = [r for r in results if r["family"] == family and r["label"] != INVISIBLE]
        cols = [c for c in (*NAMED, "inconclusive", NONE, "error")
                if c in ("inconclusive", NONE) or any(r["label"] == c for r in sub)]
        counts = Counter((r["effect"], r["label"]) for r in sub)
        lines += [f"### {family}", "",
                  "| true \\ named | " + " | ".join(cols) + " | correct | median param err "
                  "| median time s |", "|---" * (len(cols) + 4) + "|"]
        for row in (*ZOO_EFFECTS, NONE):
            rs = [r for r in sub if r["effect"] == row]
            if not rs:
                continue
            pe = [r["param_error"] for r in rs if math.isfinite(r["param_error"])]
            lines.append(
                f"| {row} | " + " | ".join(str(counts[(row, c)]) for c in cols)
                + f" | {sum(r['correct'] for r in rs)}/{len(rs)} | "
                + (f"{np.median(pe):.3f}" if pe else "-")
                + f" | {np.median([r.get('time_s', float('nan')) for r in rs]):.0f} |")
        nulls = [r for r in sub if r["effect"] == NONE]
        eff = [r for r in sub if r["effect"] != NONE]
        v = Counter(r["verdict"] for r in nulls)
        pe = [r["param_error"] for r in eff if math.isfinite(r["param_error"])]
        lines += ["", "nulls: " + ", ".join(f"{k} {n}" for k, n in sorted(v.items()))
                  + f" (of {len(nulls)}); effects named with location: "
                  f"{sum(r['correct'] for r in eff)}/{len(eff)}; median parameter error "
                  + (f"{np.median(pe):.3f}" if pe else "-")
                  + f"; median time per run {np.median([r.get('time_s', np.nan) for r in sub]):.0f} s"
                  + f", longest {np.nanmax([r.get('time_s', np.nan) for r in sub] + [0.0]):.0f} s"
                  + ", runs stopped by the time budget (discrepancy.max_time_s): "
                  + str(sum(any(n.startswith("time budget") for n in r.get("notes") or [])
                            for r in sub)),
                  ""]
        lines += _explainable_lines(eff)
        if hidden:
            lines += ["not visible after every redraw (left out): "
                      + ", ".join(f"{e} {k}" for e, k in sorted(hidden.items())), ""]
    return "\n".join(lines)


#: Issue 34's bars ("It must show", 1): named with location per effect class over the
#: families, per family, for backlash and saturation; nulls flagged per family; median
#: parameter error.
CLASS_BAR, FAMILY_BAR, ACTUATOR_BAR, NULL_BAR, PARAM_ERROR_BAR = 0.90, 0.80, 0.80, 0.05, 0.10
#: The classes held to :data:`ACTUATOR_BAR` instead of :data:`CLASS_BAR` (valve backlash,
#: saturation with windup: the issue names them apart at 80 %).
ACTUATOR_CLASSES = ("backlash", "saturation")


def issue_bars(results: list[dict[str, Any]]) -> list[str]:
    """Issue 34's bars against `results` (rows of :func:`run_zoo_trial`): one line per
    bar with the count, the rate and whether it is met.  Invisible trials are left out;
    a null is flagged when its verdict is ``effect_found`` or ``inconclusive`` (an
    error exit is counted apart)."""
    rows = [r for r in results if r["label"] != INVISIBLE]
    eff = [r for r in rows if r["effect"] != NONE]
    lines = ["| bar | count | rate | met |", "|---|---|---|---|"]

    def line(what: str, hit: int, total: int, bar: float, above: bool = True) -> None:
        rate = hit / total if total else float("nan")
        met = total > 0 and (rate >= bar if above else rate <= bar)
        sign = "≥" if above else "≤"
        lines.append(f"| {what} ({sign} {bar:.0%}) | {hit}/{total} | {rate:.1%} | "
                     + ("yes" if met else "**no**") + " |")

    for e in ZOO_EFFECTS:
        rs = [r for r in eff if r["effect"] == e]
        line(f"class {e}", sum(r["correct"] for r in rs), len(rs),
             ACTUATOR_BAR if e in ACTUATOR_CLASSES else CLASS_BAR)
    for family in dict.fromkeys(r["family"] for r in rows):
        rs = [r for r in eff if r["family"] == family]
        line(f"family {family}", sum(r["correct"] for r in rs), len(rs), FAMILY_BAR)
        nulls = [r for r in rows if r["family"] == family and r["effect"] == NONE]
        flagged = sum(r["verdict"] in ("effect_found", "inconclusive") for r in nulls)
        line(f"nulls flagged, {family}", flagged, len(nulls), NULL_BAR, above=False)
    errors = sum(r["label"] == "error" for r in rows)
    pe = [r["param_error"] for r in eff if math.isfinite(r["param_error"])]
    median = float(np.median(pe)) if pe else float("nan")
    lines.append(f"| median parameter error (≤ {PARAM_ERROR_BAR:.0%}) | {len(pe)} named | "
                 f"{median:.1%} | " + ("yes" if median <= PARAM_ERROR_BAR else "**no**")
                 + " |")
    cells = Counter((r["family"], r["effect"]) for r in eff)
    lines += ["", f"visible trials per (family, effect): {min(cells.values(), default=0)} to "
              f"{max(cells.values(), default=0)}; runs that exited with an error: {errors}"]
    return lines


def _explainable_lines(eff: list[dict[str, Any]]) -> list[str]:
    """Rates among the trials the nominal model with the true effect explains (the
    second bar, :mod:`tests.zoo.explainable`; rows from ``tests.benchmarks.zoo_explain``)
    and among the rest."""
    rows = [r for r in eff if "model_gap_reduction" in r
            and not math.isnan(r["model_gap_reduction"])]
    if not rows:
        return []
    parts = []
    for e in ZOO_EFFECTS:
        rs = [r for r in rows if r["effect"] == e]
        if not rs:
            continue
        ok = [r for r in rs if r["model_gap_reduction"] >= TRIAL_GAP_REDUCTION]
        rest = [r for r in rs if r not in ok]
        parts.append(f"{e} {sum(r['correct'] for r in ok)}/{len(ok)} explainable, "
                     f"{sum(r['correct'] for r in rest)}/{len(rest)} not")
    return [f"named among the trials the nominal model with the true effect explains "
            f"(closes at least {TRIAL_GAP_REDUCTION:.1%} of the held-out gap) and among "
            "the rest: " + "; ".join(parts), ""]


def main(argv: list[str] | None = None) -> int:
    """Tabulate the JSON lines of one or more ``--jsonl`` files together (a trial that
    appears twice -- same family, effect and seed -- counts once)."""
    rows = {}
    for path in (sys.argv[1:] if argv is None else argv):
        for line in Path(path).read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                rows.setdefault((r["family"], r["effect"], r["seed"]), r)
    print(summarise_zoo(list(rows.values())))
    print("\n".join(["", "Issue 34's bars:", ""] + issue_bars(list(rows.values()))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
