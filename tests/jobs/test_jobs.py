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


def test_each_window_is_estimated_once_and_the_run_stores_those_estimates(tmp_path,
                                                                          monkeypatch):
    """Stage 2 estimated the first and the last window at the chosen N_d; the job reads
    them from the search instead of estimating them again (issue 35, build 3), and what
    the run stores for them is what estimating the window gives."""
    import polars as pl

    import pipeline.jobs.estimation as job
    from pipeline.jobs.estimation import run_job

    write_plant_csv(tmp_path / "drop" / "export.csv", seed=5, hours=2.0)
    cfg = load_job(write_job(tmp_path))
    asked = []
    real = job.estimate_window

    def counting(prep, window, *args, **kw):
        asked.append(window)
        return real(prep, window, *args, **kw)

    monkeypatch.setattr(job, "estimate_window", counting)
    report = run_job(cfg)
    prep = prepare(cfg, load_recording(cfg))
    sr = search_orders(cfg, prep)
    assert len(sr.windows) >= 2
    first, last = tuple(sr.windows[0]), tuple(sr.windows[-1])
    assert None in asked and first not in asked and last not in asked
    assert len(asked) == 1 + len(sr.windows) - 2  # all data and the middle windows
    steps = pl.read_parquet(report.run_dir / "step_responses.parquet")
    for k, w in ((0, first), (len(sr.windows) - 1, last)):
        est = real(prep, w, *job.estimate_settings(cfg, sr, prep.x.shape[0]))
        got = steps.filter(pl.col("window") == f"w{k}").sort("lag")
        np.testing.assert_array_equal(got["step"].to_numpy(), est.step[0, 0, :sr.n_p[0, 0]])
        np.testing.assert_array_equal(got["step_std"].to_numpy(),
                                      est.step_std[0, 0, :sr.n_p[0, 0]])


def test_the_conditioning_section_reaches_the_core_as_its_spec(tmp_path):
    """``conditioning: {method: highpass}`` without a cutoff filters at the documented
    default, 500 sample periods (docs/guide/jobs.md), order 2; the prepared record is
    the core's ``condition`` of the gridded signals with exactly those settings, and
    checks.json records them."""
    from pipeline.identification.conditioning import condition, interpolate_gaps

    write_plant_csv(tmp_path / "drop" / "export.csv", seed=5, hours=2.0)
    cfg = load_job(write_job(tmp_path, conditioning={"method": "highpass"},
                             sampling={"dt_s": 2.0}))
    rec = load_recording(cfg)
    prep = prepare(cfg, rec)
    assert prep.dt_s == 2.0 and prep.conditioning == {
        "method": "highpass", "cutoff_period_s": 1000.0, "order": 2}
    # by hand: average the 1 s grid to 2 s, fill, high-pass at 1000 s
    vals = rec.values[: rec.values.shape[0] // 2 * 2].reshape(-1, 2, 2).mean(axis=1)
    filled, _ = interpolate_gaps(vals, np.isfinite(vals))
    ref = condition(filled[:, :1], filled[:, 1:], method="highpass", dt_s=2.0,
                    cutoff_period_s=1000.0, order=2)
    np.testing.assert_allclose(prep.x[:, 0], ref.x[:, 0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(prep.y[:, 0], ref.y[:, 0], rtol=1e-12, atol=1e-12)
