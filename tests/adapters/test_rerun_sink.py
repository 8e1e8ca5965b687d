"""Tests of the Rerun sink on synthetic stored runs (no estimation involved).

The run directory is written through the real ResultStore; its step responses are the
analytic step responses of first-order lags K/(tau s + 1), so every value drawn can be
checked against a closed form as well as against the parquet file it was read from.
The .rrd is decoded with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41).
"""

from __future__ import annotations

import io
import json
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

from pipeline.adapters.rerun_sink import render_run
from pipeline.adapters.store import ResultStore
from pipeline.errors import ConfigError, DataQualityError

VENV_BIN = Path(sys.executable).parent
T0_S = 1_795_000_000.0
DT_S = 5.0
N_P = 16
PAIRS = {("pressure", "steam_flow"): (-0.8, 25.0), ("level", "feed water"): (1.5, 12.0)}  # (K, tau_s)
WINDOWS = ("all", "w0", "w1", "w2")
SIGNALS = (("steam_flow", "input"), ("feed water", "input"), ("pressure", "output"), ("level", "output"))
N_SAMPLES = 120  # 120 x 5 s = 10 min: far wider than the viewer's +-30 s default
MASKED = (30, 31, 32, 33)  # masked samples; sample 31 also has no raw value
WINDOW_GAIN_SCALE = {"all": 1.0, "w0": 0.9, "w1": 1.1, "w2": 1.2}


def analytic_step(gain: float, tau_s: float, time_s: np.ndarray) -> np.ndarray:
    return gain * (1.0 - np.exp(-time_s / tau_s))


def step_frame() -> pl.DataFrame:
    lag = np.arange(1, N_P + 1, dtype=np.int32)
    time_s = DT_S * lag  # the step value at lag l is the response l samples after the step
    parts = []
    for window in WINDOWS:
        for (output, inp), (gain, tau_s) in PAIRS.items():
            step = analytic_step(gain * WINDOW_GAIN_SCALE[window], tau_s, time_s)
            parts.append(pl.DataFrame({
                "window": window, "output": output, "input": inp, "lag": lag, "time_s": time_s,
                "delta_h": np.diff(step, prepend=0.0), "step": step,
                "step_std": 0.03 * abs(gain) * np.sqrt(lag / N_P),
                "n_p": np.full(N_P, N_P, dtype=np.int32), "n_d": np.zeros(N_P, dtype=np.int32),
                "dt_s": np.full(N_P, DT_S)}))
    return pl.concat(parts)


def sample_times() -> np.ndarray:
    return np.datetime64("2026-03-01T06:00:00", "us") + np.arange(N_SAMPLES) * np.timedelta64(5, "s")


def signals_frame() -> pl.DataFrame:
    parts = []
    for k, (name, role) in enumerate(SIGNALS):
        raw = 50.0 + 10.0 * k + np.sin(np.arange(N_SAMPLES) / (6.0 + 3 * k))
        good = np.ones(N_SAMPLES, dtype=bool)
        good[list(MASKED)] = False
        parts.append(pl.DataFrame({
            "time": sample_times(), "signal": name, "role": role,
            "raw": raw, "conditioned": raw - raw.mean(), "good": good,
        }).with_columns(pl.col("time").dt.replace_time_zone("UTC"),
                        raw=pl.when(pl.int_range(pl.len()) == MASKED[1]).then(None).otherwise(pl.col("raw"))))
    return pl.concat(parts)


def residuals_frame() -> pl.DataFrame:
    rng = np.random.default_rng(3)
    parts = [pl.DataFrame({"window": window, "time": sample_times(), "output": output,
                           "residual": rng.normal(0.0, 0.05, N_SAMPLES)})
             for window in ("all", "w0") for output in ("pressure", "level")]
    return pl.concat(parts).with_columns(pl.col("time").dt.replace_time_zone("UTC"))


