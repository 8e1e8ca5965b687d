"""The Rerun sink: renders a run directory into ``recording.rrd`` (the only importer of
``rerun``).

It reads the stored files (``signals.parquet``, ``step_responses.parquet``,
``residuals.parquet``, ``checks.json``, ``manifest.json``), never in-memory results, so a
figure can be rebuilt from a run without refitting: ``render_run(run_dir)``.  Every file is
optional; what is absent is simply not drawn.

Layout (entity paths; names are escaped with ``rr.escape_entity_path_part``).  The
timeline every estimation series shares is ``elapsed`` (a duration), because a Rerun 0.41
time-series view plots against the time panel's active timeline only:

* ``signals/raw/<signal>``, ``signals/conditioned/<signal>`` on ``elapsed`` (seconds since
  the first stored sample) and on ``time`` (UTC), one row per stored sample; missing
  values and masked conditioned samples are NaN, which the viewer draws as gaps.  Masked
  samples (``good == False``) that have a raw value are also points on
  ``signals/masked/<signal>`` (red crosses over the raw line);
* ``step/<output>/<input>/window/<window>`` on ``elapsed`` (``time_s`` of the stored step
  response: seconds after the step), ``all`` and every disjoint window; under them
  ``step/<output>/<input>/band/{upper,lower}`` (step ± 2·step_std of the all-data
  estimate) and ``band/fill`` (a dense triangle wave between the two that reads as a
  filled band: Rerun has no filled area).  The viewer draws a view's series in
  entity-path order, so the band lies under every line and the thin windows over the
  thick all-data line;
* ``residuals/<output>`` on ``elapsed`` and ``time`` (residuals of the all-data estimate);
* ``trends/<output>/<input>/<metric>`` on ``run_time`` when nightly trends are given, and
  ``trends/readme`` (how to see them).

Series are sent in bulk with ``send_columns`` (≈30× faster than per-row ``log``), which
injects no ``log_time``/``log_tick``; the recording id derives from job and run id and no
wall-clock recording properties are sent, so the same run renders to the same *data*.
The file is not byte-identical between renders: Rerun stamps every chunk and row with a
time-based id (TUID), and the blueprint store gets a random id and a ``log_time``; compare
decoded contents instead (``tests/adapters/test_rerun_sink.py`` does).

The default blueprint opens on ``elapsed`` with the side panels collapsed, on tabs:

* *Step responses*: an outputs × inputs grid (rows outputs, columns inputs), each view
  titled ``output [unit] ← input [unit]`` (units from the job config), its x axis from 0
  to the pair's last lag (a pair with N_p = 3 fills its view like one with N_p = 150),
  its y axis over 0 and the band; the legend sits in the right-hand corner away from
  where the response settles (in every view up to 3 rows, else in the first);
* *Signals*: one row per signal, raw (with the masked crosses) | conditioned, each with
  its own y axis (a tag at 200 no longer flattens one at 1);
* *Residuals*: one view per output;
* *Trends*: the pairs' gain (or rate) per run; they need the ``run_time`` timeline, which
  a note at the top of the tab says.

The time tabs' views span the whole active timeline, so choosing ``time`` in the time
panel shows the same plots against UTC clock time.

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
