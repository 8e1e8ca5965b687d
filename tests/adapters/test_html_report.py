"""``report.html``: one self-contained page per run (issue 13, build item 1; must-show 1).

The runs are made through the CLI as a user makes them (``plantdyn demo``, ``plantdyn demo
--discrepancy``, ``plantdyn run`` on the fractionator export when ``../shared/data`` is
there), once per module.  The page is checked as a document (every pair, unit, gain,
grade, the rule; the statistics it recomputes from the stored files must equal the ones in
checks.json) and as a picture: headless Chromium renders it, and the regions where the
step-response matrix, the gain table and the residual plots are must hold drawings.  The
screenshots are kept in ``tests/artefacts/`` (the documentation's two small copies in
``docs/images/``).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import yaml

from flows.cli import main
from pipeline.discrepancy.report import fmt_number
from pipeline.identification.quality import GRADE_RULE, grade_from_checks

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
ARTEFACTS = ROOT / "tests" / "artefacts"
CHROMIUM = Path("/usr/bin/chromium")
FRAC_INPUTS = ["FIC-2001", "FIC-2002", "FIC-2004", "TIC-2003", "FIC-2100", "FI-2005"]
FRAC_OUTPUTS = ["AI-2020", "AI-2021", "AI-2022"]


# --------------------------------------------------------------------------- the runs


def _cli(*args: str) -> dict[str, str]:
    """Run the CLI in-process; its ``label: value`` stdout lines (or the last line)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = main(list(args))
    assert code == 0, out.getvalue()
    lines = out.getvalue().splitlines()
    found = {k.strip(): v.strip() for k, v in (ln.split(":", 1) for ln in lines if ": " in ln)}
    found["last"] = lines[-1].strip()
    return found


@pytest.fixture(scope="module")
def demo_run(demo_cli_run) -> Path:
    assert demo_cli_run.returncode == 0, demo_cli_run.stderr
    where = demo_cli_run.lines  # the session's shared `plantdyn demo --no-prefect` run
    html = Path(where["html"])  # the demo says where the page is
    assert html.name == "report.html" and html.parent == Path(where["results"])
    return html.parent


@pytest.fixture(scope="module")
def discrepancy_run(discrepancy_demo_run) -> Path:
    assert discrepancy_demo_run.returncode == 0, discrepancy_demo_run.stderr
    return discrepancy_demo_run.results  # the session's `plantdyn demo --discrepancy` run


