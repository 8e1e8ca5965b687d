"""The estimation job's summary: per-pair results, checks.json, the tables and report.md."""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.identification.checks import (
    cross_correlation_check,
    ljung_box,
    window_agreement,
    windows_disagree,
)
from pipeline.identification.conditioning import as_masked_zero
from pipeline.errors import PipelineError
from pipeline.jobs.job_types import LongTable, Prepared, Summary, WindowFailure
from pipeline.estimation.prediction import innovations, residuals
from pipeline.identification.search import SearchResult
from pipeline.readouts.run_summary import RunSummary, gain_unit, signal_units
from pipeline.estimation.step_result import StepResponseEstimate, lag_times


_ABSOLUTE_TIMES = ("dead_time_s", "settling_time_s", "peak_time_s", "inverse_peak_time_s",
                   "apparent_delay_s")


def _characteristics(est: StepResponseEstimate, i: int, j: int) -> dict:
    """Characteristic quantities of one pair (``{"error": ...}`` when none can be read).

    The gain is the FIR model's own static gain, the final step ``step[n_p - 1]`` with
    its std (the frequency response at zero; one definition everywhere), and the rate
    of an integrating pair is the estimate's ``rate``.
    """
    from pipeline.readouts import characteristics as ch

    n = int(est.n_p[i, j])
    try:
        if est.integrating[i]:
            res = ch.integrating_characteristics(est.step[i, j, :n], dt_s=est.dt,
                                                 step_std=est.step_std[i, j, :n],
                                                 rate=float(est.rate[i, j]),
                                                 rate_std=float(est.rate_std[i, j]))
        else:
            res = ch.self_regulating_characteristics(
                est.step[i, j, :n], dt_s=est.dt, step_std=est.step_std[i, j, :n],
                gain=float(est.step[i, j, n - 1]), gain_std=float(est.step_std[i, j, n - 1]))
        out = res.to_dict()
        # characteristics.py puts step[0] at t = 0; our lag times are (l - 1/2) dt
        for key in _ABSOLUTE_TIMES:
            if isinstance(out.get(key), float) and np.isfinite(out[key]):
                out[key] += 0.5 * est.dt
        return out
    except PipelineError as exc:
        return {"error": str(exc)}


def _window_table(sr: SearchResult, window_results: list, time: np.ndarray
                  ) -> tuple[list, list]:
    """Per disjoint window its samples, time range, status and error; and the estimated
    windows with their labels."""
    labelled = [(f"w{k}", e) for k, e in enumerate(window_results)]
    status = [{"window": lab, "samples": list(map(int, sr.windows[k])),
               "time": _utc_span(time, *map(int, sr.windows[k])),
               "status": "failed" if isinstance(e, WindowFailure) else "ok",
               **({"error": e.error} if isinstance(e, WindowFailure) else {"n_d": int(e.n_d)})}
              for k, (lab, e) in enumerate(labelled)]
    return status, [(lab, e) for lab, e in labelled if not isinstance(e, WindowFailure)]


def _utc_span(time: np.ndarray, a: int, b: int) -> list[str]:
    """UTC times of the first and last sample of the slice ``[a, b)`` (ISO, ``Z``)."""
    t = np.asarray(time)
    return [str(np.datetime_as_string(t[k], unit="s")) + "Z" for k in (a, min(b, len(t)) - 1)]


def _step_table(ests: list[tuple[str, StepResponseEstimate]], outs, ins) -> pl.DataFrame:
    rows = []
    for label, est in ests:
        P = est.step.shape[2]
        t = lag_times(P, est.dt)
        for i, o in enumerate(outs):
            for j, u in enumerate(ins):
                n = int(est.n_p[i, j])
                rows.append(pl.DataFrame({
                    "window": [label] * n, "output": [o] * n, "input": [u] * n,
                    "lag": np.arange(1, n + 1, dtype=np.int32), "time_s": t[:n],
                    "delta_h": est.delta_h[i, j, :n], "step": est.step[i, j, :n],
                    "step_std": est.step_std[i, j, :n],
                    "n_p": np.full(n, n, dtype=np.int32),
                    "n_d": np.full(n, est.n_d, dtype=np.int32),
                    "dt_s": np.full(n, est.dt)}))
    return pl.concat(rows)


