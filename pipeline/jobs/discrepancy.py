"""Composition: ``run_discrepancy(config) -> DiscrepancyReport``, callable from a REPL.

The discrepancy job compares a simulation model with measured data (issue 4,
design.md "Model YAML" and "Effect catalogue").  It is a readable sequence of stage
functions; the Prefect flow in ``flows/discrepancy.py`` wraps each in a task.

    load_recording (jobs) -> load_discrepancy_model -> prepare_discrepancy
      -> analyse (pipeline.discrepancy.analyse_discrepancy) -> write_discrepancy_run

Decisions (also in docs/guide/discrepancy.md):

* Grid: the recording's uniform grid (as for estimation jobs); ``sampling.dt_s``
  averages-then-decimates to a coarser period.  The α_T criterion is not used: a
  simulation is compared sample by sample and every model delay must be a whole number
  of samples, so the finest honest grid is the right one.
* Gaps: simulation needs continuous inputs.  Short bad runs (at most
  :data:`MAX_FILL_SAMPLES` consecutive bad samples of a signal, e.g. an isolated "Bad
  Input" state) are bridged by linear interpolation; then the analysis uses the longest
  stretch where every job signal is good (grid gaps up to ``max_gap_s`` are already
  bridged by the grid).  Filled and left-out samples are counted in
  ``discrepancy.json`` ``data``.
* Operating point: models are written in deviation variables (the shipped ones are).
  ``operating_point: mean`` (default) subtracts each input's mean over the analysed
  stretch, and from each output the value that makes the nominal model's residual
  zero-mean over the fit part.  (Subtracting the output's plain mean is wrong: the means
  of a finite record do not satisfy the model's static relation -- end effects of order
  K·τ/T·Δu -- and the leftover constant, many noise standard errors on a long record,
  was named a sensor bias on a perfect model.)  Given values ``{signal: value}`` are
  used as they are; ``none`` subtracts nothing.  A constant sensor bias can therefore
  only be named against given operating-point values; against ``mean`` only its drift.
* External simulators: with ``discrepancy.simulator_outputs: {output: signal}`` the
  "model" is a pass-through block named after each output, fed by the recorded
  simulator output; catalogue effects then apply at the outputs (gain, dead time, lag,
  inverse response, deadband, saturation, operating-point gain at that block, sensor
  bias/drift) and as ``unmodelled_input`` from any other recorded input.
* ``sensor_bias_drift`` changes the measurement, not the blocks: ``model_augmented.yaml``
  keeps the blocks and adds a top-level ``measurement:`` section (``bias``,
  ``drift_per_h`` from the first analysed sample), which
  :func:`pipeline.discrepancy.effects.output_offsets` applies.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.discrepancy import DiscrepancyConfig, DiscrepancyResult, analyse_discrepancy
from pipeline.discrepancy.problem import (
    AUTO_WARMUP_MAX_SHARE,
    first_holdout_sample,
    opened_signals,
)
from pipeline.discrepancy.report import effect_markup, fmt_number, summary_markdown
from pipeline.errors import ConfigError, InsufficientDataError
from pipeline.identification.conditioning import as_masked_zero, interpolate_gaps
from pipeline.models.model import Model, model_from_dict, model_to_dict, open_at
from pipeline.progress import Progress, quiet
from pipeline.jobs.recording import (
    Recording,
    configured_decimation,
    load_recording,
    longest_common_good,
)
from pipeline.jobs.stages import StageRunner
from pipeline.identification.sampling import resample_average_masked, sample_period_s

__all__ = [
    "DiscrepancyData",
    "DiscrepancyReport",
    "check_job",
    "core_config",
    "free_outputs",
    "load_discrepancy_model",
    "prepare_discrepancy",
    "analyse",
    "series_table",
    "write_discrepancy_run",
    "run_discrepancy",
]


#: Fewest samples in the analysed stretch (the core needs >= 300 in its fit part).
MIN_SAMPLES = 600

#: Longest run of bad samples bridged by interpolation (a few samples of a digital
#: state change nothing a simulation comparison can see; longer outages split the record).
MAX_FILL_SAMPLES = 5


@dataclass(frozen=True)
class DiscrepancyData:
    """The analysed stretch: deviation signals on one grid, and where they came from."""

    inputs: dict[str, np.ndarray]  # every job input (model inputs and extra signals)
    measured: dict[str, np.ndarray]  # measured outputs the model predicts
    dt_s: float
    time: np.ndarray  # datetime64[us] UTC of each analysed sample
    operating_point: dict[str, float]
    summary: dict  # JSON-ready: span, samples left out, decimation, operating point
    files: tuple[str, ...]


@dataclass(frozen=True)
class DiscrepancyReport:
    """What a discrepancy run produced (printable)."""

    job: str
    run_id: str
    run_dir: Path
    status: str
    verdict: str
    effect: dict | None
    gap: dict
    dt_s: float
    n_samples: int
    files: tuple[str, ...]
    recording: Path | None
    result: DiscrepancyResult | None = field(default=None, repr=False)
    timings_s: dict = field(default_factory=dict)
    report_md: str = field(default="", repr=False)  # report.md as written

    def __str__(self) -> str:
        g = self.gap
        lines = [f"discrepancy {self.job}/{self.run_id}: {self.verdict}",
                 f"  results: {self.run_dir}",
                 f"  {self.n_samples} samples at dt = {self.dt_s:g} s"]
        if self.effect:  # as report.md words it (pipeline.discrepancy.report)
            lines.append(f"  effect: {effect_markup(self.effect, code=str, plain=str)}")
        lines.append(f"  held-out RMS {fmt_number(g['holdout_rms_before'])} -> "
                     f"{fmt_number(g['holdout_rms_after'])} ({100 * g['reduction']:.1f} % "
                     "smaller)")
        if self.recording:
            lines.append(f"  Rerun recording: {self.recording}  (open: rerun {self.recording})")
        return "\n".join(lines)


# -------------------------------------------------------------------------- stages
def _simulator_model(cfg) -> dict:
    """Pass-through model of an external simulator's recorded outputs."""
    sim = cfg.discrepancy.simulator_outputs
    return {
        "name": f"{cfg.job}_external_simulator",
        "inputs": sorted(set(sim.values())),
        "outputs": list(sim),
        "blocks": [{"name": out, "type": "gain", "input": sig, "k": 1.0}
                   for out, sig in sim.items()],
    }