def metrics(gain: float) -> list[dict]:
    return [{"window": "all", "output": "pressure", "input": "steam_flow", "metric": "static_gain", "value": gain},
            {"window": "all", "output": "pressure", "input": "steam_flow", "metric": "agreement", "value": "pass"}]


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """Three earlier runs (for trends) and a full run rendered inside the store's temp dir."""
    clock_s = [T0_S]
    store = ResultStore(tmp_path_factory.mktemp("sink") / "storage", clock=lambda: clock_s[0])
    for k, gain in enumerate((-0.82, -0.79, -0.81)):
        clock_s[0] = T0_S + 86400.0 * k
        with store.new_run("boiler", run_id=f"night{k}", config={}, inputs=[]) as run:
            run.add_metrics(metrics(gain))
    trends = store.trend("boiler")
    clock_s[0] = T0_S + 3 * 86400.0
    with store.new_run("boiler", config={}, inputs=[]) as run:
        run.write_step_responses(step_frame())
        run.write_signals(signals_frame())
        run.write_residuals(residuals_frame())
        run.write_checks({"pairs": [{"output": o, "input": i} for o, i in PAIRS]})
        render_run(run.path, trends=trends, ident=f"boiler/{run.run_id}")
    return {"store": store, "run_dir": run.path, "run_id": run.run_id, "trends": trends}


# --------------------------------------------------------------------------- decoding


def decode_recording(path: Path) -> dict[str, dict]:
    """entity path -> {timelines, index (int64 ns), values, indexes {timeline: int64 ns}}
    of its temporal scalar chunks, plus {'static': {component: values}} for static data.
    ``index`` is on the series' own axis: ``time`` (UTC) for signals and residuals,
    ``run_time`` for trends, else ``elapsed``; ``indexes`` holds every timeline."""
    out: dict[str, dict] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        entry = out.setdefault(chunk.entity_path, {"timelines": set(), "rows": {}, "static": {}})
        data_cols = [n for n in batch.schema.names if not n.startswith("rerun.controls") and n not in chunk.timeline_names]
        if chunk.is_static:
            for name in data_cols:
                entry["static"][name] = batch.column(name).to_pylist()
            continue
        entry["timelines"].update(chunk.timeline_names)
        values = [v[0] for v in batch.column("Scalars:scalars").to_pylist()]
        for timeline in chunk.timeline_names:
            index = batch.column(timeline).cast("int64").to_numpy()
            entry["rows"].setdefault(timeline, []).extend(zip(index.tolist(), values, strict=True))
    for entry in out.values():
        per = {}
        for timeline, rows in entry.pop("rows").items():
            rows = sorted(rows, key=lambda r: r[0])
            per[timeline] = (np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1] for r in rows]))
        entry["indexes"] = {t: idx for t, (idx, _) in per.items()}
        own = next((t for t in ("time", "run_time", "elapsed") if t in per), None)
        entry["index"], entry["values"] = per[own] if own else (np.zeros(0, np.int64), np.zeros(0))
        entry["values"] = entry["values"].astype(np.float64)
    return out


def decode_blueprint(path: Path) -> dict[str, dict]:
    """blueprint entity path -> {component: value}, without log_time and row ids."""
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


def ns(times: pl.Series) -> np.ndarray:
    return times.dt.epoch("ns").to_numpy()


# --------------------------------------------------------------------------- content