def _pair_metrics(o: str, u: str, pair: dict) -> list[dict]:
    """One row per metric of a pair (unique names: what the catalog trends)."""
    vals = {"gain": pair["gain"], "gain_std": pair["gain_std"], "rate": pair["rate"],
            "rate_std": pair["rate_std"],
            "agreement_statistic": pair["agreement"].get("statistic"),
            "agreement_p_value": pair["agreement"].get("p_value")}
    for k, v in pair["characteristics"].items():
        if k not in vals and isinstance(v, (int, float)) and not isinstance(v, bool):
            vals[k] = v
    return [{"window": "all", "output": o, "input": u, "metric": k, "value": float(v)}
            for k, v in vals.items() if v is not None and np.isfinite(v)]


def summarise(cfg, prep: Prepared, sr: SearchResult, all_est: StepResponseEstimate,
              window_results: list) -> Summary:
    """Tables, checks and the report of a run (pure: no I/O).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    prep : Prepared
        The conditioned record.
    sr : SearchResult
        The order search's outcome.
    all_est : StepResponseEstimate
        The estimate on every usable sample.
    window_results : list of StepResponseEstimate or WindowFailure
        One per ``sr.windows``, in order.
    """
    ins, outs = prep.inputs, prep.outputs
    window_status, labelled = _window_table(sr, window_results, prep.time)
    window_ests = [e for _, e in labelled]
    steps = _step_table([("all", all_est)] + labelled, outs, ins)
    agreement = window_agreement(window_ests, all_est) if len(window_ests) >= 2 else \
        [[None] * len(ins) for _ in outs]
    x0, res, innov = _residual_series(prep, all_est)
    config = cfg.model_dump(mode="json")  # the resolved job, as the run's manifest holds it
    units = signal_units(config, prep.recording.quality)
    pairs, metrics, whiteness, xcorr = _pairs(cfg, prep, sr, all_est, agreement,
                                              len(window_ests), x0, innov, units)
    checks = _checks(cfg, prep, sr, all_est, window_status, pairs, whiteness, xcorr)
    # the run's status is the plant-level answer (checks.windows_disagree), the
    # question the search's N_d stopping rule asks; the pairs' verdicts keep their rates
    status = "windows_disagree" if windows_disagree(agreement) else "ok"
    report = RunSummary.from_checks(checks, job=cfg.job, status=status, config=config)
    return Summary(steps, _signals_table(prep), _residuals_table(prep, res), metrics, report)


def _residual_series(prep: Prepared, all_est: StepResponseEstimate):
    """The gap-filled inputs, and the residuals and one-step prediction errors of the
    all-data estimate (NaN where any sample they need is masked)."""
    x0, y0 = as_masked_zero(prep.x), as_masked_zero(prep.y)
    bad = ~prep.good_xy.all(axis=1)
    P = int(all_est.n_p.max())
    touched = np.convolve(bad.astype(float), np.ones(P + 1))[: bad.size] > 0
    res = residuals(all_est, x0, y0)
    res[touched] = np.nan
    innov = innovations(all_est, x0, y0, good=~touched)
    return x0, res, innov


