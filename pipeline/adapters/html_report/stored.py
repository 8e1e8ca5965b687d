"""What the estimation report reads from a run directory, and the numbers it derives from
the stored files alone (no refitting): step-response arrays per window, the held-out
fit, the residual correlations with their bands."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.adapters.series_reader import read_key
from pipeline.identification.checks import cross_correlation_check, ljung_box
from pipeline.identification.conditioning import as_masked_zero
from pipeline.estimation.noise_model import NUISANCE_NAMES
from pipeline.estimation.prediction import whiten_residual
from pipeline.identification.quality import fit_percent, simulate_fir

__all__ = ["StoredRun", "load_run", "step_arrays", "held_out_fit", "residual_correlations"]


@dataclass(frozen=True)
class StoredRun:
    """An estimation run's stored files (each None when absent).

    Attributes
    ----------
    run_dir : Path
        The run directory.
    manifest : dict
        ``manifest.json`` (or what the writer passed before the manifest exists).
    checks : dict or None
        ``checks.json``.
    steps : polars.DataFrame or None
        ``step_responses.parquet``.
    signals, residuals : Path or None
        ``signals.parquet``, ``residuals.parquet``: long tables read a series at a time
        (:mod:`pipeline.adapters.series_reader`), never whole.
    outputs, inputs : list of str
        Names in ``checks.json``'s pair order (else as stored).
    read : dict
        Series already read from ``signals.parquet`` (the held-out fit and the residual
        checks share the inputs instead of reading them twice).
    """

    run_dir: Path
    manifest: dict
    checks: dict | None
    steps: pl.DataFrame | None
    signals: Path | None
    residuals: Path | None
    outputs: list
    inputs: list
    read: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def config(self) -> dict:
        """The resolved job configuration."""
        return self.manifest.get("config") or {}

    def pair(self, output: str, inp: str) -> dict:
        """checks.json's entry for a pair (empty when absent).

        Parameters
        ----------
        output : str
            Output name.
        inp : str
            Input name.
        """
        for p in (self.checks or {}).get("pairs") or []:
            if isinstance(p, Mapping) and p.get("output") == output and p.get("input") == inp:
                return dict(p)
        return {}


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def _read_parquet(path: Path) -> pl.DataFrame | None:
    return pl.read_parquet(path) if path.is_file() else None


def load_run(run_dir: Path, manifest: Mapping[str, Any] | None = None) -> StoredRun:
    """Read a run directory's files.

    Parameters
    ----------
    run_dir : Path
        The run directory (or the store's temporary directory while it is written).
    manifest : mapping, optional
        ``job``, ``run_id``, ``config`` (and optionally ``status``, ``created_utc``) when
        ``manifest.json`` does not exist yet; default: read ``manifest.json``.
    """
    run_dir = Path(run_dir)
    man = dict(manifest) if manifest is not None else (_read_json(run_dir / "manifest.json") or {})
    checks = _read_json(run_dir / "checks.json")
    steps = _read_parquet(run_dir / "step_responses.parquet")
    outputs: list[str] = []
    inputs: list[str] = []
    for p in (checks or {}).get("pairs") or []:
        if isinstance(p, Mapping) and "output" in p and "input" in p:
            outputs.append(p["output"])
            inputs.append(p["input"])
    if steps is not None:
        outputs += steps["output"].unique(maintain_order=True).to_list()
        inputs += steps["input"].unique(maintain_order=True).to_list()
    sig, res = run_dir / "signals.parquet", run_dir / "residuals.parquet"
    return StoredRun(run_dir, man, checks, steps, sig if sig.is_file() else None,
                     res if res.is_file() else None,
                     list(dict.fromkeys(outputs)), list(dict.fromkeys(inputs)))


def window_labels(steps: pl.DataFrame) -> list[str]:
    """Windows in the table: ``all`` first, then ``w0``, ``w1``, … in number order.

    Parameters
    ----------
    steps : polars.DataFrame
        ``step_responses.parquet``.
    """
    return sorted(steps["window"].unique().to_list(),
                  key=lambda w: (w != "all", int(w[1:]) if w[1:].isdigit() else -1, w))


def step_arrays(run: StoredRun, window: str, column: str = "delta_h") -> np.ndarray | None:
    """One window's column as an array (n_y, n_x, P), zero-padded past each pair's n_p.

    Parameters
    ----------
    run : StoredRun
        The run.
    window : str
        ``"all"`` or ``"w0"``, ….
    column : str
        ``delta_h``, ``step`` or ``step_std``.
    """
    if run.steps is None:
        return None
    df = run.steps.filter(pl.col("window") == window)
    if df.height == 0:
        return None
    P = int(df["lag"].max())
    out = np.zeros((len(run.outputs), len(run.inputs), P))
    for (o, u), g in df.group_by(["output", "input"]):
        g = g.sort("lag")
        out[run.outputs.index(o), run.inputs.index(u), g["lag"].to_numpy() - 1] = \
            g[column].cast(pl.Float64).fill_null(np.nan).to_numpy()
    return out


def _signal_matrix(signals: Path, names: list[str]) -> tuple[np.ndarray, pl.Series]:
    """Conditioned values (N, n) with NaN where masked, and the sample times (read a
    signal at a time)."""
    cols, times = [], None
    for name in names:
        df = read_key(signals, {"signal": name}, ["conditioned", "good"])
        vals = df["conditioned"].cast(pl.Float64).fill_null(np.nan).to_numpy()
        cols.append(np.where(df["good"].to_numpy(), vals, np.nan))
        times = df["time"] if times is None else times
    return np.column_stack(cols), times


def _signals(run: StoredRun, names: list[str]) -> tuple[np.ndarray, pl.Series]:
    """:func:`_signal_matrix` of ``names``, read once per run."""
    key = tuple(names)
    if key not in run.read:
        run.read[key] = _signal_matrix(run.signals, names)
    return run.read[key]


def _integrating(run: StoredRun) -> list[bool]:
    outs = (run.config.get("signals") or {}).get("outputs") or {}
    return [bool((outs.get(o) or {}).get("integrating")) for o in run.outputs]


def held_out_fit(run: StoredRun) -> dict[str, Any] | None:
    """Measured vs simulated outputs on a held-out window, with MATLAB ``compare``'s fit %.

    The last disjoint window with an estimate is held out; the model is the mean of the
    other windows' step responses (equal weights: the windows are equally long), simulated
    from the conditioned inputs alone.  The all-data estimate on the same stretch (not held
    out) is given for comparison.  Integrating outputs are compared as their differences
    (what their model predicts).  Both series have their held-out mean removed.  None when
    the files needed are absent.

    Parameters
    ----------
    run : StoredRun
        The run.
    """
    if run.steps is None or run.signals is None or run.checks is None:
        return None
    wins = [w for w in (run.checks.get("search") or {}).get("windows") or []
            if w.get("status") == "ok" and w.get("window") in window_labels(run.steps)]
    x, times = _signals(run, run.inputs)
    y, _ = _signals(run, run.outputs)
    dh_all = step_arrays(run, "all")
    if len(wins) >= 2:
        held, train = wins[-1], wins[:-1]
        dh = np.mean([step_arrays(run, w["window"]) for w in train], axis=0)
        a, b = held["samples"]
        what = (f"window {held['window']} (samples {a}–{b}) held out; model = mean of the "
                f"step responses of {', '.join(w['window'] for w in train)}")
    else:
        train, dh, (a, b) = [], None, (0, x.shape[0])
        what = "no second window: in-sample fit of the all-data estimate over the record"
    integ = _integrating(run)
    bad_x = ~np.isfinite(x).all(axis=1)
    P = dh_all.shape[2]
    touched = np.convolve(bad_x.astype(float), np.ones(P))[: bad_x.size] > 0
    x0 = as_masked_zero(x)
    out: dict[str, Any] = {"what": what, "samples": [int(a), int(b)],
                           "time": times[a:b], "outputs": {}}
    for i, o in enumerate(run.outputs):
        yi = y[:, i].copy()
        coefs = {}
        for key, arr in (("held_out", dh), ("all", dh_all)):
            if arr is None:
                continue
            c = arr[i:i + 1]
            coefs[key] = np.diff(c, axis=2, prepend=0.0) if integ[i] else c
        if integ[i]:
            yi = np.concatenate([[np.nan], np.diff(yi)])
        yi[touched] = np.nan
        meas = yi[a:b] - np.nanmean(yi[a:b])
        res = {"measured": meas, "differenced": integ[i]}
        for key, c in coefs.items():
            sim = simulate_fir(c, x0)[a:b, 0]
            sim = np.where(np.isfinite(meas), sim, np.nan)
            sim = sim - np.nanmean(sim)
            res[key] = sim
            res[f"fit_{key}"] = fit_percent(meas, sim)
        out["outputs"][o] = res
    return out


def _aligned_residual(run: StoredRun, output: str, times: pl.Series) -> np.ndarray:
    df = read_key(run.residuals, {"output": output}, ["residual"]).select("time", "residual")
    grid = pl.DataFrame({"time": times})
    joined = grid.join(df, on="time", how="left", maintain_order="left")
    return joined["residual"].cast(pl.Float64).fill_null(np.nan).to_numpy()


def residual_correlations(run: StoredRun) -> dict[str, Any] | None:
    """The prediction errors' autocorrelation (Ljung–Box) per output and the input
    cross-correlation per pair, recomputed from ``residuals.parquet``, ``signals.parquet``
    and the noise models in ``checks.json`` as the checks computed them (so the stored
    statistics are reproduced), with their significance bands.

    Parameters
    ----------
    run : StoredRun
        The run.
    """
    if run.residuals is None or run.signals is None or run.checks is None:
        return None
    x, times = _signals(run, run.inputs)
    x0 = as_masked_zero(x)
    cfg_checks = run.config.get("checks") or {}
    white = ((run.checks.get("residuals") or {}).get("whiteness") or {})
    out: dict[str, Any] = {"outputs": {}, "pairs": {}}
    for o in run.outputs:
        e = _aligned_residual(run, o, times)
        nm = (run.checks.get("noise_model") or {}).get(o) or {}
        d = np.concatenate([[1.0], np.asarray(nm.get("coefficients") or [], dtype=float)])
        nuis = nm.get("nuisance", "none")
        innov = whiten_residual(e, d, level=nm.get("form") == "level",
                                nuisance=NUISANCE_NAMES.index(nuis) if nuis in NUISANCE_NAMES else 0)
        lags = int((white.get(o) or {}).get("lags") or cfg_checks.get("ljung_box_lags") or 20)
        lb = ljung_box(innov, lags=lags)
        n = int(np.isfinite(innov).sum())
        out["outputs"][o] = {**lb, "n": n, "band_99": 2.5758 / np.sqrt(max(n, 1)),
                             "of": (white.get(o) or {}).get("of", "residuals")}
        for j, u in enumerate(run.inputs):
            n_p = int(run.pair(o, u).get("n_p") or 20)
            max_lag = int(cfg_checks.get("xcorr_max_lag") or n_p)
            out["pairs"][(o, u)] = cross_correlation_check(x0[:, j], innov, max_lag=max_lag)
    return out
