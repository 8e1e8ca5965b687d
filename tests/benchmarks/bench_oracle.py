"""plantdyn's default job path against an FIR oracle that knows the truth (issue 36, build 5).

Five cases, simulated here with numpy/scipy only (exact zero-order-hold discretisation of
continuous lags by ``scipy.signal.cont2discrete``, explicit loops for the controller; never
``pipeline.models.simulate`` or ``pipeline.simulated.synthetic``), record period 1 s:

- ``si5k`` / ``si50k``: one input, open loop, N = 5 000 / 50 000; plant
  1.5 / ((8 s + 1)(3 s + 1)) with a dead time of 4 samples; ARMA output noise
  H = (1 + 0.5 q⁻¹) / (1 − 0.9 q⁻¹).
- ``pi``: a PI loop (kp 1.0, ki 0.1 per sample, acting on the same sample's measurement)
  around 1.2 / (10 s + 1), dead time 3 samples, setpoint held random steps, the same
  ARMA noise; estimated pair: controller output → measured output; N = 20 000.
- ``mimo``: 3 inputs × 2 outputs, N = 20 000, inputs mixtures of independent held-move
  signals (variance inflation factor ≈ 4.8), ARMA noise per output; y2←u3 has gain −0.40
  and dead time 6 samples, the other pairs are first/second order, settling in ~20–60 s.
- ``level``: an integrating level, open loop: level = ∫ (inflow − outflow) through a lag,
  the output declared ``integrating: true``; noise on the level
  H = (1 − 0.6 q⁻¹) / (1 − 0.97 q⁻¹) (white sensor noise plus a slow AR(1) drift);
  N = 20 000.

Inputs move as operators and setpoints move a plant: held random levels (a new one every
20–90 samples) plus a little white noise.  "Dead time d" means the first d step-response
samples are zero (plantdyn's ``n_k``); the 99 % settling lag is the first sample after
which the step (for the level, its slope) stays within 1 % of its final value.

Per case and seed, the record is written as a long historian CSV and estimated with
``plantdyn run --no-prefect`` and a job that sets nothing but the signals (and the level's
``integrating: true``).  The oracle per output: generalised least squares FIR with the TRUE
noise filter (y and u filtered by H⁻¹), the TRUE dead times (each input's lags start at
its dead time) and a horizon of the true 99.9 % settling lag, all inputs of the output in
one ``numpy.linalg.lstsq``; its step is the cumulative sum of the FIR (the level's: the FIR
on the cumulated inputs, summed twice).  plantdyn's step responses (``step_responses.
parquet``, window ``all``) are compared on the time axis, lag l at (l − ½)·dt_s, so a
sample period chosen by the α_T criterion longer than the record's is compared as is;
past plantdyn's N_p the curve is padded as its exports pad it.

Printed per case: median over seeds of plantdyn's / the oracle's max |step − true step|
over the true 99 % settling horizon (per pair and over all pairs), ±2σ gain coverage (rate
for the level; pairs with no gain counted apart), ±2σ lag coverage over lags ≤ N_p, RMS z
of the gain; for mimo whether a pair's N_p lies inside its dead time and its median N_p
against the true settling lag.  Targets: mimo gain coverage 90–98 %, no N_p inside a dead
time, mimo max error ≤ 1.1× the oracle's; si5k gain coverage ≥ 88 %; lag coverage 90–98 %
in every case.

    .venv/bin/python -m tests.benchmarks.bench_oracle [--cases si5k,mimo] [--seeds 30]
        [--first 7000] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl
import scipy.signal as ss
import yaml

ROOT = Path(__file__).resolve().parents[2]
DT_S = 1.0  # record period
ARMA = ((1.0, 0.5), (1.0, -0.9))  # H = (1 + 0.5 q⁻¹) / (1 − 0.9 q⁻¹)
LEVEL_NOISE = ((1.0, -0.6), (1.0, -0.97))
MIX = 0.527  # u_j = w_j + MIX·Σ_{i≠j} w_i: equicorrelation 0.856, VIF 4.8


@dataclass(frozen=True)
class Pair:
    """One true transfer path.

    Attributes
    ----------
    output, input : str
        Signal names as in the job.
    gain : float
        Static gain (output units per input unit); for an integrating output the rate
        (output units per input unit per second).
    taus_s : tuple of float
        Time constants of the lags, seconds.
    dead : int
        Dead time in samples: the first ``dead`` step-response samples are zero.
    """

    output: str
    input: str
    gain: float
    taus_s: tuple[float, ...]
    dead: int


@dataclass(frozen=True)
class Case:
    """One benchmark case: record length, plant, noise and how the inputs move.

    Attributes
    ----------
    name : str
    n : int
        Record length, samples.
    pairs : tuple of Pair
    noise : tuple
        ``(b, a)`` of the noise filter H (polynomials in q⁻¹), the same for every output.
    noise_sd : float
        Standard deviation of the white innovation driving H.
    kind : {"open", "pi", "level"}
    mix : bool
        Inputs as mixtures of independent held-move signals (module constant ``MIX``).
    """

    name: str
    n: int
    pairs: tuple[Pair, ...]
    noise: tuple = ARMA
    noise_sd: float = 0.1
    kind: str = "open"
    mix: bool = False

    @property
    def inputs(self) -> list[str]:
        """Input names in the order the pairs first name them."""
        return list(dict.fromkeys(p.input for p in self.pairs))

    @property
    def outputs(self) -> list[str]:
        """Output names in the order the pairs first name them."""
        return list(dict.fromkeys(p.output for p in self.pairs))


_SI = (Pair("y", "u", 1.5, (8.0, 3.0), 4),)
CASES = {
    "si5k": Case("si5k", 5_000, _SI),
    "si50k": Case("si50k", 50_000, _SI),
    "pi": Case("pi", 20_000, (Pair("y", "u", 1.2, (10.0,), 3),), kind="pi"),
    "mimo": Case("mimo", 20_000, (
        Pair("y1", "u1", 1.2, (8.0,), 2), Pair("y1", "u2", -0.7, (10.0, 4.0), 4),
        Pair("y1", "u3", 0.5, (4.0,), 1), Pair("y2", "u1", 0.8, (6.0, 3.0), 3),
        Pair("y2", "u2", 1.0, (11.0,), 5), Pair("y2", "u3", -0.40, (5.0,), 6)), mix=True),
    "level": Case("level", 20_000, (Pair("level", "inflow", 0.02, (8.0,), 3),
                                    Pair("level", "outflow", -0.02, (2.0,), 2)),
                  noise=LEVEL_NOISE, noise_sd=0.02, kind="level"),
}


def plant_filter(pair: Pair, integrating: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(b, a)`` in q⁻¹ of the pair at the record period.

    Parameters
    ----------
    pair : Pair
    integrating : bool
        True: the self-regulating part only (gain = rate·DT_S per sample), which acts on
        the cumulated input; the level itself is ``b / (a·(1 − q⁻¹))``.

    Returns
    -------
    b, a : numpy.ndarray
        Exact ZOH discretisation of ``gain / Π(τ s + 1)`` with its own one-sample delay
        replaced by ``pair.dead`` samples.
    """
    k = pair.gain * (DT_S if integrating else 1.0)
    den = np.array([1.0])
    for tau in pair.taus_s:
        den = np.polymul(den, [tau, 1.0])
    b, a, _ = ss.cont2discrete(([k], den), DT_S, method="zoh")
    b = np.trim_zeros(np.ravel(b), "f")  # ZOH: b[0] = 0, the one-sample delay
    return np.r_[np.zeros(pair.dead), b], np.ravel(a)


