"""Composition of nightly monitoring (issue 13): find and read the baseline run, compare
the new run with it (:mod:`pipeline.readouts.monitor`), and put the result into what the run
writes.  Called by :func:`pipeline.jobs.estimation.run_job` and the ``estimate`` flow between
``summarise`` and ``store``, so the baseline is read before the new run is written.

Decisions:

* ``monitor.baseline: RUN_ID`` must be a stored run of the job; otherwise the job stops
  with exit 2 before any work (:func:`check_baseline`, called by the CLI and the nightly
  flow's discovery), naming ``monitor.baseline`` and the runs that exist.  A baseline
  whose files no longer match its manifest stops it the same way (a night's files
  would otherwise each be marked failed for a fault that is not theirs).
* ``monitor.baseline: first`` is the job's oldest catalogued estimation run (status
  ``ok`` or ``windows_disagree``: a run reaches the catalog only when it completed; a
  discrepancy run of the same job name has no step responses and is skipped).  With no
  such run the new run is its own baseline and says so.  A nightly flow processing
  several new files of a first night concurrently may make each its own baseline;
  later nights take the oldest.
* The comparison reads the same tables for both runs — ``checks.json`` ``pairs`` and the
  ``all`` window of ``step_responses.parquet`` — for the baseline from its run folder
  (sha256 verified against its manifest), for the new run from its summary.
* Recorded in the run: ``checks.json`` ``monitor`` (:meth:`MonitorResult.to_dict`), a
  line below the title of ``report.md``, and catalog metrics per pair — ``gain_z``,
  ``dead_time_z``, ``step_max_z``, ``monitor`` (label ``changed`` / ``unchanged`` /
  ``baseline``), ``monitor_max_z`` (the largest z), ``monitor_low`` / ``monitor_high``
  (the gain or rate range within which this run counts as unchanged: baseline ±
  threshold × the combined σ) and ``monitor_baseline`` (label: the baseline's run id).
  Metrics live in the manifest, so ``plantdyn reindex`` rebuilds them.
"""

from __future__ import annotations

import dataclasses
import math

import polars as pl

from pipeline.adapters.store import CATALOG_NAME, ResultStore
from pipeline.errors import ConfigError, DataQualityError
from pipeline.jobs.job_types import Summary
from pipeline.readouts.monitor import MonitorResult, PairResponse, compare_runs

__all__ = ["ESTIMATION_STATUSES", "check_baseline", "baseline_run_id", "pair_responses",
           "monitor_run", "monitor_metrics"]

#: Statuses of completed estimation runs (candidates for ``monitor.baseline: first``).
ESTIMATION_STATUSES = ("ok", "windows_disagree")


def _runs(cfg) -> pl.DataFrame | None:
    """The job's catalogued runs (read-only; ``None`` when there is no catalog yet)."""
    root = cfg.storage_root
    if not (root / CATALOG_NAME).is_file():
        return None
    return ResultStore(root, readonly=True).list_runs(cfg.job)


def baseline_run_id(cfg) -> str | None:
    """The run id ``monitor.baseline`` names, resolved against the catalog.

    Returns ``None`` for ``first`` when the job has no completed estimation run yet.

    Parameters
    ----------
    cfg : JobConfig
        The validated job, with a ``monitor`` section.

    Raises
    ------
    ConfigError
        A pinned run id that is not a stored run of the job (the message lists the
        runs that exist).
    """
    want = cfg.monitor.baseline
    runs = _runs(cfg)
    ids = [] if runs is None else runs["run_id"].to_list()
    if want == "first":
        if runs is None:
            return None
        ok = runs.filter(pl.col("status").is_in(list(ESTIMATION_STATUSES)))
        return ok["run_id"][0] if ok.height else None
    if want in ids or (cfg.storage_root / cfg.job / want / "manifest.json").is_file():
        return want
    shown = ", ".join(ids[:10]) + (f", … ({len(ids)} in all)" if len(ids) > 10 else "")
    have = f"the runs that exist: {shown}" if ids else "the job has no runs yet"
    raise ConfigError(
        f"monitor.baseline: run {want!r} of job {cfg.job!r} is not under "
        f"{cfg.storage_root}; {have} (`plantdyn runs {cfg.job}` lists them) — give one of "
        "them, or monitor.baseline: first (the job's first run)")


def check_baseline(cfg) -> None:
    """Check before any work that the baseline can be used: a pinned
    ``monitor.baseline`` run exists (exit 2 with the runs that exist otherwise), and the
    baseline run (pinned, or the job's first) reads back whole — files matching its
    manifest, step responses present.  Nothing to check without ``monitor``.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    """
    if cfg.monitor is None:
        return
    bid = baseline_run_id(cfg)
    if bid is not None:
        _baseline_pairs(cfg, bid)