def _pairs(cfg, prep: Prepared, sr: SearchResult, all_est: StepResponseEstimate,
           agreement: list, n_windows: int, x0: np.ndarray, innov: np.ndarray,
           units: dict):
    """Per pair its results, warnings and metric rows; per output the whiteness of its
    prediction errors; per pair the input cross-correlation check (``units``: per signal,
    :func:`pipeline.readouts.run_summary.signal_units`)."""
    from pipeline.readouts.lti_fit import model_record, reported_model
    from pipeline.identification.verdicts import end_jump_z, pair_warnings

    ins, outs = prep.inputs, prep.outputs
    tags = cfg.tags()
    pairs = []
    metrics = []
    xcorr = {}
    whiteness = {}
    for i, o in enumerate(outs):
        lb = ljung_box(innov[:, i], lags=cfg.checks.ljung_box_lags)
        whiteness[o] = {k: lb[k] for k in ("statistic", "p_value", "lags", "white")}
        whiteness[o]["of"] = "residuals" if all_est.noise_model[i].order == 0 and \
            all_est.noise_model[i].form != "level" else "prediction errors (noise model)"
        nm = all_est.noise_model[i].to_dict()
        for j, u in enumerate(ins):
            n = int(all_est.n_p[i, j])
            a = agreement[i][j]
            agr = a.to_dict() if a is not None else {
                "statistic": None, "p_value": None, "verdict": "insufficient_data",
                "n_windows": n_windows}
            xc = cross_correlation_check(x0[:, j], innov[:, i],
                                         max_lag=cfg.checks.xcorr_max_lag or n)
            xcorr[f"{o}<-{u}"] = {k: xc[k] for k in ("band", "fraction_outside", "max_abs_r",
                                                     "statistic", "p_value", "ok")}
            chars = _characteristics(all_est, i, j)
            fb = sr.feedback[i][j] if sr.feedback else None
            fbd = fb.to_dict() if fb is not None else None
            integ = bool(all_est.integrating[i])
            st = _settledness(sr, all_est, i, j, gain_unit(units, o, u))
            final, final_std = _reported(st, integ, all_est, i, j)
            pair = {"output": o, "input": u, "n_p": n, "n_k": int(all_est.n_k[i, j]),
                    "settled": {"verdict": st.verdict, "tail_sum": _num(st.tail_sum),
                                "tail_sum_std": _num(st.tail_sum_std),
                                "tail_lags": st.tail_lags, "left_out": _num(st.left_out),
                                "left_out_std": _num(st.left_out_std)},
                    "integrating": integ,
                    "gain": None if integ else final,
                    "gain_std": None if integ else final_std,
                    "gain_extrapolated": None if integ else st.gain_extrapolated,
                    "sign_established": st.sign_established,
                    "gain_note": st.note,
                    "rate": final if integ else None,
                    "rate_std": final_std if integ else None,
                    "rate_extrapolated": st.gain_extrapolated if integ else None,
                    "peak": None if integ else float(np.max(np.abs(all_est.step[i, j, :n]))),
                    "method": all_est.method,
                    "agreement": agr, "feedback": fbd, "characteristics": chars}
            # the transfer function the export writes, fitted once here (one rule:
            # lti_fit.reported_model; the export and report.html read this record)
            pair["transfer_function"] = model_record(reported_model(
                all_est.step[i, j, :n], dt_s=all_est.dt, step_std=all_est.step_std[i, j, :n],
                integrating=integ, value=final, std=final_std, pair=f"{o}<-{u}",
                settled=st.verdict))
            if chars.get("gain") is not None and not integ:
                # characteristics read the curve at the horizon; the reported gain (and
                # its σ) is the settledness verdict's — one number everywhere
                chars["gain"], chars["gain_std"] = final, final_std
            pair["warnings"] = pair_warnings(
                inp=u, out=o, tag_in=tags[u], tag_out=tags[o], noise=cfg.estimation.noise,
                noise_model=nm, whiteness_p=lb["p_value"], feedback=fbd,
                feedback_mode=cfg.estimation.feedback, instruments=prep.instruments,
                n_k=pair["n_k"], n_p=n, n_p_min=cfg.search.n_p_min,
                settled=bool(sr.settled[i, j]) or st.verdict == "moving",
                significant=_significant(pair), dt_s=prep.dt_s,
                end_jump=end_jump_z(*_settling_increments(all_est, i, j)),
                agreement=agr)
            if st.verdict == "moving":
                pair["warnings"].insert(0, {"code": "not_settled", "message": st.note})
            pairs.append(pair)
            metrics += _pair_metrics(o, u, pair)
    return pairs, metrics, whiteness, xcorr


