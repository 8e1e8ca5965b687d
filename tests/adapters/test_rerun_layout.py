"""The default viewer layout of an estimation recording (issue 13): what an engineer sees
when the file opens, checked in the saved blueprint and in the real viewer.

The run is synthetic and written through the real ResultStore (so ``manifest.json`` holds
the job config and its units): 2 outputs × 3 inputs, first-order lags K/(tau s + 1), one
pair with N_p = 3 next to pairs with N_p = 40, an all-data estimate with a ±2σ band and
two windows; five signals, one of them a tag at ~200 next to tags at ~1 (on one shared
y axis the others would be flat lines); residuals of both outputs.

The viewer tests spawn the real viewer headless (software Vulkan: libvulkan1 +
mesa-vulkan-drivers, installed by scripts/test.sh) and screenshot single views
(``ViewerClient.take_screenshot(view_id)``); the screenshots are kept in
``tests/artefacts/`` (ignored by git), and small copies for the documentation are written
to ``docs/images/``.
"""

from __future__ import annotations

import io
import socket
import sys
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.adapters.rerun_sink import render_run
from pipeline.adapters.rerun_sink.common import BAND_FILL_COLOUR, ROLE_COLOURS, RESIDUAL_COLOUR
from pipeline.adapters.rerun_sink.estimation import BAND_POINTS
from pipeline.adapters.store import ResultStore

VENV_BIN = Path(sys.executable).parent
ARTEFACTS = Path(__file__).parents[1] / "artefacts"
DT_S = 5.0
INPUTS = ("steam_flow", "fuel_flow", "feed water")
OUTPUTS = ("pressure", "level")
UNITS = {"steam_flow": "kg/s", "fuel_flow": "kg/s", "feed water": "t/h", "pressure": "bar", "level": "mm"}
#: (gain, time constant s, N_p) per pair; level <- fuel_flow has N_p = 3 (15 s)
PAIRS = {("pressure", "steam_flow"): (-0.8, 25.0, 40), ("pressure", "fuel_flow"): (1.2, 40.0, 40),
         ("pressure", "feed water"): (0.3, 30.0, 40), ("level", "steam_flow"): (0.5, 20.0, 40),
         ("level", "fuel_flow"): (-0.4, 4.0, 3), ("level", "feed water"): (1.5, 30.0, 40)}
WINDOW_SCALE = {"all": 1.0, "w0": 0.93, "w1": 1.06}
N_SAMPLES = 720  # one hour at 5 s
#: signal -> (role, level, amplitude): the tag at 200 would flatten the others on one axis
SIGNALS = {"steam_flow": ("input", 200.0, 2.0), "fuel_flow": ("input", 1.0, 0.05),
           "feed water": ("input", 3.0, 0.2), "pressure": ("output", 1.5, 0.1), "level": ("output", 0.2, 0.02)}
MASKED = (300, 301, 302)


def step_frame() -> pl.DataFrame:
    parts = []
    for (output, inp), (gain, tau_s, n_p) in PAIRS.items():
        lag = np.arange(1, n_p + 1, dtype=np.int32)
        time_s = DT_S * lag
        for window, scale in WINDOW_SCALE.items():
            step = gain * scale * (1.0 - np.exp(-time_s / tau_s))
            parts.append(pl.DataFrame({
                "window": window, "output": output, "input": inp, "lag": lag, "time_s": time_s,
                "delta_h": np.diff(step, prepend=0.0), "step": step,
                "step_std": 0.04 * abs(gain) * np.sqrt(lag / n_p),
                "n_p": np.full(n_p, n_p, dtype=np.int32), "n_d": np.full(n_p, 360, dtype=np.int32),
                "dt_s": np.full(n_p, DT_S)}))
    return pl.concat(parts)


def sample_times() -> np.ndarray:
    return np.datetime64("2026-03-01T06:00:00", "us") + np.arange(N_SAMPLES) * np.timedelta64(5, "s")


