"""The whole discrepancy workflow on 1e5 samples (issue 4, "It must show" 4), one run.

Run:  .venv/bin/python -m tests.benchmarks.bench_discrepancy_workflow [--samples N]

Writes a historian export of the discrepancy demo plant (the boiler loop with the
controller gain 20 % high, 1 s samples; 1e5 samples = 27.8 h) into a temporary folder,
runs ``plantdyn discrepancy`` through :func:`pipeline.jobs.discrepancy.run_discrepancy`
(ingest, grid, analysis, run directory, Rerun recording) and prints the wall time per
stage, side by side with two references measured in the same run on the same data:
a bare ``polars.read_csv`` of the export and one nominal simulation of the model.
The goal is "minutes, not hours".
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.adapters.config import load_job
from pipeline.jobs.demo import BOILER_MODEL, DISCREPANCY_JOB, write_discrepancy_export
from pipeline.jobs.discrepancy import run_discrepancy
from pipeline.models.model import model_from_dict
from pipeline.models.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=100_000)
    args = ap.parse_args()
    hours = args.samples / 3600.0
    folder = Path(tempfile.mkdtemp(prefix="bench_disc_"))
    try:
        (folder / "models").mkdir()
        shutil.copyfile(BOILER_MODEL, folder / "models" / BOILER_MODEL.name)
        t0 = time.perf_counter()
        csv = write_discrepancy_export(folder / "discrepancy", hours=hours)
        t_write = time.perf_counter() - t0
        job = folder / "job.yaml"
        job.write_text(DISCREPANCY_JOB.read_text().replace("../demo/discrepancy/*.csv",
                                                           "discrepancy/*.csv"))
        cfg = load_job(job)

        t0 = time.perf_counter()
        pl.read_csv(csv, schema_overrides={"value": pl.String})
        t_read = time.perf_counter() - t0
        import yaml

        model = model_from_dict(yaml.safe_load(BOILER_MODEL.read_text()))
        u = np.random.default_rng(0).standard_normal(args.samples)
        t0 = time.perf_counter()
        simulate(model, {"steam_flow": u}, dt_s=1.0)
        t_sim = time.perf_counter() - t0

        stamps: list[tuple[float, str, str]] = []
        start = time.perf_counter()
        report = run_discrepancy(cfg, progress=lambda s, m: stamps.append(
            (time.perf_counter() - start, s, m)))
        total = time.perf_counter() - start
    finally:
        shutil.rmtree(folder, ignore_errors=True)

    print(f"discrepancy workflow on {args.samples} samples ({hours:.1f} h at 1 s); export "
          f"written in {t_write:.1f} s ({csv.name})")
    print(f"  verdict {report.verdict}: {report.effect and report.effect['name']} at "
          f"{report.effect and report.effect['location']}, parameters "
          f"{report.effect and report.effect['parameters']}")
    print(f"  held-out RMS {report.gap['holdout_rms_before']:.4g} -> "
          f"{report.gap['holdout_rms_after']:.4g}")
    print("  stage timings (s):")
    for stage, sec in report.timings_s.items():
        print(f"    {stage:<12s} {sec:8.2f}")
    if report.result is not None:
        for stage, sec in report.result.timings_s.items():
            print(f"      analyse/{stage:<20s} {sec:8.2f}")
    print(f"  total {total:.1f} s = {total / 60:.2f} min "
          f"(goal: minutes, not hours)")
    print(f"  references in this run: bare polars.read_csv {t_read:.2f} s "
          f"(workflow = {total / t_read:.0f}x), one nominal simulation {t_sim:.3f} s "
          f"(workflow = {total / t_sim:.0f}x)")


if __name__ == "__main__":
    main()
