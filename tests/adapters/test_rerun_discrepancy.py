"""Tests of ``render_discrepancy``: the Rerun recording of a discrepancy run.

The run directory is written here, independently of the pipeline's job code, from a real
:func:`pipeline.discrepancy.analyse_discrepancy` result on a one-hour demo record
(controller gain 20 % above the model's): ``discrepancy.json`` is ``result.to_dict()``
(plus ``job``, ``run_id`` and ``model`` as the job adds them) and
``discrepancy_series.parquet`` is built from ``result.series``.  The .rrd is decoded with
``rerun.chunk.RrdReader`` (rerun-sdk 0.41) and every drawn number is compared with the
in-memory result, and where possible with an independent recomputation (block RMS from
the residual itself).
"""

from __future__ import annotations

import io
import json
import math
import shutil
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from rerun.chunk import RrdReader

from pipeline.adapters.rerun_sink import discrepancy as rerun_discrepancy_mod
from pipeline.adapters.rerun_sink import render_discrepancy
from pipeline.discrepancy import DiscrepancyConfig, analyse_discrepancy
from pipeline.simulated.synthetic import make_discrepancy_demo
from pipeline.jobs.demo import boiler_model
from pipeline.errors import ConfigError, DataQualityError

VENV_BIN = Path(sys.executable).parent
OUTPUT = "turbine_pressure"
TABS = {"Summary", "Measured vs simulated", "Residual before/after", "Localisation", "Candidates"}
# Three effect families instead of all nine and four fitted classes instead of five: the
# analysis takes ~4 s instead of ~10 s and still yields candidates that pass (gain) and
# candidates that fail (gain at the output, operating_point_gain at the drum), so both
# bar groups of the candidate charts are drawn.
# whitened acceptance only (holdout_rms_alpha 0): on the demo plant every candidate that
# closes part of the 35 % gap also passes the held-out RMS test, and the recording's
# "failed" group must exist for these tests
CONFIG = DiscrepancyConfig(effects=("gain", "dead_time", "operating_point_gain"), n_fit_candidates=4,
                           holdout_rms_alpha=0.0)


def series_frame(series) -> pl.DataFrame:
    """The long table of DiscrepancySeries (one row per output and sample)."""
    idx = np.arange(series.t_s.size)
    part = np.where(idx < series.fit_start, "warmup", np.where(idx < series.holdout_start, "fit", "holdout"))
    return pl.concat([pl.DataFrame({
        "output": out, "time_s": series.t_s, "part": part, "measured": series.measured[out],
        "nominal": series.nominal[out], "augmented": series.augmented[out],
        "residual_before": series.residual_before[out], "residual_after": series.residual_after[out],
        "rolling_rms": series.rolling_rms[out]}) for out in series.measured])


def write_run(run_dir: Path, summary: dict, frame: pl.DataFrame) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "discrepancy.json", "w", encoding="utf-8") as f:
        json.dump(summary, f)
    frame.write_parquet(run_dir / "discrepancy_series.parquet")
    return run_dir


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    inputs, measured, dt_s = make_discrepancy_demo(boiler_model(), 7, hours=1.0)
    result = analyse_discrepancy(boiler_model(), inputs=inputs, measured=measured,
                                 dt_s=dt_s, config=CONFIG)
    summary = {**result.to_dict(), "job": "demo_discrepancy", "run_id": "20260301T060000Z-ab12",
               "model": "boiler_pressure"}
    run_dir = write_run(tmp_path_factory.mktemp("disc") / "run", summary, series_frame(result.series))
    t0 = time.perf_counter()
    out = render_discrepancy(run_dir)
    return {"result": result, "dir": run_dir, "rrd": out, "render_s": time.perf_counter() - t0,
            "summary": summary}


# --------------------------------------------------------------------------- decoding


def decode_recording(path: Path) -> dict[str, dict]:
    """entity path -> {timelines, index (int64 ns), values} of its temporal scalar rows
    (in stored order within equal times), and {static: {component: values}}."""
    out: dict[str, dict] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        entry = out.setdefault(chunk.entity_path, {"timelines": set(), "rows": [], "static": {}})
        data_cols = [n for n in batch.schema.names if not n.startswith("rerun.controls") and n not in chunk.timeline_names]
        if chunk.is_static:
            for name in data_cols:
                entry["static"][name] = batch.column(name).to_pylist()
            continue
        entry["timelines"].update(chunk.timeline_names)
        (timeline,) = chunk.timeline_names
        index = batch.column(timeline).cast("int64").to_numpy()
        values = [v[0] for v in batch.column("Scalars:scalars").to_pylist()]
        entry["rows"].extend(zip(index.tolist(), values, strict=True))
    for entry in out.values():
        rows = sorted(entry.pop("rows"), key=lambda r: r[0])
        entry["index"] = np.array([r[0] for r in rows], dtype=np.int64)
        entry["values"] = np.array([r[1] for r in rows], dtype=np.float64)
    return out


