"""The horizon comes from the plant, a gain only from a settled curve, and the exported model
is the reported one (issue 32, build 1, 3, 4) — driven as a user does: ``plantdyn run`` on a
historian export, reading checks.json / report.md, then ``plantdyn export``.

The plant is simulated here, independently of the estimator: four inputs (AR(1) 0.97 moves,
mutually independent), one output ``y = sum_j K_j e^{-theta_j s}/(tau_j s + 1) u_j`` plus
AR(1) 0.9 disturbance, integrated exactly at 0.1 s (first-order hold) and sampled every
second, 6,000 samples.  The slow pair (tau 30 s) settles to 98 % in 3.9 tau + theta = 120 s;
the old default horizon ``N // (22 n_x) = 68`` lags cut it at 1 - e^{-(68-3)/30} = 89 % of
its gain.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import control
import numpy as np
import pytest
import scipy.signal as ss

from flows.cli import main
from pipeline.adapters.export import load_control
from pipeline.adapters.historian_writer import write_long_csv
from tests.conftest import write_job

GAINS = (2.0, -1.0, 0.5, 1.5)
TAUS_S = (30.0, 5.0, 10.0, 2.0)
THETAS_S = (3.0, 1.0, 2.0, 0.0)
N = 6000
OLD_DEFAULT_N_P_MAX = N // (22 * 4)


def _simulate(seed: int, fine_s: float = 0.1):
    rng = np.random.default_rng(seed)
    r = int(round(1 / fine_s))
    us, y = [], np.zeros(N)
    for k, tau, theta in zip(GAINS, TAUS_S, THETAS_S):
        u = ss.lfilter([1.0], [1, -0.97], rng.standard_normal(N + 1)) * 0.3
        fine = np.interp(np.arange(N * r + 1) * fine_s, np.arange(N + 1), u)
        b, a, _ = ss.cont2discrete(([k], [tau, 1.0]), fine_s, method="foh")
        yf = ss.lfilter(np.ravel(b), np.ravel(a), fine)
        shift = int(round(theta / fine_s))
        yf = np.r_[np.zeros(shift), yf[: yf.size - shift]] if shift else yf
        y += yf[::r][:N]
        us.append(u[:N])
    y += ss.lfilter([0.05], [1, -0.9], rng.standard_normal(N))
    return us, y


def _quiet(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def _run(root: Path, seed: int, **job) -> Path:
    us, y = _simulate(seed)
    t = np.datetime64("2026-03-02T00:00:00", "us") + \
        (np.arange(N) * 1_000_000).astype("timedelta64[us]")
    (root / "drop").mkdir(parents=True, exist_ok=True)
    write_long_csv(root / "drop" / "plant.csv", t,
                   {**{f"U{j}.PV": 10 + u for j, u in enumerate(us)}, "Y.PV": 50 + y})
    path = write_job(root, sampling={"dt_s": 1.0}, signals={
        "inputs": {f"u{j}": {"tag": f"U{j}.PV", "unit": "kg/s"} for j in range(4)},
        "outputs": {"y": {"tag": "Y.PV", "unit": "bar"}}}, **job)
    code, stdout, stderr = _quiet(["run", str(path), "--no-prefect"])
    assert code == 0, stderr
    return Path(stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def default_run(tmp_path_factory) -> Path:
    return _run(tmp_path_factory.mktemp("horizon_default"), seed=3)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory) -> Path:
    """The same plant with the horizon forced below the slow pair's settling time."""
    return _run(tmp_path_factory.mktemp("horizon_short"), seed=3,
                search={"n_p_max": 40})


def _pairs(run_dir: Path) -> dict:
    checks = json.loads((run_dir / "checks.json").read_text())
    return {p["input"]: p for p in checks["pairs"]}