def signals_frame() -> pl.DataFrame:
    parts = []
    k = np.arange(N_SAMPLES)
    for j, (name, (role, level, amplitude)) in enumerate(SIGNALS.items()):
        raw = level + amplitude * np.sin(k / (40.0 + 17 * j)) + 0.1 * amplitude * np.sin(k / 3.0)
        good = np.ones(N_SAMPLES, dtype=bool)
        good[list(MASKED)] = False
        parts.append(pl.DataFrame({"time": sample_times(), "signal": name, "role": role, "raw": raw,
                                   "conditioned": raw - raw.mean(), "good": good}))
    return pl.concat(parts).with_columns(pl.col("time").dt.replace_time_zone("UTC"))


def residuals_frame() -> pl.DataFrame:
    rng = np.random.default_rng(13)
    parts = [pl.DataFrame({"window": "all", "time": sample_times(), "output": o,
                           "residual": rng.normal(0.0, 0.02, N_SAMPLES)}) for o in OUTPUTS]
    return pl.concat(parts).with_columns(pl.col("time").dt.replace_time_zone("UTC"))


def job_config() -> dict:
    def spec(name):
        return {"tag": name.upper(), "unit": UNITS[name]}
    return {"job": "layout", "signals": {"inputs": {i: spec(i) for i in INPUTS},
                                         "outputs": {o: spec(o) for o in OUTPUTS}, "instruments": {}}}


def write_run(root: Path) -> Path:
    """A committed run directory (manifest with the config), rendered from its manifest."""
    store = ResultStore(root / "storage", clock=lambda: 1_795_000_000.0)
    with store.new_run("layout", run_id="r1", config=job_config(), inputs=[]) as run:
        run.write_step_responses(step_frame())
        run.write_signals(signals_frame())
        run.write_residuals(residuals_frame())
        run.write_checks({"pairs": [{"output": o, "input": i} for o, i in PAIRS]})
    run_dir = store.run_dir("layout", "r1")
    render_run(run_dir)  # units and ident from manifest.json
    return run_dir


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return write_run(tmp_path_factory.mktemp("layout"))


# --------------------------------------------------------------------------- decoding


def blueprint_of(path: Path) -> dict[str, dict]:
    from tests.adapters.test_rerun_sink import decode_blueprint

    return decode_blueprint(path)


def recording_of(path: Path) -> dict[str, dict]:
    from tests.adapters.test_rerun_sink import decode_recording

    return decode_recording(path)


def views_by_name(blueprint: dict) -> dict[str, str]:
    """view name -> blueprint path of the view."""
    return {c["ViewBlueprint:display_name"][0][0]: p for p, c in blueprint.items()
            if p.startswith("/view/") and p.count("/") == 2}


def container(blueprint: dict, name_prefix: str) -> dict:
    (found,) = [c for p, c in blueprint.items() if p.startswith("/container/")
                and str(c.get("ContainerBlueprint:display_name", [[""]])[0][0]).startswith(name_prefix)]
    return found


def contents_names(blueprint: dict, box: dict) -> list[str]:
    """Names of a container's views, in its order."""
    return [blueprint[f"/{ref}"]["ViewBlueprint:display_name"][0][0] for ref in box["ContainerBlueprint:contents"][0]]


def pair_name(o: str, i: str) -> str:
    return f"{o} [{UNITS[o]}] ← {i} [{UNITS[i]}]"


# --------------------------------------------------------------------------- blueprint


def test_step_responses_are_an_outputs_by_inputs_grid_named_with_units(run_dir):
    blueprint = blueprint_of(run_dir / "recording.rrd")
    steps = container(blueprint, "Step responses")
    assert steps["ContainerBlueprint:container_kind"] == [[4]]  # Grid
    assert steps["ContainerBlueprint:grid_columns"] == [[len(INPUTS)]]
    # row-major: rows are outputs, columns inputs, titled "output [unit] <- input [unit]"
    assert contents_names(blueprint, steps) == [pair_name(o, i) for o in OUTPUTS for i in INPUTS]
    tabs = container(blueprint, "plantdyn")
    assert len(tabs["ContainerBlueprint:contents"][0]) == 3  # steps, signals, residuals
    assert blueprint["/time_panel"]["TimePanelBlueprint:timeline"] == [["elapsed"]]