def test_every_stored_series_is_drawn_with_its_values(stored):
    run_dir = stored["run_dir"]
    data = decode_recording(run_dir / "recording.rrd")
    steps = pl.read_parquet(run_dir / "step_responses.parquet")
    signals = pl.read_parquet(run_dir / "signals.parquet")
    resid = pl.read_parquet(run_dir / "residuals.parquet")

    expected_paths = {"/__properties", "/trends/readme"}
    expected_paths |= {f"/step/{o}/{i}/window/{w}".replace(" ", "\\ ") for o, i in PAIRS for w in WINDOWS}
    expected_paths |= {f"/step/{o}/{i}/band/{b}".replace(" ", "\\ ") for o, i in PAIRS for b in ("upper", "lower", "fill")}
    expected_paths |= {f"/signals/{kind}/{s}".replace(" ", "\\ ")
                       for s, _ in SIGNALS for kind in ("raw", "conditioned", "masked")}
    expected_paths |= {"/residuals/pressure", "/residuals/level", "/trends/pressure/steam_flow/static_gain"}
    assert set(data) == expected_paths

    for (output, inp), (gain, tau_s) in PAIRS.items():
        base = f"/step/{output}/{inp}".replace(" ", "\\ ")
        for window in WINDOWS:
            stored_rows = steps.filter(window=window, output=output, input=inp).sort("lag")
            drawn = data[f"{base}/window/{window}"]
            assert drawn["timelines"] == {"elapsed"}
            # elapsed holds time_s as integer nanoseconds: l * 5 s exactly
            np.testing.assert_array_equal(drawn["index"], stored_rows["lag"].to_numpy().astype(np.int64) * 5_000_000_000)
            np.testing.assert_array_equal(drawn["values"], stored_rows["step"].to_numpy())  # float64, exact
            # ... which is the first-order lag's analytic step response
            np.testing.assert_allclose(drawn["values"], analytic_step(gain * WINDOW_GAIN_SCALE[window], tau_s,
                                                                      DT_S * np.arange(1, N_P + 1)), rtol=1e-15, atol=0)
        all_rows = steps.filter(window="all", output=output, input=inp).sort("lag")
        two_sigma = 2.0 * all_rows["step_std"].to_numpy()
        np.testing.assert_array_equal(data[f"{base}/band/upper"]["values"], all_rows["step"].to_numpy() + two_sigma)
        np.testing.assert_array_equal(data[f"{base}/band/lower"]["values"], all_rows["step"].to_numpy() - two_sigma)

    for name, _ in SIGNALS:
        rows = signals.filter(signal=name).sort("time")
        part = name.replace(" ", "\\ ")
        raw, cond, masked = (data[f"/signals/{k}/{part}"] for k in ("raw", "conditioned", "masked"))
        for series in (raw, cond, masked):
            assert series["timelines"] == {"time", "elapsed"}
        np.testing.assert_array_equal(raw["index"], ns(rows["time"]))
        # elapsed: the same samples, 0 at the first stored sample (every signal starts there)
        np.testing.assert_array_equal(raw["indexes"]["elapsed"], ns(rows["time"]) - ns(signals["time"]).min())
        np.testing.assert_array_equal(masked["indexes"]["elapsed"], masked["index"] - ns(signals["time"]).min())
        # every stored sample, a missing raw value as NaN (a gap in the line)
        np.testing.assert_array_equal(raw["values"], rows["raw"].fill_null(np.nan).to_numpy())
        assert np.isnan(raw["values"][MASKED[1]]) and np.isfinite(raw["values"]).sum() == N_SAMPLES - 1
        # conditioned: masked samples are gaps
        expected_cond = np.where(rows["good"].to_numpy(), rows["conditioned"].to_numpy(), np.nan)
        np.testing.assert_array_equal(cond["values"], expected_cond)
        # masked points: the masked samples that have a raw value, at their raw value
        marked = [k for k in MASKED if k != MASKED[1]]
        np.testing.assert_array_equal(masked["index"], ns(rows["time"])[marked])
        np.testing.assert_array_equal(masked["values"], rows["raw"].to_numpy()[marked])

    for output in ("pressure", "level"):
        rows = resid.filter(window="all", output=output).sort("time")
        drawn = data[f"/residuals/{output}"]
        assert drawn["timelines"] == {"time", "elapsed"}
        np.testing.assert_array_equal(drawn["index"], ns(rows["time"]))
        np.testing.assert_array_equal(drawn["indexes"]["elapsed"], ns(rows["time"]) - ns(signals["time"]).min())
        np.testing.assert_array_equal(drawn["values"], rows["residual"].to_numpy())


