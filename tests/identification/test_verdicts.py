"""pipeline.identification.verdicts: the advice under feedback follows the evidence (issue 36, build 4).

Under feedback the direct estimate is consistent only with a right noise model (white
prediction errors) and a loop delay; an instrument is consistent whatever the noise
colour.  So the warning recommends the setpoint as instrument when the output's
prediction errors are not white, and keeps the direct estimate otherwise.
"""

from __future__ import annotations

from pipeline.identification.verdicts import pair_warnings


def _warnings(whiteness_p: float, instruments=()) -> dict:
    w = pair_warnings(inp="fuel", out="pressure", tag_in="FI-1", tag_out="PI-2", noise="auto",
                      noise_model={"order": 3}, whiteness_p=whiteness_p,
                      feedback={"detected": True, "p_value": 1e-9}, feedback_mode="auto",
                      instruments=list(instruments), n_k=1, n_p=40, n_p_min=3, settled=True,
                      significant=True, dt_s=1.0, end_jump=None,
                      agreement={"verdict": "pass"})
    return {x["code"]: x["message"] for x in w}


def test_white_prediction_errors_keep_the_direct_estimate():
    msg = _warnings(0.4)["feedback"]
    assert "more accurate than an instrument's" in msg
    assert "not white" not in msg


def test_coloured_prediction_errors_recommend_the_instrument():
    w = _warnings(1e-5)
    assert "coloured_residuals" in w
    msg = w["feedback"]
    assert "prediction errors are not white (Ljung–Box p = 1e-05)" in msg
    assert "list the loop's setpoint under signals.instruments" in msg


def test_with_instruments_the_warning_says_they_were_used():
    msg = _warnings(1e-5, instruments=["pressure_sp"])["feedback"]
    assert "estimated with the instruments pressure_sp" in msg
