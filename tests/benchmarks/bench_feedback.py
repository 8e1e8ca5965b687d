"""Feedback test on integrating outputs: open-loop false alarms, closed-loop detection
(issue 36, build 3 / must-show 3).

Open loop: levels that nothing controls (``tests/plants.open_level_record``: 1-2 inputs of
held random moves, each through a first-order lag and dead time into the level's rate,
plus white level-sensor noise alone or with an AR(1) on the level, a random walk or an
integrated AR(1)), 1,500-20,000 samples at 1 s.  Closed loops
(``tests/plants.pi_controlled_record``): a PI controller's output moving a level, and one
moving a self-regulating output, with setpoint moves and an unmeasured disturbance.
Everything is simulated with numpy/scipy here, written as a long historian CSV
(``pipeline.adapters.historian_writer.write_long_csv``) and estimated by
``plantdyn run --no-prefect`` with a job that sets only the signals (``integrating: true``
on the level), so the sample period is α_T's and the feedback test is the job's own
(``estimation.feedback: auto``).  Per pair: ``checks.json`` → ``pairs[].feedback``.
``--mode direct`` runs the job's own stages in-process up to the search, which runs the
test (``pipeline.jobs.recording.load_recording``, ``pipeline.jobs.estimation.prepare``,
``search_orders``; the same p-values, without the windows, the report and the store).

Printed: the open-loop false-alarm rate with pair counts (overall, per record length, per
disturbance), detection per loop kind.  Targets: false alarms <= 2 % over >= 200
open-loop pairs (the test's stated rate is 1 % per pair); detection >= 95 %.

    .venv/bin/python -m tests.benchmarks.bench_feedback --seeds 160 --closed 40 \\
        [--first 7000000] [--mode cli|direct] [--json out.json]
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
import yaml

from tests.plants import LEVEL_NOISES, open_level_record, pi_controlled_record

OPEN_LENGTHS = (1500, 3000, 6000, 12000, 20000)
CLOSED_LENGTHS = (3000, 6000, 12000, 20000)
CLOSED_SEED_OFFSET = {"pi_level": 10_000, "pi_self": 20_000}


def write_job(folder: Path, x: np.ndarray, y: np.ndarray, *, integrating: bool) -> Path:
    """``x`` (n, n_x) and ``y`` (n,) at 1 s as a long historian CSV, and a job that
    names the signals and nothing else; returns the job's path."""
    from pipeline.adapters.historian_writer import write_long_csv

    n = y.size
    t = np.datetime64("2026-01-01T00:00:00", "us") + \
        (np.arange(n) * 1_000_000).astype("timedelta64[us]")
    (folder / "drop").mkdir(parents=True, exist_ok=True)
    write_long_csv(folder / "drop" / "plant.csv", t,
                   {**{f"U{j}.PV": 50 + x[:, j] for j in range(x.shape[1])},
                    "Y.PV": 20 + y})
    job = {"job": "feedback", "source": {"path": "drop/*.csv", "timezone": "UTC"},
           "signals": {"inputs": {f"u{j}": {"tag": f"U{j}.PV"} for j in range(x.shape[1])},
                       "outputs": {"y": {"tag": "Y.PV", "integrating": integrating}}},
           "storage": "storage", "rerun": {"enabled": False}}
    path = folder / "job.yaml"
    path.write_text(yaml.safe_dump(job, sort_keys=False))
    return path


