"""The quality grade rule and the numbers the run reports judge pairs by
(``pipeline/identification/quality.py``), against hand-computed answers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from pipeline.errors import ConfigError
from pipeline.identification.quality import (
    GRADE_RULE,
    fit_percent,
    grade_from_checks,
    pair_grade,
    relative_gain_array,
    simulate_fir,
)

CLEAN = dict(verdict="pass", value=2.0, std=0.1, whiteness_p=0.5, xcorr_ok=True,
             feedback_detected=False, feedback_handled_by=None, vif=1.2, settled="settled")


def test_a_pair_that_passes_everything_is_an_a():
    g = pair_grade(**CLEAN)
    assert g.grade == "A" and g.reasons == ()
    assert all(c["cap"] == "A" for c in g.criteria.values())


@pytest.mark.parametrize(("change", "grade", "reason"), [
    ({"verdict": "insufficient_data"}, "C", "windows insufficient_data"),
    ({"verdict": "fail"}, "D", "windows fail"),
    ({"std": 0.2}, "A", None),               # relative σ 0.10: still A
    ({"std": 0.21}, "B", "relative σ"),      # 0.105
    ({"std": 0.5}, "B", "relative σ"),       # 0.25
    ({"std": 0.6}, "C", "relative σ"),       # 0.30
    ({"std": 1.0}, "C", "relative σ"),       # 0.5 = |gain| at 2σ
    ({"std": 1.01}, "D", "gain within 2σ of zero"),
    ({"value": -2.0, "std": 0.1}, "A", None),  # the sign does not matter
    ({"value": 0.0}, "D", "gain within 2σ of zero"),
    ({"whiteness_p": 0.01}, "A", None),
    ({"whiteness_p": 0.0099}, "C", "not white"),
    ({"xcorr_ok": False}, "C", "cross-correlation"),
    ({"feedback_detected": True}, "C", "not handled"),
    ({"feedback_detected": True, "feedback_handled_by": "n_k"}, "B", "n_k ≥ 1"),
    ({"feedback_detected": True, "feedback_handled_by": "instruments"}, "A", None),
    ({"feedback_detected": None}, "A", None),   # not tested
    ({"vif": 5.0}, "A", None),
    ({"vif": 7.0}, "B", "VIF"),
    ({"vif": 10.5}, "C", "collinear"),
])
def test_each_criterion_caps_the_grade(change, grade, reason):
    g = pair_grade(**{**CLEAN, **change})
    assert g.grade == grade
    if reason is None:
        assert g.reasons == ()
    else:
        assert len(g.reasons) == 1 and reason in g.reasons[0] and g.reasons[0].startswith(grade)


def test_the_worst_cap_wins_and_missing_values_are_not_judged():
    g = pair_grade(**{**CLEAN, "verdict": "insufficient_data", "vif": 7.0, "std": 1.5})
    assert g.grade == "D"
    assert [r[0] for r in g.reasons] == ["D", "C", "B"]  # worst first
    g = pair_grade(verdict=None, value=None, std=None)
    assert g.grade == "A" and g.criteria["agreement"]["cap"] is None
    assert g.criteria["relative_sigma"]["cap"] is None


def test_bad_arguments_name_what_is_allowed():
    with pytest.raises(ConfigError, match="verdict 'passed' is not one of 'pass', 'fail'"):
        pair_grade(**{**CLEAN, "verdict": "passed"})
    with pytest.raises(ConfigError, match="feedback_handled_by 'nk' is not one of"):
        pair_grade(**{**CLEAN, "feedback_handled_by": "nk"})


def test_the_written_rule_has_the_implemented_thresholds():
    rule = {row[0]: row for row in GRADE_RULE}
    assert rule["relative σ of the gain"][2:5] == ("≤ 0.1", "≤ 0.25", "≤ 0.5")
    assert rule["window agreement"][2] == "pass" and rule["window agreement"][5] == "fail"
    assert rule["excitation"][2:4] == ("VIF ≤ 5", "VIF ≤ 10")
    assert all(len(row) == 6 for row in GRADE_RULE)


def test_grade_from_checks_reads_the_stored_document():
    pair = {"output": "y", "input": "u", "integrating": False, "gain": 1.0, "gain_std": 0.05,
            "rate": None, "rate_std": None, "n_k": 1,
            "agreement": {"verdict": "pass"}, "feedback": {"detected": True, "p_value": 0.001}}
    checks = {"residuals": {"whiteness": {"y": {"p_value": 0.3}},
                            "input_cross_correlation": {"y<-u": {"ok": True}}},
              "excitation": {"vif": {"u": 1.0}}, "estimation": {"instruments": {}}}
    assert grade_from_checks(pair, checks).grade == "B"  # feedback handled by n_k = 1
    checks["estimation"] = {"instruments": {"sp": "SP.TAG"}, "method": "instrumental_variables"}
    assert grade_from_checks(pair, checks).grade == "A"
    checks["residuals"]["whiteness"]["y"]["p_value"] = 0.001
    assert grade_from_checks(pair, checks).grade == "C"
    integ = {**pair, "integrating": True, "gain": None, "gain_std": None, "rate": 0.01,
             "rate_std": 0.009}
    assert grade_from_checks(integ, {}).grade == "D"  # rate within 2σ of zero
    assert grade_from_checks({}, {}).grade == "A"       # nothing to judge


def test_fit_percent_is_matlab_compare_nrmse():
    y = np.array([1.0, 2.0, 3.0, 4.0])
    assert fit_percent(y, y) == 100.0
    assert fit_percent(y, np.full(4, 2.5)) == pytest.approx(0.0)
    # ‖e‖ = 1, ‖y − ȳ‖ = √5
    assert fit_percent(y, np.array([1.0, 2.0, 3.0, 5.0])) == pytest.approx(100 * (1 - 1 / np.sqrt(5)))
    assert fit_percent(np.append(y, np.nan), np.append(y, 7.0)) == 100.0  # NaN left out
    assert np.isnan(fit_percent(np.ones(5), np.zeros(5)))
    with pytest.raises(ConfigError, match="1-D arrays of one length"):
        fit_percent(y, y[:3])


def test_relative_gain_array():
    g = np.array([[2.0, 1.0], [1.0, 2.0]])
    lam = relative_gain_array(g)
    np.testing.assert_allclose(lam, [[4 / 3, -1 / 3], [-1 / 3, 4 / 3]])
    g3 = np.array([[1.0, 0.2, 0.1], [0.3, 2.0, 0.4], [0.5, 0.1, 1.5]])
    lam3 = relative_gain_array(g3)
    np.testing.assert_allclose(lam3.sum(axis=0), 1.0)
    np.testing.assert_allclose(lam3.sum(axis=1), 1.0)
    assert relative_gain_array(np.ones((2, 3))) is None
    assert relative_gain_array(np.ones((2, 2))) is None          # singular
    assert relative_gain_array(np.array([[1.0, np.nan], [0.0, 1.0]])) is None


def test_simulate_fir_is_the_convolution_of_the_increments():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((200, 2))
    dh = rng.standard_normal((3, 2, 5))
    y = simulate_fir(dh, x)
    for i in range(3):
        ref = sum(scipy.signal.lfilter(dh[i, j], [1.0], x[:, j]) for j in range(2))
        np.testing.assert_allclose(y[4:, i], ref[4:])
    assert np.isnan(y[:4]).all()
    with pytest.raises(ConfigError, match="same n_x"):
        simulate_fir(dh, x[:, :1])


def test_a_gain_known_to_be_zero_after_a_clear_transient_is_a_result_not_a_d():
    """Issue 32, build 6: a closed loop that removes an input's effect at steady state
    (gain 1e-5 ± 5.5e-5 after a transient peaking at 0.02) grades by its σ against the
    peak; a pair with no transient above the noise (peak 0.25 with σ 0.1) stays D."""
    zero = pair_grade(**{**CLEAN, "value": 1e-5, "std": 5.5e-5, "peak": 0.02})
    assert zero.grade == "A", zero.reasons
    noise = pair_grade(**{**CLEAN, "value": 0.01, "std": 0.1, "peak": 0.25})
    assert noise.grade == "D" and "within 2σ of zero" in noise.reasons[0]


@pytest.mark.parametrize("change", [
    {"verdict": "insufficient_data"}, {"verdict": "fail"}, {"value": 2.0, "std": 0.8},
    {"value": 0.01, "std": 0.1}, {"whiteness_p": 0.001}, {"xcorr_ok": False},
    {"feedback_detected": True}, {"vif": 20.0}, {"settled": "moving"}])
def test_every_c_or_d_says_what_to_change_in_the_job(change):
    """Issue 32, build 6: a C or D reason names the job's YAML key (or the data) to change."""
    g = pair_grade(**{**CLEAN, **change})
    assert g.grade in "CD", g
    words = ("search.", "estimation.", "signals.", "source.", "longer record", "more data")
    assert all(any(w in r for w in words) for r in g.reasons if r[0] in "CD"), g.reasons