def test_each_step_view_frames_its_own_lags_zero_and_band(run_dir):
    """x from 0 to the pair's last lag (+2 %): the N_p = 3 pair spans its view instead of
    the first 15 s of an hour-long timeline; y over 0 and the band; legend in the
    right-hand corner away from where the response settles (Corner2D: 2 RightTop,
    4 RightBottom)."""
    blueprint = blueprint_of(run_dir / "recording.rrd")
    views = views_by_name(blueprint)
    steps = pl.read_parquet(run_dir / "step_responses.parquet")
    for (o, i), (gain, _, n_p) in PAIRS.items():
        path = views[pair_name(o, i)]
        assert blueprint[f"{path}/TimeAxis"]["TimeAxis:view_range"] == [
            [{"start": 0, "end": int(round(1.02 * n_p * DT_S * 1e9))}]]
        rows = steps.filter(output=o, input=i)
        alls = rows.filter(window="all")
        lo = min(0.0, rows["step"].min(), (alls["step"] - 2 * alls["step_std"]).min())
        hi = max(0.0, rows["step"].max(), (alls["step"] + 2 * alls["step_std"]).max())
        (y_lo, y_hi), = blueprint[f"{path}/ScalarAxis"]["ScalarAxis:range"][0]
        assert y_lo < lo and y_hi > hi and (y_hi - y_lo) < 1.2 * (hi - lo)
        legend = blueprint[f"{path}/PlotLegend"]
        assert legend["PlotLegend:visible"] == [[True]]
        assert legend["PlotLegend:corner"] == [[2 if gain < 0 else 4]]


def test_band_lies_under_every_line_and_fills_the_bounds(run_dir):
    """The viewer draws a view's series in entity-path order (seen in its screenshots):
    band first, then the all-data line, then the windows on top.  The fill is a triangle
    wave between the ±2σ bounds, linear between lags, every point kept (no aggregation)."""
    data = recording_of(run_dir / "recording.rrd")
    steps = pl.read_parquet(run_dir / "step_responses.parquet")
    for (o, i), (_, _, n_p) in PAIRS.items():
        base = f"/step/{o}/{i}".replace(" ", "\\ ")
        drawn = sorted(p for p in data if p.startswith(base + "/"))
        assert drawn == [f"{base}/band/{k}" for k in ("fill", "lower", "upper")] + [
            f"{base}/window/{w}" for w in WINDOW_SCALE]
        alls = steps.filter(output=o, input=i, window="all").sort("lag")
        t_s, step, std = (alls[c].to_numpy() for c in ("time_s", "step", "step_std"))
        fill = data[f"{base}/band/fill"]
        assert fill["timelines"] == {"elapsed"} and fill["values"].size == BAND_POINTS
        ft = fill["index"] / 1e9
        np.testing.assert_allclose(ft, np.linspace(t_s[0], t_s[-1], BAND_POINTS), atol=1e-9)
        np.testing.assert_allclose(fill["values"][0::2], np.interp(ft[0::2], t_s, step - 2 * std), atol=1e-12)
        np.testing.assert_allclose(fill["values"][1::2], np.interp(ft[1::2], t_s, step + 2 * std), atol=1e-12)
        assert fill["static"]["SeriesLines:aggregation_policy"] == [[1]]  # Off
        assert fill["static"]["SeriesLines:names"] == data[f"{base}/band/upper"]["static"]["SeriesLines:names"] \
            == [["±2σ (all data)"]]  # one legend entry for fill and edges
        assert data[f"{base}/window/all"]["values"].size == n_p


def test_time_tabs_have_data_on_the_timeline_the_file_opens_on(run_dir):
    """Signals: one row per signal (raw | conditioned), each view its own y axis; every
    series of the Signals and Residuals tabs is on ``elapsed`` (the opening timeline) and
    on ``time`` (UTC), and their views query both."""
    path = run_dir / "recording.rrd"
    blueprint, data = blueprint_of(path), recording_of(path)
    signals_tab = container(blueprint, "Signals")
    assert signals_tab["ContainerBlueprint:display_name"] == [["Signals (0 s = 2026-03-01 06:00:00 UTC)"]]
    assert signals_tab["ContainerBlueprint:grid_columns"] == [[2]]
    expected = []
    for name, (role, _, _) in SIGNALS.items():
        label = f"{name} [{UNITS[name]}] ({role})"
        expected += [f"{label}: raw, × masked", f"{label}: conditioned"]
    assert contents_names(blueprint, signals_tab) == expected
    residuals_tab = container(blueprint, "Residuals")
    assert contents_names(blueprint, residuals_tab) == [
        f"{o} [{UNITS[o]}]: residual of the all-data estimate" for o in OUTPUTS]
    views = views_by_name(blueprint)
    for name in [*expected, *contents_names(blueprint, residuals_tab)]:
        ranges = blueprint[f"{views[name]}/VisibleTimeRanges"]["VisibleTimeRanges:ranges"][0]
        assert [r["timeline"] for r in ranges] == ["elapsed", "time"]
    time_series = [p for p in data if p.startswith(("/signals/", "/residuals/"))]
    assert len(time_series) == 3 * len(SIGNALS) + len(OUTPUTS)
    for p in time_series:
        assert data[p]["timelines"] == {"elapsed", "time"}, p


