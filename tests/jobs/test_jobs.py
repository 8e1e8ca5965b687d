"""Composition stages: a window that cannot be estimated is a recorded status."""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.adapters.config import load_job
from pipeline.jobs.estimation import (
    WindowFailure,
    estimate_window,
    load_recording,
    prepare,
    search_orders,
    summarise,
)
from tests.conftest import write_job, write_plant_csv


def test_window_where_the_input_does_not_move_is_recorded_not_fatal(tmp_path):
    write_plant_csv(tmp_path / "drop" / "export.csv", seed=5, hours=2.0)
    # a fixed horizon: four windows of 10 N_p fit in the 2-hour record
    cfg = load_job(write_job(tmp_path, search={"n_p": 60}))
    prep = prepare(cfg, load_recording(cfg))
    sr = search_orders(cfg, prep)
    assert len(sr.windows) >= 3
    a, b = sr.windows[1]
    x = prep.x.copy()
    x[a:b] = 0.3  # the input sits still (at an offset) through window w1
    prep2 = dataclasses.replace(prep, x=x)
    results = [estimate_window(prep2, tuple(w), sr.n_p) for w in sr.windows]
    assert isinstance(results[1], WindowFailure)
    assert "u (tag U.PV) does not vary" in results[1].error
    all_est = estimate_window(prep2, None, sr.n_p)
    summary = summarise(cfg, prep2, sr, all_est, results)
    status = {w["window"]: w["status"] for w in summary.checks["search"]["windows"]}
    assert status["w1"] == "failed" and all(v == "ok" for k, v in status.items() if k != "w1")
    windows_in_table = set(summary.step_responses["window"].unique())
    assert "w1" not in windows_in_table and {"all", "w0", "w2"} <= windows_in_table
    agr = summary.checks["pairs"][0]["agreement"]
    assert agr["n_windows"] == len(sr.windows) - 1
    assert np.isfinite(agr["statistic"])
