"""The Rerun sink: renders a run directory into ``recording.rrd`` (the only importer of
``rerun``).

It reads the stored files (``signals.parquet``, ``step_responses.parquet``,
``residuals.parquet``, ``checks.json``, ``manifest.json``), never in-memory results, so a
figure can be rebuilt from a run without refitting: ``render_run(run_dir)``.  Every file is
optional; what is absent is simply not drawn.

Layout (entity paths; names are escaped with ``rr.escape_entity_path_part``):

* ``signals/raw/<signal>``, ``signals/conditioned/<signal>`` on the ``time`` timeline, one
  row per stored sample; missing values and masked conditioned samples are NaN, which the
  viewer draws as gaps.  Masked samples (``good == False``) that have a raw value are also
  points on ``signals/masked/<signal>`` (red crosses over the raw line);
* ``step/<output>/<input>/<window>`` on the ``lag_s`` timeline (``time_s`` of the stored
  step response, as a duration), with ``step/<output>/<input>/all_upper`` and
  ``all_lower`` (step ± 2·step_std of the estimate over all data); every disjoint window
  overlaid in the same view;
* ``residuals/<output>`` on ``time`` (residuals of the all-data estimate);
* ``trends/<output>/<input>/<metric>`` on ``run_time`` when nightly trends are given.

Series are sent in bulk with ``send_columns`` (≈30× faster than per-row ``log``), which
injects no ``log_time``/``log_tick``; the recording id derives from job and run id and no
wall-clock recording properties are sent, so the same run renders to the same *data*.
The file is not byte-identical between renders: Rerun stamps every chunk and row with a
time-based id (TUID), and the blueprint store gets a random id and a ``log_time``; compare
decoded contents instead (``tests/test_rerun_sink.py`` does).

A default blueprint opens tabs *Step responses* (one view per pair), *Signals*,
*Residuals* and *Trends*, starting on the ``lag_s`` timeline; every TimeSeriesView is
given the full time range explicitly (without it the viewer shows only ±30 s around the
time cursor).  The other tabs need the ``time`` (signals, residuals) or ``run_time``
(trends) timeline, chosen in the time panel.

Discrepancy runs are rendered by ``render_discrepancy(run_dir)`` from
``discrepancy.json`` and ``discrepancy_series.parquet`` (both required): measured vs
nominal vs augmented outputs and the residual before/after on a ``time_s`` timeline, the
localisation as bar charts and documents under ``discrepancy/<output>/localisation``,
the candidate ranking under ``discrepancy/candidates``; its docstring lists the paths.
"""

from __future__ import annotations

from pipeline.adapters.rerun_sink.common import APPLICATION_ID, TIMELINES, recording_id_for
from pipeline.adapters.rerun_sink.discrepancy import render_discrepancy
from pipeline.adapters.rerun_sink.estimation import render_run

__all__ = ["APPLICATION_ID", "TIMELINES", "recording_id_for", "render_discrepancy", "render_run"]
