"""Benchmark: historian long-CSV ingestion vs a bare ``polars.read_csv``, and a month
of 1 Hz data through ingestion and ``to_grid``.

Run::

    .venv/bin/python -m tests.benchmarks.bench_ingest            # both parts
    .venv/bin/python -m tests.benchmarks.bench_ingest --days 3 --no-month
    .venv/bin/python -m tests.benchmarks.bench_ingest --no-month --year   # ~35 GB disk, ~25 min

Part 1 — a generated PI-style long CSV (20 tags x 1 Hz x ``--days`` days, ISO UTC
timestamps, status column, a few text states): best-of-``--repeat`` wall time of
``polars.read_csv(path)`` and of ``read_recording(path)``, interleaved, and their ratio
(target <= 1.5).

Part 2 — a month (20 tags x 1 Hz x 30 days ≈ 52 M rows, ≈ 2.3 GB) generated once, tag
by tag, under ``--cache-dir`` (default ``/tmp/plantdyn_bench``). Each stage runs in its
own subprocess so its peak resident memory (``resource.getrusage(...).ru_maxrss``, which
also counts polars' Rust allocations that ``tracemalloc`` cannot see) is its own:
bare ``polars.read_csv``; ``read_recording``; ``read_recording`` + ``to_grid`` at 1 s.

Part 3 (``--year``) — a year (20 tags x 1 Hz x 365 days = 631 M rows, ≈ 32 GB) generated
once under ``--cache-dir`` (delete it afterwards; never commit it). A bare
``polars.read_csv`` of it cannot fit in 24 GiB (the month already takes 5 GiB), so the
bare reference is polars' own streaming reader: ``scan_csv(...).collect_batches()`` parsing
time and value and dropping each batch. Then ``read_recording`` + ``to_grid``, time and
peak RSS, in its own subprocess.

Part 4 (``--job``, ``--job-days 30``) — the whole job end to end: a 40-tag plant export
(4 step inputs, 8 outputs that are first-order lags of them, 28 other tags; 1 Hz,
``--job-days`` days, ≈ 5.2 GB for 30 days) generated once under ``--cache-dir``, and
``plantdyn run`` (``--no-prefect``; ``--prefect`` for the default path) on a job reading 12
of the 40 tags at T = 1 s, in a ``nice`` subprocess: peak resident memory of the process
tree (target ≤ 3 GiB including report.html and recording.rrd), the result files' sizes
(recording ≤ 200 MB), every stage's done line and time, and the time outside every stage::

    .venv/bin/python -m tests.benchmarks.bench_ingest --no-ratio --no-month --job --job-days 7
    .venv/bin/python -m tests.benchmarks.bench_ingest --no-ratio --no-month --job

Performance claims live here, printed from one run — never in a timed unit test.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import polars as pl

N_TAGS = 20
STATE_EVERY = 50_000  # one "Bad Input" text state per tag every ~14 h of 1 Hz data


def generate_long_csv(path: Path, *, days: float, n_tags: int = N_TAGS, seed: int = 0) -> Path:
    """Write a tag-grouped PI-style long CSV at 1 Hz, one tag at a time (bounded memory).

    Columns ``tag,timestamp,value,status``; timestamps ISO 8601 with ``Z``; values a
    random walk with 4 decimals; every ``STATE_EVERY``-th sample is the text state
    ``Bad Input`` with status ``Bad``.
    """
    n = int(days * 86_400)
    start = np.datetime64("2024-01-01T00:00:00", "ms")
    offsets = np.arange(n).astype("timedelta64[s]").astype("timedelta64[ms]")
    stamps = pl.Series("timestamp", start + offsets).dt.strftime("%Y-%m-%dT%H:%M:%SZ")
    rng = np.random.default_rng(seed)
    tmp = path.with_suffix(".partial")
    with tmp.open("wb") as f:
        f.write(b"tag,timestamp,value,status\n")
        for k in range(n_tags):
            walk = np.round(np.cumsum(rng.normal(0, 0.1, n)) + 50.0, 4)
            value = pl.Series("value", walk).cast(pl.String)
            is_state = pl.Series((np.arange(n) % STATE_EVERY) == (k * 997) % STATE_EVERY)
            frame = pl.DataFrame(
                {
                    "tag": pl.repeat(f"PLANT.TAG{k:03d}.PV", n, dtype=pl.String, eager=True),
                    "timestamp": stamps,
                    "value": pl.select(
                        pl.when(pl.lit(is_state)).then(pl.lit("Bad Input")).otherwise(pl.lit(value))
                    ).to_series(),
                    "status": pl.select(
                        pl.when(pl.lit(is_state)).then(pl.lit("Bad")).otherwise(pl.lit("Good"))
                    ).to_series(),
                }
            )
            frame.write_csv(f, include_header=False)
    tmp.replace(path)
    return path


PLANT_TAGS = 40
PLANT_INPUTS = 4
PLANT_OUTPUTS = 8


def _plant_input(n: int, k: int, seed: int) -> np.ndarray:
    """Input tag ``k``: random steps (holds of ~2 min on average) plus a little noise."""
    rng = np.random.default_rng([seed, k])
    holds = rng.exponential(120.0, n // 60 + 10).astype(int) + 1
    levels = rng.normal(50.0, 5.0, holds.size)
    u = np.repeat(levels, holds)[:n]
    return u + rng.normal(0.0, 0.02, n)


def _plant_value(n: int, k: int, seed: int) -> np.ndarray:
    """The 1 Hz values of tag ``k`` of the plant export (inputs, outputs, others)."""
    from scipy.signal import lfilter

    if k < PLANT_INPUTS:
        return _plant_input(n, k, seed)
    rng = np.random.default_rng([seed, k])
    if k < PLANT_INPUTS + PLANT_OUTPUTS:  # first-order lags (2-6 s) of every input
        y = np.full(n, 100.0)
        for i in range(PLANT_INPUTS):
            u = _plant_input(n, i, seed) - 50.0
            gain, tau_s, delay = rng.uniform(-2, 2), rng.uniform(2, 6), int(rng.integers(0, 3))
            a = np.exp(-1.0 / tau_s)
            y += gain * lfilter([0.0] * delay + [1 - a], [1, -a], u)
        return y + rng.normal(0.0, 0.05, n)
    return np.cumsum(rng.normal(0, 0.1, n)) + 50.0  # tags the job does not read


def generate_plant_csv(path: Path, *, days: float, seed: int = 0) -> Path:
    """Write a 40-tag PI-style long CSV at 1 Hz of a plant (4 step inputs, 8 outputs that
    are first-order lags of them, 28 random walks), one tag at a time (bounded memory).

    Columns and text states as :func:`generate_long_csv`.
    """
    n = int(days * 86_400)
    start = np.datetime64("2024-01-01T00:00:00", "ms")
    offsets = np.arange(n).astype("timedelta64[s]").astype("timedelta64[ms]")
    stamps = pl.Series("timestamp", start + offsets).dt.strftime("%Y-%m-%dT%H:%M:%SZ")
    tmp = path.with_suffix(".partial")
    with tmp.open("wb") as f:
        f.write(b"tag,timestamp,value,status\n")
        for k in range(PLANT_TAGS):
            value = pl.Series("value", np.round(_plant_value(n, k, seed), 4)).cast(pl.String)
            is_state = pl.Series((np.arange(n) % STATE_EVERY) == (k * 997) % STATE_EVERY)
            pl.DataFrame({
                "tag": pl.repeat(f"PLANT.TAG{k:03d}.PV", n, dtype=pl.String, eager=True),
                "timestamp": stamps,
                "value": pl.select(pl.when(pl.lit(is_state)).then(pl.lit("Bad Input"))
                                   .otherwise(pl.lit(value))).to_series(),
                "status": pl.select(pl.when(pl.lit(is_state)).then(pl.lit("Bad"))
                                    .otherwise(pl.lit("Good"))).to_series(),
            }).write_csv(f, include_header=False)
    tmp.replace(path)
    return path


def write_plant_job(folder: Path, csv: Path) -> Path:
    """The job YAML of the end-to-end part: 4 inputs and 8 outputs, 12 of the export's 40
    tags, at T = 1 s (every one of the record's samples is stored, drawn and recorded: the
    worst case for writing results); ``search.n_p_max`` 40 (the plant settles in < 30 s)."""
    folder.mkdir(parents=True, exist_ok=True)
    ins = "\n".join(f"    u{k}: {{tag: PLANT.TAG{k:03d}.PV, unit: '%'}}" for k in range(PLANT_INPUTS))
    outs = "\n".join(f"    y{j}: {{tag: PLANT.TAG{PLANT_INPUTS + j:03d}.PV, unit: bar}}"
                     for j in range(PLANT_OUTPUTS))
    job = folder / "bench_plant.yaml"
    job.write_text(f"""job: bench_plant
