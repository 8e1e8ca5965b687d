"""plantdyn: step responses of industrial plants from normal operating data.

The folders are the layers (design.md; imports point down only, checked by
``tests/project/test_layers.py`` from the folders themselves):

* core, numeric and pure (numpy/scipy): :mod:`pipeline.estimation` (the least-squares
  estimate and its noise models), :mod:`pipeline.identification` (sample period,
  conditioning, the N_p/N_d search, checks, verdicts), :mod:`pipeline.readouts`
  (characteristics, frequency responses, transfer-function fits, monitoring),
  :mod:`pipeline.models` (block-diagram models and their simulation),
  :mod:`pipeline.discrepancy` (the simulation-versus-plant workflow and its effect
  catalogue), :mod:`pipeline.simulated` (simulated plant records for the demo and the
  benchmarks); shared: :mod:`pipeline.errors`, :mod:`pipeline.progress`;
* adapters (files, YAML, store, report, Rerun, export): :mod:`pipeline.adapters`;
* composition (jobs a person can call from a REPL): :mod:`pipeline.jobs`;
* orchestration: the ``flows`` package (Prefect, the ``plantdyn`` CLI).

The names in ``__all__`` are the public face; each is imported on first use, so
``import pipeline.errors`` does not load the composition.
"""

from __future__ import annotations

from pipeline._lazy import lazy_names

__version__ = "0.1.0"

_PUBLIC = {
    "estimate_step_responses": "pipeline.estimation.estimate",
    "StepResponseEstimate": "pipeline.estimation.step_result",
    "search": "pipeline.identification.search",
    "SearchResult": "pipeline.identification.search",
    "choose_sample_period": "pipeline.identification.sampling",
    "window_agreement": "pipeline.identification.checks",
    "Model": "pipeline.models.model",
    "model_from_dict": "pipeline.models.model",
    "simulate": "pipeline.models.simulate",
    "analyse_discrepancy": "pipeline.discrepancy.analyse",
    "run_job": "pipeline.jobs.estimation",
    "RunReport": "pipeline.jobs.job_types",
    "run_discrepancy": "pipeline.jobs.discrepancy",
    "DiscrepancyReport": "pipeline.jobs.discrepancy",
    "PipelineError": "pipeline.errors",
}
__all__ = ["__version__", *_PUBLIC]

__getattr__, __dir__ = lazy_names(__name__, _PUBLIC)