def load_discrepancy_model(cfg) -> tuple[Model, str]:
    """The job's model (``model:`` path or mapping, or the external-simulator wrapper).

    Returns ``(model, source)`` with ``source`` = ``"model"`` or ``"external_simulator"``.
    Checks that model inputs are job signals and job outputs are model outputs.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (with its ``model:`` or ``discrepancy.simulator_outputs``).
    """
    from pipeline.adapters.config import load_model_spec

    section = cfg.discrepancy
    if section is not None and section.simulator_outputs:
        spec, source = _simulator_model(cfg), "external_simulator"
    else:
        spec, source = load_model_spec(cfg), "model"
    model = model_from_dict({"model": spec})
    ins, outs = list(cfg.signals.inputs), list(cfg.signals.outputs)
    missing = [u for u in model.inputs if u not in ins]
    if missing:
        raise ConfigError(
            f"model {model.name!r}: inputs {missing} are not signals of job {cfg.job!r} "
            f"(signals.inputs: {ins}); add them under signals.inputs with their tags, or "
            "rename the model's inputs to the job's signal names")
    stray = [o for o in outs if o not in model.outputs]
    if stray:
        raise ConfigError(
            f"model {model.name!r} has no output {stray} (model outputs: {list(model.outputs)}); "
            "remove them from signals.outputs or name the model block that predicts each "
            "after the measured signal")
    return model, source