def true_fir(pair: Pair, n: int, integrating: bool = False) -> np.ndarray:
    """Impulse response (FIR coefficients 0..n−1) of :func:`plant_filter`."""
    b, a = plant_filter(pair, integrating)
    return ss.lfilter(b, a, np.r_[1.0, np.zeros(n - 1)])


def true_step(pair: Pair, n: int, integrating: bool = False) -> np.ndarray:
    """Step response ``s[m]``, m samples after a unit step held from sample 0."""
    s = np.cumsum(true_fir(pair, n, integrating))
    return np.cumsum(s) if integrating else s


def settling_lag(pair: Pair, integrating: bool = False, frac: float = 0.01) -> int:
    """First sample after which the step (its slope when integrating) stays within
    ``frac`` of its final value."""
    curve = np.cumsum(true_fir(pair, 2000, integrating))
    final = curve[-1]
    outside = np.flatnonzero(np.abs(curve - final) > frac * abs(final))
    return int(outside[-1] + 1) if outside.size else 0


def held_moves(rng: np.random.Generator, n: int) -> np.ndarray:
    """Held random levels, a new N(0, 1) level every 20–90 samples."""
    u = np.zeros(n)
    t = 0
    while t < n:
        hold = int(rng.integers(20, 91))
        u[t:t + hold] = rng.normal(0.0, 1.0)
        t += hold
    return u


