"""pipeline.readouts.run_summary: one summary per run, read from checks.json alone.

* a stored run re-renders to the report.md it wrote (no refit, nothing else read) and its
  terminal lines are the ones ``plantdyn demo`` printed;
* each pair's cell says what the pair has: ``v ± σ unit``, a rate without the gain's
  unit, ``moving (no gain)``, feedback with its n_k; a window that could not be
  estimated is named with its time span; a checks document without the optional
  sections still renders.
"""

from __future__ import annotations

import json

from pipeline.readouts.run_summary import RunSummary


def test_a_stored_run_renders_to_the_report_it_wrote(demo_cli_run):
    assert demo_cli_run.returncode == 0, demo_cli_run.stderr
    run_dir = demo_cli_run.results
    manifest = json.loads((run_dir / "manifest.json").read_text())
    checks = json.loads((run_dir / "checks.json").read_text())
    summary = RunSummary.from_checks(checks, job=manifest["job"], status=manifest["status"],
                                     config=manifest["config"])
    assert summary.to_markdown() == (run_dir / "report.md").read_text(encoding="utf-8")
    printed = [ln.strip() for ln in (demo_cli_run.stdout + demo_cli_run.stderr).splitlines()]
    for line in summary.to_text():
        assert line in printed, line
    assert len(summary.pairs) == len(checks["pairs"]) == 4


def _pair(output, input, **kw):
    p = {"output": output, "input": input, "n_p": 40, "n_k": 0, "integrating": False,
         "gain": None, "gain_std": None, "rate": None, "rate_std": None,
         "settled": {"verdict": "settled"}, "agreement": {"verdict": "pass", "p_value": 0.5},
         "feedback": None, "warnings": []}
    p.update(kw)
    return p


def _checks(pairs, **kw):
    return {"dt_s": 2.0, "pairs": pairs, **kw}


def test_each_cell_says_what_the_pair_has():
    checks = _checks([
        _pair("T", "F", gain=1.23456, gain_std=0.0123),
        _pair("L", "F", integrating=True, rate=-0.5, rate_std=0.01),
        _pair("T", "Q", settled={"verdict": "moving"},
              feedback={"detected": True, "p_value": 0.0012}, n_k=2,
              warnings=[{"code": "not_settled", "message": "still moving"}])])
    config = {"signals": {"outputs": {"T": {"unit": "degC"}, "L": {"unit": "m"}},
                          "inputs": {"F": {"unit": "t/h"}}}}
    s = RunSummary.from_checks(checks, job="j", status="ok", config=config)
    gain, rate, moving = s.pairs
    assert gain.value_text == "1.235 ± 0.012 degC/t/h" and gain.value_plain == "1.235 ± 0.012"
    assert gain.horizon_s == 80.0 and gain.windows_text == "pass (0.5)"
    assert rate.quantity == "rate" and rate.value_text == "-0.5 ± 0.01"  # unit per s: no gain unit
    assert moving.value_text == "moving (no gain)" and moving.unit == ""  # Q has no unit
    assert moving.feedback_text == "detected (0.0012), n_k = 2"
    md = s.to_markdown().splitlines()
    assert "| T | F | A | 40 | 80 | settled | 1.235 ± 0.012 degC/t/h |  | pass (0.5) " \
           "| not tested | none |" in md
    assert any(ln.startswith("| L | F |") and "|  | -0.5 ± 0.01 |" in ln for ln in md)
    assert any("**detected (0.0012), n_k = 2**" in ln for ln in md)
    assert "- **T<-Q** (C) — not_settled: still moving." in md  # moving caps at C
    assert s.pair_records()[0] == {
        "output": "T", "input": "F", "grade": "A", "n_p": 40, "gain": "1.235 ± 0.012 degC/t/h",
        "settled": "settled", "windows": "pass (0.5)", "feedback": "not tested",
        "warnings": ""}


def test_a_window_that_could_not_be_estimated_is_named_with_its_time():
    failed = {"window": "w1", "samples": [100, 200], "status": "failed",
              "time": ["2026-01-01T00:03:20Z", "2026-01-01T00:06:38Z"],
              "error": "input F does not move"}
    s = RunSummary.from_checks(_checks([], search={"n_d": 100, "windows": [failed]}),
                               job="j", status="ok")
    assert s.window_notes() == ["Window w1 (2026-01-01T00:03:20Z to 2026-01-01T00:06:38Z, "
                                "samples 100–200) could not be estimated: input F does not "
                                "move."]
    trace = [{"n_d": 400, "failed_window": [0, 400], "error": "F is constant",
              "failed_window_time": ["2026-01-01T00:00:00Z", "2026-01-01T00:13:18Z"]}]
    none = RunSummary.from_checks(_checks([], search={"windows": [], "nd_trace": trace}),
                                  job="j", status="ok")
    assert none.window_notes() == ["No window check: the window 2026-01-01T00:00:00Z to "
                                   "2026-01-01T00:13:18Z (samples 0–400) cannot be "
                                   "estimated: F is constant."]
    assert "## The window check" in none.to_markdown()


def test_a_checks_document_without_optional_sections_renders():
    s = RunSummary.from_checks({"pairs": [_pair("y", "u", gain=2.0, gain_std=0.1)]},
                               job="bare", status="ok")
    md = s.to_markdown()
    assert md.startswith("# plantdyn run: bare\n\nStatus: **ok**.")
    assert s.header_facts() == [] and s.data_notes() == [] and s.window_notes() == []
    assert s.pairs[0].horizon_s is None and "| 2 ± 0.1 |" in md