def test_default_horizon_reaches_past_the_slow_pairs_settling(default_run):
    p = _pairs(default_run)["u0"]
    settle_98 = 3.9 * TAUS_S[0] + THETAS_S[0]
    assert p["n_p"] > OLD_DEFAULT_N_P_MAX
    assert p["n_p"] >= settle_98  # lags of 1 s
    assert p["settled"]["verdict"] == "settled"
    assert abs(p["gain"] - GAINS[0]) < 3 * p["gain_std"], p
    assert p["gain_std"] < 0.1 * GAINS[0]


def test_every_pair_settled_with_its_gain_within_3_sigma(default_run):
    for j, p in enumerate(_pairs(default_run)[f"u{j}"] for j in range(4)):
        assert p["settled"]["verdict"] == "settled", p["gain_note"]
        assert abs(p["gain"] - GAINS[j]) < 3 * p["gain_std"], (j, p["gain"], p["gain_std"])


def test_a_horizon_too_short_gives_no_bare_gain(short_run):
    """Forced to 40 lags, the slow pair (98 % at 120 s) is still rising: no gain, the
    verdict ``moving``, report.md and the terminal say so, and the fast pairs keep theirs."""
    pairs = _pairs(short_run)
    slow = pairs["u0"]
    assert slow["settled"]["verdict"] == "moving"
    assert slow["gain"] is None and slow["gain_std"] is None
    assert "still moving" in slow["gain_note"] and "n_p_max" in slow["gain_note"]
    assert any(w["code"] == "not_settled" for w in slow["warnings"])
    assert slow["settled"]["tail_sum"] > 2 * slow["settled"]["tail_sum_std"]
    report = (short_run / "report.md").read_text()
    row = next(line for line in report.splitlines() if line.startswith("| y | u0 |"))
    assert "moving" in row and "2 ±" not in row
    for j in (1, 3):  # 98 % within 40 s: settled, gain right
        p = pairs[f"u{j}"]
        assert p["settled"]["verdict"] == "settled"
        assert abs(p["gain"] - GAINS[j]) < 3 * p["gain_std"]


def test_exported_model_is_the_reported_model(default_run, short_run, tmp_path):
    """``plantdyn export --format control``: every transfer function's DC gain within
    max(2σ, 10 %) of the reported gain; the moving pair's transfer function is left out
    with its reason, and the CSV carries the verdict, grade, gain and tags."""
    for run_dir in (default_run, short_run):
        out = tmp_path / f"{run_dir.name}.json"
        code, _, err = _quiet(["export", str(run_dir), "--format", "control",
                               "--out", str(out)])
        assert code == 0, err
        tfs = load_control(out)
        doc = json.loads(out.read_text())
        pairs = _pairs(run_dir)
        for entry in doc["pairs"]:
            p = pairs[entry["input"]]
            if p["gain"] is None:
                assert entry["transfer_function"] is None
                assert "no gain" in entry["fit_error"]
                continue
            dc = float(np.real(control.dcgain(tfs[("y", entry["input"])])))
            assert abs(dc - p["gain"]) <= max(2 * p["gain_std"], 0.1 * abs(p["gain"])), \
                (entry["input"], dc, p["gain"], p["gain_std"])
    # report.html overlays the exported transfer function on the step matrix
    assert "exported transfer function" in (default_run / "report.html").read_text()
    out = tmp_path / "short.csv"
    code, _, err = _quiet(["export", str(short_run), "--format", "csv", "--out", str(out)])
    assert code == 0, err
    rows = {line[2:].split(",")[0]: line[2:].split(",")[2:]
            for line in out.read_text().splitlines() if line.startswith("# ") and
            "," in line.split(":")[0]}
    assert rows["settled"][0] == "moving" and rows["gain"][0] == ""
    assert rows["input_tag"] == ["U0.PV", "U1.PV", "U2.PV", "U3.PV"]
    assert float(rows["gain"][1]) == pytest.approx(pairs["u1"]["gain"])


