"""Localisation: which signal, which lags, which frequency band, which period explains the residual."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import scipy.fft
import scipy.optimize
import scipy.signal

from pipeline.discrepancy.effects import Effect
from pipeline.discrepancy.problem import Problem
from pipeline.errors import ConfigError, DataQualityError, PipelineError, SingularSystemError
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.estimation.prediction import residuals as fir_residuals
from pipeline.models.simulate import simulate

RELEVANCE_ALPHA = 0.05
"""Level of the circular-shift relevance test (:func:`input_relevance`): a signal with a
smaller p-value is ``significant`` for an output and in its ``explained_by``; an effect
whose measured source is not (``Effect.measured_source``) does not pass the selection
(:func:`corroborated`)."""


def lag_filter(x: np.ndarray, tau_samples: float) -> np.ndarray:
    """ZOH first-order lag (unit gain, strictly proper) of x along axis 0.

    Parameters
    ----------
    x : ndarray
        Signal(s), time along axis 0: (N,) or (N, m).
    tau_samples : float
        Time constant, in samples (pole ``exp(-1 / tau_samples)``).
    """
    a = math.exp(-1.0 / tau_samples)
    return scipy.signal.lfilter([0.0, 1.0 - a], [1.0, -a], x, axis=0)


def _bank(x: np.ndarray, taus: Sequence[float]) -> np.ndarray:
    """Columns: x and its unit-gain lags with time constants `taus` (samples)."""
    return np.column_stack([x] + [lag_filter(x, t) for t in taus])


def input_relevance(P: Problem, resid: np.ndarray, signals: list[str], start: int,
                    rng: np.random.Generator) -> dict[str, dict[str, float]]:
    """Partial statistic per signal and circular-shift bootstrap p-value.

    The residual (after removing mean and trend) is regressed on a bank of each
    signal's filtered versions (the signal and 4 unit-gain lags, time constants from 2
    samples to half the settling time).  The statistic of signal j is the relative
    drop of the residual sum of squares when j's columns join the others (a partial
    R², scaled by N).  Its null distribution comes from shifting j's columns circularly
    by a random offset (10-90 % of the record): this is a block bootstrap with one cut
    that keeps the autocorrelation of both the residual and the signal but breaks their
    alignment, which a naive F test on autocorrelated data would not.

    Parameters
    ----------
    P : Problem
        Validated signals and split.
    resid : ndarray (N,)
        One output's residual, full record.
    signals : list of str
        The candidate signals (model inputs and extra signals).
    start : int
        First analysed sample.
    rng : numpy.random.Generator
        Random offsets of the circular shifts.
    """
    n_s = P.settling_s / P.dt_s
    taus = np.geomspace(2.0, max(3.0, n_s / 2), 4)
    r = resid[start:]
    n = r.size
    t = np.linspace(-1, 1, n)
    trend = np.column_stack([np.ones(n), t])
    blocks = []
    for name in signals:
        x = P.inputs[name]
        blocks.append(_bank(x - x.mean(), taus)[start:])
    x_all = np.column_stack([trend] + blocks)
    m = blocks[0].shape[1]
    gram = x_all.T @ x_all
    cross = x_all.T @ r
    rr = float(r @ r)

    def rss(g: np.ndarray, c: np.ndarray) -> float:
        try:
            sol = np.linalg.solve(g + 1e-12 * np.trace(g) / len(g) * np.eye(len(g)), c)
        except np.linalg.LinAlgError:
            return rr
        return max(rr - float(c @ sol), 1e-300)

    rss_full = rss(gram, cross)
    out: dict[str, dict[str, float]] = {}
    for j, name in enumerate(signals):
        cols = np.arange(2 + j * m, 2 + (j + 1) * m)
        keep = np.setdiff1d(np.arange(x_all.shape[1]), cols)
        rss_without = rss(gram[np.ix_(keep, keep)], cross[keep])
        stat = n * (rss_without - rss_full) / rss_full
        exceed = 0
        for _ in range(P.config.n_bootstrap):
            shift = int(rng.integers(n // 10, 9 * n // 10))
            xs = np.roll(blocks[j], shift, axis=0)
            g = gram.copy()
            c = cross.copy()
            g_cross = x_all.T @ xs
            g[:, cols] = g_cross
            g[cols, :] = g_cross.T
            g[np.ix_(cols, cols)] = xs.T @ xs
            c[cols] = xs.T @ r
            s_b = n * (rss_without - rss(g, c)) / rss(g, c)
            exceed += s_b >= stat
        out[name] = {
            "partial_r2": float((rss_without - rss_full) / max(rss_without, 1e-300)),
            "statistic": float(stat),
            "p_value": float((1 + exceed) / (1 + P.config.n_bootstrap)),
        }
    return out


def _change_points(series: np.ndarray, max_points: int = 3, min_seg: int = 3,
                   threshold: float = 4.0) -> list[int]:
    """Binary segmentation for level shifts in a short series (block statistics).

    The noise scale is the median absolute difference of neighbours (robust to the
    shifts themselves); a split is kept when the two-sample t statistic exceeds
    `threshold`.  Hand-written: scipy has no change-point detection.
    """
    s = np.asarray(series, dtype=float)
    scale = 1.4826 * float(np.median(np.abs(np.diff(s)))) / math.sqrt(2) if s.size > 2 else 0.0
    if not scale > 0:
        return []
    found: list[int] = []

    def split(lo: int, hi: int) -> None:
        if len(found) >= max_points or hi - lo < 2 * min_seg:
            return
        best, best_k = 0.0, -1
        for k in range(lo + min_seg, hi - min_seg + 1):
            a, b = s[lo:k], s[k:hi]
            t = abs(a.mean() - b.mean()) / (scale * math.sqrt(1 / a.size + 1 / b.size))
            if t > best:
                best, best_k = t, k
        if best > threshold:
            found.append(best_k)
            split(lo, best_k)
            split(best_k, hi)

    split(0, s.size)
    return sorted(found)


def _fir_signals(P: Problem, signals: list[str], x: np.ndarray, r: np.ndarray
                 ) -> tuple[list[str], dict[str, list[str]]]:
    """Signals the residual FIR regression can use jointly, and those left out.

    All signals when their lagged normal equations are regular (the usual case).
    Otherwise (e.g. an external simulator's recorded output is a linear filter of a
    recorded plant input) signals join greedily, model inputs first, and a signal that
    makes the system singular is left out and reported as collinear with those kept.
    """
    try:
        estimate_step_responses(x, r, n_p=P.n_p, dt=P.dt_s)
        return list(signals), {}
    except SingularSystemError:
        pass
    order = [s for s in signals if s in P.model.inputs] + \
        [s for s in signals if s not in P.model.inputs]
    kept: list[str] = []
    left: dict[str, list[str]] = {}
    for name in order:
        trial = kept + [name]
        try:
            estimate_step_responses(x[:, [signals.index(s) for s in trial]], r, n_p=P.n_p,
                                    dt=P.dt_s)
            kept = trial
        except SingularSystemError:
            left[name] = list(kept)
    return [s for s in signals if s in kept], left


class _FirFit(NamedTuple):
    """Detrended fit-part data and the residual FIR regression shared by the per-output stages."""

    start: int
    signals: list[str]
    n: int
    trend: np.ndarray
    r_all: np.ndarray
    fir_signals: list[str]
    collinear: dict[str, list[str]]
    est: Any
    fir_res: np.ndarray


class _Spectra(NamedTuple):
    """Model step responses and the frequency grid / band edges of the band comparison."""

    model_step: dict[str, dict[str, np.ndarray]]
    nfft: int
    freqs: np.ndarray
    edges: np.ndarray


def _fir_fit(P: Problem, resid: np.ndarray) -> _FirFit:
    """Detrend signals and residual on the fit part and regress the residual on FIR lags."""
    start = P.fit_start
    signals = list(P.inputs)
    x = np.column_stack([P.inputs[s] for s in signals])[start:]
    n = x.shape[0]
    t = np.linspace(-1.0, 1.0, n)
    trend = np.column_stack([np.ones(n), t])
    # Remove mean and trend from every series (Frisch-Waugh: the FIR coefficients are
    # then those of a regression that includes the trend terms).
    proj = lambda z: z - trend @ np.linalg.lstsq(trend, z, rcond=None)[0]  # noqa: E731
    x_d = proj(x)
    r_all = resid[start:]
    r_d = proj(r_all)
    fir_signals, collinear = _fir_signals(P, signals, x_d, r_d)
    cols = [signals.index(s) for s in fir_signals]
    try:
        est = estimate_step_responses(x_d[:, cols], r_d, n_p=P.n_p, dt=P.dt_s)
        fir_res = fir_residuals(est, x_d[:, cols], r_d)
    except PipelineError as exc:
        raise DataQualityError(
            f"discrepancy localisation: the residual FIR regression failed ({exc}); the "
            "inputs do not excite the model enough or are collinear"
        ) from None
    return _FirFit(start, signals, n, trend, r_all, fir_signals, collinear, est, fir_res)


def _spectra(P: Problem) -> _Spectra:
    """Model step responses (per model input) for the frequency comparison, and the bands."""
    model_step = {}
    for name in P.model.inputs:
        u = {k: (np.ones(P.n_p) if k == name else np.zeros(P.n_p)) for k in P.model.inputs}
        sim = simulate(P.model, u, dt_s=P.dt_s)
        model_step[name] = {o: sim.signals[o] for o in P.outputs}
    nfft = int(scipy.fft.next_fast_len(8 * P.n_p))
    freqs = np.fft.rfftfreq(nfft, d=P.dt_s)
    f_lo, f_hi = 1.0 / (P.n_p * P.dt_s), 0.5 / P.dt_s
    edges = np.geomspace(f_lo, f_hi, 5)
    return _Spectra(model_step, nfft, freqs, edges)


def _frequency_bands(h_model: np.ndarray, dh: np.ndarray, sp: _Spectra) -> list[dict[str, float]]:
    """Mean |H| of the model and of the data (model + discrepancy) per frequency band."""
    hm = np.abs(np.fft.rfft(h_model, sp.nfft))
    hd = np.abs(np.fft.rfft(h_model + dh, sp.nfft))
    hr = np.abs(np.fft.rfft(dh, sp.nfft))
    bands = []
    for lo, hi in zip(sp.edges[:-1], sp.edges[1:], strict=True):
        sel = (sp.freqs >= lo) & (sp.freqs < hi)
        m_mean = float(hm[sel].mean()) if sel.any() else float("nan")
        bands.append({
            "f_lo_hz": float(lo), "f_hi_hz": float(hi),
            "model_gain": m_mean,
            "data_gain": float(hd[sel].mean()) if sel.any() else float("nan"),
            "relative_difference": (float(hr[sel].mean()) / m_mean
                                    if sel.any() and m_mean > 0 else float("nan")),
        })
    return bands


def _signal_entry(P: Problem, ff: _FirFit, sp: _Spectra, rel: dict[str, dict[str, float]],
                  i: int, out: str, name: str) -> dict[str, Any]:
    """Localisation entry of signal `name` for output `out` (index `i`)."""
    if name not in ff.fir_signals:  # left out of the FIR regression (collinear)
        entry = dict(rel[name])
        entry.update(significant=bool(rel[name]["p_value"] < RELEVANCE_ALPHA),
                     first_significant_lag_s=None, peak_lag_s=None,
                     significant_lags=0, discrepancy_step_final=None,
                     discrepancy_step_final_std=None,
                     fir_left_out=f"collinear with {ff.collinear[name]}")
        return entry
    est = ff.est
    j = ff.fir_signals.index(name)
    dh = est.delta_h[i, j]
    sd = est.delta_h_std[i, j]
    z = np.abs(dh) / np.where(sd > 0, sd, np.inf)
    sig_lags = np.flatnonzero(z > 3.0)
    entry = dict(rel[name])
    entry.update(
        significant=bool(rel[name]["p_value"] < RELEVANCE_ALPHA),
        first_significant_lag_s=(float(sig_lags[0] * P.dt_s) if sig_lags.size else None),
        peak_lag_s=float(np.argmax(np.abs(dh)) * P.dt_s),
        significant_lags=int(sig_lags.size),
        discrepancy_step_final=float(est.step[i, j, -1]),
        discrepancy_step_final_std=float(est.step_std[i, j, -1]),
    )
    if name in sp.model_step:
        h_model = np.diff(sp.model_step[name][out], prepend=0.0)
        bands = _frequency_bands(h_model, dh, sp)
        worst = max(bands, key=lambda b: -1 if math.isnan(b["relative_difference"])
                    else b["relative_difference"])
        entry["frequency_bands"] = bands
        entry["band_of_largest_discrepancy_hz"] = [worst["f_lo_hz"], worst["f_hi_hz"]]
        entry["model_step_final"] = float(sp.model_step[name][out][-1])
        entry["data_step_final"] = float(sp.model_step[name][out][-1] + est.step[i, j, -1])
    return entry


def _time_windows(P: Problem, ff: _FirFit, resid: np.ndarray, i: int, window: int
                  ) -> tuple[np.ndarray, dict[str, Any]]:
    """Rolling RMS of output `i`'s residual and its block RMS / change points summary."""
    start = ff.start
    # time windows: block RMS and change points of block mean / block RMS
    e = resid[:, i]
    kernel = np.ones(window) / window
    rolling = np.sqrt(np.convolve(e**2, kernel, mode="same"))
    nb = ff.n // window
    blocks = ff.r_all[: nb * window, i].reshape(nb, window)
    b_mean = blocks.mean(axis=1)
    b_rms = np.sqrt((blocks**2).mean(axis=1))
    cp_mean = _change_points(b_mean)
    cp_level = _change_points(np.log(b_rms + 1e-300))
    med = float(np.median(b_rms))
    return rolling, {
        "window_s": float(window * P.dt_s),
        "block_rms": [float(v) for v in b_rms],
        "block_mean": [float(v) for v in b_mean],
        "high_rms_windows_s": [
            [float((start + k * window) * P.dt_s), float((start + (k + 1) * window) * P.dt_s)]
            for k in np.flatnonzero(b_rms > 1.5 * med)
        ],
        "mean_change_points_s": [float((start + k * window) * P.dt_s) for k in cp_mean],
        "level_change_points_s": [float((start + k * window) * P.dt_s) for k in cp_level],
    }