def make_inputs(case: Case, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Open-loop inputs: held moves (mixed for ``case.mix``) plus 0.05 white noise."""
    w = [held_moves(rng, case.n) for _ in case.inputs]
    if case.mix:
        total = np.sum(w, axis=0)
        w = [wj + MIX * (total - wj) for wj in w]
    return {name: wj + 0.05 * rng.standard_normal(case.n)
            for name, wj in zip(case.inputs, w, strict=True)}


def simulate(case: Case, seed: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Inputs and outputs of one record (mean levels not added).

    Returns
    -------
    inputs, outputs : dict of str to numpy.ndarray, each shape (case.n,)
    """
    rng = np.random.default_rng([seed, list(CASES).index(case.name)])
    noise = {o: case.noise_sd * ss.lfilter(*case.noise, rng.standard_normal(case.n))
             for o in case.outputs}
    if case.kind == "pi":
        return simulate_pi(case, rng, noise["y"])
    us = make_inputs(case, rng)
    ys = {o: noise[o].copy() for o in case.outputs}
    for p in case.pairs:
        b, a = plant_filter(p, case.kind == "level")
        drive = np.cumsum(us[p.input]) if case.kind == "level" else us[p.input]
        ys[p.output] += ss.lfilter(b, a, drive)
    return us, ys


def simulate_pi(case: Case, rng: np.random.Generator, noise: np.ndarray,
                kp: float = 1.0, ki: float = 0.1):
    """The PI loop: setpoint held random steps, the controller acting on the same
    sample's measurement, the process strictly delayed (dead time ≥ 1)."""
    b, a = plant_filter(case.pairs[0])
    b, a = b / a[0], a / a[0]
    r = held_moves(rng, case.n)
    u, y, yp = np.zeros(case.n), np.zeros(case.n), np.zeros(case.n)
    integral = 0.0
    for k in range(case.n):
        # b[0] = 0 (dead time >= 1): the process sees only past controller moves
        yp[k] = sum(b[i] * u[k - i] for i in range(1, min(b.size, k + 1))) \
            - sum(a[i] * yp[k - i] for i in range(1, min(a.size, k + 1)))
        y[k] = yp[k] + noise[k]
        e = r[k] - y[k]
        integral += ki * e
        u[k] = kp * e + integral
    return {"u": u}, {"y": y}


def oracle_steps(case: Case, us: dict, ys: dict) -> dict[tuple[str, str], np.ndarray]:
    """GLS FIR per output with the true noise filter, dead times and horizons.

    Returns
    -------
    dict of (output, input) to numpy.ndarray
        Estimated step response at samples 0..horizon (the level's summed twice).
    """
    integ = case.kind == "level"
    hb, ha = case.noise
    out = {}
    for o in case.outputs:
        pairs = [p for p in case.pairs if p.output == o]
        horizon = {p.input: max(settling_lag(p, integ, 0.001), p.dead + 1) for p in pairs}
        m_max = max(horizon.values())
        yf = ss.lfilter(ha, hb, ys[o])
        cols, index = [], []
        for p in pairs:
            xf = ss.lfilter(ha, hb, np.cumsum(us[p.input]) if integ else us[p.input])
            for m in range(p.dead, horizon[p.input] + 1):
                cols.append(xf[m_max - m: case.n - m])
                index.append((p.input, m))
        theta = np.linalg.lstsq(np.column_stack(cols), yf[m_max:], rcond=None)[0]
        for p in pairs:
            g = np.zeros(horizon[p.input] + 1)
            for (name, m), v in zip(index, theta, strict=True):
                if name == p.input:
                    g[m] = v
            s = np.cumsum(g)
            out[(o, p.input)] = np.cumsum(s) if integ else s
    return out


def write_job(case: Case, us: dict, ys: dict, folder: Path) -> Path:
    """The long historian CSV and the minimal job YAML; returns the YAML's path."""
    from pipeline.adapters.historian_writer import write_long_csv

    t = np.datetime64("2026-01-01T00:00:00", "us") + \
        (np.arange(case.n) * int(DT_S * 1e6)).astype("timedelta64[us]")
    (folder / "drop").mkdir(parents=True, exist_ok=True)
    values = {**{f"{k.upper()}.PV": 50 + v for k, v in us.items()},
              **{f"{k.upper()}.PV": 20 + v for k, v in ys.items()}}
    write_long_csv(folder / "drop" / "plant.csv", t, values)
    outputs = {o: {"tag": f"{o.upper()}.PV", **({"integrating": True}
                                                  if case.kind == "level" else {})}
               for o in ys}
    job = {"job": case.name, "source": {"path": "drop/*.csv", "timezone": "UTC"},
           "signals": {"inputs": {k: {"tag": f"{k.upper()}.PV"} for k in us},
                       "outputs": outputs},
           "storage": "storage", "rerun": {"enabled": False}}
    path = folder / "job.yaml"
    path.write_text(yaml.safe_dump(job, sort_keys=False))
    return path


def run_plantdyn(job: Path) -> tuple[Path | None, str, float]:
    """``plantdyn run JOB --no-prefect --progress never``: (run folder or None, error
    text, seconds)."""
    t0 = time.perf_counter()
    r = subprocess.run([str(ROOT / ".venv" / "bin" / "plantdyn"), "run", str(job),
                        "--no-prefect", "--progress", "never"], capture_output=True, text=True,
                       env={**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"})
    sec = time.perf_counter() - t0
    if r.returncode != 0:
        lines = (r.stderr.strip() or r.stdout.strip() or "no output").splitlines()
        return None, f"exit {r.returncode}: {lines[-1]}", sec
    return Path(r.stdout.strip().splitlines()[-1]), "", sec


def padded_curve(step: np.ndarray, n_lags: int, integrating: bool) -> np.ndarray:
    """plantdyn's step extended to ``n_lags`` lags as its exports pad it: held last value,
    or for an integrating pair the last increment continued."""
    if step.size >= n_lags:
        return step[:n_lags]
    extra = np.arange(1, n_lags - step.size + 1)
    slope = step[-1] - step[-2] if integrating and step.size > 1 else 0.0
    return np.r_[step, step[-1] + slope * extra]


def score_pair(case: Case, p: Pair, rec: dict, sr: pl.DataFrame, dt_s: float,
               oracle: np.ndarray) -> dict:
    """Errors, coverages and z of one pair against the truth.

    Parameters
    ----------
    rec : dict
        The pair's entry of ``checks.json`` ``pairs``.
    sr : polars.DataFrame
        The pair's rows of ``step_responses.parquet`` (window ``all``), sorted by lag.
    dt_s : float
        plantdyn's sample period.
    oracle : numpy.ndarray
        The oracle's step at samples 0..its horizon.
    """
    integ = case.kind == "level"
    m99 = settling_lag(p, integ)
    truth = true_step(p, 4 * max(m99, 50) + int(8 * dt_s / DT_S) + 2000, integ)
    step, std = sr["step"].to_numpy(), sr["step_std"].to_numpy()
    n_p = int(rec["n_p"])
    horizon_s = (m99 + 0.5) * DT_S
    n_lags = max(n_p, int(np.floor(horizon_s / dt_s + 0.5)))
    t_lag = (np.arange(1, n_lags + 1) - 0.5) * dt_s
    keep = t_lag <= horizon_s + 1e-9
    s_true = np.interp(t_lag / DT_S - 0.5, np.arange(truth.size), truth)
    err = np.abs(padded_curve(step, n_lags, integ) - s_true)
    max_err = float(err[keep].max()) if keep.any() else float("nan")
    oracle_err = float(np.max(np.abs(oracle[:m99 + 1] - truth[:m99 + 1])))
    inside = np.abs(step - s_true[:step.size]) <= 2 * std + 1e-12
    key, key_std = ("rate", "rate_std") if integ else ("gain", "gain_std")
    gain, gain_std = rec.get(key), rec.get(key_std)
    z = None if gain is None or not gain_std else (gain - p.gain) / gain_std
    return {"output": p.output, "input": p.input, "gain": gain, "gain_std": gain_std,
            "z": z, "n_p": n_p, "n_p_samples": n_p * dt_s / DT_S, "n_k": rec.get("n_k"),
            "settled": rec["settled"]["verdict"], "m99": m99,
            "inside_dead": n_p * dt_s <= p.dead * DT_S, "max_err": max_err,
            "oracle_err": oracle_err, "ratio": max_err / oracle_err,
            "lags_covered": int(inside.sum()), "lags": int(inside.size)}


def run_seed(case: Case, seed: int, folder: Path) -> dict:
    """Simulate, run plantdyn and the oracle, score every pair of one record."""
    us, ys = simulate(case, seed)
    oracle = oracle_steps(case, us, ys)
    run_dir, error, sec = run_plantdyn(write_job(case, us, ys, folder))
    if run_dir is None:
        return {"case": case.name, "seed": seed, "error": error, "seconds": sec}
    checks = json.loads((run_dir / "checks.json").read_text())
    dt_s = float(checks["dt_s"])
    sr = pl.read_parquet(run_dir / "step_responses.parquet").filter(pl.col("window") == "all")
    recs = {(q["output"], q["input"]): q for q in checks["pairs"]}
    pairs = []
    for p in case.pairs:
        rows = sr.filter((pl.col("output") == p.output) & (pl.col("input") == p.input))
        pairs.append(score_pair(case, p, recs[(p.output, p.input)], rows.sort("lag"), dt_s,
                                oracle[(p.output, p.input)]))
    est = checks["estimation"]
    return {"case": case.name, "seed": seed, "seconds": sec, "dt_s": dt_s,
            "method": est.get("method"),
            "choice": (est.get("method_choice") or {}).get("method"), "pairs": pairs}


def summarise(case: Case, rows: list[dict]) -> list[str]:
    """The printed table of one case (module docstring)."""
    ok = [r for r in rows if "pairs" in r]
    lines = [f"\n== {case.name}: N {case.n}, {len(ok)}/{len(rows)} records run, median "
             f"{np.median([r['seconds'] for r in rows]):.1f} s per run; dt_s "
             f"{sorted({r['dt_s'] for r in ok})}; methods "
             f"{sorted({str(r['method']) + '/' + str(r['choice']) for r in ok})}"]
    if not ok:
        return lines + [f"  errors: {[r.get('error') for r in rows]}"]
    lines.append(f"  {'pair':<16}{'K':>7}{'d':>3}{'T99':>5}{'N_p med':>8}{'inside d':>9}"
                 f"{'ratio':>7}{'cov':>6}{'null':>5}{'RMS z':>7}{'lag cov':>8}")
    all_ratio, z_all, lag_c, lag_n, inside_any = [], [], 0, 0, 0
    for j, p in enumerate(case.pairs):
        ps = [r["pairs"][j] for r in ok]
        z = np.array([q["z"] for q in ps if q["z"] is not None])
        ratio = [q["ratio"] for q in ps]
        all_ratio.append(ratio)
        z_all += list(z)
        lc, ln = sum(q["lags_covered"] for q in ps), sum(q["lags"] for q in ps)
        lag_c, lag_n = lag_c + lc, lag_n + ln
        n_in = sum(q["inside_dead"] for q in ps)
        inside_any += n_in
        cov = f"{100 * np.mean(np.abs(z) <= 2):5.0f}%" if z.size else "   - "
        rms = f"{np.sqrt(np.mean(z**2)):7.2f}" if z.size else "      -"
        lines.append(f"  {p.output + '<-' + p.input:<16}{p.gain:>7.3g}{p.dead:>3}"
                     f"{ps[0]['m99']:>5}{np.median([q['n_p_samples'] for q in ps]):>8.1f}"
                     f"{n_in:>9}{np.median(ratio):>7.2f}{cov}"
                     f"{len(ps) - z.size:>5}{rms}{100 * lc / max(ln, 1):>7.1f}%")
    z_all = np.array(z_all)
    per_seed = np.median(np.array(all_ratio), axis=0)  # per seed: median over pairs
    lines.append(f"  max-error ratio plantdyn/oracle: median over seeds and pairs "
                 f"{np.median(all_ratio):.2f}, of per-seed pair medians "
                 f"{np.median(per_seed):.2f}"
                 + ("  (target <= 1.1)" if case.name == "mimo" else ""))
    target = {"mimo": "  (target 90-98 %)", "si5k": "  (target >= 88 %)"}.get(case.name, "")
    if z_all.size:
        lines.append(f"  gain +-2 sigma coverage {100 * np.mean(np.abs(z_all) <= 2):.1f} % of "
                     f"{z_all.size} gains{target}; RMS z {np.sqrt(np.mean(z_all**2)):.2f}; "
                     f"no gain: {sum(len(ok) for _ in case.pairs) - z_all.size}")
    lines.append(f"  lag +-2 sigma coverage {100 * lag_c / max(lag_n, 1):.1f} % of {lag_n} lags "
                 f"(target 90-98 %)")
    if case.name == "mimo":
        lines.append(f"  N_p inside a dead time: {inside_any} pair-records (target 0)")
    worst = max(((abs(q["z"]), r["seed"], q) for r in ok for q in r["pairs"]
                 if q["z"] is not None), key=lambda w: w[0], default=None)
    if worst is not None:
        _, seed, q = worst
        lines.append(f"  largest |z|: {q['z']:+.1f} (seed {seed}, {q['output']}<-{q['input']} "
                     f"{q['gain']:.4g} ± {q['gain_std']:.2g}, N_p {q['n_p']})")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Run the chosen cases and seeds, print each record's line and the tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES),
                    help=f"comma list out of {', '.join(CASES)}")
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--first", type=int, default=7000)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    names = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        ap.error(f"--cases {unknown} not known; allowed: {', '.join(CASES)}")
    rows: dict[str, list[dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            rows[name] = []
            for k in range(args.seeds):
                res = run_seed(CASES[name], args.first + k, Path(tmp) / f"{name}{k}")
                rows[name].append(res)
                if "error" in res:
                    print(f"{name} seed {res['seed']}: {res['error']}", file=sys.stderr)
                    continue
                txt = ", ".join(
                    f"{q['output']}<-{q['input']} "
                    + (f"{q['gain']:.3g}±{q['gain_std']:.2g}" if q["gain"] is not None
                       else q["settled"]) + f" N_p {q['n_p']} r {q['ratio']:.2f}"
                    for q in res["pairs"])
                print(f"{name} seed {res['seed']}: {res['seconds']:.1f} s, dt "
                      f"{res['dt_s']:g}, {res['method']}: {txt}", flush=True)
    for name in names:
        print("\n".join(summarise(CASES[name], rows[name])))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
