"""Nightly monitoring against a baseline run (issue 13, must-show 4).

* The statistics (:mod:`pipeline.readouts.monitor`) against their definitions, and the config
  section's errors in YAML terms.
* Calibration on the core API: a plant that does not change, simulated independently of
  the estimator (python-control's exact ZOH discretisation of two continuous transfer
  functions, one with 3 s dead time, plus AR(1) noise with pole 0.9 at 30 % of the
  output's s.d. by scipy's lfilter — not the estimator's FIR-plus-AR model), 1e4
  samples a night, each night estimated by ``estimate_step_responses(noise="auto")``
  and compared with a baseline night.  The decision's design false-alarm rate per
  night is at most 2 pairs × 3 tests × 0.27 % = 1.6 % (union bound at 3 σ); Šidák's
  correction is conservative for correlated lags and the stored σ slightly so, so the
  real rate is lower.  Allowed: at most 1 night flagged of 60 (1.7 %).  Binomially, a
  true rate of 5 % passes that with probability 19 %, the design bound 1.6 % with 75 %;
  the seeds are fixed, and ``python -m tests.readouts.test_monitor`` measures the rate on many
  more nights and baselines (the numbers in docs/guide/nightly.md).  Power: a 30 % gain
  change of one pair is flagged — that pair and only it — on at least 19 of 20 nights
  (≥ 95 %; expected z ≈ 12, so every night).
* User level: five nights of historian exports through ``plantdyn nightly``'s flow with
  ``monitor: {baseline: first}``; the gain of one of two pairs rises 30 % on night 5.
  Nights 1–4 raise nothing, night 5 flags exactly that pair in checks.json, the catalog
  (also after ``plantdyn reindex``) and report.md; ``plantdyn runs`` lists it first and
  writes the trend figure, in which night 5's gain lies outside its band; a sixth night
  through the estimate flow (gain back to normal) is unchanged and published as a
  Prefect markdown artifact.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import control as ct
import numpy as np
import pytest
import scipy.signal as ss

from pipeline.errors import ConfigError
from pipeline.readouts.monitor import (
    PairResponse,
    compare_pair,
    compare_runs,
    monitor_banner,
    sidak_z,
    step_difference_z,
)
from tests.plants import ar1

THRESHOLD = 3.0


# ----------------------------------------------------------------- the statistics
def _pair(step, std, *, value=None, value_std=None, dead=1.5, dt=1.0, inp="u"):
    step, std = np.asarray(step, float), np.asarray(std, float)
    return PairResponse("y", inp, False, float(step[-1] if value is None else value),
                        float(std[-1] if value_std is None else value_std), dead, step, std,
                        dt)


def test_sidak_z_is_the_single_comparison_z_of_the_corrected_p():
    from scipy import stats

    assert sidak_z(2.5, 1) == pytest.approx(2.5, rel=1e-9)  # one lag: no correction
    for z, m in ((3.0, 10), (4.0, 60), (2.0, 5)):
        p1 = 2 * stats.norm.sf(z)
        pm = 1 - (1 - p1) ** m
        assert sidak_z(z, m) == pytest.approx(stats.norm.isf(pm / 2), rel=1e-9)
        assert sidak_z(z, m) < z  # the largest of m is less surprising than one
    # far tails keep their order (no underflow to a tie)
    assert 30 < sidak_z(40.0, 100) < sidak_z(50.0, 100) < 50
    with pytest.raises(ConfigError, match="m=0 lags"):
        sidak_z(3.0, 0)


def test_pair_comparison_follows_its_formulas():
    t = np.arange(1, 21, dtype=float)
    base = _pair(2 * (1 - np.exp(-t / 5)), np.full(20, 0.01))
    run = _pair(base.step + 0.1, np.full(20, 0.02))
    ch = compare_pair(base, run, threshold_sigma=THRESHOLD, base_dead_time_std=0.3,
                      run_dead_time_std=0.4)
    z = 0.1 / np.hypot(0.01, 0.02)  # 4.47 σ
    assert ch.gain_z == pytest.approx(z)
    assert ch.dead_time_z == pytest.approx(0.0)
    assert ch.step_max_abs_z == pytest.approx(z) and ch.step_lags == 20
    assert ch.step_max_z == pytest.approx(sidak_z(z, 20))  # 3.78: above 3 too
    assert ch.changed and ch.reasons == ("gain", "step")
    assert ch.relative_change == pytest.approx(0.1 / base.value)


def test_pair_below_threshold_is_unchanged_and_dead_time_shift_counts():
    t = np.arange(1, 31, dtype=float)
    base = _pair(np.where(t > 3, 1 - np.exp(-(t - 3) / 4), 0), np.full(30, 0.05), dead=3.5)
    quiet = compare_pair(base, _pair(base.step + 0.05, base.step_std, dead=3.5),
                         threshold_sigma=THRESHOLD)
    assert not quiet.changed and quiet.reasons == ()
    late = compare_pair(base, _pair(base.step, base.step_std, dead=6.5),
                        threshold_sigma=THRESHOLD, base_dead_time_std=0.5,
                        run_dead_time_std=0.5)
    assert late.dead_time_z == pytest.approx(3.0 / np.hypot(0.5, 0.5))
    assert late.changed and late.reasons == ("dead_time",)


def test_step_comparison_leaves_out_the_shorter_runs_last_lag_and_aligns_periods():
    base = _pair(np.linspace(0.1, 2.0, 20), np.full(20, 0.01))
    short = _pair(np.r_[np.linspace(0.1, 2.0, 20)[:14], 2.0], np.full(15, 0.01))
    # the short run's last lag is its gain (2.0, far from base's 1.5 at lag 15): not compared
    z, zabs, _, m = step_difference_z(base, short)
    assert m == 14 and zabs == pytest.approx(0.0, abs=1e-9)
    # the same response sampled at 2 s is compared at the coarse lag times
    fine_t = (np.arange(40) + 0.5) * 1.0
    coarse_t = (np.arange(20) + 0.5) * 2.0
    fine = _pair(1 - np.exp(-fine_t / 8), np.full(40, 0.01))
    coarse = _pair(1 - np.exp(-coarse_t / 8), np.full(20, 0.01), dt=2.0)
    z, zabs, _, m = step_difference_z(fine, coarse)
    assert m >= 18 and zabs < 0.5  # linear interpolation error of a smooth response


def test_compare_runs_reports_pairs_missing_from_the_baseline_and_bad_threshold():
    a = _pair(np.ones(5), np.full(5, 0.1))
    b = _pair(np.ones(5), np.full(5, 0.1), inp="v")
    res = compare_runs([a], [a, b], baseline_run="r0")
    assert [p.pair for p in res.pairs] == ["y<-u"] and "y<-v" in res.not_compared
    assert monitor_banner(res.to_dict()) == "No pair moved beyond 3 σ of baseline r0."
    none = compare_runs([b], [a], baseline_run="r0").to_dict()
    assert monitor_banner(none).startswith("**Not compared with baseline r0:**")
    with pytest.raises(ConfigError, match="monitor.threshold_sigma: 0"):
        compare_runs([a], [a], baseline_run="r0", threshold_sigma=0)
    with pytest.raises(ConfigError, match="baseline pair y<-u is not the run's y<-v"):
        compare_pair(a, b, threshold_sigma=3)


@pytest.mark.parametrize(("monitor", "message"), [
    ({"baseline": "../etc"}, r"monitor.baseline: must be 'first' or a run id"),
    ({"threshold_sigma": 0.5}, r"monitor.threshold_sigma: Input should be greater than or "
                               r"equal to 1"),
    ({"baseline": "first", "sigma": 3}, r"monitor.sigma: unknown key"),
])
def test_monitor_section_errors_name_the_yaml_key(tmp_path, monitor, message):
    from pipeline.adapters.config import job_from_dict

    data = {"job": "j", "source": {"path": "x.csv", "timezone": "UTC"},
            "signals": {"inputs": {"u": {"tag": "U"}}, "outputs": {"y": {"tag": "Y"}}},
            "monitor": monitor}
    with pytest.raises(ConfigError, match=message):
        job_from_dict(data, base_dir=tmp_path)
    ok = job_from_dict({**data, "monitor": {}}, base_dir=tmp_path)
    assert (ok.monitor.baseline, ok.monitor.threshold_sigma) == ("first", 3.0)


# -------------------------------------------------------- calibration, core API
G1 = ct.tf([2.0], [30.0, 13.0, 1.0])  # 2 / ((10 s + 1)(3 s + 1)), 3 s dead time
G2 = ct.tf([-1.0], [6.0, 1.0])        # -1 / (6 s + 1), 1 s dead time
N_NIGHT, N_P = 10_000, 60
QUIET_NIGHTS, CHANGED_NIGHTS = 60, 20


def _zoh(G, u: np.ndarray, delay: int) -> np.ndarray:
    """Response of ``G`` to a held input, by python-control's exact ZOH discretisation
    filtered with scipy (zero initial state; ``tests.plants.zoh_response`` equals it and
    is 10x slower), delayed by whole samples."""
    Gd = ct.sample_system(G, 1.0, method="zoh")
    num, den = np.ravel(Gd.num[0][0]), np.ravel(Gd.den[0][0])
    num = np.concatenate([np.zeros(den.size - num.size), num])  # powers of z aligned
    y = ss.lfilter(num, den, u)
    return np.concatenate([np.zeros(delay), y[: u.size - delay]])


def simulate_night(seed: int, gain1: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """One night of the two-input plant (module notes): conditioned inputs and output."""
    rng = np.random.default_rng(seed)
    u = np.column_stack([ar1(N_NIGHT, 0.9, rng), ar1(N_NIGHT, 0.8, rng)])
    y0 = gain1 * _zoh(G1, u[:, 0], 3) + _zoh(G2, u[:, 1], 1)
    v = ss.lfilter([1.0], [1.0, -0.9], rng.standard_normal(N_NIGHT))
    y = y0 + v * 0.3 * y0.std() / v.std()
    return u - u.mean(0), (y - y.mean())[:, None]


def night_pairs(seed: int, gain1: float = 1.0) -> list[PairResponse]:
    """A night estimated as a job does (noise model chosen from the data), as stored."""
    from pipeline.readouts.characteristics import self_regulating_characteristics
    from pipeline.estimation.estimate import estimate_step_responses

    est = estimate_step_responses(*simulate_night(seed, gain1), n_p=N_P, dt=1.0,
                                  noise="auto")
    out = []
    for j, name in enumerate(("u1", "u2")):
        step, std = est.step[0, j, :N_P], est.step_std[0, j, :N_P]
        ch = self_regulating_characteristics(step, dt_s=1.0, step_std=std, gain=step[-1],
                                             gain_std=std[-1])
        out.append(PairResponse("y", name, False, float(step[-1]), float(std[-1]),
                                ch.dead_time_s + 0.5, step, std, 1.0))
    return out


def calibration(quiet: int, changed: int, *, baselines: int = 1, seed0: int = 0,
                gain1: float = 1.3) -> dict:
    """False alarms on quiet nights and detections of a gain change of ``y<-u1`` (by
    the factor ``gain1``), against ``baselines`` baseline nights (each compared with
    every night)."""
    bases = [night_pairs(seed0 + 9000 + b) for b in range(baselines)]
    quiet_nights = [night_pairs(seed0 + 1000 + k) for k in range(quiet)]
    changed_nights = [night_pairs(seed0 + 5000 + k, gain1=gain1) for k in range(changed)]
    out = {"false_alarms": 0, "quiet": 0, "detected": 0, "exactly": 0, "changed": 0,
           "gain_z2": []}
    for b, base in enumerate(bases):
        for night in quiet_nights:
            res = compare_runs(base, night, baseline_run=f"b{b}", threshold_sigma=THRESHOLD)
            out["quiet"] += 1
            out["false_alarms"] += bool(res.changed)
        for night in changed_nights:
            res = compare_runs(base, night, baseline_run=f"b{b}", threshold_sigma=THRESHOLD)
            out["changed"] += 1
            out["detected"] += "y<-u1" in res.changed
            out["exactly"] += res.changed == ("y<-u1",)
    # honesty of the σ: nights compared in disjoint pairs (independent differences)
    for a, b in zip(quiet_nights[0::2], quiet_nights[1::2]):
        out["gain_z2"] += [p.gain_z ** 2 for p in compare_runs(a, b, baseline_run="a").pairs]
    return out


def test_quiet_nights_rarely_alarm_and_a_30_percent_gain_change_is_flagged():
    from tests.plants import zoh_response

    u = ar1(500, 0.9, np.random.default_rng(0))  # the fast simulation is python-control's
    np.testing.assert_allclose(_zoh(G1, u, 3), zoh_response(G1, u, 1.0, 3), atol=1e-12)
    r = calibration(QUIET_NIGHTS, CHANGED_NIGHTS)
    print(f"false alarms {r['false_alarms']}/{r['quiet']}, 30 % change flagged "
          f"{r['detected']}/{r['changed']} (exactly that pair {r['exactly']}), "
          f"mean gain z² {np.mean(r['gain_z2']):.2f}")
    assert r["false_alarms"] <= 1, r
    assert r["detected"] >= 19 and r["exactly"] >= 19, r
    # the low false-alarm rate is not bought with inflated σ: over 60 independent
    # differences the mean z² of a calibrated σ is 1 ± 0.18 (χ²₁: var 2/60)
    assert 0.5 <= np.mean(r["gain_z2"]) <= 1.6, r["gain_z2"]


# ------------------------------------------------------------------- user level
TAGS = {"u1": "U1.PV", "u2": "U2.PV", "y": "Y.PV"}
START = np.datetime64("2026-06-01T00:00:00", "us")


def write_night(path: Path, night: int, *, gain1: float, hours: float = 0.75) -> Path:
    """A night's historian export of ``y = K1/(8 s+1) u1 + 0.5/(4 s+1) u2`` (exact ZOH
    by scipy, 1 s samples, white sensor noise); the night's own time span."""
    from pipeline.adapters.historian_writer import write_long_csv

    rng = np.random.default_rng(4000 + night)
    n = int(hours * 3600)
    u = np.column_stack([ar1(n, 0.9, rng), ar1(n, 0.8, rng)])
    a1, a2 = np.exp(-1 / 8), np.exp(-1 / 4)
    y = ss.lfilter([0, gain1 * (1 - a1)], [1, -a1], u[:, 0]) + \
        ss.lfilter([0, 0.5 * (1 - a2)], [1, -a2], u[:, 1]) + 0.03 * rng.standard_normal(n)
    t = START + np.timedelta64(night, "D") + (np.arange(n) * 1_000_000).astype("timedelta64[us]")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_long_csv(path, t, {TAGS["u1"]: 50 + u[:, 0], TAGS["u2"]: 20 + u[:, 1],
                             TAGS["y"]: 10 + y})
    return path