def decode_blueprint(path: Path) -> dict[str, dict]:
    reader = RrdReader(path)
    (blueprint,) = reader.blueprints()
    out: dict[str, dict] = {}
    for chunk in reader.stream(store=blueprint).to_chunks():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.startswith("rerun.controls") or name in ("log_time", "blueprint"):
                continue
            out.setdefault(chunk.entity_path, {})[name] = batch.column(name).to_pylist()
    return out


def bars(entry: dict) -> dict[str, np.ndarray]:
    """values, abscissa (left edges) and widths of a static BarChart."""
    static = entry["static"]
    return {"values": np.array(static["BarChart:values"][0][0]["buffer"], dtype=np.float64),
            "abscissa": np.array(static["BarChart:abscissa"][0][0]["buffer"], dtype=np.float64),
            "widths": np.array(static["BarChart:widths"][0], dtype=np.float64)}


def text(entry: dict) -> str:
    return entry["static"]["TextDocument:text"][0][0]


def ns(seconds) -> np.ndarray:
    return np.rint(np.asarray(seconds, dtype=np.float64) * 1e9).astype(np.int64)


BASE = f"/discrepancy/{OUTPUT}"


# --------------------------------------------------------------------------- content


def test_entity_paths(run):
    data = decode_recording(run["rrd"])
    loc = run["result"].localization[OUTPUT]
    signals = list(loc["signals"])
    banded = [s for s in signals if "frequency_bands" in loc["signals"][s]]
    passed = {c.passed for c in run["result"].candidates}
    expected = {"/__properties", "/discrepancy/summary", "/discrepancy/candidates/table"}
    expected |= {f"{BASE}/signals/{k}" for k in ("measured", "nominal", "augmented", "fit_start", "holdout_start")}
    expected |= {f"{BASE}/residual/{k}" for k in ("before", "after", "fit_start", "holdout_start")}
    expected |= {f"{BASE}/rolling_rms", f"{BASE}/localisation/report",
                 f"{BASE}/localisation/time_windows/block_rms", f"{BASE}/localisation/operating_range/rms"}
    expected |= {f"{BASE}/localisation/{k}/{s}" for k in ("partial_r2", "neg_log10_p") for s in signals}
    expected |= {f"{BASE}/localisation/frequency_bands/{s}/{k}" for s in banded for k in ("model_gain", "data_gain")}
    if loc["time_windows"]["high_rms_windows_s"]:
        expected.add(f"{BASE}/localisation/time_windows/high_rms")
    expected |= {f"/discrepancy/candidates/{k}/{'passed' if p else 'failed'}"
                 for k in ("delta_bic", "holdout_z") for p in passed}
    assert passed == {True, False}  # CONFIG is chosen so that both groups exist
    assert banded == ["steam_flow"]  # the model input; aux_flow is not in the model
    assert set(data) == expected


def test_series_equal_the_analysis_result(run):
    data = decode_recording(run["rrd"])
    s = run["result"].series
    frame = pl.read_parquet(run["dir"] / "discrepancy_series.parquet")
    expected_ns = np.arange(s.t_s.size, dtype=np.int64) * 1_000_000_000  # 1 s samples from 0
    columns = {"signals/measured": s.measured, "signals/nominal": s.nominal, "signals/augmented": s.augmented,
               "residual/before": s.residual_before, "residual/after": s.residual_after,
               "rolling_rms": s.rolling_rms}
    for path, source in columns.items():
        drawn = data[f"{BASE}/{path}"]
        assert drawn["timelines"] == {"time_s"}
        np.testing.assert_array_equal(drawn["index"], expected_ns)
        np.testing.assert_array_equal(drawn["values"], source[OUTPUT])  # float64 end to end: exact
    np.testing.assert_array_equal(data[f"{BASE}/rolling_rms"]["values"], frame["rolling_rms"].to_numpy())
    # residual after = measured - augmented (what the plot claims to show)
    np.testing.assert_allclose(data[f"{BASE}/residual/after"]["values"],
                               s.measured[OUTPUT] - s.augmented[OUTPUT], rtol=0, atol=1e-15)


