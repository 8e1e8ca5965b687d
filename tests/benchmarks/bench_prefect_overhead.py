"""Per-command overhead of Prefect (issue 33, build 1).

The same small job (the test plant: one input, one output, a 1-hour 1 Hz export, Rerun
off) run through the ``plantdyn`` CLI as a user runs it, wall-clock seconds per command:

* ``--no-prefect``: the pipeline called directly (the reference);
* ``cold server``: ``plantdyn run`` on a fresh storage root, so the command starts the
  project's Prefect server (``flows/server.py``; a new database) before the flow;
* ``warm server``: ``plantdyn run`` again on that storage root, reusing the running server;
* ``embedded (before)``: the estimate flow with no API configured, so Prefect starts its
  embedded server inside the command -- what every command paid before the project server.

Printed: median, min and max seconds per mode, the ratio to ``--no-prefect`` and the
overhead in seconds; and the server's own start-up as the cold commands reported it.
Every server the benchmark starts is stopped at the end.

    .venv/bin/python -m tests.benchmarks.bench_prefect_overhead [--repeat 3] [--cold 2]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
READY = re.compile(r"Prefect server ready at \S+ \(pid \d+\) after ([\d.]+) s")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env.update(PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1",
               PYTHONPATH=str(ROOT), **extra)
    return env


def _timed(args: list[str], env: dict[str, str]) -> tuple[float, str]:
    """Seconds of one command (exits non-zero: the benchmark stops with its stderr)."""
    t0 = time.perf_counter()
    r = subprocess.run(args, env=env, capture_output=True, text=True, timeout=900,
                       check=False)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"{' '.join(args)} exited {r.returncode}:\n{r.stderr[-3000:]}")
    return dt, r.stderr


def _job(folder: Path) -> Path:
    from tests.conftest import write_job

    return write_job(folder, source="../drop/*.csv", storage="storage")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table (module docstring).

    Parameters
    ----------
    argv : list of str, optional
        ``--repeat`` (commands per warm / no-Prefect / embedded mode), ``--cold`` (fresh
        storage roots), ``--hours`` (export length).
    """
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--cold", type=int, default=2)
    p.add_argument("--hours", type=float, default=1.0)
    args = p.parse_args(argv)
    from flows.server import stop_server
    from tests.conftest import write_plant_csv

    cli = [sys.executable, "-m", "flows.cli", "run"]
    times: dict[str, list[float]] = {}
    starts: list[float] = []
    homes: list[Path] = []
    with tempfile.TemporaryDirectory(prefix="bench_prefect_") as tmp:
        work = Path(tmp)
        write_plant_csv(work / "drop" / "export.csv", seed=1, hours=args.hours)
        env = _env()
        try:
            job = _job(work / "direct")
            times["--no-prefect"] = [_timed([*cli, str(job), "--no-prefect"], env)[0]
                                     for _ in range(args.repeat)]
            for k in range(args.cold):
                job = _job(work / f"cold{k}")
                homes.append(job.parent / "storage" / ".prefect")
                dt, err = _timed([*cli, str(job)], env)
                times.setdefault("cold server", []).append(dt)
                starts += [float(m) for m in READY.findall(err)]
            times["warm server"] = [_timed([*cli, str(job)], env)[0]
                                    for _ in range(args.repeat)]
            emb = _job(work / "embedded")
            code = ("import sys; from flows.common import prefect_env_defaults; "
                    "prefect_env_defaults(); from flows.estimate import run_estimate; "
                    "print(run_estimate(sys.argv[1]).run_dir)")
            times["embedded (before)"] = [
                _timed([sys.executable, "-c", code, str(emb)],
                       _env(PREFECT_HOME=str(work / "embedded" / "home")))[0]
                for _ in range(args.repeat)]
        finally:
            for home in homes:
                stop_server(home, note=lambda _msg: None)
    _print(times, starts, args)
    return 0


def _print(times: dict[str, list[float]], starts: list[float], args) -> None:
    ref = statistics.median(times["--no-prefect"])
    load = os.getloadavg()[0]
    print(f"plantdyn run, {args.hours:g} h export at 1 Hz, 1x1 plant; {os.cpu_count()} cores, "
          f"load average {load:.1f} at the end")
    print(f"{'mode':<20}{'runs':>5}{'median s':>10}{'min-max s':>14}{'x no-prefect':>14}"
          f"{'overhead s':>12}")
    for mode, ts in times.items():
        med = statistics.median(ts)
        print(f"{mode:<20}{len(ts):>5}{med:>10.1f}{f'{min(ts):.1f}-{max(ts):.1f}':>14}"
              f"{med / ref:>14.2f}{med - ref:>12.1f}")
    if starts:
        print(f"project server start-up inside the cold commands: "
              f"{', '.join(f'{s:.1f}' for s in starts)} s (fresh database)")


if __name__ == "__main__":
    sys.exit(main())
