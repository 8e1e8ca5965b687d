"""Composition (design.md layer 3): plain functions a person can call from a REPL that
wire the adapters and the core — the estimation job (:mod:`pipeline.jobs.estimation`,
``run_job``), the discrepancy job (:mod:`pipeline.jobs.discrepancy`,
``run_discrepancy``), monitoring against a baseline, the nightly drop folder, the Rerun
recording, the stage runner and the demo.

``from pipeline.jobs import run_job`` keeps working as it did when this was one module;
the names are imported on first use (a composition module importing another one does not
load all of them).
"""

from __future__ import annotations

from pipeline._lazy import lazy_names

_PUBLIC = {
    "run_job": "pipeline.jobs.estimation",
    "prepare": "pipeline.jobs.estimation",
    "search_orders": "pipeline.jobs.estimation",
    "estimate_window": "pipeline.jobs.estimation",
    "RunReport": "pipeline.jobs.job_types",
    "run_discrepancy": "pipeline.jobs.discrepancy",
    "DiscrepancyReport": "pipeline.jobs.discrepancy",
}
__all__ = list(_PUBLIC)

__getattr__, __dir__ = lazy_names(__name__, _PUBLIC)
