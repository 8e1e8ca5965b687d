"""A slow plant on a short record, with default settings (issue 32, must-show 3).

Three inputs, one output, time constants 8 / 20 / 40 min with dead times 2 / 5 / 3 min,
gains 1.5 / -0.8 / 2.0; 1.5 days at 1 min (2,160 samples); inputs: held random moves
(a new level every 20-90 min, as operators and setpoints move a plant) plus a little
noise; the output adds an AR(1) 0.98 disturbance and white sensor noise.  Simulated
here with scipy only (exact first-order-hold discretisation at 6 s, sampled every
minute), written as a long historian CSV and estimated with ``plantdyn run --no-prefect``
and a job that sets nothing but the signals.

Per seed and pair: the reported gain ± σ (``checks.json``), or the verdict when none is
reported.  Printed: median relative gain error, ±2σ coverage of the gains reported, how
many pairs report no gain (moving) and the run time.  Targets: median error ≤ 10 %,
coverage 90–98 %.

    .venv/bin/python -m tests.benchmarks.bench_slow_plant --seeds 40 [--first 5000]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.signal as ss
import yaml

GAINS = (1.5, -0.8, 2.0)
TAUS_MIN = (8.0, 20.0, 40.0)
DEAD_MIN = (2.0, 5.0, 3.0)
N = 2160
ROOT = Path(__file__).resolve().parents[2]


def simulate(seed: int, fine_s: float = 6.0):
    """Inputs and output at 1-min samples (module docstring)."""
    rng = np.random.default_rng(seed)
    r = int(round(60 / fine_s))
    us, y = [], np.zeros(N)
    for k, tau, dead in zip(GAINS, TAUS_MIN, DEAD_MIN):
        u = np.zeros(N + 1)
        t = 0
        while t < N + 1:
            hold = int(rng.integers(20, 91))
            u[t:t + hold] = rng.normal(0.0, 1.0)
            t += hold
        u += 0.05 * rng.standard_normal(N + 1)
        fine = np.interp(np.arange(N * r + 1) * fine_s / 60, np.arange(N + 1), u)
        b, a, _ = ss.cont2discrete(([k], [tau * 60, 1.0]), fine_s, method="foh")
        yf = ss.lfilter(np.ravel(b), np.ravel(a), fine)
        shift = int(round(dead * 60 / fine_s))
        yf = np.r_[np.zeros(shift), yf[: yf.size - shift]]
        y += yf[::r][:N]
        us.append(u[:N])
    y += ss.lfilter([0.05], [1, -0.98], rng.standard_normal(N)) + 0.02 * rng.standard_normal(N)
    return us, y


def run_seed(seed: int, folder: Path) -> dict:
    from pipeline.adapters.historian_writer import write_long_csv

    us, y = simulate(seed)
    t = np.datetime64("2026-01-01T00:00:00", "us") + \
        (np.arange(N) * 60_000_000).astype("timedelta64[us]")
    (folder / "drop").mkdir(parents=True, exist_ok=True)
    write_long_csv(folder / "drop" / "plant.csv", t,
                   {**{f"U{j}.PV": 50 + u for j, u in enumerate(us)}, "Y.PV": 20 + y})
    job = {"job": "slow", "source": {"path": "drop/*.csv", "timezone": "UTC"},
           "signals": {"inputs": {f"u{j}": {"tag": f"U{j}.PV"} for j in range(3)},
                       "outputs": {"y": {"tag": "Y.PV"}}},
           "storage": "storage", "rerun": {"enabled": False}}
    (folder / "job.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    t0 = time.perf_counter()
    r = subprocess.run([str(ROOT / ".venv" / "bin" / "plantdyn"), "run", str(folder / "job.yaml"),
                        "--no-prefect", "--progress", "never"], capture_output=True, text=True,
                       env={**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"})
    sec = time.perf_counter() - t0
    if r.returncode != 0:
        return {"seed": seed, "error": r.stderr.strip().splitlines()[-1], "seconds": sec}
    run_dir = Path(r.stdout.strip().splitlines()[-1])
    checks = json.loads((run_dir / "checks.json").read_text())
    pairs = [{"input": p["input"], "gain": p["gain"], "gain_std": p["gain_std"],
              "n_p": p["n_p"], "settled": p["settled"]["verdict"],
              "extrapolated": p.get("gain_extrapolated")} for p in checks["pairs"]]
    return {"seed": seed, "pairs": pairs, "seconds": sec,
            "method": checks["estimation"]["method"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--first", type=int, default=5000)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.seeds):
            res = run_seed(args.first + k, Path(tmp) / f"s{k}")
            rows.append(res)
            if "error" in res:
                print(f"seed {res['seed']}: error {res['error']}", file=sys.stderr)
                continue
            txt = ", ".join(
                f"{p['input']} {p['gain']:.3g}±{p['gain_std']:.2g} (N_p {p['n_p']})"
                if p["gain"] is not None else f"{p['input']} {p['settled']} (N_p {p['n_p']})"
                for p in res["pairs"])
            print(f"seed {res['seed']}: {res['seconds']:.1f} s, {res['method']}: {txt}",
                  flush=True)
    errs, z, none = [], [], [0, 0, 0]
    for res in rows:
        for j, p in enumerate(res.get("pairs", [])):
            if p["gain"] is None:
                none[j] += 1
                continue
            errs.append(abs(p["gain"] - GAINS[j]) / abs(GAINS[j]))
            z.append((p["gain"] - GAINS[j]) / p["gain_std"])
    z = np.array(z)
    print(f"\n{len(rows)} records, {len(errs)} reported gains; pairs with no gain per "
          f"input {none}")
    if errs:
        print(f"median relative gain error {100 * np.median(errs):.1f} % (target <= 10 %)")
        print(f"+-2 sigma coverage {100 * np.mean(np.abs(z) <= 2):.1f} % (target 90-98 %), "
              f"RMS z {np.sqrt(np.mean(z**2)):.2f}")
    print(f"median run time {np.median([r['seconds'] for r in rows]):.1f} s")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
