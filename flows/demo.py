"""``plantdyn demo``: write the demo export and job (``pipeline.jobs.demo``), run them through
the Prefect flow or directly, and print where the results are and how to view them."""

from __future__ import annotations

import sys
from pathlib import Path

from pipeline.adapters.config import load_job
from pipeline.jobs.demo import prepare_demo, prepare_discrepancy_demo
from pipeline.progress import quiet


def rerun_command() -> str:
    """The Rerun viewer beside this Python (works from any folder), else ``rerun``."""
    exe = Path(sys.executable).parent / "rerun"
    return str(exe) if exe.exists() else "rerun"


def _print_where(report, *extra: tuple[str, Path]) -> int:
    print(report, file=sys.stderr)
    print(f"\nresults:   {report.run_dir}")
    print(f"report:    {report.run_dir / 'report.md'}")
    if (report.run_dir / "report.html").is_file():
        print(f"html:      {report.run_dir / 'report.html'}")
    for label, path in extra:
        print(f"{label + ':':<10} {path}")
    if report.recording:
        print(f"recording: {report.recording}")
        print(f"view it:   {rerun_command()} {report.recording}")
    return 0


def _run(job: Path, *, no_prefect: bool, progress, discrepancy: bool):
    """Run ``job`` directly (the composition function) or through its Prefect flow."""
    if no_prefect:
        if discrepancy:
            from pipeline.jobs.discrepancy import run_discrepancy as direct
        else:
            from pipeline.jobs.estimation import run_job as direct
        return direct(load_job(job), progress=progress or quiet)
    from flows.server import project_prefect

    with project_prefect(load_job(job).storage_root):  # the project server, started or reused
        if discrepancy:
            from flows.discrepancy import run_discrepancy_flow as through_flow
        else:
            from flows.estimate import run_estimate as through_flow
        return through_flow(job)


def run_demo(folder: Path, *, no_prefect: bool = False, progress=None) -> int:
    """Write the export and run the demo job; print where results are and how to view.

    Parameters
    ----------
    folder : Path
        Where the export and the job are written (:func:`pipeline.jobs.demo.prepare_demo`).
    no_prefect : bool
        Call the pipeline directly instead of through the Prefect flow.
    progress : callable (stage, message), optional
        Told what the demo writes and, with ``no_prefect``, each stage of the run.
    """
    job = prepare_demo(folder, progress=progress)
    return _print_where(_run(job, no_prefect=no_prefect, progress=progress, discrepancy=False))


def run_discrepancy_demo(folder: Path, *, no_prefect: bool = False, progress=None,
                         two_effects: bool = False) -> int:
    """Write the discrepancy demo export and run ``configs/demo_discrepancy.yaml`` (or
    ``configs/demo_discrepancy_two.yaml``).

    Parameters
    ----------
    folder : Path
        Where the export, model and job are written
        (:func:`pipeline.jobs.demo.prepare_discrepancy_demo`).
    no_prefect : bool
        Call the pipeline directly instead of through the Prefect flow.
    progress : callable (stage, message), optional
        Told what the demo writes and, with ``no_prefect``, each stage of the run.
    two_effects : bool
        The two-effect demo.
    """
    job = prepare_discrepancy_demo(folder, progress=progress, two_effects=two_effects)
    report = _run(job, no_prefect=no_prefect, progress=progress, discrepancy=True)
    return _print_where(report, ("model", report.run_dir / "model_augmented.yaml"))
