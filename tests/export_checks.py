"""One check shared by the real-record tests: the exported model is the reported model
(issue 32, must-show 2), run as a user does with ``plantdyn export``."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import control
import numpy as np

from flows.cli import main
from pipeline.adapters.export import load_control


def assert_export_matches_report(run_dir: Path, checks: dict, tmp_path: Path) -> None:
    """No pair reports a bare gain off a moving curve; every exported transfer function's
    DC gain (rate) is within max(2σ, 10 %) of the reported one, python-control's
    ``dcgain`` of the file ``plantdyn export --format control`` writes (for an
    integrating pair: the DC gain of ``s G(s)``); a left-out pair says why."""
    for p in checks["pairs"]:
        key = "rate" if p["integrating"] else "gain"
        if p["settled"]["verdict"] != "settled":
            assert p[key] is None and p["gain_note"], p
        else:
            assert p[key] is not None and p[f"{key}_std"] > 0, p
    out = tmp_path / "model.json"
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(["export", str(run_dir), "--format", "control", "--out", str(out)])
    assert code == 0, err.getvalue()
    tfs = load_control(out)
    by_pair = {(p["output"], p["input"]): p for p in checks["pairs"]}
    written = 0
    for entry in json.loads(out.read_text())["pairs"]:
        p = by_pair[(entry["output"], entry["input"])]
        key = "rate" if p["integrating"] else "gain"
        if entry["transfer_function"] is None:
            assert entry.get("fit_error"), entry
            continue
        tf = tfs[(entry["output"], entry["input"])]
        if p["integrating"]:
            tf = tf * control.tf([1, 0], [1])
        dc = float(np.real(control.dcgain(tf)))
        tol = max(2 * p[f"{key}_std"], 0.1 * abs(p[key]))
        assert abs(dc - p[key]) <= tol, (entry["output"], entry["input"], dc, p[key], tol)
        written += 1
    assert written > 0