def test_split_lines_mark_fit_and_holdout_starts(run):
    data = decode_recording(run["rrd"])
    s = run["result"].series
    dt_s = run["result"].dt_s
    plotted = {"signals": np.concatenate([s.measured[OUTPUT], s.nominal[OUTPUT], s.augmented[OUTPUT]]),
               "residual": np.concatenate([s.residual_before[OUTPUT], s.residual_after[OUTPUT]])}
    for view, values in plotted.items():
        for key, start in (("fit_start", s.fit_start), ("holdout_start", s.holdout_start)):
            line = data[f"{BASE}/{view}/{key}"]
            # a vertical line: two rows at the split time, spanning the view's data
            np.testing.assert_array_equal(line["index"], ns([start * dt_s] * 2))
            assert sorted(line["values"]) == [np.nanmin(values), np.nanmax(values)]
            assert line["static"]["SeriesLines:aggregation_policy"] == [[1]]  # Off: keep both points


def test_localisation_bars_equal_the_json(run):
    data = decode_recording(run["rrd"])
    doc = json.loads((run["dir"] / "discrepancy.json").read_text())
    loc = doc["localization"][OUTPUT]
    for j, (name, entry) in enumerate(loc["signals"].items()):
        r2 = bars(data[f"{BASE}/localisation/partial_r2/{name}"])
        lp = bars(data[f"{BASE}/localisation/neg_log10_p/{name}"])
        assert r2["values"].tolist() == [entry["partial_r2"]]
        assert lp["values"].tolist() == [-math.log10(entry["p_value"])]
        for b in (r2, lp):  # one bar centred on x = j (abscissa is the left edge)
            assert b["abscissa"] + b["widths"] / 2 == pytest.approx([j], abs=1e-6)
    steam = loc["signals"]["steam_flow"]
    assert steam["significant"] and not loc["signals"]["aux_flow"]["significant"]  # the demo's answer

    bands = steam["frequency_bands"]
    model = bars(data[f"{BASE}/localisation/frequency_bands/steam_flow/model_gain"])
    data_gain = bars(data[f"{BASE}/localisation/frequency_bands/steam_flow/data_gain"])
    np.testing.assert_array_equal(model["values"], [b["model_gain"] for b in bands])
    np.testing.assert_array_equal(data_gain["values"], [b["data_gain"] for b in bands])
    lo = np.log10([b["f_lo_hz"] for b in bands])
    hi = np.log10([b["f_hi_hz"] for b in bands])
    mid = (lo + hi) / 2
    tol = 1e-6  # widths are stored as float32
    # model bar inside the left half of its band on a log10 f axis, data bar in the right half
    assert np.all(model["abscissa"] >= lo - tol) and np.all(model["abscissa"] + model["widths"] <= mid + tol)
    assert np.all(data_gain["abscissa"] >= mid - tol) and np.all(data_gain["abscissa"] + data_gain["widths"] <= hi + tol)

    bins = loc["operating_range"]["bins"]
    rng = bars(data[f"{BASE}/localisation/operating_range/rms"])
    np.testing.assert_array_equal(rng["values"], [b["rms"] for b in bins])
    lo = np.array([b["load_lo"] for b in bins])
    hi = np.array([b["load_hi"] for b in bins])
    centre = rng["abscissa"] + rng["widths"] / 2
    np.testing.assert_allclose(centre, (lo + hi) / 2, rtol=0, atol=1e-6 * np.abs(lo).max())  # float32 widths
    assert np.all(rng["abscissa"] >= lo) and np.all(rng["abscissa"] + rng["widths"] <= hi + 1e-6 * np.abs(hi).max())