def test_units_come_from_the_config_argument_or_the_manifest(run_dir, tmp_path):
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    (copy / "manifest.json").unlink()  # as in the store's temporary directory
    names = set(views_by_name(blueprint_of(render_run(copy, ident="layout/r1"))))
    assert "pressure ← steam_flow" in names  # no config: plain names
    config = {"signals": {"inputs": {"steam_flow": {"unit": "t/h"}}, "outputs": {"pressure": {"unit": "-"}}}}
    names = set(views_by_name(blueprint_of(render_run(copy, ident="layout/r1", out_name="u.rrd", config=config))))
    assert "pressure ← steam_flow [t/h]" in names  # "-" is no unit


# --------------------------------------------------------------------------- the real viewer


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _mask(img: np.ndarray, colour: tuple[int, int, int], tol: int) -> np.ndarray:
    return (np.abs(img.astype(int) - np.array(colour)).max(axis=2) <= tol)


def _readme_copy(img: np.ndarray, name: str) -> Path:
    """A small copy for the documentation (1280 px wide, 256 colours, ≤ 300 KB)."""
    from PIL import Image

    from tests.readme_images import DOCS_IMAGES, save_if_changed

    out = DOCS_IMAGES / name
    small = Image.fromarray(img).resize((1280, round(img.shape[0] * 1280 / img.shape[1])), Image.LANCZOS)
    save_if_changed(small.quantize(colors=256, method=Image.Quantize.MEDIANCUT), out)
    assert out.stat().st_size <= 300_000, out.stat().st_size
    return out