def test_trends_are_on_the_run_time_timeline(stored):
    drawn = decode_recording(stored["run_dir"] / "recording.rrd")["/trends/pressure/steam_flow/static_gain"]
    assert drawn["timelines"] == {"run_time"}
    np.testing.assert_array_equal(drawn["values"], [-0.82, -0.79, -0.81])  # run order
    expected_ns = [int(round((T0_S + 86400.0 * k) * 1e6)) * 1000 for k in range(3)]
    np.testing.assert_array_equal(drawn["index"], expected_ns)


def test_no_wallclock_timelines_and_a_derived_recording_id(stored):
    run_dir, run_id = stored["run_dir"], stored["run_id"]
    data = decode_recording(run_dir / "recording.rrd")
    timelines = set().union(*(entry["timelines"] for entry in data.values()))
    assert timelines == {"time", "elapsed", "run_time"}  # no log_time, no log_tick
    (recording,) = RrdReader(run_dir / "recording.rrd").recordings()
    assert recording.application_id == "plantdyn"
    assert recording.recording_id == str(uuid.uuid5(uuid.NAMESPACE_URL, f"plantdyn:boiler/{run_id}"))
    assert data["/__properties"]["static"]["RecordingInfo:name"] == [[f"boiler/{run_id}"]]


def test_default_blueprint_has_a_view_per_pair_and_full_ranges(stored):
    blueprint = decode_blueprint(stored["run_dir"] / "recording.rrd")
    views = {comps["ViewBlueprint:display_name"][0][0]: path for path, comps in blueprint.items()
             if path.startswith("/view/") and path.count("/") == 2}
    assert all(blueprint[p]["ViewBlueprint:class_identifier"] == [["TimeSeries"]]
               for n, p in views.items() if n != "How to see the trends")
    # outputs x inputs: pressure, level x steam_flow, feed water; two pairs were not estimated
    steps = [n for n in views if "←" in n and not n.startswith("trend") and "per run" not in n]
    assert sorted(steps) == sorted(["pressure ← steam_flow", "pressure ← feed water (not estimated)",
                                    "level ← steam_flow (not estimated)", "level ← feed water"])
    signal_views = {f"{s} ({r}): {k}" for s, r in SIGNALS for k in ("raw, × masked", "conditioned")}
    assert signal_views <= set(views)
    assert {"pressure: residual of the all-data estimate", "level: residual of the all-data estimate",
            "pressure ← steam_flow: static_gain per run"} <= set(views)
    for name, path in views.items():
        if name == "How to see the trends":
            continue
        ranges = blueprint[f"{path}/VisibleTimeRanges"]["VisibleTimeRanges:ranges"][0]
        axis = blueprint[f"{path}/TimeAxis"]["TimeAxis:view_range"]
        timelines = [r["timeline"] for r in ranges]
        assert all(r["range"] == {"start": None, "end": None} for r in ranges)  # all data on each timeline
        if name in ("pressure ← steam_flow", "level ← feed water"):
            # x from 0 to the last lag (+2 %), not the whole timeline (which holds 10 min of signals)
            assert timelines == ["elapsed"] and axis == [[{"start": 0, "end": int(round(1.02 * N_P * DT_S * 1e9))}]]
        elif "per run" in name:  # the runs' span and 5 % on either side: no point on an edge
            first_ns, last_ns = int(T0_S * 1e9), int((T0_S + 2 * 86400.0) * 1e9)
            pad_ns = 0.05 * (last_ns - first_ns)
            assert timelines == ["run_time"]
            assert abs(axis[0][0]["start"] - (first_ns - pad_ns)) < 1e6 and abs(axis[0][0]["end"] - (last_ns + pad_ns)) < 1e6
        elif "←" not in name:  # signals, residuals: on elapsed and on UTC time alike
            assert timelines == ["elapsed", "time"] and axis == [[{"start": None, "end": None}]]
    containers = {c["ContainerBlueprint:display_name"][0][0]: c for p, c in blueprint.items()
                  if p.startswith("/container/") and "ContainerBlueprint:display_name" in c}
    assert len(containers["plantdyn"]["ContainerBlueprint:contents"][0]) == 4  # steps, signals, residuals, trends
    assert containers["Step responses"]["ContainerBlueprint:grid_columns"] == [[2]]
    assert {"Signals (0 s = 2026-03-01 06:00:00 UTC)", "Residuals (0 s = 2026-03-01 06:00:00 UTC)",
            "Trends"} <= set(containers)
    assert blueprint["/time_panel"]["TimePanelBlueprint:timeline"] == [["elapsed"]]