def test_block_rms_staircase_matches_an_independent_computation(run):
    data = decode_recording(run["rrd"])
    result = run["result"]
    s, dt_s = result.series, result.dt_s
    tw = result.localization[OUTPUT]["time_windows"]
    window = int(round(tw["window_s"] / dt_s))
    e = s.residual_before[OUTPUT][s.fit_start:]
    nb = e.size // window
    block_rms = np.sqrt((e[: nb * window].reshape(nb, window) ** 2).mean(axis=1))
    drawn = data[f"{BASE}/localisation/time_windows/block_rms"]
    assert drawn["timelines"] == {"time_s"}
    starts_s = (s.fit_start + window * np.arange(nb + 1)) * dt_s  # block starts, then the last block's end
    np.testing.assert_array_equal(drawn["index"], ns(starts_s))
    np.testing.assert_allclose(drawn["values"], [*block_rms, block_rms[-1]], rtol=1e-12, atol=0)
    assert drawn["static"]["SeriesLines:interpolation_mode"] == [[2]]  # StepAfter: a staircase
    # high-RMS windows (block RMS > 1.5 x median, method of pipeline.discrepancy): points at their centres
    high = np.flatnonzero(block_rms > 1.5 * np.median(block_rms))
    assert high.size == len(tw["high_rms_windows_s"]) > 0
    points = data[f"{BASE}/localisation/time_windows/high_rms"]
    np.testing.assert_array_equal(points["index"], ns((s.fit_start + window * (high + 0.5)) * dt_s))
    np.testing.assert_allclose(points["values"], block_rms[high], rtol=1e-12, atol=0)