def _output_offsets_from_nominal(cfg, model: Model, inputs: dict, measured: dict,
                                 outputs: list[str], dt_s: float) -> dict[str, float]:
    """Mean of measured - nominal over the fit part (after the warm-up) per output."""
    from pipeline.models.simulate import simulate

    if not outputs:
        return {}
    core = core_config(cfg)
    sim = simulate(model, {u: inputs[u] for u in model.inputs}, dt_s=dt_s,
                   initial=core.initial).signals
    n = next(iter(measured.values())).size
    # the fit part as the core will use it, conservatively: skip the core's longest
    # automatic warm-up unless a warm-up is configured
    start = (int(round(core.warmup_s / dt_s)) if core.warmup_s is not None
             else int(AUTO_WARMUP_MAX_SHARE * n))
    stop = first_holdout_sample(n, core.holdout_fraction)
    return {o: float(np.mean(measured[o][start:stop] - sim[o][start:stop])) for o in outputs}


def prepare_discrepancy(cfg, rec: Recording, model: Model) -> DiscrepancyData:
    """Longest all-good stretch, optional decimation, operating point removed.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``sampling.dt_s``, ``discrepancy.operating_point``).
    rec : Recording
        The gridded signals from :func:`pipeline.jobs.recording.load_recording`.
    model : Model
        The job's model; its outputs select the measured signals.
    """
    from pipeline.models.stability import check_delays, check_simulable

    section = cfg.discrepancy
    check_delays(model, record_s=rec.values.shape[0] * rec.grid_dt_s)
    factor = configured_decimation(cfg, rec.grid_dt_s) or 1
    vals, good = rec.values, rec.good
    if factor > 1:
        vals, good = resample_average_masked(as_masked_zero(vals), good, factor)
    t = rec.time[::factor][: vals.shape[0]]
    vals, filled = interpolate_gaps(vals, good, MAX_FILL_SAMPLES)
    good = good | filled
    a, b = longest_common_good(good)
    n_grid = vals.shape[0]
    dt_s = sample_period_s(factor, rec.grid_dt_s)
    if b - a < MIN_SAMPLES:
        bad = {n: int((~good[:, k]).sum()) for k, n in enumerate(rec.names)}
        raise InsufficientDataError(
            f"the longest stretch where every signal is good has {b - a} samples at "
            f"{dt_s:g} s (of {n_grid}); the discrepancy workflow needs at least {MIN_SAMPLES}. "
            f"Bad samples per signal: {bad} — drop a signal with many bad samples from the "
            "job, or supply a cleaner export")
    check_simulable(model, dt_s=dt_s, n_samples=b - a)
    seg = vals[a:b]
    op_mode = section.operating_point if section is not None else "mean"
    op: dict[str, float] = {}
    for k, name in enumerate(rec.names):
        if op_mode == "none":
            op[name] = 0.0
        elif isinstance(op_mode, dict) and name in op_mode:
            op[name] = float(op_mode[name])
        else:
            op[name] = float(np.mean(seg[:, k]))
    if isinstance(op_mode, dict):
        unknown = sorted(set(op_mode) - set(rec.names))
        if unknown:
            raise ConfigError(
                f"discrepancy.operating_point names {unknown}, which are not job signals "
                f"({list(rec.names)}); fix the names")
    dev = {name: seg[:, k] - op[name] for k, name in enumerate(rec.names)}
    inputs = {n: dev[n] for n, r in zip(rec.names, rec.roles) if r == "input"}
    measured = {n: dev[n] for n, r in zip(rec.names, rec.roles)
                if r == "output" and n in model.outputs}
    if op_mode != "none":
        given = op_mode if isinstance(op_mode, dict) else {}
        free = [o for o in measured if o not in given]
        for o, shift in _output_offsets_from_nominal(cfg, model, inputs, measured, free,
                                                     dt_s).items():
            measured[o] = measured[o] - shift
            op[o] += shift
    summary = {
        "grid_dt_s": rec.grid_dt_s, "dt_s": dt_s, "decimation": factor,
        "grid_samples": int(n_grid), "analysed_samples": int(b - a),
        "left_out_samples": int(n_grid - (b - a)),
        "filled_samples": {n: int(filled[a:b, k].sum()) for k, n in enumerate(rec.names)},
        "start_utc": str(t[a]) + "Z", "end_utc": str(t[b - 1]) + "Z",
        "operating_point": {"mode": op_mode if isinstance(op_mode, str) else "given",
                            "values": op},
        "quality": rec.quality,
    }
    return DiscrepancyData(inputs, measured, dt_s, t[a:b], op, summary, rec.files)