def _checks(cfg, prep: Prepared, sr: SearchResult, all_est: StepResponseEstimate,
            window_status: list, pairs: list, whiteness: dict, xcorr: dict) -> dict:
    """The run's checks.json document."""
    ins, outs = prep.inputs, prep.outputs
    tags = cfg.tags()
    d = all_est.diagnostics
    return {
        "dt_s": prep.dt_s,
        "sampling": prep.sampling,
        "conditioning": prep.conditioning,
        "estimation": {"method": all_est.method, "noise": cfg.estimation.noise,
                       "method_choice": _method_choice(cfg, sr, prep).to_dict(),
                       "feedback": cfg.estimation.feedback,
                       "instruments": {r: tags[r] for r in prep.instruments},
                       **({"first_stage": {ins[k]: v for k, v in
                                           all_est.extra["first_stage"].items()
                                           if k < len(ins)}}
                          if "first_stage" in all_est.extra else {}),
                       **({"hyperparameters": dict(zip(outs,
                                                       all_est.extra["hyperparameters"]))}
                          if "hyperparameters" in all_est.extra else {})},
        "noise_model": {o: all_est.noise_model[i].to_dict() for i, o in enumerate(outs)},
        "search": {
            "n_p": {f"{outs[i]}<-{ins[j]}": int(sr.n_p[i, j])
                    for i in range(len(outs)) for j in range(len(ins))},
            "n_k": {f"{outs[i]}<-{ins[j]}": int(all_est.n_k[i, j])
                    for i in range(len(outs)) for j in range(len(ins))},
            "n_d": sr.n_d, "window_samples": sr.window_samples,
            "windows": window_status,
            "bic_order": None if sr.bic_order is None else
            {outs[i]: int(v) for i, v in enumerate(sr.bic_order)},
            "noise_model_at_n_p_max": {outs[i]: m.to_dict()
                                       for i, m in enumerate(sr.noise_model)},
            "order_trace": _named_trace(sr.order_trace, outs, ins),
            "nd_trace": _named_trace(sr.nd_trace, outs, ins, prep.time),
        },
        "pairs": pairs,
        "residuals": {
            "whiteness": whiteness,
            "input_cross_correlation": xcorr,
        },
        "excitation": {
            "condition_number": d.condition_number,
            "input_rms": {u: float(v) for u, v in zip(ins, d.input_rms)},
            "input_correlation": {ins[a]: {ins[b]: float(d.input_correlation[a, b])
                                           for b in range(len(ins))} for a in range(len(ins))},
            "vif": {u: float(v) for u, v in zip(ins, d.vif)},
            "near_collinear": [{"inputs": [ins[a], ins[b]], "correlation": c}
                               for a, b, c in d.near_collinear],
        },
        "data_quality": {
            "grid_dt_s": prep.recording.grid_dt_s,
            "samples_at_dt": int(prep.good.shape[0]),
            "samples_used_all": int(all_est.n_d),
            "signals": prep.recording.quality,
            "ingest": prep.recording.ingest,
        },
    }


def _residuals_table(prep: Prepared, res: np.ndarray) -> LongTable:
    """The residuals table (long form, an output at a time; rows where lags touch a gap
    left out)."""
    outs, n = prep.outputs, res.shape[0]

    def make(rows: int):
        for i, o in enumerate(outs):
            for a in range(0, n, rows):
                b = min(a + rows, n)
                yield pl.DataFrame({
                    "window": pl.repeat("all", b - a, dtype=pl.String, eager=True),
                    "time": prep.time[a:b],
                    "output": pl.repeat(o, b - a, dtype=pl.String, eager=True),
                    "residual": res[a:b, i]}).with_columns(
                        pl.col("time").cast(pl.Datetime("us", "UTC"))).filter(
                            pl.col("residual").is_not_nan())  # undefined where lags touch a gap

    return LongTable(n * len(outs), make)


def _settling_increments(est: StepResponseEstimate, i: int, j: int):
    """The increments that must die out and their stds: ``delta_h`` for a self-regulating
    pair, ``delta_g`` (the change of slope) for an integrating one — from the step
    covariance, so a level-form pair's precise final slope is compared with the noisy
    transient slopes before it as a difference, not as a value."""
    n = int(est.n_p[i, j])
    D = np.eye(n) - np.eye(n, k=-1)
    T = D @ D if est.integrating[i] else D
    inc = T @ est.step[i, j, :n]
    if est.step_cov is None:
        return inc, (est.delta_h_std[i, j, :n] if not est.integrating[i] else
                     np.full(n, np.inf))
    var = np.einsum("ab,bc,ac->a", T, est.step_cov[i, j, :n, :n], T)
    return inc, np.sqrt(np.clip(var, 0, None))