def test_candidate_bars_equal_the_json(run):
    data = decode_recording(run["rrd"])
    candidates = json.loads((run["dir"] / "discrepancy.json").read_text())["candidates"]
    assert len(candidates) == len(run["result"].candidates) >= 3
    for key in ("delta_bic", "holdout_z"):
        for group, flag in (("passed", True), ("failed", False)):
            ranks = [k for k, c in enumerate(candidates, 1) if c["passed"] is flag]
            b = bars(data[f"/discrepancy/candidates/{key}/{group}"])
            np.testing.assert_array_equal(b["values"], [candidates[k - 1][key] for k in ranks])
            np.testing.assert_allclose(b["abscissa"] + b["widths"] / 2, ranks, rtol=0, atol=1e-6)
    table = text(data["/discrepancy/candidates/table"])
    rows = [line for line in table.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert len(rows) == len(candidates)
    assert rows[0].startswith("| 1 | `gain` at `controller`")


def test_summary_states_verdict_effect_and_gap(run):
    data = decode_recording(run["rrd"])
    result = run["result"]
    assert result.verdict == "effect_found" and (result.effect.name, result.effect.location) == ("gain", "controller")
    summary = text(data["/discrepancy/summary"])
    assert data["/discrepancy/summary"]["static"]["TextDocument:media_type"] == [["text/markdown"]]
    factor = result.effect.parameters["factor"]
    assert abs(factor - 1.2) < 0.05  # the demo's hidden 20 % (recovered within a few %, seed 7)
    assert "# Discrepancy: effect_found" in summary
    assert f"`gain` at `controller` (factor = {factor:.4g})" in summary
    g = result.gap
    assert 0.2 < g["reduction"] < 1.0
    assert (f"| {OUTPUT} | {g['holdout_rms_before']:.4g} | {g['holdout_rms_after']:.4g} "
            f"| {100 * g['reduction']:.1f} % |") in summary
    s = result.series
    assert f"hold-out {s.holdout_start * result.dt_s:g}–{(s.t_s.size - 1) * result.dt_s:g} s" in summary
    report = text(data[f"{BASE}/localisation/report"])
    assert "| 0 | steam_flow |" in report and "| 1 | aux_flow |" in report
    assert "explained by: steam_flow" in report


def test_blueprint_tabs_views_and_time_panel(run):
    blueprint = decode_blueprint(run["rrd"])
    containers = {c["ContainerBlueprint:display_name"][0][0]: c for p, c in blueprint.items()
                  if p.startswith("/container/") and "ContainerBlueprint:display_name" in c}
    assert set(containers) == TABS | {"plantdyn discrepancy"}
    assert len(containers["plantdyn discrepancy"]["ContainerBlueprint:contents"][0]) == 5
    views = {path: comps for path, comps in blueprint.items() if path.startswith("/view/") and path.count("/") == 2}
    kinds = {}
    for path, comps in views.items():
        kind = comps["ViewBlueprint:class_identifier"][0][0]
        kinds.setdefault(kind, set()).add(comps["ViewBlueprint:space_origin"][0][0])
        if kind == "TimeSeries":  # full range on time_s, or the viewer shows +-30 s
            assert blueprint[f"{path}/VisibleTimeRanges"]["VisibleTimeRanges:ranges"] == [
                [{"timeline": "time_s", "range": {"start": None, "end": None}}]]
            assert blueprint[f"{path}/TimeAxis"]["TimeAxis:view_range"] == [[{"start": None, "end": None}]]
    assert kinds == {
        "TimeSeries": {f"{BASE}/signals", BASE},  # residual and residual-level views share the output origin
        "BarChart": {f"{BASE}/localisation/{k}" for k in
                     ("partial_r2", "neg_log10_p", "frequency_bands/steam_flow", "operating_range")}
                    | {"/discrepancy/candidates/delta_bic", "/discrepancy/candidates/holdout_z"},
        "TextDocument": {"/discrepancy/summary", "/discrepancy/candidates/table", f"{BASE}/localisation/report"},
    }
    # names, not indices or entity paths: bar charts have no series names, so their legends
    # (which would list raw entity paths) are hidden and the titles say what each bar is
    names = {comps["ViewBlueprint:display_name"][0][0]: path for path, comps in views.items()}
    assert f"{OUTPUT}: partial R² — 0 steam_flow · 1 aux_flow" in names
    assert f"{OUTPUT}: −log10 p (1.3: p = 0.05) — 0 steam_flow · 1 aux_flow" in names
    for name, path in names.items():
        kind = views[path]["ViewBlueprint:class_identifier"][0][0]
        if kind in ("BarChart", "TimeSeries"):
            assert blueprint[f"{path}/PlotLegend"]["PlotLegend:visible"] == [[False]], name
    # the summary has a tab of its own (full width: its tables are not cut off)
    summary_tab = containers["Summary"]["ContainerBlueprint:contents"][0]
    assert summary_tab == [names["Summary"].lstrip("/")]
    for panel_name in ("/blueprint_panel", "/selection_panel"):
        assert blueprint[panel_name]["PanelBlueprint:state"] == [[2]]  # collapsed
    s = run["result"].series
    panel = blueprint["/time_panel"]
    assert panel["TimePanelBlueprint:timeline"] == [["time_s"]]
    assert panel["TimePanelBlueprint:time_selection"] == [[{"min": int(ns(s.holdout_start)),
                                                           "max": int(ns(s.t_s.size - 1))}]]


def test_recording_id_verify_and_reproducibility(run, tmp_path):
    (recording,) = RrdReader(run["rrd"]).recordings()
    ident = "demo_discrepancy/20260301T060000Z-ab12"  # from discrepancy.json's job and run_id
    assert recording.application_id == "plantdyn"
    assert recording.recording_id == str(uuid.uuid5(uuid.NAMESPACE_URL, f"plantdyn:{ident}"))
    data = decode_recording(run["rrd"])
    assert data["/__properties"]["static"]["RecordingInfo:name"] == [[ident]]
    timelines = set().union(*(e["timelines"] for e in data.values()))
    assert timelines == {"time_s"}  # no log_time / log_tick

    result = subprocess.run([str(VENV_BIN / "rerun"), "rrd", "verify", str(run["rrd"])],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "1 file verified without error" in result.stdout + result.stderr

    again = render_discrepancy(run["dir"], out_name="again.rrd")
    try:
        second = decode_recording(again)
        assert second.keys() == data.keys()
        for path in data:
            assert data[path]["timelines"] == second[path]["timelines"]
            assert data[path]["static"] == second[path]["static"]
            np.testing.assert_array_equal(data[path]["index"], second[path]["index"])
            np.testing.assert_array_equal(data[path]["values"], second[path]["values"])
        assert decode_blueprint(again) == decode_blueprint(run["rrd"])
        assert RrdReader(again).recordings()[0].recording_id == recording.recording_id
    finally:
        again.unlink()
    explicit = render_discrepancy(run["dir"], out_name="explicit.rrd", ident="other/r9")
    try:
        assert RrdReader(explicit).recordings()[0].recording_id == str(
            uuid.uuid5(uuid.NAMESPACE_URL, "plantdyn:other/r9"))
    finally:
        explicit.unlink()


def test_extra_output_without_localisation_and_no_effect(run, tmp_path):
    """A second output (name with a space) that has series but no localisation, and a
    run whose verdict is no_significant_effect with no candidates."""
    frame = pl.read_parquet(run["dir"] / "discrepancy_series.parquet")
    other = frame.with_columns(pl.lit("drum level").alias("output"), (pl.col("measured") * 2).alias("measured"))
    summary = {**run["summary"], "verdict": "no_significant_effect", "effect": None, "candidates": []}
    run_dir = write_run(tmp_path / "run", summary, pl.concat([frame, other]))
    out = render_discrepancy(run_dir)
    data = decode_recording(out)
    level = "/discrepancy/drum\\ level"
    assert {p for p in data if p.startswith(level)} == {
        f"{level}/signals/{k}" for k in ("measured", "nominal", "augmented", "fit_start", "holdout_start")} | {
        f"{level}/residual/{k}" for k in ("before", "after", "fit_start", "holdout_start")} | {f"{level}/rolling_rms"}
    np.testing.assert_array_equal(data[f"{level}/signals/measured"]["values"], 2 * run["result"].series.measured[OUTPUT])
    assert not any(p.startswith("/discrepancy/candidates/") and p != "/discrepancy/candidates/table" for p in data)
    assert "**No effect accepted**" in text(data["/discrepancy/summary"])
    assert "No candidate effect was fitted." in text(data["/discrepancy/candidates/table"])
    blueprint = decode_blueprint(out)
    origins = {c["ViewBlueprint:space_origin"][0][0] for p, c in blueprint.items()
               if p.startswith("/view/") and p.count("/") == 2}
    assert f"{level}/signals" in origins and "/discrepancy/candidates/delta_bic" not in origins


# --------------------------------------------------------------------------- errors


def _damage_missing_json(d: Path) -> None:
    (d / "discrepancy.json").unlink()


def _damage_missing_series(d: Path) -> None:
    (d / "discrepancy_series.parquet").unlink()


def _damage_truncated_json(d: Path) -> None:
    raw = (d / "discrepancy.json").read_bytes()
    (d / "discrepancy.json").write_bytes(raw[: len(raw) // 2])


def _damage_garbage_parquet(d: Path) -> None:
    (d / "discrepancy_series.parquet").write_bytes(b"PAR1 this is not a parquet file PAR1")


def _damage_missing_column(d: Path) -> None:
    pl.read_parquet(d / "discrepancy_series.parquet").drop("augmented").write_parquet(d / "discrepancy_series.parquet")


def _damage_bad_part(d: Path) -> None:
    df = pl.read_parquet(d / "discrepancy_series.parquet")
    df.with_columns(part=pl.when(pl.int_range(pl.len()) == 5).then(pl.lit("test")).otherwise("part")).write_parquet(
        d / "discrepancy_series.parquet")


def _damage_text_in_numbers(d: Path) -> None:
    df = pl.read_parquet(d / "discrepancy_series.parquet")
    df.with_columns(pl.col("nominal").cast(pl.String).fill_null("").str.replace(r"^", "x")).write_parquet(
        d / "discrepancy_series.parquet")


def _damage_json_missing_key(d: Path) -> None:
    doc = json.loads((d / "discrepancy.json").read_text())
    del doc["gap"]
    (d / "discrepancy.json").write_text(json.dumps(doc))


@pytest.mark.parametrize(("damage", "message"), [
    (_damage_missing_json, r"discrepancy\.json: missing; .*re-run the discrepancy job"),
    (_damage_missing_series, r"discrepancy_series\.parquet: missing"),
    (_damage_truncated_json, r"discrepancy\.json: not readable JSON"),
    (_damage_garbage_parquet, r"discrepancy_series\.parquet: not a readable parquet file"),
    (_damage_missing_column, r"missing columns \['augmented'\]"),
    (_damage_bad_part, r"column 'part' holds \['test'\]; allowed \['warmup', 'fit', 'holdout'\]"),
    (_damage_text_in_numbers, r"columns have the wrong types"),
    (_damage_json_missing_key, r"discrepancy\.json: missing keys \['gap'\]"),
])
def test_bad_files_raise_and_leave_the_old_recording(run, tmp_path, damage, message):
    run_dir = tmp_path / "run"
    shutil.copytree(run["dir"], run_dir)
    before = (run_dir / "recording.rrd").read_bytes()
    damage(run_dir)
    names = sorted(p.name for p in run_dir.iterdir())
    with pytest.raises(DataQualityError, match=message):
        render_discrepancy(run_dir)
    assert sorted(p.name for p in run_dir.iterdir()) == names  # no .part left behind
    assert (run_dir / "recording.rrd").read_bytes() == before


def test_failure_while_writing_leaves_no_file(run, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    shutil.copytree(run["dir"], run_dir)
    before = (run_dir / "recording.rrd").read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("injected failure")

    monkeypatch.setattr(rerun_discrepancy_mod, "_send_candidates", boom)
    with pytest.raises(RuntimeError, match="injected failure"):
        render_discrepancy(run_dir)
    assert not [p for p in run_dir.iterdir() if p.name.endswith(".part")]
    assert (run_dir / "recording.rrd").read_bytes() == before
    with pytest.raises(ConfigError, match="must be a plain file name"):
        render_discrepancy(run_dir, out_name="../escape.rrd")
    assert not (tmp_path / "escape.rrd").exists()


# --------------------------------------------------------------------------- the real viewer


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _pixels_near(img: np.ndarray, colour: tuple[int, int, int], tol: int = 30) -> int:
    """Pixels near ``colour`` in the viewport of a 1920x1080 screenshot (below the top and
    tab bars, above the collapsed time panel; the side panels start collapsed)."""
    area = img[70:1050, :].astype(int)
    return int((np.abs(area - np.array(colour)).max(axis=2) <= tol).sum())


ARTEFACTS = Path(__file__).parents[1] / "artefacts"


def activate(viewer, tab: str) -> None:
    """Make the tab named ``tab`` the active one, through the blueprint API."""
    blueprint = viewer.get_blueprint().blueprint
    tabs = next(k for k, e in blueprint.items() if e.get("ContainerBlueprint", {}).get("container_kind") == "Tabs"
                and e["ContainerBlueprint"].get("display_name") == "plantdyn discrepancy")
    target = next(k for k, e in blueprint.items() if e.get("ContainerBlueprint", {}).get("display_name") == tab)
    blueprint[tabs]["ContainerBlueprint"]["active_tab"] = target
    viewer.set_blueprint(blueprint, of="recording")


@pytest.mark.slow
def test_headless_viewer_draws_every_view(run):
    """The real viewer opens the file with no view reporting an error.  *Measured vs
    simulated* tab (the file opens on *Summary*): the
    red split lines are drawn (two 1 px lines of ~650 px: ~650-700 pixels were measured;
    0 with the lines removed).  Candidates tab: the passed and failed bars are drawn.
    The viewer fills bars at ~80 % opacity over its dark background, so green
    (44, 160, 44) shows as ~(46, 133, 46) and red (214, 39, 40) as ~(174, 42, 43);
    ~70 000 and ~47 000 such pixels were measured, 0 without candidates.  Screenshots go
    to tests/artefacts/ for people to look at."""
    from PIL import Image
    from rerun.experimental import ViewerClient

    def shot() -> np.ndarray:
        return np.asarray(Image.open(io.BytesIO(viewer.take_screenshot())).convert("RGB"))

    def wait_for(check, seconds: float) -> np.ndarray:
        deadline = time.monotonic() + seconds
        while True:  # the first frames may be painted before the chunks arrive
            img = shot()
            if check(img) or time.monotonic() > deadline:
                return img
            time.sleep(1.0)

    red = (220, 0, 0)
    ARTEFACTS.mkdir(exist_ok=True)
    with ViewerClient.spawn(headless=True, port=_free_port(), hide_welcome_screen=True,
                            executable_path=str(VENV_BIN / "rerun")) as viewer:
        viewer.open(str(run["rrd"]))
        wait_for(lambda img: bool(viewer.get_state().views), 20.0)
        state = viewer.get_state()
        assert len(state.views) == 12
        assert all(not v.reports for v in state.views), [(v.name, v.reports) for v in state.views]
        activate(viewer, "Measured vs simulated")
        first = wait_for(lambda img: _pixels_near(img, red, 40) >= 300, 40.0)
        Image.fromarray(first).save(ARTEFACTS / "discrepancy_signals.png")
        activate(viewer, "Candidates")
        green, red_bar = (46, 133, 46), (174, 42, 43)  # as rendered (see the docstring)
        second = wait_for(lambda img: min(_pixels_near(img, green, 15), _pixels_near(img, red_bar, 15)) >= 5000, 20.0)
        Image.fromarray(second).save(ARTEFACTS / "discrepancy_candidates.png")
    assert _pixels_near(first, red, 40) >= 300
    assert _pixels_near(second, green, 15) >= 5000 and _pixels_near(second, red_bar, 15) >= 5000
