"""The HTML report: one self-contained ``report.html`` per run (the only importer of
matplotlib).

Like the Rerun sink it reads the run's stored files, never in-memory results, so a report
can be rebuilt without refitting (``python -m pipeline.adapters.html_report RUN_DIR``).
Figures are matplotlib (without pyplot): inline SVG with the text kept as text (the
step-response, frequency-response and correlation matrices, the search trace) or base64
PNG for dense time series.  Every matrix panel has the same size and its units on both
axes.  A section that cannot be drawn shows its error in place (and warns) instead of
failing the run.

* :func:`render_run_html` — an estimation run: a monitor banner when checks.json has one,
  the outputs × inputs step-response matrix (all-data estimate with ±2σ, each disjoint
  window), the gain matrix with σ and grades, the relative gain array (square gain
  matrices), the grade per pair with the rule (:mod:`pipeline.identification.quality`), measured vs
  predicted on a held-out window with the fit %, residual autocorrelation and
  input–residual cross-correlation with their bands, frequency responses, the N_p/N_d
  search trace, data quality.
* :func:`render_discrepancy_html` — a discrepancy run: measured / nominal / augmented per
  output, the held-out gap effect by effect, all candidates, the localisation by signal
  name, minor effects.
* :func:`add_report_html` — write ``report.html`` into a run being written (inside the
  store's ``new_run`` block, so the run appears with it or not at all).
* :func:`write_report_html` — render an existing run directory to a file of your choice.
"""

from __future__ import annotations

import os
import secrets
import time
from pathlib import Path

from pipeline.adapters.html_report.discrepancy import render_discrepancy_html
from pipeline.adapters.html_report.estimation import render_run_html

__all__ = ["REPORT_NAME", "add_report_html", "render_run_html", "render_discrepancy_html",
           "write_report_html"]

REPORT_NAME = "report.html"


def write_report_html(run_dir: Path, out: Path) -> Path:
    """Render the stored run ``run_dir`` (estimation or discrepancy, told apart by its
    files) into ``out`` (written to a temporary name and renamed).

    Parameters
    ----------
    run_dir : Path
        A committed run directory (with ``manifest.json``).
    out : Path
        The HTML file to write (outside the storage root: the store is its only writer).
    """
    run_dir, out = Path(run_dir), Path(out)
    if not (run_dir / "manifest.json").is_file():
        from pipeline.errors import ConfigError

        raise ConfigError(f"{run_dir} has no manifest.json; give a run directory "
                          "(<storage>/<job>/<run-id>)")
    if (run_dir / "discrepancy.json").is_file():
        text = render_discrepancy_html(run_dir)
    else:
        text = render_run_html(run_dir)
    tmp = out.parent / f".{out.name}.{secrets.token_hex(4)}.part"
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def add_report_html(run, *, config: dict, inputs: list, kind: str = "estimation") -> Path:
    """Render ``report.html`` from the files already in a run being written and write it
    there (atomically, through the writer); the seconds go to the manifest as
    ``html_report``.

    Parameters
    ----------
    run : pipeline.adapters.store.RunWriter
        The run being written (its files so far are what the report shows).
    config : dict
        The resolved job configuration (the manifest does not exist before the commit).
    inputs : list of path
        The input files.
    kind : ``"estimation"`` or ``"discrepancy"``
        Which report.
    """
    if kind not in ("estimation", "discrepancy"):
        from pipeline.errors import ConfigError

        raise ConfigError(f"kind {kind!r} is not one of 'estimation', 'discrepancy'")
    t0 = time.perf_counter()
    manifest = {"job": run.job, "run_id": run.run_id, "status": run.status,
                "created_utc": run.created_utc.strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
                "config": config, "inputs": [{"path": str(f)} for f in inputs]}
    render = render_discrepancy_html if kind == "discrepancy" else render_run_html
    path = run.write_text(REPORT_NAME, render(run.path, manifest=manifest))
    run.record_timing("html_report", time.perf_counter() - t0)
    return path