def _significant(pair: dict) -> bool:
    """The pair's gain (rate) is more than 2 standard deviations from zero."""
    v, s = (pair["rate"], pair["rate_std"]) if pair["integrating"] else \
        (pair["gain"], pair["gain_std"])
    return v is not None and bool(abs(v) > 2 * s)


def _method_choice(cfg, sr: SearchResult, prep: Prepared):
    from pipeline.jobs.estimation import method_choice

    return method_choice(cfg, sr, prep.x.shape[0])


def _settledness(sr: SearchResult, est: StepResponseEstimate, i: int, j: int, unit: str):
    """The pair's :func:`pipeline.identification.settledness.settledness` with what its horizon leaves
    out in the search's reference fit."""
    from pipeline.identification.settledness import settledness

    # what the search's horizon leaves out; an estimate at another horizon (the
    # regularised one, longer) has no measured left-out part
    same = int(est.n_p[i, j]) == int(sr.n_p[i, j])
    lo = 0.0 if sr.left_out is None or not same else float(sr.left_out[i, j])
    lo_std = 0.0 if sr.left_out_std is None or not same else float(sr.left_out_std[i, j])
    return settledness(est, i, j, left_out=lo, left_out_std=lo_std, unit=unit)


def _reported(st, integrating: bool, est: StepResponseEstimate, i: int, j: int
              ) -> tuple[float | None, float | None]:
    """The reported gain and its σ including what the horizon leaves out (an integrating
    pair: the estimate's rate and its own σ, :func:`pipeline.identification.settledness.left_out_of`), or
    ``(None, None)`` when the pair has none (moving, nothing to judge)."""
    if st.gain is None:
        return None, None
    if integrating:
        return float(est.rate[i, j]), float(est.rate_std[i, j])
    return float(st.gain), float(st.gain_std)


def _num(v: float) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def _named_trace(trace: list, outs: list[str], ins: list[str],
                 time: np.ndarray | None = None) -> list:
    """The search's trace with signal names for indices (and, given the record's time,
    the UTC span of a window that could not be estimated)."""
    out = []
    for t in trace:
        t = dict(t)
        if time is not None and "failed_window" in t:
            t["failed_window_time"] = _utc_span(time, *map(int, t["failed_window"]))
        for key in ("pairs", "uninformative"):  # per pair: a trial's, a skipped one's
            if key in t:
                t[key] = [{**p, "output": outs[p["output"]], "input": ins[p["input"]]}
                          for p in t[key]]
        out.append(t)
    return out


def _signals_table(prep: Prepared) -> LongTable:
    """The signals table (long form, a signal at a time, in chunks)."""
    rec = prep.recording
    blocks = [prep.x, prep.y] + ([prep.r] if prep.r is not None else [])
    columns = [(blk, j) for blk in blocks for j in range(blk.shape[1])]  # conditioned, by signal
    n = prep.time.size

    def make(rows: int):
        for k, (name, role) in enumerate(zip(rec.names, rec.roles)):
            blk, j = columns[k]
            for a in range(0, n, rows):
                b = min(a + rows, n)
                yield pl.DataFrame({
                    "time": prep.time[a:b],
                    "signal": pl.repeat(name, b - a, dtype=pl.String, eager=True),
                    "role": pl.repeat(role, b - a, dtype=pl.String, eager=True),
                    "raw": prep.raw[a:b, k], "conditioned": blk[a:b, j],
                    "good": prep.good[a:b, k]}).with_columns(
                        pl.col("raw").fill_nan(None), pl.col("conditioned").fill_nan(None),
                        pl.col("time").cast(pl.Datetime("us", "UTC")))

    return LongTable(n * len(rec.names), make)
