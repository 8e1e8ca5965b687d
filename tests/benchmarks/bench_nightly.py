"""Benchmark: ``plantdyn nightly`` over a backlog of small exports — peak memory and
threads side by side with the concurrency bound.

Run::

    .venv/bin/python -m tests.benchmarks.bench_nightly                    # 100 files
    .venv/bin/python -m tests.benchmarks.bench_nightly --files 20 --bounds 1 2 100

For each bound (``nightly.max_parallel``; ``default`` leaves the key out, so the bound
comes from the cores and the free memory; 100 with 100 files is what the nightly did
before it had a bound: every file at once) a fresh storage root is processed by
``plantdyn nightly JOB --no-prefect`` in its own subprocess.  The subprocess's
``/proc/<pid>/status`` is read every 0.1 s: the peak resident memory (``VmHWM``) and the
largest thread count seen.  Also printed: the most files processed at one instant (from
the start and end times in the per-file status lines), the wall time and the time to
the first finished file.  The exports are the test plant (``tests.conftest``), 15 min at
1 s each (≈ 60 kB), generated once under ``--cache-dir``.

Performance claims live here, printed from one run — never in a timed unit test.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from tests.conftest import INPUT_TAG, OUTPUT_TAG, plant_signals

LINE = re.compile(r"^\[nightly\] (?P<status>[a-z_]+): \S+.*?\[(?P<start>\S+) to (?P<end>\S+),")


def make_backlog(folder: Path, n_files: int, hours: float) -> Path:
    """``n_files`` exports of the test plant, one day apart, under ``folder/drop``."""
    from pipeline.adapters.historian_writer import write_long_csv

    drop = folder / "drop"
    have = sorted(drop.glob("export_*.csv")) if drop.is_dir() else []
    if len(have) != n_files:
        shutil.rmtree(drop, ignore_errors=True)
        drop.mkdir(parents=True)
        for k in range(n_files):
            sig = plant_signals(seed=k + 1, hours=hours)
            write_long_csv(drop / f"export_{k:03d}.csv", sig["time"] + np.timedelta64(k, "D"),
                           {INPUT_TAG: sig["u"], OUTPUT_TAG: sig["y"]})
    return drop


def write_bench_job(folder: Path, bound: str) -> Path:
    """A job over ``../drop/*.csv`` with ``nightly.max_parallel: bound`` (or none)."""
    folder.mkdir(parents=True, exist_ok=True)
    data = {"job": "plant", "source": {"path": "../drop/*.csv", "timezone": "UTC"},
            "signals": {"inputs": {"u": {"tag": INPUT_TAG}},
                        "outputs": {"y": {"tag": OUTPUT_TAG}}},
            "storage": "storage", "rerun": {"enabled": False}, "search": {"n_p": 40},
            "nightly": {"settle_s": 0}}
    if bound != "default":
        data["nightly"]["max_parallel"] = int(bound)
    job = folder / "job.yaml"
    job.write_text(yaml.safe_dump(data, sort_keys=False))
    return job


def _status(pid: int) -> dict[str, int]:
    out = {}
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key in ("VmHWM", "VmRSS", "Threads"):
                    out[key] = int(value.split()[0])
    except (OSError, ValueError):
        pass
    return out


def peak_overlap(lines: list[str]) -> int:
    """Most files in progress at one instant, from the status lines' start/end times."""
    events = []
    for m in filter(None, map(LINE.match, lines)):
        for key, step in (("start", 1), ("end", -1)):
            events.append((np.datetime64(m[key].removesuffix("Z"), "ms"), step))
    now = peak = 0
    for _, step in sorted(events):
        now += step
        peak = max(peak, now)
    return peak


def run_one(job: Path) -> dict:
    """``plantdyn nightly JOB --no-prefect`` with its memory and threads sampled."""
    shutil.rmtree(job.parent / "storage", ignore_errors=True)
    cmd = [sys.executable, "-m", "flows.cli", "nightly", str(job), "--no-prefect"]
    t0 = time.perf_counter()
    first = None
    hwm_kb = threads = 0
    with subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True) as proc:
        import threading

        lines: list[str] = []

        def read() -> None:
            nonlocal first
            for line in proc.stderr:
                lines.append(line.rstrip("\n"))
                if first is None and line.startswith("[nightly] ok:"):
                    first = time.perf_counter() - t0

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        while proc.poll() is None:
            st = _status(proc.pid)
            hwm_kb = max(hwm_kb, st.get("VmHWM", 0))
            threads = max(threads, st.get("Threads", 0))
            time.sleep(0.1)
        reader.join()
    wall = time.perf_counter() - t0
    header = next((ln for ln in lines if "at a time" in ln), "")
    bound = re.search(r"at most (\d+) at a time", header)
    n_ok = sum(ln.startswith("[nightly] ok:") for ln in lines)
    return {"code": proc.returncode, "bound": int(bound[1]) if bound else None,
            "peak_rss_mib": hwm_kb / 1024, "threads": threads, "overlap": peak_overlap(lines),
            "wall_s": wall, "first_s": first, "ok": n_ok, "tail": lines[-3:]}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one row per bound (module notes)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--files", type=int, default=100)
    p.add_argument("--hours", type=float, default=0.25, help="length of each export")
    p.add_argument("--bounds", nargs="+", default=["1", "2", "4", "default", "100"],
                   help="nightly.max_parallel values ('default': the key left out)")
    p.add_argument("--cache-dir", default="/tmp/plantdyn_bench_nightly")
    args = p.parse_args(argv)
    root = Path(args.cache_dir)
    make_backlog(root, args.files, args.hours)
    print(f"{args.files} exports of {args.hours:g} h at 1 s; plantdyn nightly --no-prefect")
    print(f"{'max_parallel':>12} {'bound':>5} {'at once':>7} {'peak RSS MiB':>12} "
          f"{'threads':>7} {'first s':>7} {'wall s':>7} {'ok':>4}")
    for b in args.bounds:
        r = run_one(write_bench_job(root / f"bound_{b}", b))
        first = f"{r['first_s']:.1f}" if r["first_s"] is not None else "-"
        print(f"{b:>12} {r['bound'] or '-':>5} {r['overlap']:>7} {r['peak_rss_mib']:>12.0f} "
              f"{r['threads']:>7} {first:>7} {r['wall_s']:>7.1f} {r['ok']:>4}", flush=True)
        if r["code"] != 0:
            print(f"  exit {r['code']}: {' | '.join(r['tail'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