def core_config(cfg) -> DiscrepancyConfig:
    """The job's ``discrepancy`` core settings as the core's :class:`DiscrepancyConfig`.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    """
    settings = cfg.discrepancy.core_settings() if cfg.discrepancy is not None else {}
    return DiscrepancyConfig(**settings)


def free_outputs(cfg, measured) -> tuple[str, ...]:
    """The outputs measured from their mean (``discrepancy.operating_point``): their
    constant follows the model, profiled out of every prediction.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    measured : iterable of str
        The measured outputs, in order.
    """
    op_mode = cfg.discrepancy.operating_point if cfg.discrepancy is not None else "mean"
    return () if op_mode == "none" else tuple(
        o for o in measured if not (isinstance(op_mode, dict) and o in op_mode))


def check_job(cfg) -> tuple[Model, str]:
    """Validate a discrepancy job before any data is read: the model, its names, the
    core settings.  Returns :func:`load_discrepancy_model`'s ``(model, source)``.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (with its ``model:`` or ``discrepancy.simulator_outputs``).
    """
    model, source = load_discrepancy_model(cfg)
    core_config(cfg)
    return model, source


def analyse(cfg, model: Model, data: DiscrepancyData, *,
            progress: Progress = quiet) -> DiscrepancyResult:
    """Run the discrepancy core on the prepared data.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``discrepancy`` core settings and seed).
    model : Model
        The nominal model.
    data : DiscrepancyData
        The analysed stretch from :func:`prepare_discrepancy`.
    progress : callable (stage, message)
        Called at the start of each stage of the core.
    """
    seed = cfg.discrepancy.seed if cfg.discrepancy is not None else 0
    return analyse_discrepancy(model, inputs=data.inputs, measured=data.measured,
                               dt_s=data.dt_s, config=core_config(cfg), seed=seed,
                               progress=progress, clock=time.perf_counter,
                               free_offsets=free_outputs(cfg, data.measured))


def series_table(result: DiscrepancyResult) -> pl.DataFrame:
    """``discrepancy_series.parquet``: one row per (output, sample).

    Columns ``output``, ``time_s``, ``part`` (warmup | fit | holdout), ``measured``,
    ``nominal``, ``augmented``, ``residual_before``, ``residual_after``, ``rolling_rms``.

    Parameters
    ----------
    result : DiscrepancyResult
        The core's outcome (its ``series``).
    """
    s = result.series
    n = s.t_s.size
    part = np.full(n, "fit", dtype=object)
    part[: s.fit_start] = "warmup"
    part[s.holdout_start:] = "holdout"
    frames = []
    for out in s.measured:
        frames.append(pl.DataFrame({
            "output": [out] * n,
            "time_s": s.t_s.astype(float),
            "part": part.tolist(),
            "measured": s.measured[out], "nominal": s.nominal[out],
            "augmented": s.augmented[out], "residual_before": s.residual_before[out],
            "residual_after": s.residual_after[out], "rolling_rms": s.rolling_rms[out],
        }, schema={"output": pl.String, "time_s": pl.Float64, "part": pl.String,
                   **{c: pl.Float64 for c in ("measured", "nominal", "augmented",
                                              "residual_before", "residual_after",
                                              "rolling_rms")}}))
    return pl.concat(frames)


def augmented_model_document(result: DiscrepancyResult) -> dict:
    """``model_augmented.yaml`` content: the augmented model (+ ``measurement:``).

    Parameters
    ----------
    result : DiscrepancyResult
        The core's outcome (its augmented model and accepted effects).
    """
    doc = model_to_dict(result.augmented_model)
    measurement: dict[str, dict[str, float]] = {}
    for step in result.effects:  # every accepted effect's measurement-side part
        eff = step.candidate.effect
        if eff.is_sensor_correction:
            m = measurement.setdefault(eff.location, {"bias": 0.0, "drift_per_h": 0.0})
            m["bias"] += float(eff.parameters["bias"])
            m["drift_per_h"] += float(eff.parameters["drift_per_h"])
    if measurement:
        doc["measurement"] = measurement
    return doc