source:
  path: ../{csv.name}
  timezone: UTC
signals:
  inputs:
{ins}
  outputs:
{outs}
storage: storage
sampling:
  dt_s: 1
search:
  n_p_max: 40
""")
    return job


def run_job_measured(job: Path, *, prefect: bool = False, log: Path | None = None) -> dict:
    """``plantdyn run JOB`` in a subprocess (``nice``), its stderr echoed line by line;
    returns wall time, the peak resident memory of the process tree (``wait4``'s
    ``ru_maxrss``: the largest of the process and the children it waited for), the run
    directory and the stage lines."""
    cmd = ["nice", sys.executable, "-m", "flows.cli", "run", str(job)]
    if not prefect:
        cmd.append("--no-prefect")
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PLANTDYN_PROGRESS": "0", "PYTHONPATH": str(root)}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    lines = []
    with (log or Path(os.devnull)).open("w") as fh:
        for line in proc.stderr:
            lines.append(line.rstrip("\n"))
            fh.write(line)
            print(f"  | {line}", end="", flush=True)
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise SystemExit(f"plantdyn run exited {code}")
    return {"wall_s": wall, "peak_rss_gib": usage.ru_maxrss / 2**20,
            "run_dir": Path(out.strip().splitlines()[-1]), "lines": lines}


def stage_lines(lines: list[str]) -> tuple[list[str], dict[str, float]]:
    """Stages that printed a ``start`` line, in order, and the seconds of their ``done in``
    lines (a stage missing from the dict printed none)."""
    import re

    started, done = [], {}
    for line in lines:
        m = re.match(r"\[\s*[\d.]+ s\] ([\w/.-]+): (start|done in ([\d.]+) s)", line)
        if m and m.group(2) == "start":
            started.append(m.group(1))
        elif m:
            done[m.group(1)] = float(m.group(3))
    return started, done


def bench_job(cache_dir: Path, days: float, *, prefect: bool = False) -> dict:
    """Part 4: the whole job (ingest .. report.html and recording.rrd) on ``days`` of the
    40-tag plant export, reading 12 tags; peak memory, sizes and stage times."""
    csv = cache_dir / f"plant_{PLANT_TAGS}tags_{days:g}d_1Hz.csv"
    if not csv.exists():
        t0 = time.perf_counter()
        generate_plant_csv(csv, days=days)
        print(f"[job] generated {csv} in {time.perf_counter() - t0:.0f} s", flush=True)
    job = write_plant_job(cache_dir / f"job_{days:g}d", csv)
    print(f"[job] {csv.name}: {csv.stat().st_size / 1e9:.2f} GB, {PLANT_TAGS} tags x "
          f"{int(days * 86400):,} s; plantdyn run {job} ({'Prefect' if prefect else '--no-prefect'})",
          flush=True)
    r = run_job_measured(job, prefect=prefect, log=job.parent / "run.log")
    run_dir = r["run_dir"]
    sizes = {f.name: f.stat().st_size / 1e6 for f in sorted(run_dir.iterdir()) if f.is_file()}
    started, done = stage_lines(r["lines"])
    undone = [k for k in started if k not in done]
    top = sum(v for k, v in done.items() if "/" not in k)
    print(f"[job] run dir {run_dir}")
    print("[job] files: " + ", ".join(f"{k} {v:.1f} MB" for k, v in sizes.items()))
    print(f"[job] wall {r['wall_s']:.0f} s; peak RSS {r['peak_rss_gib']:.2f} GiB (target <= 3); "
          f"recording.rrd {sizes.get('recording.rrd', 0):.1f} MB (target <= 200); "
          f"report.html {sizes.get('report.html', 0):.1f} MB")
    print("[job] stage times: " + ", ".join(f"{k} {v:.1f} s" for k, v in done.items()))
    print(f"[job] {len(started)} stages started, without a done line: {undone or 'none'}; "
          f"top-level stages {top:.0f} s of {r['wall_s']:.0f} s wall, outside every stage "
          f"{r['wall_s'] - top:.0f} s (interpreter and imports, config checks)")
    return {"peak_rss_gib": r["peak_rss_gib"], "wall_s": r["wall_s"], "sizes_mb": sizes,
            "undone": undone}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _stage(stage: str, path: str) -> dict[str, float]:
    """One measured stage (run inside a fresh subprocess)."""
    from pipeline.adapters.grid import to_grid
    from pipeline.adapters.ingest import read_recording

    base = _peak_rss_mb()
    t0 = time.perf_counter()
    out: dict[str, float] = {}
    if stage == "bare":
        df = pl.read_csv(path)
        out["rows"] = len(df)
    elif stage == "scan":
        # polars' streaming reader alone: parse every batch (time, value, tag) and drop it
        lazy = pl.scan_csv(path, schema={"tag": pl.Categorical, "timestamp": pl.String,
                                         "value": pl.String, "status": pl.String})
        lazy = lazy.with_columns(
            pl.col("timestamp").str.strptime(pl.Datetime("us", "UTC"), "%Y-%m-%dT%H:%M:%SZ"),
            pl.col("value").cast(pl.Float64, strict=False))
        rows = 0
        for batch in lazy.collect_batches(chunk_size=1_000_000):
            rows += len(batch)
        out["rows"] = rows
    elif stage in ("ingest", "ingest+grid"):
        table, report = read_recording(path)
        out["rows"] = len(table)
        out["bad"] = sum(s.bad for s in report.signals)
        out["ingest_s"] = time.perf_counter() - t0
        if stage == "ingest+grid":
            t1 = time.perf_counter()
            grid = to_grid(table, dt_s=1.0)
            out["grid_s"] = time.perf_counter() - t1
            out["grid_points"] = float(grid.values.size)
            out["grid_masked"] = float((~grid.good).sum())
    else:
        raise SystemExit(f"unknown stage {stage!r}")
    out["seconds"] = time.perf_counter() - t0
    out["peak_rss_mb"] = _peak_rss_mb()
    out["rss_before_mb"] = base
    return out


def _run_stage(stage: str, path: Path) -> dict[str, float]:
    cmd = [sys.executable, "-m", "tests.benchmarks.bench_ingest", "--stage", stage, "--path", str(path)]
    root = Path(__file__).resolve().parents[2]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=root)
    return json.loads(res.stdout.strip().splitlines()[-1])


def bench_ratio(path: Path, repeat: int) -> None:
    """Part 1: bare read_csv vs read_recording on the same file, best of ``repeat``."""
    from pipeline.adapters.ingest import read_recording

    pl.read_csv(path)  # warm the page cache and polars
    read_recording(path)
    bare, ours = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        pl.read_csv(path)
        bare.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        table, _ = read_recording(path)
        ours.append(time.perf_counter() - t0)
    size_mb = path.stat().st_size / 1e6
    print(f"[ratio] {path.name}: {size_mb:.0f} MB, {len(table):,} rows")
    for label, times in (("polars.read_csv", bare), ("read_recording", ours)):
        print(
            f"[ratio] {label:16s} best {min(times):.3f} s ({size_mb / min(times):.0f} MB/s), "
            f"median {float(np.median(times)):.3f} s, all {[round(x, 3) for x in times]}"
        )
    print(
        f"[ratio] read_recording / polars.read_csv = {min(ours) / min(bare):.2f} (best of "
        f"{repeat}), {float(np.median(ours)) / float(np.median(bare)):.2f} (medians); target <= 1.5"
    )


def bench_month(cache_dir: Path, days: float) -> None:
    """Part 2: a month through ingestion and to_grid, each stage in its own process."""
    path = cache_dir / f"month_{N_TAGS}tags_{days:g}d_1Hz.csv"
    if not path.exists():
        t0 = time.perf_counter()
        generate_long_csv(path, days=days)
        print(f"[month] generated {path} in {time.perf_counter() - t0:.1f} s")
    size_gb = path.stat().st_size / 1e9
    print(f"[month] {path.name}: {size_gb:.2f} GB, {N_TAGS} tags x {int(days * 86400):,} s")
    results = {}
    for stage in ("bare", "ingest", "ingest+grid"):
        results[stage] = r = _run_stage(stage, path)
        extra = ""
        if stage == "ingest+grid":
            extra = (
                f", ingest {r['ingest_s']:.1f} s + to_grid {r['grid_s']:.1f} s, "
                f"grid {int(r['grid_points']):,} points, {int(r['grid_masked']):,} masked"
            )
        print(
            f"[month] {stage:12s} {r['seconds']:6.1f} s  peak RSS {r['peak_rss_mb'] / 1024:5.2f} GiB  "
            f"rows {int(r['rows']):,}{extra}"
        )
    print(
        f"[month] read_recording / polars.read_csv = "
        f"{results['ingest']['seconds'] / results['bare']['seconds']:.2f}; "
        f"peak memory ratio {results['ingest']['peak_rss_mb'] / results['bare']['peak_rss_mb']:.2f}"
    )


def bench_year(cache_dir: Path, days: float = 365.0) -> None:
    """Part 3: a year through ingestion and to_grid next to polars' bare streaming scan."""
    path = cache_dir / f"year_{N_TAGS}tags_{days:g}d_1Hz.csv"
    if not path.exists():
        t0 = time.perf_counter()
        print(f"[year] generating {path} (once) ...", flush=True)
        generate_long_csv(path, days=days)
        print(f"[year] generated in {time.perf_counter() - t0:.0f} s")
    size_gb = path.stat().st_size / 1e9
    print(f"[year] {path.name}: {size_gb:.1f} GB, {N_TAGS} tags x {int(days * 86400):,} s", flush=True)
    results = {}
    for stage in ("scan", "ingest+grid"):
        results[stage] = r = _run_stage(stage, path)
        extra = ""
        if stage == "ingest+grid":
            extra = (f", ingest {r['ingest_s']:.0f} s + to_grid {r['grid_s']:.0f} s, "
                     f"grid {int(r['grid_points']):,} points")
        print(f"[year] {stage:12s} {r['seconds']:6.0f} s  peak RSS {r['peak_rss_mb'] / 1024:5.2f} GiB  "
              f"rows {int(r['rows']):,}{extra}", flush=True)
    grid_gib = results["ingest+grid"]["grid_points"] * 9 / 2**30  # float64 value + bool mask
    print(f"[year] read_recording+to_grid / bare streaming scan = "
          f"{results['ingest+grid']['seconds'] / results['scan']['seconds']:.2f} (time); "
          f"peak {results['ingest+grid']['peak_rss_mb'] / 1024:.1f} GiB = "
          f"{results['ingest+grid']['peak_rss_mb'] / 1024 / grid_gib:.1f} x the gridded data "
          f"({grid_gib:.1f} GiB); machine limit 24 GiB")