def _load_bins(P: Problem, ff: _FirFit, i: int) -> tuple[str, list[dict[str, Any]]]:
    """Load signal and residual mean / RMS of output `i` per load-quantile bin."""
    signals = ff.signals
    load_name = P.config.load_signal or (P.model.inputs[0] if P.model.inputs else signals[0])
    if load_name not in P.inputs:
        raise ConfigError(
            f"discrepancy.load_signal={load_name!r} is not a measured signal; choose one "
            f"of {signals}"
        )
    load = P.inputs[load_name][ff.start:]
    q = np.quantile(load, np.linspace(0, 1, P.config.n_load_bins + 1))
    idx = np.clip(np.searchsorted(q, load, side="right") - 1, 0, P.config.n_load_bins - 1)
    bins = []
    for b in range(P.config.n_load_bins):
        sel = idx == b
        if not sel.any():
            continue
        eb = ff.r_all[sel, i]
        bins.append({"load_lo": float(q[b]), "load_hi": float(q[b + 1]), "n": int(sel.sum()),
                     "mean": float(eb.mean()), "rms": float(np.sqrt(np.mean(eb**2)))})
    return load_name, bins


def _localise_output(P: Problem, ff: _FirFit, sp: _Spectra, resid: np.ndarray, i: int,
                     out: str, rel: dict[str, dict[str, float]], window: int
                     ) -> tuple[dict[str, Any], np.ndarray]:
    """Localisation dict and rolling RMS of output `out` (index `i`)."""
    start, r_all, n = ff.start, ff.r_all, ff.n
    per_signal = {name: _signal_entry(P, ff, sp, rel, i, out, name) for name in ff.signals}
    # trend terms of the residual (mean and drift over the record)
    coef = np.linalg.lstsq(ff.trend, r_all[:, i], rcond=None)[0]
    duration_h = n * P.dt_s / 3600.0
    rolling, time_windows = _time_windows(P, ff, resid, i, window)
    # operating range
    load_name, bins = _load_bins(P, ff, i)
    rms_bins = [b["rms"] for b in bins]
    total_rms = float(np.sqrt(np.mean(r_all[:, i] ** 2)))
    return {
        "residual_rms": total_rms,
        "residual_mean": float(r_all[:, i].mean()),
        "measured_std": float(np.std(P.y[start:, i])),
        "relative_residual": total_rms / max(float(np.std(P.y[start:, i])), 1e-300),
        # over the samples the FIR fit predicts (its warm-up and gaps are NaN, not zero)
        "fir_residual_rms": float(np.sqrt(np.nanmean(ff.fir_res[:, i] ** 2)))
        if np.isfinite(ff.fir_res[:, i]).any() else float("nan"),
        "signals": per_signal,
        "explained_by": [s for s, v in sorted(rel.items(), key=lambda kv: kv[1]["p_value"])
                         if v["p_value"] < RELEVANCE_ALPHA],
        "lags_n_p": P.n_p,
        "trend": {"mean": float(coef[0]),
                  "drift_per_h": float(2 * coef[1] / duration_h) if duration_h > 0 else 0.0},
        "time_windows": time_windows,
        "operating_range": {
            "load_signal": load_name,
            "bins": bins,
            "rms_spread": (max(rms_bins) - min(rms_bins)) / max(total_rms, 1e-300)
            if rms_bins else 0.0,
        },
    }, rolling