def resimulate_holdout_rms(doc: dict, data: DiscrepancyData, result: DiscrepancyResult,
                           ) -> dict[str, float]:
    """Held-out RMS of an augmented-model document re-simulated from scratch.

    An independent check that ``model_augmented.yaml`` reproduces the reported
    ``gap.holdout_rms_after`` (the run records both).  With loops the analysis opened
    (:attr:`DiscrepancyResult.opened_loops`) the document, loops closed, is opened at
    the same controllers and driven by their measured OPs, as the analysis compared it.

    Parameters
    ----------
    doc : dict
        An augmented-model document (:func:`augmented_model_document`).
    data : DiscrepancyData
        The analysed stretch (inputs, measured outputs, sample period).
    result : DiscrepancyResult
        The core's outcome (initial condition, hold-out start).
    """
    from pipeline.discrepancy.effects import predict_outputs

    model = model_from_dict({"model": doc["model"]}, max_blocks=None)
    opened = result.opened_loops
    inputs, measured = opened_signals(data.inputs, data.measured, opened)
    sim = predict_outputs(open_at(model, opened) if opened else model, None, inputs,
                          dt_s=data.dt_s, outputs=list(measured),
                          initial=result.config.initial)
    n = next(iter(measured.values())).size
    meas = doc.get("measurement") or {}
    offsets = {o: np.zeros(n) for o in measured}
    for o, p in meas.items():
        offsets[o] = p["bias"] + p["drift_per_h"] * np.arange(n) * data.dt_s / 3600.0
    h = result.series.holdout_start
    shift = result.operating_point_shift
    return {o: float(np.sqrt(np.mean((measured[o][h:] - shift.get(o, 0.0) - sim[o][h:]
                                      - offsets[o][h:]) ** 2)))
            for o in measured}


def write_discrepancy_run(cfg, model: Model, source: str, data: DiscrepancyData,
                          result: DiscrepancyResult, *, timings: dict[str, float],
                          run_id: str | None = None) -> tuple[str, Path, Path | None, dict]:
    """Write the run directory atomically (store) with its Rerun recording.

    Returns ``(run_id, run_dir, recording_path, discrepancy_json)``.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    model : Model
        The nominal model.
    source : str
        ``"model"`` or ``"external_simulator"`` (from :func:`load_discrepancy_model`).
    data : DiscrepancyData
        The analysed stretch.
    result : DiscrepancyResult
        The core's outcome.
    timings : dict of str to float
        Seconds per stage, recorded with the run.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    """
    from pipeline.adapters.config import dump_yaml
    from pipeline.adapters.store import ResultStore

    store = ResultStore(cfg.storage_root)
    doc = augmented_model_document(result)
    check = resimulate_holdout_rms(doc, data, result)
    reported = {o: v["holdout_rms_after"] for o, v in result.gap["per_output"].items()}
    body = result.to_dict()
    with store.new_run(cfg.job, run_id=run_id, config=cfg.model_dump(mode="json"),
                       inputs=list(data.files)) as run:
        for stage, sec in timings.items():
            run.record_timing(stage, sec)
        out = {"job": cfg.job, "run_id": run.run_id, "kind": "discrepancy",
               "model": model.name, "model_source": source,
               "inputs": list(data.inputs), "outputs": list(data.measured),
               "data": data.summary,
               "augmented_model_check": {"holdout_rms_resimulated": check,
                                         "holdout_rms_reported": reported},
               **body}
        run.write_json("discrepancy.json", out)
        header = (f"{cfg.job} run {run.run_id}: nominal model {model.name!r} "
                  f"+ {result.effect.describe() if result.effect else 'no effect'} "
                  f"(verdict {result.verdict}).\nRe-simulated held-out RMS {check}"
                  + (f", with the loop(s) of {', '.join(result.opened_loops)} opened and "
                     "driven by the measured OP as the analysis compared them"
                     if result.opened_loops else "") + ".")
        run.write_text("model_augmented.yaml", dump_yaml(doc, header=header))
        run.write_parquet("discrepancy_series.parquet", series_table(result))
        run.write_report(summary_markdown(out))
        run.set_status(result.verdict)
        from pipeline.adapters.html_report import add_report_html

        add_report_html(run, config=cfg.model_dump(mode="json"), inputs=list(data.files),
                        kind="discrepancy")
        metrics = []
        for o, pg in result.gap["per_output"].items():
            for key in ("holdout_rms_before", "holdout_rms_after", "reduction"):
                metrics.append({"window": "all", "output": o, "input": "model",
                                "metric": key, "value": pg[key]})
        metrics.append({"window": "all", "output": "model", "input": "model",
                        "metric": "verdict", "value": result.verdict})
        run.add_metrics(metrics)
        if cfg.rerun.enabled:
            from pipeline.adapters.rerun_sink import render_discrepancy

            t0 = time.perf_counter()
            render_discrepancy(run.path, ident=f"{cfg.job}/{run.run_id}")
            run.record_timing("rerun", time.perf_counter() - t0)
        rid = run.run_id
    run_dir = store.run_dir(cfg.job, rid)
    rrd = run_dir / "recording.rrd" if cfg.rerun.enabled else None
    return rid, run_dir, rrd, out


