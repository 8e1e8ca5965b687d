"""The sample period for integrating outputs, step-wise signals and short records
(pipeline/identification/sampling.py, as ``plantdyn run`` uses it through pipeline/jobs.prepare).

The plant (a boiler drum, thesis §6.4), simulated here with scipy alone: steam flow and
feedwater in kg/s, the level in cm integrates ``K (feedwater - steam)`` and swells the wrong
way after a steam-flow increase, ``SWELL / (TAU s + 1)``, so

    level <- steam:      -K/s + SWELL/(TAU s + 1)   (rate -K, wrong-way peak PEAK)
    level <- feedwater:   K/s                        (rate +K, no wrong-way move)

Inputs are piecewise constant at 0.1 s (exact zero-order-hold discretisation of both paths,
``scipy.signal.cont2discrete``), the export holds point samples every 1 s for 6 h, plus
``NOISE_CM`` of white level-sensor noise.  Steam flow moves as band-limited noise (two
30 s lags), feedwater follows it through a 20 s lag plus its own band-limited moves (two
20 s lags): inputs this smooth are why α_T on the level gave T = 24 s here (22 s in the
user's report, where the run then failed).

The bound on T: the swell's time constant must be resolved, ``T <= TAU / 3 = 5 s`` (three
samples per time constant, four before the wrong-way peak at ``t* = TAU ln(SWELL/(K TAU))
= 23 s``).  The lower bound is the α_T definition applied, by brute force here, to the
noise-free level's first difference (what eq. 3.15 regresses): ``T_NF`` = 4.4 s; sensor
noise may lengthen T (pipeline/identification/sampling.py's notes) but must not pin it to the record's 1 s, where the
per-lag scatter of the estimate put the data's wrong-way peak at 0.51 instead of 0.32
(measured with ``sampling.dt_s: 1`` on this record; 0.32 at the 5 s chosen).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.signal as ss
import yaml

from pipeline.errors import ConfigError
from pipeline.identification.sampling import (
    SEARCH_N_P_MIN,
    SEARCH_OBS_PER_UNKNOWN,
    choose_sample_period,
    search_fits,
)
from tests.conftest import subprocess_env
from tests.identification.test_sampling import first_order_multisine

K = 0.01  # cm per (kg/s) per s
SWELL = 0.7  # cm per kg/s
TAU = 15.0  # s
NOISE_CM = 0.2  # white level-sensor noise (std, cm)
FINE_S = 0.1
HOURS = 6.0
WARMUP_S = 1800.0
TAGS = {"steam_flow": "FI-401.PV", "feedwater": "FI-402.PV", "level": "LI-403.PV"}

#: Wrong-way peak of the steam step response, -K t + SWELL (1 - exp(-t/TAU)), at
#: t* = TAU ln(SWELL / (K TAU)).
PEAK = SWELL - K * TAU * (1.0 + np.log(SWELL / (K * TAU)))
T_BOUND_S = TAU / 3.0


def _lag(u: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag at FINE_S (exact for a zero-order-hold input)."""
    a = np.exp(-FINE_S / tau_s)
    return ss.lfilter([0.0, 1.0 - a], [1.0, -a], u)


def _zoh(num, den, u: np.ndarray) -> np.ndarray:
    """Response of num/den (polynomials in s) to ``u`` held over each FINE_S."""
    b, a, _ = ss.cont2discrete((num, den), FINE_S, method="zoh")
    return ss.lfilter(np.ravel(b), np.ravel(a), u)


