"""CI samples of the seeded fuzz campaign (issues 10 and 33; the full campaign is
scripts/fuzz.sh).

Each case is a valid job + export mutated one to three times (``tests/fuzzing.py``); the
case passes when ``plantdyn run --no-prefect`` ends with exit 0 or 2, prints no traceback
(exactly one error line on exit 2), stays under the time and memory limits and leaves no
half-written run.  The seeds here (10001..) are disjoint from the campaign's in
docs/reliability.md (1..2000), so the sample checks cases the fixes were not written against.
"""

from __future__ import annotations

from tests import fuzzing

#: 60 cases (about 30 s on a clean run; the suite's 10-minute budget): the campaigns in
#: docs/reliability.md run thousands.
CI_CASES = 60
CI_SEED = 10_001


def test_fuzz_sample_has_no_internal_errors_hangs_or_leftovers():
    outcomes = fuzzing.campaign(CI_CASES, CI_SEED, surface_share=0.0)
    s = fuzzing.summary(outcomes)
    bad = [o for o in outcomes if o.problem]
    detail = "\n".join(f"seed {o.seed} {o.base} {o.mutations}: {o.problem}\n  {o.stderr_tail[-400:]}"
                       for o in bad)
    assert not bad, f"{len(bad)} of {len(outcomes)} fuzz cases failed:\n{detail}"
    # every base (CSV long/wide, MCAP, YAML, numeric) is exercised, and the mutations
    # are hostile enough that a real share of cases is refused with exit 2
    assert all(n > 0 for n in s["by_base"].values()), s["by_base"]
    assert s["exit_codes"].get("2", 0) >= CI_CASES // 5, s["exit_codes"]
    assert s["exit_codes"].get("0", 0) >= 1, s["exit_codes"]


#: Store-surface cases (export, runs --plot, reindex, monitor baselines, discrepancy models,
#: corrupt catalogs and manifests, FIFOs and sockets): about 0.1 s each after the template
#: store (two runs of a 20-minute plant, about 10 s); a valid discrepancy model runs the
#: whole analysis (3-5 s, far longer on a loaded machine: the hang limit is 120 s).
SURFACE_CASES = 20  # four per surface; the campaign (scripts/fuzz.sh) runs thousands
SURFACE_SEED = 20_001


def test_fuzz_surfaces_sample_writes_only_where_it_may():
    outcomes = fuzzing.campaign(SURFACE_CASES, SURFACE_SEED, surface_share=1.0, time_limit=120.0)
    s = fuzzing.summary(outcomes)
    bad = [o for o in outcomes if o.problem]
    detail = "\n".join(f"seed {o.seed} {o.base} {o.mutations}: {o.problem}\n  "
                       f"{o.stderr_tail[-400:]}" for o in bad)
    assert not bad, f"{len(bad)} of {len(outcomes)} surface cases failed:\n{detail}"
    # every surface is exercised, and hostile enough that most cases are refused (exit 2)
    from tests.fuzz_surfaces import SURFACES

    assert set(s["by_base"]) == set(SURFACES), s["by_base"]
    assert s["exit_codes"].get("2", 0) >= SURFACE_CASES // 3, s["exit_codes"]