def monitored_job(folder: Path, **monitor) -> Path:
    from tests.conftest import write_job

    return write_job(folder, name="plant",
                     signals={"inputs": {"u1": {"tag": TAGS["u1"]}, "u2": {"tag": TAGS["u2"]}},
                              "outputs": {"y": {"tag": TAGS["y"]}}},
                     monitor={"baseline": "first", "threshold_sigma": THRESHOLD, **monitor})


def test_nightly_sequence_flags_the_changed_pair_on_night_5(prefect_harness, tmp_path, capsys):
    from flows.cli import main
    from flows.nightly import run_nightly
    from pipeline.adapters.store import ResultStore
    from pipeline.adapters.trend_plot import pair_trends

    job = monitored_job(tmp_path)
    storage = tmp_path / "storage"
    runs = []
    for night in range(1, 6):
        write_night(tmp_path / "drop" / f"night_{night}.csv", night,
                    gain1=2.6 if night == 5 else 2.0)
        rows = [r for r in run_nightly(job) if r["status"] == "ok"]
        assert len(rows) == 1, rows  # the earlier nights' files are skipped
        runs.append(rows[0]["run_id"])
    checks = [json.loads((storage / "plant" / r / "checks.json").read_text()) for r in runs]
    mon = [c["monitor"] for c in checks]
    assert mon[0]["is_baseline"] and mon[0]["baseline_run"] == runs[0] and not mon[0]["changed"]
    for m in mon[1:]:
        assert m["baseline_run"] == runs[0]
        assert set(m["pairs"]) == {"y<-u1", "y<-u2"}
    assert [m["changed"] for m in mon[1:]] == [[], [], [], ["y<-u1"]]
    night5 = mon[4]["pairs"]["y<-u1"]
    assert night5["changed"] and night5["gain_z"] > THRESHOLD
    assert night5["relative_change"] == pytest.approx(0.30, abs=0.03)
    assert not mon[4]["pairs"]["y<-u2"]["changed"]
    reports = [(storage / "plant" / r / "report.md").read_text().splitlines()[2] for r in runs]
    assert reports[0].startswith("**Baseline:** this run")
    assert all(line.startswith("No pair moved beyond 3 σ") for line in reports[1:4])
    assert re.fullmatch(rf"\*\*Changed vs baseline {runs[0]}:\*\* y<-u1 \(gain "
                        r"\+(2[6-9]|3[0-4]) %, [0-9.]+ σ\)", reports[4]), reports[4]

    store = ResultStore(storage)

    def labels():
        t = store.trend("plant", metric="monitor")
        return {(r, p): lab for r, p, lab in zip(
            t["run_id"], t["input"], t["label"])}

    catalogued = labels()
    assert catalogued[(runs[4], "u1")] == "changed"
    assert [v for (r, _), v in catalogued.items() if r != runs[4] and v == "changed"] == []
    assert catalogued[(runs[4], "u2")] == "unchanged"
    assert store.reindex().n_runs == 5  # what `plantdyn reindex` does
    assert labels() == catalogued  # rebuilt from the run folders' manifests

    capsys.readouterr()
    assert main(["runs", str(job)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("CHANGED vs baseline: 1 pair-run(s)")
    first_table = out.split("shape:")[1]
    assert runs[4] in first_table and "y<-u1" in first_table and "y<-u2" not in first_table
    png = Path(out.strip().splitlines()[-1].removeprefix("trend plot: "))
    assert png == storage / "plant" / "trend.png"
    from PIL import Image

    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[0] >= 600 and im.size[1] >= 400
        colours = np.unique(np.asarray(im.convert("RGB")).reshape(-1, 3), axis=0)
        assert len(colours) > 50  # drawn, not blank
    trends = {t.pair: t for t in pair_trends(store.trend("plant"))}
    u1 = trends["y<-u1"]
    assert list(u1.run_ids) == runs
    assert u1.outside().tolist() == [False, False, False, False, True]
    assert not trends["y<-u2"].outside().any()

    # night 6 through the estimate flow (`plantdyn run`): the gain is back, the flow
    # publishes the comparison as a Prefect markdown artifact
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from flows.common import artifact_key
    from flows.estimate import run_estimate

    night6 = run_estimate(job, files=[write_night(tmp_path / "night_6.csv", 6, gain1=2.0)],
                          run_id="night6")
    mon6 = json.loads((night6.run_dir / "checks.json").read_text())["monitor"]
    assert mon6["baseline_run"] == runs[0] and mon6["changed"] == []
    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=[artifact_key("plant", "monitor")])))
    texts = [a.data for a in arts]
    assert any(t.startswith(f"No pair moved beyond 3 σ of baseline {runs[0]}.") and
               "| y<-u1 | no |" in t and "| y<-u2 | no |" in t for t in texts), texts