def simulate_drum(*, seed: int, noise_cm: float = NOISE_CM) -> dict[str, np.ndarray]:
    """Steam flow, feedwater (kg/s) and level (cm) sampled every 1 s for HOURS."""
    rng = np.random.default_rng(seed)
    n = int(round((HOURS * 3600 + WARMUP_S) / FINE_S))

    def band_limited(tau_s: float, std: float) -> np.ndarray:
        v = _lag(_lag(rng.standard_normal(n), tau_s), tau_s)
        return std * v / v[n // 4:].std()

    steam = band_limited(30.0, 3.0)
    feed = _lag(steam, 20.0) + band_limited(20.0, 2.0)
    level = (_zoh([SWELL - K * TAU, -K], [TAU, 1.0, 0.0], steam)  # -K/s + SWELL/(TAU s+1)
             + _zoh([K], [1.0, 0.0], feed))  # K/s
    keep = slice(int(round(WARMUP_S / FINE_S)), None, int(round(1.0 / FINE_S)))
    level = level[keep]
    return {"steam_flow": 60.0 + steam[keep], "feedwater": 60.0 + feed[keep],
            "level": level + noise_cm * rng.standard_normal(level.size)}


def brute_force_period(x: np.ndarray, target: float, max_hold: int = 40) -> float:
    """T (in samples) where α_T of ``x`` (linear trend removed) reaches ``target``: holds
    of m samples replayed with np.repeat, hold period (m - 1) samples, T = twice it."""
    x = ss.detrend(x)
    prev = 0.0
    for m in range(2, max_hold):
        held = np.repeat(x[::m], m)[: x.size]
        a = float(np.mean((x - held) ** 2) / np.mean(x**2))
        if a >= target:
            return 2.0 * ((m - 2) + (target - prev) / (a - prev))
        prev = a
    raise AssertionError("target not reached")


def test_true_peak_from_the_continuous_step_response():
    """The closed form against scipy's step response of (SWELL-K TAU) s - K / (TAU s² + s)."""
    t, h = ss.step(([SWELL - K * TAU, -K], [TAU, 1.0, 0.0]), T=np.linspace(0, 200, 200_001))
    assert h.max() == pytest.approx(PEAK, rel=1e-6)
    assert t[np.argmax(h)] == pytest.approx(TAU * np.log(SWELL / (K * TAU)), abs=1e-2)
    assert PEAK == pytest.approx(0.319, abs=1e-3)


@pytest.fixture(scope="module")
def drum():
    return simulate_drum(seed=6_400_001)


@pytest.fixture(scope="module")
def t_noise_free_s() -> float:
    """α_T's T (1 % target, record dt = 1 s) of the noise-free level's first difference."""
    return brute_force_period(np.diff(simulate_drum(seed=6_400_001, noise_cm=0.0)["level"]),
                              0.01)


ROLES = {"steam_flow": "input", "feedwater": "input", "level": "output"}


def test_first_difference_of_an_integrating_output_sets_t(t_noise_free_s):
    """Noise-free level: α_T on its first difference gives the brute-force T (rounded
    down), well under TAU/3; measured on the level itself it would be over 20 s."""
    sig = simulate_drum(seed=6_400_001, noise_cm=0.0)
    assert 3.0 < t_noise_free_s < T_BOUND_S
    choice = choose_sample_period(sig, grid_dt_s=1.0, roles=ROLES, integrating={"level": True})
    assert choice.limiting_signal == "level"
    assert choice.measured_on["level"] == "first difference"
    assert choice.preferred_dt_s["level"] == pytest.approx(t_noise_free_s, rel=0.02)
    assert choice.dt_s == np.floor(t_noise_free_s)
    assert choice.to_dict()["measured_on"]["level"] == "first difference"
    old = choose_sample_period(sig, grid_dt_s=1.0, roles=ROLES)  # the level as a plain signal
    assert old.dt_s > 20.0 and old.measured_on["level"] == "signal"


def test_sensor_noise_neither_pins_t_to_the_record_nor_hides_the_swell(drum, t_noise_free_s):
    """With 2 mm of level noise α_T of Δy is the noise's (T far below 1 s); measured above
    the noise floor T stays between the noise-free answer (rounded down) and TAU/3."""
    choice = choose_sample_period(drum, grid_dt_s=1.0, roles=ROLES, integrating={"level": True})
    assert choice.measured_on["level"] == "first difference above the noise floor"
    assert np.floor(t_noise_free_s) <= choice.dt_s <= T_BOUND_S
    assert any("above that floor" in n for n in choice.notes)


def test_a_random_walk_level_is_not_mistaken_for_noise():
    """A level whose rate is white (a random walk, no sensor noise) needs T < dt: the
    record period with a 'too slowly' note, not a long T invented by the noise floor."""
    lvl = np.cumsum(np.random.default_rng(3).standard_normal(20_000))
    choice = choose_sample_period({"level": lvl}, grid_dt_s=1.0, roles={"level": "output"},
                                  integrating={"level": True})
    assert choice.decimation == 1
    assert any("too slowly" in n for n in choice.notes)


def test_integrating_applies_to_named_outputs_only(drum):
    with pytest.raises(ConfigError, match="only outputs integrate"):
        choose_sample_period(drum, grid_dt_s=1.0, roles=ROLES, integrating={"steam_flow": True})
    with pytest.raises(ConfigError, match="not among the signals.*allowed: level"):
        choose_sample_period(drum, grid_dt_s=1.0, roles=ROLES, integrating={"drum": True})


# ------------------------------------------------------------------ step-wise signals
def _setpoint(n: int, every: int, rng) -> np.ndarray:
    """A held setpoint toggling between -1 and +1, a step every ``every`` samples on
    average (exponential intervals)."""
    steps = np.cumsum(rng.exponential(every, size=2 * n // every + 10)).astype(int)
    sp = np.ones(n)
    for k in steps[steps < n]:
        sp[k:] *= -1.0
    return sp


def test_a_held_setpoint_does_not_set_t():
    """A setpoint toggling every ~20 samples has α_T ≈ λ J² T'/2 / var = T'/10 (λ = 1/20,
    J = 2, var 1): 5 % at T ≈ 1 sample.  The continuously moving input (first-order,
    w0 dt = 0.01: T = 0.1017/w0 = 10.2 samples) sets T instead."""
    rng = np.random.default_rng(21)
    n = 2**17
    sig = {"u": first_order_multisine(n, 0.01, rng), "sp": _setpoint(n, 20, rng)}
    assert np.mean(np.diff(sig["sp"]) == 0) > 0.9  # held: most samples unchanged
    choice = choose_sample_period(sig, grid_dt_s=1.0, roles={"u": "input", "sp": "input"})
    assert choice.stepwise == ("sp",)
    assert choice.preferred_dt_s["sp"] < 2.0  # it would have forced T to the record's
    assert choice.limiting_signal == "u"
    assert choice.decimation == int(np.floor(choice.preferred_dt_s["u"]))
    assert choice.dt_s == pytest.approx(10.0, abs=1.0)
    assert any("do not set T" in n for n in choice.notes)
    assert choice.to_dict()["stepwise"] == ["sp"]
    # nothing continuous: the step-wise signals set T, and a note says what that means
    alone = choose_sample_period({"sp": sig["sp"]}, grid_dt_s=1.0, roles={"sp": "input"})
    assert alone.limiting_signal == "sp" and alone.decimation == 1
    assert any("every signal is step-wise" in n for n in alone.notes)


# ------------------------------------------------------------ T the search can use
def test_search_fits_counts_two_windows_of_ten_observations_per_unknown():
    """Need: 2 windows x 10 observations x 3 lags x n_x inputs, plus 3 lead-in samples."""
    assert SEARCH_OBS_PER_UNKNOWN == 20 and SEARCH_N_P_MIN == 3
    assert search_fits(123, 2) and not search_fits(122, 2)  # 2 * 10 * 3 * 2 + 3
    assert search_fits(63, 1) and not search_fits(62, 1)
    assert search_fits(63, 0)  # no inputs: counted as one
    assert search_fits(2 * 10 * 5 * 2 + 5, 2, n_p_min=5)


def test_a_record_too_short_for_the_search_gets_a_shorter_t():
    """Two inputs with T ≈ 20 samples by α_T (w0 dt = 0.005) in a 1000-sample record: 50
    samples at that T, fewer than the 123 the search needs; the largest decimation
    holding 123 is 8 (1000 // 8 = 125, 1000 // 9 = 111)."""
    rng = np.random.default_rng(8)
    sig = {k: first_order_multisine(1000, 0.005, rng) for k in ("u1", "u2")}
    roles = {"u1": "input", "u2": "input"}
    choice = choose_sample_period(sig, grid_dt_s=2.0, roles=roles)
    assert choice.alpha_t_dt_s >= 2.0 * 9  # the α_T choice did not fit
    assert choice.decimation == 8 and choice.dt_s == 16.0
    assert "fewer than the 123 the N_p search needs" in choice.reduced_reason
    assert "T = 16 s, the longest at which it fits" in choice.reduced_reason
    d = choice.to_dict()
    assert d["reduced_reason"] == choice.reduced_reason and d["alpha_t_dt_s"] > d["dt_s"]
    assert "shorter than the α_T choice" in str(choice)
    # the whole record the search sees is longer than the stretch α_T was measured on
    roomy = choose_sample_period(sig, grid_dt_s=2.0, roles=roles, n_search_samples=10_000)
    assert roomy.reduced_reason is None and roomy.dt_s == roomy.alpha_t_dt_s
    # not even the record period fits: T = dt and the reason says so
    short = choose_sample_period({k: v[:100] for k, v in sig.items()}, grid_dt_s=2.0,
                                 roles=roles, max_hold_samples=5)
    assert short.decimation == 1 and "even the record period" in short.reduced_reason


# ------------------------------------------------------------ the user's job, end to end
def _write_wide_csv(path: Path, sig: dict[str, np.ndarray]) -> None:
    """Wide historian CSV: a timestamp column (UTC, 1 s) and one column per tag."""
    n = sig["level"].size
    t0 = np.datetime64("2026-05-04T00:00:00", "s")
    stamps = np.datetime_as_string(t0 + np.arange(n).astype("timedelta64[s]"), unit="s")
    cols = np.column_stack([sig[k] for k in TAGS])
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(["timestamp", *TAGS.values()]) + "\n")
        for s, row in zip(stamps, cols, strict=True):
            fh.write(f"{s}Z," + ",".join(f"{v:.9g}" for v in row) + "\n")


@pytest.fixture(scope="module")
def drum_run(tmp_path_factory, drum) -> tuple[subprocess.CompletedProcess, Path]:
    folder = tmp_path_factory.mktemp("drum_alpha")
    _write_wide_csv(folder / "drop" / "drum.csv", drum)
    job = {"job": "drum", "source": {"path": "drop/*.csv", "timezone": "UTC"},
           "signals": {"inputs": {"steam_flow": {"tag": TAGS["steam_flow"]},
                                  "feedwater": {"tag": TAGS["feedwater"]}},
                       "outputs": {"level": {"tag": TAGS["level"], "integrating": True}}},
           "storage": "storage", "rerun": {"enabled": False}}
    path = folder / "drum.yaml"
    path.write_text(yaml.safe_dump(job, sort_keys=False))
    r = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(path), "--no-prefect"],
                       capture_output=True, text=True, env=subprocess_env(), timeout=600)
    return r, folder