@pytest.mark.slow
def test_headless_viewer_shows_bands_and_non_empty_time_tabs(run_dir):
    """The real viewer, as the file opens (no timeline switched, only tabs selected):

    * *Step responses*: six equal panels (2 rows × 3 columns); each shows the band fill
      colour over ≥ 4000 pixels (~16 000-19 500 measured in 634×459-pixel panels) — the
      band is drawn, not hidden under the lines; in the N_p = 3 panel it spans ≥ 55 % of
      the width (62 % measured: it starts at the first lag, 5 of 15.3 s; on the
      whole-timeline axis it was a sliver of ~0.4 %);
    * *Signals*: every one of the ten views has ≥ 300 pixels of its role's line colour,
      and each raw line spans ≥ 40 % of its view's height (one y axis per signal: on a
      shared axis the tags at ~1 next to the one at ~200 spanned ~1 %);
    * *Residuals*: both views have ≥ 300 pixels of the residual colour;
    * switching the time panel to ``time`` (UTC) keeps the residuals drawn, and leaves the
      step panels without a single band pixel: the checks above can fail, and the step
      responses live on ``elapsed`` only.

    Screenshots: tests/artefacts/viewer_{steps,signals,residuals}.png; documentation copies
    in docs/images/.
    """
    from PIL import Image
    from rerun.experimental import ViewerClient

    def shot(view_id=None) -> np.ndarray:
        return np.asarray(Image.open(io.BytesIO(viewer.take_screenshot(view_id))).convert("RGB"))

    def activate(prefix: str) -> None:
        blueprint = viewer.get_blueprint().blueprint
        tabs = next(k for k, e in blueprint.items() if e.get("ContainerBlueprint", {}).get("container_kind") == "Tabs")
        target = next(k for k, e in blueprint.items()
                      if str(e.get("ContainerBlueprint", {}).get("display_name", "")).startswith(prefix))
        blueprint[tabs]["ContainerBlueprint"]["active_tab"] = target
        viewer.set_blueprint(blueprint, of="recording")

    def wait_for(views, check, seconds: float = 30.0) -> dict[str, np.ndarray]:
        """Screenshots of ``views`` (name -> id) once ``check`` holds for all (or time is up)."""
        deadline = time.monotonic() + seconds
        while True:  # the first frames may be painted before the chunks arrive
            imgs = {name: shot(vid) for name, vid in views.items()}
            if all(check(name, img) for name, img in imgs.items()) or time.monotonic() > deadline:
                return imgs
            time.sleep(1.0)

    band = lambda img: int(_mask(img, BAND_FILL_COLOUR, 12).sum())  # noqa: E731
    ARTEFACTS.mkdir(exist_ok=True)
    with ViewerClient.spawn(headless=True, port=_free_port(), hide_welcome_screen=True,
                            executable_path=str(VENV_BIN / "rerun")) as viewer:
        viewer.open(str(run_dir / "recording.rrd"))
        deadline = time.monotonic() + 30.0
        while not viewer.get_state().views and time.monotonic() < deadline:
            time.sleep(0.5)
        ids = {v.name: v.view_id for v in viewer.get_state().views}
        step_ids = {pair_name(o, i): ids[pair_name(o, i)] for o, i in PAIRS}
        steps = wait_for(step_ids, lambda name, img: band(img) >= 4000)
        Image.fromarray(whole := shot()).save(ARTEFACTS / "viewer_steps.png")
        _readme_copy(whole, "viewer_steps.png")

        activate("Signals")
        signal_ids = {n: vid for n, vid in ids.items() if ": raw, × masked" in n or ": conditioned" in n}
        role_of = {n: SIGNALS[n.split(" [")[0]][0] for n in signal_ids}
        signals = wait_for(signal_ids, lambda n, img: _mask(img, ROLE_COLOURS[role_of[n]], 40).sum() >= 300)
        Image.fromarray(whole := shot()).save(ARTEFACTS / "viewer_signals.png")
        _readme_copy(whole, "viewer_signals.png")

        activate("Residuals")
        resid_ids = {n: vid for n, vid in ids.items() if "residual of" in n}
        resid = wait_for(resid_ids, lambda n, img: _mask(img, RESIDUAL_COLOUR, 40).sum() >= 300)
        Image.fromarray(shot()).save(ARTEFACTS / "viewer_residuals.png")

        viewer.set_time("time")  # UTC clock time: the same plots, the step responses gone
        resid_clock = wait_for(resid_ids, lambda n, img: _mask(img, RESIDUAL_COLOUR, 40).sum() >= 300, 15.0)
        activate("Step responses")
        some = [pair_name("level", "fuel_flow"), pair_name("pressure", "steam_flow")]
        steps_clock = wait_for({n: step_ids[n] for n in some}, lambda n, img: band(img) == 0, 15.0)

    sizes = {img.shape for img in steps.values()}
    assert len(steps) == 6 and max(h for h, _, _ in sizes) - min(h for h, _, _ in sizes) <= 2 \
        and max(w for _, w, _ in sizes) - min(w for _, w, _ in sizes) <= 2, sizes  # equal panels
    counts = {name: band(img) for name, img in steps.items()}
    assert min(counts.values()) >= 4000, counts
    sliver = steps[pair_name("level", "fuel_flow")]
    columns = np.flatnonzero(_mask(sliver, BAND_FILL_COLOUR, 12).any(axis=0))
    assert (columns.max() - columns.min()) / sliver.shape[1] >= 0.55
    assert len(signals) == 2 * len(SIGNALS)
    for name, img in signals.items():
        line = _mask(img, ROLE_COLOURS[role_of[name]], 40)
        assert line.sum() >= 300, (name, line.sum())
        if "raw" in name:
            rows = np.flatnonzero(line.any(axis=1))
            assert (rows.max() - rows.min()) / img.shape[0] >= 0.4, name  # its own y axis
    assert len(resid) == len(OUTPUTS)
    for imgs in (resid, resid_clock):
        assert all(_mask(img, RESIDUAL_COLOUR, 40).sum() >= 300 for img in imgs.values())
    assert all(band(img) == 0 for img in steps_clock.values()), {n: band(i) for n, i in steps_clock.items()}