def feedback_cli(job: Path) -> dict:
    """``plantdyn run`` the job; per pair the feedback verdict from ``checks.json``."""
    exe = Path(sys.executable).parent / "plantdyn"
    r = subprocess.run([str(exe), "run", str(job), "--no-prefect", "--progress", "never"],
                       capture_output=True, text=True,
                       env={**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"})
    if r.returncode != 0:
        return {"error": (r.stderr.strip().splitlines() or ["?"])[-1]}
    run_dir = Path(r.stdout.strip().splitlines()[-1])
    checks = json.loads((run_dir / "checks.json").read_text())
    return {"pairs": [p["feedback"] for p in checks["pairs"]],
            "dt_s": checks["sampling"]["dt_s"] if "sampling" in checks else None,
            "form": checks["noise_model"]["y"]["form"]}


def feedback_direct(job: Path) -> dict:
    """The job's own stages in-process, up to the search (which runs the feedback test):
    load and prepare the record, then :func:`pipeline.jobs.estimation.search_orders`."""
    from pipeline.adapters.config import load_job
    from pipeline.jobs.estimation import load_recording, prepare, search_orders

    cfg = load_job(job)
    prep = prepare(cfg, load_recording(cfg))
    sr = search_orders(cfg, prep)
    return {"pairs": [None if f is None else f.to_dict() for f in sr.feedback[0]],
            "dt_s": prep.dt_s, "form": sr.noise_model[0].form}


def run_record(kind: str, index: int, first: int, folder: Path, mode: str) -> dict:
    """Simulate record ``index`` of ``kind`` (``open``, ``pi_level``, ``pi_self``), run
    the job on it, and return its pairs' feedback verdicts."""
    if kind == "open":
        seed = first + index
        n = OPEN_LENGTHS[index % len(OPEN_LENGTHS)]
        noise = LEVEL_NOISES[(index // len(OPEN_LENGTHS)) % len(LEVEL_NOISES)]
        x, y, info = open_level_record(n, noise, seed)
        integrating = True
    else:
        seed = first + CLOSED_SEED_OFFSET[kind] + index
        n = CLOSED_LENGTHS[index % len(CLOSED_LENGTHS)]
        noise = None
        integrating = kind == "pi_level"
        x, y, info = pi_controlled_record(n, integrating, seed)
    t0 = time.perf_counter()
    job = write_job(folder / f"{kind}{index}", x, y, integrating=integrating)
    res = (feedback_cli if mode == "cli" else feedback_direct)(job)
    return {"kind": kind, "seed": seed, "n": n, "disturbance": noise, "n_x": x.shape[1],
            "plant": info["plant"], "noise": info["noise"],
            "seconds": time.perf_counter() - t0, **res}


def _flags(row: dict) -> list[bool]:
    return [bool(p is not None and p["detected"]) for p in row.get("pairs", [])]


def _rate(rows: list[dict]) -> tuple[int, int]:
    flags = [f for r in rows for f in _flags(r)]
    return sum(flags), len(flags)


def _line(row: dict) -> str:
    if "error" in row:
        return f"{row['kind']} seed {row['seed']}: error {row['error']}"
    ps = ", ".join("untested" if p is None else
                   f"p {p['p_value']:.2g}{' FEEDBACK' if p['detected'] else ''}"
                   f" (dof {p.get('residual_dof')})" for p in row["pairs"])
    return (f"{row['kind']} seed {row['seed']} N {row['n']} {row['disturbance'] or ''} "
            f"T {row['dt_s']} s {row['form']}: {ps} [{row['seconds']:.1f} s]")


def summary(rows: list[dict]) -> list[str]:
    """The printed summary: false alarms and detection with their pair counts."""
    out = []
    opened = [r for r in rows if r["kind"] == "open"]
    errors = sum("error" in r for r in rows)
    if opened:
        a, n = _rate(opened)
        out.append(f"open-loop integrating pairs: false alarms {a}/{n} = "
                   f"{100 * a / max(n, 1):.1f} % (target <= 2 % over >= 200 pairs; stated 1 %)")
        for length in OPEN_LENGTHS:
            a, n = _rate([r for r in opened if r["n"] == length])
            out.append(f"  N = {length:>6}: {a}/{n}")
        for noise in LEVEL_NOISES:
            a, n = _rate([r for r in opened if r["disturbance"] == noise])
            out.append(f"  {noise:>8} disturbance: {a}/{n}")
    for kind in CLOSED_SEED_OFFSET:
        loops = [r for r in rows if r["kind"] == kind]
        if loops:
            d, n = _rate(loops)
            out.append(f"closed loops {kind}: feedback detected {d}/{n} = "
                       f"{100 * d / max(n, 1):.1f} % (target >= 95 %)")
    if errors:
        out.append(f"{errors} record(s) failed (see above)")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=160, help="open-loop records")
    ap.add_argument("--closed", type=int, default=40, help="closed loops of each kind")
    ap.add_argument("--first", type=int, default=7_000_000, help="first seed")
    ap.add_argument("--mode", choices=("cli", "direct"), default="cli")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    plan = [("open", k) for k in range(args.seeds)] + \
        [(kind, k) for k in range(args.closed) for kind in CLOSED_SEED_OFFSET]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind, k in plan:
            rows.append(run_record(kind, k, args.first, Path(tmp), args.mode))
            print(_line(rows[-1]), flush=True)
    print()
    print("\n".join(summary(rows)))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