def localise(P: Problem, resid: np.ndarray, rng: np.random.Generator
              ) -> tuple[dict[str, Any], list[np.ndarray], dict[str, np.ndarray]]:
    """Localisation per output; returns (dict, noise residual per output, rolling RMS).

    The noise residual, which the noise model is fitted on, is the residual's FIR
    regression on the inputs less the measured OPs of opened loops (``P.opened_loops``).
    From the method (§10): driven by a measured OP the direct method is consistent
    only when the noise model is right, and an OP carries the
    controller's answer to the noise's past; regressed on it, the residual loses the
    part of the unmeasured disturbance the controller fed back, the noise model comes
    out too small and too white, and a gain that cancels that feedback looks like a
    discrepancy.  On a zoo heat-exchanger null (seed 8 638 003, opened) the exchanger's
    gain 0.87 had a whitened BIC gain of 2 617 with the OP in the regression and -3.6
    without it (factor 0.976).

    Parameters
    ----------
    P : Problem
        Validated signals, nominal simulation and split; only samples from
        ``P.fit_start`` on are analysed (the noise model is not used).
    resid : ndarray (N, n_y)
        Residual: measured minus nominal simulated outputs, full record.
    rng : numpy.random.Generator
        Random offsets of the circular-shift bootstrap.
    """
    ff = _fir_fit(P, resid)
    noise_res = ff.fir_res
    if P.opened_loops:
        exogenous = {k: v for k, v in P.inputs.items() if k not in P.opened_loops}
        noise_res = _fir_fit(dataclasses.replace(P, inputs=exogenous), resid).fir_res
    sp = _spectra(P)
    window = max(P.n_p, ff.n // 40)
    rolling: dict[str, np.ndarray] = {}
    loc: dict[str, Any] = {}
    fir_out = []
    for i, out in enumerate(P.outputs):
        rel = input_relevance(P, resid[:, i], ff.signals, ff.start, rng)
        fir_out.append(np.nan_to_num(noise_res[:, i]))
        loc[out], rolling[out] = _localise_output(P, ff, sp, resid, i, out, rel, window)
    return loc, fir_out, rolling


def corroborated(effect: Effect, localization: dict[str, Any]) -> bool:
    """Whether an effect may pass the statistical tests at all: always, unless it names
    a measured signal driving an output (``Effect.measured_source``) that localisation's
    circular-shift test did not find relevant to that output at
    :data:`RELEVANCE_ALPHA`.  One that is not counts as
    failed, so with the best BIC it makes the verdict ``no_significant_effect``
    (:func:`pipeline.discrepancy.select.decide`).

    Neither acceptance path has the right null for such a claim.  The plain test's block
    bootstrap of held-out errors treats blocks as exchangeable, which a slow unmeasured
    disturbance is not over a hold-out of a few of its time constants; the whitened BIC
    and held-out z compare fits of a lag of the signal that can follow the same
    disturbance by chance in both parts of the record.  On fresh zoo nulls three false
    alarms were such inputs: recycle flow -> composition in the blend (seed 8 508 019,
    plain test only, whitened BIC -28, relevance p 0.66), agitator power ->
    cooling-water flow (8 508 007, plain only, BIC +6.8, p 0.44) and bypass flow ->
    outlet temperature with a 1 152 s lag (8 618 010, both paths, BIC +104, p 0.96).
    The circular-shift test asks the claim's own question with a null that keeps both
    signals' autocorrelation; every true unmodelled input of the fresh zoo trials
    8 607 000 had p 0.01, its floor.

    Parameters
    ----------
    effect : Effect
        The candidate's effect.
    localization : dict
        :func:`pipeline.discrepancy.localise.localise`'s result (per output, per signal
        ``p_value``).
    """
    source = effect.measured_source
    if source is None:
        return True
    signal, output = source
    entry = localization.get(output, {}).get("signals", {}).get(signal)
    return entry is not None and entry["p_value"] < RELEVANCE_ALPHA