def finish_discrepancy(cfg, model: Model, source: str, data: DiscrepancyData,
                       result: DiscrepancyResult, timings: dict, *,
                       run_id: str | None = None) -> DiscrepancyReport:
    """Write the results and build the :class:`DiscrepancyReport` (the ``store`` stage).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    model : Model
        The nominal model.
    source : str
        ``"model"`` or ``"external_simulator"`` (from :func:`load_discrepancy_model`).
    data : DiscrepancyData
        The analysed stretch.
    result : DiscrepancyResult
        The core's outcome.
    timings : dict of str to float
        Seconds per stage so far, recorded with the run (the report's timings).
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    """
    rid, run_dir, rrd, _ = write_discrepancy_run(cfg, model, source, data, result,
                                                 timings=timings, run_id=run_id)
    return DiscrepancyReport(cfg.job, rid, run_dir, result.verdict, result.verdict,
                             None if result.effect is None else result.effect.to_dict(),
                             result.gap, data.dt_s, int(result.series.t_s.size), data.files,
                             rrd, result, timings,
                             # the report.md just written, not rendered a second time
                             (run_dir / "report.md").read_text(encoding="utf-8"))


def run_discrepancy(cfg, *, files: list[Path] | None = None, run_id: str | None = None,
                    progress: Progress = quiet,
                    stage: StageRunner | None = None) -> DiscrepancyReport:
    """Run a discrepancy job end to end: the one stage list of the discrepancy workflow.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    files : list of Path, optional
        Files to read; ``None`` resolves the job's ``source``.
    run_id : str, optional
        Id of the run directory; ``None`` lets the store choose one.
    progress : callable (stage, message)
        Told when each stage starts and ends; the core's own stages as
        ``analyse/<stage>``.
    stage : StageRunner, optional
        Runs each stage: in this process (default, ``--no-prefect``) or as Prefect tasks
        (``flows.common.TaskStages``, the ``discrepancy`` flow).
    """
    stage = stage if stage is not None else StageRunner(progress)
    rec = stage("ingest", load_recording, cfg, files)
    model, source = stage("model", load_discrepancy_model, cfg)
    data = stage("prepare", prepare_discrepancy, cfg, rec, model)
    progress("prepare", f"{data.summary['analysed_samples']} samples analysed")
    result = stage("analyse", analyse, cfg, model, data,
                   progress=lambda name, message: progress(f"analyse/{name}", message))
    progress("analyse", f"verdict {result.verdict}")
    report = stage("store", finish_discrepancy, cfg, model, source, data, result,
                   dict(stage.timings), run_id=run_id)
    report.timings_s.update(stage.timings)  # the store stage's own time
    return report