def test_default_job_on_the_drum_resolves_rates_and_swell(drum_run, t_noise_free_s):
    """Rates within 5 % of ±K, the wrong-way peak within 20 % of PEAK (the tolerances of
    tests/jobs/test_integrating_job.py's must-show, looser for the rates; the estimates' own
    scatter: the four quarter-record windows' rates agree within 0.8 %, the step points
    near the peak have σ ≈ 0.01 cm, 3 % of PEAK)."""
    r, folder = drum_run
    assert r.returncode == 0, r.stderr[-3000:]
    run_dir = Path(r.stdout.strip().splitlines()[-1])
    checks = json.loads((run_dir / "checks.json").read_text())
    sampling = checks["sampling"]
    assert sampling["source"] == "alpha_t"
    assert np.floor(t_noise_free_s) <= sampling["dt_s"] <= T_BOUND_S
    assert sampling["measured_on"]["level"] == "first difference above the noise floor"
    assert sampling["reduced_reason"] is None
    pairs = {p["input"]: p for p in checks["pairs"]}
    assert abs(pairs["steam_flow"]["rate"] / -K - 1) <= 0.05, pairs["steam_flow"]["rate"]
    assert abs(pairs["feedwater"]["rate"] / K - 1) <= 0.05, pairs["feedwater"]["rate"]
    peak = pairs["steam_flow"]["characteristics"]["inverse_peak"]
    assert abs(peak / PEAK - 1) <= 0.20, peak
    model_peak = pairs["steam_flow"]["characteristics"]["inverse_peak_model"]
    print(f"T = {sampling['dt_s']} s; rates {pairs['steam_flow']['rate']:.6f}, "
          f"{pairs['feedwater']['rate']:.6f} (truth ∓{K}); peak {peak:.4f} "
          f"(truth {PEAK:.4f}, fitted model {model_peak:.4f})")