@pytest.fixture(scope="module")
def frac_run(tmp_path_factory) -> Path:
    if not DATA.is_dir():
        pytest.skip(f"shared data folder {DATA} is absent (a fresh clone without ../shared)")
    folder = tmp_path_factory.mktemp("frac2")
    name = lambda tag: tag.replace("-", "_").lower()  # noqa: E731
    job = {"job": "frac2",
           "source": {"path": str(DATA / "frac2_historian_export.csv"),
                      "timezone": "America/Chicago"},
           "signals": {"inputs": {name(t): {"tag": t} for t in FRAC_INPUTS},
                       "outputs": {name(t): {"tag": t} for t in FRAC_OUTPUTS}},
           "storage": "storage", "rerun": {"enabled": False}}
    (folder / "frac2.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    os.environ["PLANTDYN_ALLOWED_ROOTS"] = str(DATA)
    try:
        return Path(_cli("run", str(folder / "frac2.yaml"), "--no-prefect")["last"])
    finally:
        del os.environ["PLANTDYN_ALLOWED_ROOTS"]


@pytest.fixture(scope="module")
def drum_run(tmp_path_factory) -> Path:
    """An integrating output (drum level, level-form noise model) through ``plantdyn run``."""
    from tests.plants import DRUM_TAGS, write_drum_export

    folder = tmp_path_factory.mktemp("drum")
    write_drum_export(folder / "drop" / "drum.csv", hours=3.0, seed=5_100_001)
    job = {"job": "drum", "source": {"path": "drop/*.csv", "timezone": "UTC"},
           "signals": {"inputs": {"steam_flow": {"tag": DRUM_TAGS["steam_flow"], "unit": "kg/s"},
                                  "feedwater": {"tag": DRUM_TAGS["feedwater"], "unit": "kg/s"}},
                       "outputs": {"drum_level": {"tag": DRUM_TAGS["drum_level"], "unit": "cm",
                                                  "integrating": True}}},
           "storage": "storage", "sampling": {"dt_s": 1.0}, "rerun": {"enabled": False}}
    (folder / "drum.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    return Path(_cli("run", str(folder / "drum.yaml"), "--no-prefect")["last"])


# --------------------------------------------------------------------------- a small DOM


class Doc(HTMLParser):
    """What the tests read from a page: text per element id, tables by id (rows of cell
    texts), the SVG text inside each section, images per section, and where each id
    starts in the document."""

    def __init__(self, text: str):
        super().__init__(convert_charrefs=True)
        self.text_by_id: dict[str, list[str]] = {}
        self.tables: dict[str, list[list[str]]] = {}
        self.svg_text: dict[str, list[str]] = {}
        self.images: dict[str, list[str]] = {}
        self.classes: list[str] = []
        self.order: list[str] = []
        self._open: list[tuple[str, str | None]] = []
        self._section: str | None = None
        self._table: str | None = None
        self._cell: list[str] | None = None
        self._in_svg_text = 0
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        ident = a.get("id")
        self.classes += (a.get("class") or "").split()
        if ident:
            self.order.append(ident)
            self.text_by_id.setdefault(ident, [])
        if tag in ("br", "img", "meta", "input", "hr", "link"):
            if tag == "br":
                self.handle_data(" ")
            if tag == "img" and self._section:
                self.images.setdefault(self._section, []).append(a.get("src", ""))
            return
        self._open.append((tag, ident))
        if tag == "section":
            self._section = ident
        elif tag == "table":
            self._table = ident or f"table{len(self.tables)}"
            self.tables[self._table] = []
        elif tag == "tr" and self._table:
            self.tables[self._table].append([])
        elif tag in ("td", "th"):
            self._cell = []
        elif tag == "text":
            self._in_svg_text += 1
            self.svg_text.setdefault(self._section or "", []).append("")

    def handle_endtag(self, tag):
        while self._open:
            t, _ = self._open.pop()
            if t == tag:
                break
        if tag in ("td", "th") and self._cell is not None and self._table:
            self.tables[self._table][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None
        elif tag == "table":
            self._table = None
        elif tag == "section":
            self._section = None
        elif tag == "text":
            self._in_svg_text -= 1

    def handle_data(self, data):
        for _, ident in self._open:
            if ident:
                self.text_by_id[ident].append(data)
        if self._cell is not None:
            self._cell.append(data)
        if self._in_svg_text:
            self.svg_text[self._section or ""][-1] += data

    def text(self, ident: str) -> str:
        return " ".join("".join(self.text_by_id[ident]).split())

    def rows(self, table_id: str) -> list[list[str]]:
        return self.tables[table_id][1:]


def _doc(run_dir: Path) -> tuple[Doc, str]:
    text = (run_dir / "report.html").read_text(encoding="utf-8")
    return Doc(text), text


def _units(run_dir: Path) -> dict[str, str]:
    m = json.loads((run_dir / "manifest.json").read_text())
    checks = json.loads((run_dir / "checks.json").read_text())
    units = {n: q["ingest"]["unit"] for n, q in checks["data_quality"]["signals"].items()
             if q["ingest"].get("unit")}
    for role in ("inputs", "outputs"):
        units |= {n: s["unit"] for n, s in m["config"]["signals"][role].items() if s.get("unit")}
    return units


# --------------------------------------------------------------------------- estimation runs


def _check_estimation_page(run_dir: Path, *, expect_units: bool) -> tuple[Doc, dict]:
    doc, text = _doc(run_dir)
    checks = json.loads((run_dir / "checks.json").read_text())
    pairs = checks["pairs"]
    outs = list(dict.fromkeys(p["output"] for p in pairs))
    ins = list(dict.fromkeys(p["input"] for p in pairs))
    units = _units(run_dir)
    assert not [c for c in doc.classes if c == "section-error"], "a section failed to draw"
    # self-contained: nothing is fetched
    assert not re.search(r"<(script|link|iframe)\b", text)
    assert not re.search(r"""src=["'](?!data:image/png;base64,)""", text)
    # the matrix: every pair's panel, with units on both axes of every panel
    svg = doc.svg_text["step-matrix"]
    for p in pairs:
        assert f"{p['output']} ← {p['input']}" in svg
        uo, ui = units.get(p["output"]), units.get(p["input"])
        if expect_units:
            assert uo and ui, (p["output"], p["input"])
        assert f"step ({uo or 'output unit'} per {ui or 'input unit'})" in svg
    assert svg.count("time after the step (s)") == len(pairs)
    assert "±2σ (all data)" in svg and "window w0" in svg and "window w1" in svg
    # the gain matrix: rows = outputs, columns = inputs, gain ± σ, unit and grade per cell
    head, *rows = doc.tables["gain-matrix"]
    assert [h.split()[0] for h in head[1:]] == ins
    assert [r[0].split()[0] for r in rows] == outs
    for p in pairs:
        cell = rows[outs.index(p["output"])][1 + ins.index(p["input"])]
        g = grade_from_checks(p, checks).grade
        value, std = ("rate", "rate_std") if p["integrating"] else ("gain", "gain_std")
        if p[value] is None:  # still moving at its horizon: no bare number, the verdict
            assert p["settled"]["verdict"] in cell and " ± " not in cell.split("extrap")[0]
        else:
            assert f"{fmt_number(p[value])} ± {fmt_number(p[std], 2)}" in cell, cell
        assert f" {g}" in cell, cell
        assert f"{units.get(p['output'], 'output unit')} per {units.get(p['input'], 'input unit')}" in cell
    # grades, the same in report.md; the rule as a table
    graded = {r[0]: r[1] for r in doc.rows("grade-table")}
    assert set(graded) == {f"{p['output']}<-{p['input']}" for p in pairs}
    md = (run_dir / "report.md").read_text()
    for p in pairs:
        assert graded[f"{p['output']}<-{p['input']}"] == grade_from_checks(p, checks).grade
        assert f"| {p['output']} | {p['input']} | {graded[p['output'] + '<-' + p['input']]} |" in md
    assert [r[0] for r in doc.rows("grade-rule")] == [row[0] for row in GRADE_RULE]
    assert "worst cap" in doc.text("grades") and "| criterion | read from | A | B | C | D |" in md
    # statistics recomputed from the stored files equal the stored ones
    white = {r[0]: r for r in doc.rows("whiteness-table")}
    for o, w in checks["residuals"]["whiteness"].items():
        assert white[o][3] == fmt_number(w["statistic"]) and white[o][4] == fmt_number(w["p_value"], 2)
    xcorr = {r[0]: r for r in doc.rows("xcorr-table")}
    for name, x in checks["residuals"]["input_cross_correlation"].items():
        assert xcorr[name][4] == fmt_number(x["statistic"]), name
        assert xcorr[name][6] == ("ok" if x["ok"] else "outside")
    assert len(doc.svg_text["residuals"]) > 0
    # held-out fit, frequency responses, search, data quality
    assert "held out" in doc.text("held-out")
    assert [r[0] for r in doc.rows("fit-table")] == outs
    assert doc.svg_text["frequency"].count("phase (°)") == len(pairs)
    search = {r[0]: int(r[1]) for r in doc.rows("search-table")}
    assert search == checks["search"]["n_p"]
    masked = {r[0]: r for r in doc.rows("masked-table")}
    for name, q in checks["data_quality"]["signals"].items():
        assert int(masked[name][5]) == q["masked"]
        for why in q["masked_by_reason"]:
            assert why in masked[name][6]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert "report.html" in [f["name"] for f in manifest["files"]]
    return doc, manifest


def test_demo_report_shows_every_pair_with_units_gains_grades_and_checks(demo_run):
    doc, manifest = _check_estimation_page(demo_run, expect_units=True)
    grades = {r[0]: r[1] for r in doc.rows("grade-table")}
    assert set(grades) == {f"{o}<-{u}" for o in ("turbine_pressure", "fuel_flow")
                           for u in ("pressure_sp", "steam_flow")}
    # the demo plant is known (configs/demo_boiler.yaml): the load's effect on the pressure
    # and the setpoint's on the fuel are removed by the controller at steady state; the
    # pressure follows its setpoint and the fuel the load one to one.  Every gain is
    # within 3σ of the physics, and a ≈ 0 gain after a clear transient is a result, not
    # a D (issue 32)
    checks = json.loads((demo_run / "checks.json").read_text())
    truth = {("turbine_pressure", "pressure_sp"): 1.0, ("turbine_pressure", "steam_flow"): 0.0,
             ("fuel_flow", "pressure_sp"): 0.0, ("fuel_flow", "steam_flow"): 1.0}
    for p in checks["pairs"]:
        assert abs(p["gain"] - truth[p["output"], p["input"]]) < 3 * p["gain_std"], p["gain"]
    p = next(q for q in checks["pairs"]
             if (q["output"], q["input"]) == ("turbine_pressure", "steam_flow"))
    assert abs(p["gain"]) < 2 * p["gain_std"] and p["peak"] > 4 * p["gain_std"]
    assert "controller removes this input's effect" in p["gain_note"]
    assert grades["turbine_pressure<-steam_flow"] == "A"
    assert "t/h per kg/s" in doc.text("gain-matrix")
    assert doc.rows("rga")  # 2 x 2: the relative gain array is shown
    assert "window w1" in doc.text("held-out")  # the last of 2 windows is held out
    fit = {r[0]: float(r[1]) for r in doc.rows("fit-table")}
    assert fit["fuel_flow"] > 50.0  # well-identified pairs predict unseen data
    assert "bad_quality:I/O Timeout" in doc.text("masked-table")
    # the step is timed in the manifest like every stage (its speed is not a unit test's
    # business: machines are shared and noisy)
    assert manifest["timings_s"]["html_report"] > 0.0


def test_frac_report_on_the_real_export(frac_run):
    doc, _ = _check_estimation_page(frac_run, expect_units=True)  # units from the header
    checks = json.loads((frac_run / "checks.json").read_text())
    grades = {r[0]: r[1] for r in doc.rows("grade-table")}
    assert len(grades) == 18
    for p in checks["pairs"]:
        g = grades[f"{p['output']}<-{p['input']}"]
        if p["agreement"]["verdict"] == "insufficient_data":
            assert g in "CD"
        if p["gain"] is None:  # still moving at its horizon: indicative at best
            assert p["settled"]["verdict"] != "settled" and g in "CD"
        elif abs(p["gain"]) < 2 * p["gain_std"]:
            assert g == "D"
    assert "MOL per MBBL/D" in doc.text("gain-matrix")


def test_integrating_output_report(drum_run):
    """Rates instead of gains, the differenced comparison, and the level-form noise model
    (cumulated residual, polynomial per stretch) reproducing the stored whiteness."""
    doc, _ = _check_estimation_page(drum_run, expect_units=True)
    cells = doc.rows("gain-matrix")[0]
    assert all(c.startswith("rate ") and c.endswith("cm per kg/s per s") for c in cells[1:])
    assert doc.rows("fit-table")[0][3] == "differences Δy"
    assert doc.text("rga-absent").endswith("(1 output × 2 inputs) is not square.")
    checks = json.loads((drum_run / "checks.json").read_text())
    assert checks["noise_model"]["drum_level"]["form"] == "level"


def test_rebuild_from_stored_files_does_not_touch_the_run(demo_run, tmp_path):
    before = sorted((p.name, p.stat().st_mtime_ns) for p in demo_run.iterdir())
    out = tmp_path / "rebuilt.html"
    r = subprocess.run([sys.executable, "-m", "pipeline.adapters.html_report", str(demo_run),
                        "-o", str(out)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert sorted((p.name, p.stat().st_mtime_ns) for p in demo_run.iterdir()) == before
    rebuilt, original = Doc(out.read_text()), _doc(demo_run)[0]
    for table_id in ("gain-matrix", "grade-table", "whiteness-table", "fit-table"):
        assert rebuilt.tables[table_id] == original.tables[table_id], table_id
    r = subprocess.run([sys.executable, "-m", "pipeline.adapters.html_report",
                        str(tmp_path / "nowhere")], capture_output=True, text=True, timeout=300,
                       cwd=ROOT)
    assert r.returncode == 2 and "has no manifest.json" in r.stderr


def _rerender(run_dir: Path, tmp_path: Path, edit) -> tuple[Doc, str]:
    from pipeline.adapters.html_report import write_report_html

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    checks = json.loads((copy / "checks.json").read_text())
    edit(checks)
    (copy / "checks.json").write_text(json.dumps(checks))
    text = write_report_html(copy, tmp_path / "page.html").read_text()
    return Doc(text), text


def test_monitor_banner_at_the_top(demo_run, tmp_path):
    monitor = {"baseline_run": "20260101T020000Z-abc123", "threshold_sigma": 3.0,
               "changed": ["fuel_flow<-steam_flow"],
               "pairs": {"fuel_flow<-steam_flow": {"gain_z": 4.2, "baseline_gain": 0.9}}}
    doc, _ = _rerender(demo_run, tmp_path / "a", lambda c: c.update(monitor=monitor))
    banner = doc.text("monitor-banner")
    assert "1 pair(s) moved beyond 3 σ of baseline run 20260101T020000Z-abc123" in banner
    assert "fuel_flow<-steam_flow" in banner and "gain_z 4.2" in banner
    assert doc.order.index("monitor-banner") < doc.order.index("step-matrix")
    doc, _ = _rerender(demo_run, tmp_path / "b",
                       lambda c: c.update(monitor={**monitor, "changed": []}))
    assert doc.text("monitor-banner") == ("Monitor: no pair moved beyond 3 σ of baseline run "
                                          "20260101T020000Z-abc123.")
    doc, _ = _rerender(demo_run, tmp_path / "c", lambda c: c.update(monitor="garbled"))
    assert "monitor-banner" not in doc.order and "section-error" not in doc.classes
    assert "monitor-banner" not in _doc(demo_run)[0].order  # the demo has no monitor


def test_a_section_that_cannot_be_drawn_is_shown_not_fatal(demo_run, tmp_path):
    def spoil(c):
        c["search"]["order_trace"] = [{"n_p": "many", "pairs": [{"output": "fuel_flow",
                                                                  "input": "steam_flow"}]}]
    with pytest.warns(RuntimeWarning, match="section 'search' failed"):
        doc, _ = _rerender(demo_run, tmp_path, spoil)
    assert doc.classes.count("section-error") == 1
    assert "could not be drawn" in doc.text("search")
    assert doc.tables["gain-matrix"] == _doc(demo_run)[0].tables["gain-matrix"]


def test_relative_gain_array_of_a_square_matrix():
    from pipeline.adapters.html_report.estimation import gain_table
    from pipeline.adapters.html_report.stored import StoredRun
    from pipeline.readouts.run_summary import RunSummary

    gains = {("y1", "u1"): 2.0, ("y1", "u2"): 1.0, ("y2", "u1"): 1.0, ("y2", "u2"): 2.0}
    checks = {"pairs": [{"output": o, "input": u, "gain": g, "gain_std": 0.01,
                         "integrating": False, "agreement": {"verdict": "pass"}}
                        for (o, u), g in gains.items()]}
    run = StoredRun(Path("."), {"config": {}}, checks, None, None, None, ["y1", "y2"], ["u1", "u2"])
    config = {"signals": {"outputs": {"y1": {"unit": "bar"}}, "inputs": {"u1": {"unit": "kg/s"}}}}

    def summary(config):
        return RunSummary.from_checks(checks, job="square", status="ok", config=config)

    doc = Doc(gain_table(run, summary(config)))
    # Λ11 = 1 / (1 − g12 g21 / (g11 g22)) = 4/3; rows and columns sum to 1
    assert doc.rows("rga") == [["y1", "1.33", "-0.333"], ["y2", "-0.333", "1.33"]]
    assert "bar per kg/s" in doc.text("gain-matrix") and "bar per input unit" in doc.text("gain-matrix")
    checks["pairs"][0]["gain"] = None
    assert "rga" not in Doc(gain_table(run, summary({}))).tables


# --------------------------------------------------------------------------- discrepancy


def test_discrepancy_report_shows_series_chain_candidates_and_localisation(discrepancy_run):
    doc, text = _doc(discrepancy_run)
    d = json.loads((discrepancy_run / "discrepancy.json").read_text())
    assert "section-error" not in doc.classes
    assert "gain at controller" in doc.text("finding")  # the demo's 20 % controller gain
    assert doc.images["series"][0].startswith("data:image/png;base64,")
    chain = doc.rows("chain-table")
    assert len(chain) == len(d["effects"]) >= 1
    for row, e in zip(chain, d["effects"]):
        assert row[2] == fmt_number(e["gap_before"]) and row[3] == fmt_number(e["gap_after"])
        assert float(row[2]) > float(row[3])  # the gap shrinks effect by effect
    head, *cands = doc.tables["candidates-table"]
    assert "gap_reduction" in head and "passed_by" in head and "ΔBIC" in head
    assert len(cands) == len(d["candidates"])
    for row, c in zip(cands, d["candidates"]):
        assert row[1] == c["name"] and row[2] == c["location"]
        assert row[head.index("gap_reduction")] == f"{100 * c['gap_reduction']:.1f} %"
        low = c["gap_reduction_low"]  # computed for candidates that passed only
        assert row[head.index("largest output gap_reduction, 95 % lower bound")] == (
            f"{100 * low:.1f} % ({c['gap_reduction_low_output']})" if c["passed"] else "–")
        assert row[head.index("passed_by")] == (c.get("passed_by") or "–")
    for o, loc in d["localization"].items():
        names = [r[0] for r in doc.rows(f"localisation-{o}")]
        assert names == list(loc["signals"]) and set(names) == set(d["inputs"])
    assert "No minor effects" in doc.text("minor-effects")
    assert "bar" in [r[4] for r in doc.rows("gap-table")]  # the output's unit from the job
    manifest = json.loads((discrepancy_run / "manifest.json").read_text())
    assert "report.html" in [f["name"] for f in manifest["files"]]
    assert "html_report" in manifest["timings_s"]


# --------------------------------------------------------------------------- screenshots


def _screenshot(html: Path, png: Path, *, height: int) -> None:
    assert CHROMIUM.is_file(), "chromium is missing: run scripts/setup.sh --test (as root)"
    with tempfile.TemporaryDirectory() as profile:
        r = subprocess.run(
            [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", f"--user-data-dir={profile}", f"--window-size=1400,{height}",
             f"--screenshot={png}", f"file://{html}"],
            capture_output=True, text=True, timeout=180)
    assert r.returncode == 0 and png.is_file(), r.stderr[-2000:]


def _rgb(png: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(png) as im:
        return np.asarray(im.convert("RGB")).astype(int)


def _regions(html: Path, ids: list[str], tmp: Path, height: int) -> dict[str, tuple[int, int]]:
    """Rows of the screenshot each section covers: the page again with each section on
    its own pure background colour (a probe; the real screenshot is unchanged)."""
    colours = [(255, 0, 255), (0, 255, 255), (255, 255, 0), (0, 0, 255)]
    css = "".join(f"section#{i}{{background:rgb{c}}}" for i, c in zip(ids, colours))
    probe = tmp / "probe.html"
    probe.write_text(html.read_text().replace("</style>", css + "</style>", 1))
    _screenshot(probe, tmp / "probe.png", height=height)
    img = _rgb(tmp / "probe.png")
    out = {}
    for i, c in zip(ids, colours):
        rows = np.flatnonzero((np.abs(img - np.array(c)).sum(axis=2) == 0).any(axis=1))
        assert rows.size, f"section {i} is not on the screenshot"
        out[i] = (int(rows.min()), int(rows.max()))
    return out


def _has(img: np.ndarray, colour: str, tol: int = 40) -> int:
    rgb = np.array([int(colour[k:k + 2], 16) for k in (1, 3, 5)])
    return int((np.abs(img - rgb).sum(axis=2) < tol).sum())


def _check_drawn(img: np.ndarray, region: tuple[int, int], *, colours: list[str],
                 least: int | list[int] = 30) -> None:
    part = img[region[0]:region[1]]
    ink = (part.sum(axis=2) < 600).mean()
    assert ink > 0.02, f"region {region} is nearly blank ({ink:.3%} ink)"
    assert len(np.unique(part.reshape(-1, 3), axis=0)) > 50  # drawings, not flat boxes
    for c, n in zip(colours, least if isinstance(least, list) else [least] * len(colours)):
        assert _has(part, c) > n, f"no {c} in region {region}"


def _keep(png: Path, name: str, readme: str | None = None) -> None:
    from PIL import Image

    from tests.readme_images import DOCS_IMAGES, save_if_changed

    ARTEFACTS.mkdir(exist_ok=True)
    shutil.copy(png, ARTEFACTS / name)
    if readme:
        with Image.open(png) as im:
            top = im.convert("RGB").crop((0, 0, 1400, min(im.height, 2300)))
            small = top.resize((900, top.height * 900 // 1400), Image.LANCZOS).quantize(
                256, method=Image.Quantize.FASTOCTREE)
            save_if_changed(small, DOCS_IMAGES / readme)
        assert (DOCS_IMAGES / readme).stat().st_size <= 300_000


@pytest.mark.parametrize("which", ["demo", "frac2"])
def test_screenshot_of_an_estimation_report(which, request, tmp_path):
    run_dir = request.getfixturevalue("demo_run" if which == "demo" else "frac_run")
    height = 4000 if which == "demo" else 9000
    html = run_dir / "report.html"
    t0 = time.perf_counter()
    _screenshot(html, tmp_path / "shot.png", height=height)
    print(f"chromium screenshot {time.perf_counter() - t0:.1f} s")
    img = _rgb(tmp_path / "shot.png")
    assert img.shape[:2] == (height, 1400)
    where = _regions(html, ["step-matrix", "gains", "residuals"], tmp_path, height)
    assert where["step-matrix"][1] < where["gains"][0] < where["residuals"][0]
    # the matrix: the all-data line (black) and its ±2σ band (light blue) are drawn; the
    # demo's σ are below a pixel (its legend shows the band), the fractionator's are wide
    _check_drawn(img, where["step-matrix"], colours=["#000000", "#9ecae1"],
                 least=[300, 100 if which == "demo" else 5000])
    # the gain table: its grade badges (the demo has two As; the fractionator Cs and Ds)
    _check_drawn(img, where["gains"], colours=["#1a7f37"] if which == "demo" else ["#c62828"])
    # the residual plots: the autocorrelation bars and the dashed significance bands
    _check_drawn(img, where["residuals"], colours=["#1f77b4", "#c62828"])
    _keep(tmp_path / "shot.png", f"report_{which}.png", "report_demo.png" if which == "demo" else None)


def test_screenshot_of_a_discrepancy_report(discrepancy_run, tmp_path):
    html = discrepancy_run / "report.html"
    _screenshot(html, tmp_path / "shot.png", height=4000)
    img = _rgb(tmp_path / "shot.png")
    where = _regions(html, ["series", "gap-chain", "candidates"], tmp_path, 4000)
    # measured (grey) vs nominal (blue) vs augmented (red) over the held-out shading
    _check_drawn(img, where["series"], colours=["#1f77b4", "#d62728", "#fff3c4"])
    _check_drawn(img, where["gap-chain"], colours=["#1f77b4", "#d62728"])
    _check_drawn(img, where["candidates"], colours=["#d0d7de"])
    _keep(tmp_path / "shot.png", "report_discrepancy.png", "report_discrepancy.png")