def test_a_missing_pinned_baseline_is_exit_2_naming_the_runs(tmp_path, capsys):
    from flows.cli import main

    job = monitored_job(tmp_path, baseline="nosuchrun")
    write_night(tmp_path / "drop" / "night_1.csv", 1, gain1=2.0, hours=0.5)
    assert main(["run", "--no-prefect", str(job)]) == 2
    err = capsys.readouterr().err
    assert "monitor.baseline: run 'nosuchrun' of job 'plant'" in err
    assert "the job has no runs yet" in err
    # with a run in the catalog the message lists it; nightly stops before any file
    assert main(["run", "--no-prefect", "--run-id", "night1",
                 str(monitored_job(tmp_path, baseline="first"))]) == 0
    job = monitored_job(tmp_path, baseline="nosuchrun")
    capsys.readouterr()
    assert main(["nightly", str(job)]) == 2
    err = capsys.readouterr().err
    assert "the runs that exist: night1" in err and "monitor.baseline: first" in err
    # a baseline changed after it was written cannot be trusted: exit 2 before any work
    report = tmp_path / "storage" / "plant" / "night1" / "report.md"
    report.write_text(report.read_text() + "edited\n")
    job = monitored_job(tmp_path, baseline="night1")
    assert main(["run", "--no-prefect", str(job)]) == 2
    err = capsys.readouterr().err
    assert "monitor.baseline: the baseline run cannot be used: run plant/night1: " \
        "report.md has sha256" in err


if __name__ == "__main__":  # the numbers in docs/guide/nightly.md: many nights, several baselines
    import argparse
    import time

    ap = argparse.ArgumentParser(description="monitoring calibration on simulated nights")
    ap.add_argument("--quiet", type=int, default=100)
    ap.add_argument("--changed", type=int, default=50)
    ap.add_argument("--baselines", type=int, default=4)
    ap.add_argument("--gain", type=float, default=1.3, help="gain factor of the change")
    ns = ap.parse_args()
    t0 = time.perf_counter()
    r = calibration(ns.quiet, ns.changed, baselines=ns.baselines, seed0=100_000,
                    gain1=ns.gain)
    z2 = f"{np.mean(r['gain_z2']):.2f}" if r["gain_z2"] else "n/a"
    print(f"{ns.baselines} baseline nights × {ns.quiet} quiet nights: "
          f"{r['false_alarms']}/{r['quiet']} flagged; gain × {ns.gain:g}: "
          f"{r['detected']}/{r['changed']} flagged, {r['exactly']} exactly that pair; "
          f"mean gain z² over independent pairs {z2}; {time.perf_counter() - t0:.0f} s")