def test_rendering_twice_gives_the_same_content(stored, tmp_path):
    """Same decoded data, recording id and blueprint (ids included).  The bytes differ:
    Rerun stamps chunks and rows with time-based ids and the blueprint store with a
    random id and a log_time; those are excluded from the comparison."""
    run_dir = stored["run_dir"]
    a = render_run(run_dir, trends=stored["trends"], out_name="again_a.rrd")
    b = render_run(run_dir, trends=stored["trends"], out_name="again_b.rrd")
    try:
        first, second = decode_recording(a), decode_recording(b)
        assert first.keys() == second.keys() == decode_recording(run_dir / "recording.rrd").keys()
        for path in first:
            assert first[path]["timelines"] == second[path]["timelines"]
            assert first[path]["static"] == second[path]["static"]
            np.testing.assert_array_equal(first[path]["index"], second[path]["index"])
            np.testing.assert_array_equal(first[path]["values"], second[path]["values"])
        assert decode_blueprint(a) == decode_blueprint(b)
        assert RrdReader(a).recordings()[0].recording_id == RrdReader(b).recordings()[0].recording_id
    finally:
        a.unlink()
        b.unlink()


def test_recording_is_in_the_manifest_and_verifies(stored):
    run_dir = stored["run_dir"]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    names = [f["name"] for f in manifest["files"]]
    assert "recording.rrd" in names and not any(n.endswith(".part") for n in names)
    stored["store"].read_run("boiler", stored["run_id"])  # sha256 of the .rrd verified too
    result = subprocess.run([str(VENV_BIN / "rerun"), "rrd", "verify", str(run_dir / "recording.rrd")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "1 file verified without error" in result.stdout + result.stderr


# --------------------------------------------------------------------------- edge cases


def test_absent_files_are_not_drawn(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    step_frame().filter(window="all").write_parquet(run_dir / "step_responses.parquet")
    out = render_run(run_dir, ident="solo/r1")
    data = decode_recording(out)
    assert {p.split("/")[1] for p in data} == {"step", "__properties"}
    blueprint = decode_blueprint(out)
    tab_names = {c["ContainerBlueprint:display_name"][0][0] for p, c in blueprint.items() if p.startswith("/container/")}
    assert tab_names == {"plantdyn", "Step responses"}


def test_distinct_names_stay_distinct(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    signals = signals_frame().filter(signal="pressure")
    pl.concat([signals.with_columns(signal=pl.lit(n)) for n in ("flow rate", "flow_rate", "a/b")]).write_parquet(
        run_dir / "signals.parquet")
    data = decode_recording(render_run(run_dir, ident="names/r1"))
    assert {p for p in data if p.startswith("/signals/raw/")} == {
        "/signals/raw/flow\\ rate", "/signals/raw/flow_rate", "/signals/raw/a\\/b"}


def test_bad_arguments_leave_no_file(stored, tmp_path):
    run_dir = stored["run_dir"]
    before = sorted(p.name for p in run_dir.iterdir())
    with pytest.raises(ConfigError, match=r"trends: missing columns \['metric'\]"):
        render_run(run_dir, trends=stored["trends"].drop("metric"), out_name="bad.rrd")
    doubled = pl.concat([stored["trends"], stored["trends"]])
    with pytest.raises(DataQualityError, match=r"trends: 3 duplicate \(output, input, metric, created_utc\)"):
        render_run(run_dir, trends=doubled, out_name="bad.rrd")
    with pytest.raises(ConfigError, match="must be a plain file name"):
        render_run(run_dir, out_name="../escape.rrd")
    assert sorted(p.name for p in run_dir.iterdir()) == before
    assert not (run_dir.parent / "escape.rrd").exists()


# --------------------------------------------------------------------------- the real viewer


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _pixels_near(img: np.ndarray, colour: tuple[int, int, int], tol: int = 30) -> int:
    """Pixels within ``tol`` of ``colour`` in the viewport of a 1920x1080 screenshot
    (below the top bar and the tab bar, above the collapsed time panel; the side panels,
    whose badges and highlights use similar colours, start collapsed)."""
    plot_area = img[70:1050, :].astype(int)
    return int((np.abs(plot_area - np.array(colour)).max(axis=2) <= tol).sum())


@pytest.mark.slow
def test_headless_viewer_draws_steps_and_signals(stored, tmp_path):
    """The real viewer (software Vulkan: libvulkan1 + mesa-vulkan-drivers) opens the file.

    Step tab: the window series are drawn in their colours (blue, orange, green: a line of
    ~600 px length and 1 px width gives several hundred pixels; a run without windows
    gave 0 such pixels in the plot area).  Signals tab (made active through the blueprint
    API, on the timeline the file opens on -- no timeline switch): the red masked-sample
    crosses are drawn (~100 pixels measured; 0 for a run without masked samples, and 0
    when the tab's data were not on the opening timeline).  Screenshots are kept in
    tests/artefacts/ for people to look at.
    """
    from PIL import Image
    from rerun.experimental import ViewerClient

    def shot() -> np.ndarray:
        return np.asarray(Image.open(io.BytesIO(viewer.take_screenshot())).convert("RGB"))

    artefacts = Path(__file__).parents[1] / "artefacts"
    artefacts.mkdir(exist_ok=True)
    window_colours = [(31, 119, 180), (255, 127, 14), (44, 160, 44)]
    with ViewerClient.spawn(headless=True, port=_free_port(), hide_welcome_screen=True,
                            executable_path=str(VENV_BIN / "rerun")) as viewer:
        viewer.open(str(stored["run_dir"] / "recording.rrd"))
        deadline = time.monotonic() + 40.0
        while True:  # the first frames may be painted before the chunks arrive
            img = shot()
            counts = [_pixels_near(img, c) for c in window_colours]
            if min(counts) >= 300 or time.monotonic() > deadline:
                break
            time.sleep(1.0)
        Image.fromarray(img).save(artefacts / "sink_steps.png")
        state = viewer.get_state()
        assert {v.name for v in state.views} >= {"pressure ← steam_flow", "level ← feed water"}
        assert all(not v.reports for v in state.views), [v.reports for v in state.views]

        blueprint = viewer.get_blueprint().blueprint
        tabs = next(k for k, e in blueprint.items() if e.get("ContainerBlueprint", {}).get("container_kind") == "Tabs")
        signals_tab = next(k for k, e in blueprint.items()
                           if str(e.get("ContainerBlueprint", {}).get("display_name", "")).startswith("Signals"))
        blueprint[tabs]["ContainerBlueprint"]["active_tab"] = signals_tab
        viewer.set_blueprint(blueprint, of="recording")
        deadline = time.monotonic() + 20.0
        while True:
            signals_img = shot()
            red = _pixels_near(signals_img, (220, 0, 0), tol=40)
            if red >= 60 or time.monotonic() > deadline:
                break
            time.sleep(1.0)
        Image.fromarray(signals_img).save(artefacts / "sink_signals.png")

    assert img.shape == (1080, 1920, 3) and img.std() > 10.0
    assert min(counts) >= 300, counts
    assert red >= 60, red  # 4 signals x 3 masked samples with a raw value: 12 crosses