def main(argv: list[str] | None = None) -> None:
    """Command-line entry point (see module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=float, default=3.0, help="days of 1 Hz data (ratio part)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--month-days", type=float, default=30.0)
    parser.add_argument("--no-month", action="store_true", help="skip the month part")
    parser.add_argument("--year", action="store_true", help="add the year part (~35 GB disk)")
    parser.add_argument("--job", action="store_true",
                        help="add the end-to-end part: plantdyn run on the 40-tag plant month")
    parser.add_argument("--job-days", type=float, default=30.0)
    parser.add_argument("--prefect", action="store_true", help="end-to-end part through Prefect")
    parser.add_argument("--no-ratio", action="store_true", help="skip the ratio part")
    default_cache = Path(os.environ.get("TMPDIR", "/tmp")) / "plantdyn_bench"
    parser.add_argument("--cache-dir", type=Path, default=default_cache)
    parser.add_argument("--stage", help=argparse.SUPPRESS)
    parser.add_argument("--path", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.stage:
        print(json.dumps(_stage(args.stage, args.path)))
        return
    args.cache_dir.mkdir(parents=True, exist_ok=True)
    if not args.no_ratio:
        ratio_path = args.cache_dir / f"long_{N_TAGS}tags_{args.days:g}d_1Hz.csv"
        if not ratio_path.exists():
            generate_long_csv(ratio_path, days=args.days)
        bench_ratio(ratio_path, args.repeat)
    if not args.no_month:
        bench_month(args.cache_dir, args.month_days)
    if args.year:
        bench_year(args.cache_dir)
    if args.job:
        bench_job(args.cache_dir, args.job_days, prefect=args.prefect)


if __name__ == "__main__":
    main()