def test_an_input_flat_in_one_window_is_named_with_the_window_and_its_time(tmp_path):
    """Build 8: the input u2 is held still over the last 60 % of the record (a valve in
    manual).  The run succeeds on all data; the window that cannot be estimated is named in
    checks.json and report.md with its time range, the input and its tag."""
    us, y = _simulate(7)
    us[2][int(0.4 * N):] = us[2][int(0.4 * N)]
    t = np.datetime64("2026-03-02T00:00:00", "us") + \
        (np.arange(N) * 1_000_000).astype("timedelta64[us]")
    (tmp_path / "drop").mkdir()
    write_long_csv(tmp_path / "drop" / "plant.csv", t,
                   {**{f"U{j}.PV": 10 + u for j, u in enumerate(us)}, "Y.PV": 50 + y})
    path = write_job(tmp_path, sampling={"dt_s": 1.0}, signals={
        "inputs": {f"u{j}": {"tag": f"U{j}.PV"} for j in range(4)},
        "outputs": {"y": {"tag": "Y.PV"}}})
    code, stdout, stderr = _quiet(["run", str(path), "--no-prefect"])
    assert code == 0, stderr
    run_dir = Path(stdout.strip().splitlines()[-1])
    search = json.loads((run_dir / "checks.json").read_text())["search"]
    report = (run_dir / "report.md").read_text()
    failed = [w for w in search["windows"] if w["status"] == "failed"]
    if failed:  # a chosen window that could not be estimated
        assert all(w["samples"][0] >= 0.4 * N for w in failed)
        assert all("u2 (tag U2.PV)" in w["error"] for w in failed)
        line = next(x for x in report.splitlines()
                    if x.startswith(f"- Window {failed[-1]['window']}"))
        assert failed[-1]["time"][1] in line and "u2 (tag U2.PV)" in line
    else:  # no two windows could be estimated at any N_d: the last trial says why
        trial = [t for t in search["nd_trace"] if "error" in t][-1]
        a, b = trial["failed_window"]
        assert a >= 0.4 * N - 1 and "u2 (tag U2.PV) does not vary" in trial["error"]
        line = next(x for x in report.splitlines() if x.startswith("- No window check"))
        t_end = str(np.datetime64("2026-03-02T00:00:00", "s") + np.timedelta64(b - 1, "s"))
        assert f"{t_end}Z (samples {a}–{b})" in line and "u2 (tag U2.PV)" in line


def test_gain_sigma_holds_the_truncation_bias_not_the_reference_fits_noise():
    """σ of a settled gain: sqrt(σ_final² + max(0, L² − σ_L²)) (settledness module doc):
    E[L²] = b² + σ_L², so a left-out change L within its own noise adds nothing, and one
    beyond it adds the excess.  A first-order plant simulated here (numpy only), fitted at
    a horizon past its settling; L and σ_L are given as the search would pass them."""
    from pipeline.estimation.estimate import estimate_step_responses
    from pipeline.identification.settledness import settledness

    rng = np.random.default_rng(11)
    n = 4000
    u = np.repeat(rng.standard_normal(n // 20), 20)
    y = ss.lfilter([0.0, 0.2], [1.0, -0.8], u) + 0.05 * rng.standard_normal(n)
    est = estimate_step_responses(u[:, None], y[:, None], n_p=40, dt=1.0)
    final_std = float(est.step_std[0, 0, 39])
    assert abs(est.step[0, 0, 39] - 1.0) < 3 * final_std  # the truth: gain 0.2/(1-0.8)
    quiet = settledness(est, 0, 0, left_out=0.5 * final_std, left_out_std=3 * final_std)
    assert quiet.verdict == "settled" and quiet.gain_std == pytest.approx(final_std)
    biased = settledness(est, 0, 0, left_out=0.02, left_out_std=0.006)
    assert biased.verdict == "settled"
    assert biased.gain_std == pytest.approx(np.hypot(final_std, np.sqrt(0.02**2 - 0.006**2)))
    assert "for what the horizon leaves out" in biased.note