def pair_responses(checks: dict, steps: pl.DataFrame) -> list[PairResponse]:
    """Every pair of a run as :class:`PairResponse`: ``checks.json`` ``pairs`` (gain or
    rate ± σ, dead time) and the ``all`` window of the step responses.

    Parameters
    ----------
    checks : dict
        The run's checks.json document.
    steps : polars.DataFrame
        The run's step_responses table.
    """
    allw = steps.filter(pl.col("window") == "all")
    out = []
    for p in checks["pairs"]:
        rows = allw.filter((pl.col("output") == p["output"]) & (pl.col("input") == p["input"]))
        rows = rows.sort("lag")
        integ = bool(p.get("integrating"))
        value, std = (p.get("rate"), p.get("rate_std")) if integ else \
            (p.get("gain"), p.get("gain_std"))
        dead = (p.get("characteristics") or {}).get("dead_time_s")
        dt_s = float(rows["dt_s"][0]) if rows.height else float(checks["dt_s"])
        out.append(PairResponse(
            p["output"], p["input"], integ, _f(value), _f(std), _f(dead),
            rows["step"].to_numpy().astype(float), rows["step_std"].to_numpy().astype(float),
            dt_s))
    return out


def _f(v) -> float:
    return float("nan") if v is None else float(v)


def _baseline_pairs(cfg, run_id: str) -> list[PairResponse]:
    try:
        stored = ResultStore(cfg.storage_root, readonly=True).read_run(cfg.job, run_id)
    except DataQualityError as exc:
        raise DataQualityError(f"monitor.baseline: the baseline run cannot be used: {exc}; "
                               "pin another run (monitor.baseline: RUN_ID)") from None
    if stored.checks is None or stored.step_responses is None or \
            "pairs" not in stored.checks:
        raise DataQualityError(
            f"monitor.baseline: run {cfg.job}/{run_id} has no step responses or checks "
            "(not an estimation run); pin an estimation run of the job")
    return pair_responses(stored.checks, stored.step_responses)


def monitor_metrics(result: MonitorResult, own: list[PairResponse]) -> list[dict]:
    """The catalog rows of a monitoring result (module notes).

    Parameters
    ----------
    result : MonitorResult
        The comparison (or the self-baseline result).
    own : list of PairResponse
        This run's pairs (for the self-baseline band).
    """
    thr = result.threshold_sigma
    rows = []

    def add(o, u, metric, value):
        if value is not None and not (isinstance(value, float) and not math.isfinite(value)):
            rows.append({"window": "all", "output": o, "input": u, "metric": metric,
                         "value": value})

    for p in result.pairs:
        zs = [z for z in (p.gain_z, p.dead_time_z, p.step_max_z) if z is not None]
        for name, z in (("gain_z", p.gain_z), ("dead_time_z", p.dead_time_z),
                        ("step_max_z", p.step_max_z)):
            add(p.output, p.input, name, z)
        add(p.output, p.input, "monitor", "changed" if p.changed else "unchanged")
        add(p.output, p.input, "monitor_max_z", max(zs) if zs else None)
        half = thr * math.hypot(p.baseline_std, p.value_std)
        add(p.output, p.input, "monitor_low", p.baseline - half)
        add(p.output, p.input, "monitor_high", p.baseline + half)
        add(p.output, p.input, "monitor_baseline", result.baseline_run)
    if result.is_baseline:
        for p in own:
            half = thr * math.hypot(p.value_std, p.value_std)
            add(p.output, p.input, "monitor", "baseline")
            add(p.output, p.input, "monitor_low", p.value - half)
            add(p.output, p.input, "monitor_high", p.value + half)
            add(p.output, p.input, "monitor_baseline", result.baseline_run)
    return rows


def monitor_run(cfg, summary: Summary, run_id: str | None = None) -> tuple[Summary, str]:
    """Compare the new run with its baseline and return the summary to write (checks,
    metrics and report with the result) and the run id (chosen here when ``None``:
    a run that becomes its own baseline names itself).

    Parameters
    ----------
    cfg : JobConfig
        The validated job, with a ``monitor`` section.
    summary : Summary
        The new run's summary (:func:`pipeline.jobs.summary.summarise`).
    run_id : str, optional
        The new run's id; ``None`` lets the store choose one now.
    """
    if run_id is None:
        run_id = ResultStore(cfg.storage_root).new_run_id()
    own = pair_responses(summary.checks, summary.step_responses)
    bid = baseline_run_id(cfg)
    thr = float(cfg.monitor.threshold_sigma)
    if bid is None:
        result = MonitorResult(run_id, thr, (), True, {})
    else:
        result = compare_runs(_baseline_pairs(cfg, bid), own, baseline_run=bid,
                              threshold_sigma=thr)
    section = result.to_dict()
    if result.is_baseline:
        section["message"] = (f"no earlier run of job {cfg.job} in the catalog: this run "
                              "is the baseline later runs are compared with")
    new = dataclasses.replace(
        summary, report=summary.report.with_checks({**summary.checks, "monitor": section}),
        metrics=[*summary.metrics, *monitor_metrics(result, own)])
    return new, run_id
