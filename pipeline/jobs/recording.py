"""The recording every workflow starts from, and the grid and sample-period policy.

Composition shared by the estimation, discrepancy and nightly workflows: ingest a job's
files (:mod:`pipeline.adapters.ingest`), put them on one uniform grid
(:mod:`pipeline.adapters.grid`) with the job's gap policy, mask spikes, and the choices
about time every workflow makes the same way:

* Grid: the median sample spacing of the signals to two significant figures (or
  ``source.grid_dt_s``); inputs are linearly interpolated, outputs and instruments held,
  each up to ``max_gap_s`` (default: the larger of 10 grid periods and
  :data:`DEFAULT_MAX_GAP_S`), beyond which samples are masked.
* A configured sample period (``sampling.dt_s``) must be a whole multiple of the grid
  period (:func:`configured_decimation`); otherwise the estimation job chooses it by α_T.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError
from pipeline.jobs.job_types import Recording
from pipeline.estimation.normal_equations import good_segments
from pipeline.progress import Tick, silent

__all__ = ["DEFAULT_MAX_GAP_S", "STRAY_FRACTION", "configured_decimation", "load_recording",
           "longest_common_good"]


DEFAULT_MAX_GAP_S = 600.0
"""Default longest span bridged on the grid.  Historians record by exception: no record
means "no change beyond the deadband", and a tag is re-recorded at least every
exception-max interval (PI's default ExcMax is 600 s).  Longer gaps are outages: masked."""


STRAY_FRACTION = 0.001
"""An island of the record (samples separated from the rest by more than every signal's
``max_gap_s``) holding fewer than 0.1 % of the samples is a stray — mistyped or clock-reset
timestamps — and is left out and reported (``checks.json`` → ``data_quality.stray_samples``)."""





def load_recording(cfg, files: list[Path] | None = None, tick: Tick = silent) -> Recording:
    """Ingest the job's files and put its signals on one uniform grid (``tick``: bytes
    read, :mod:`pipeline.progress`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    files : list of Path, optional
        Files to read; ``None`` resolves the job's ``source`` (``resolve_sources``).
    tick : callable (done, total)
        Progress of the bytes read.
    """
    from pipeline.adapters.config import resolve_sources
    from pipeline.adapters.grid import to_grid
    from pipeline.adapters.ingest import read_recordings

    files = list(files) if files is not None else resolve_sources(cfg)
    sig = {**{n: ("input", s) for n, s in cfg.signals.inputs.items()},
           **{n: ("output", s) for n, s in cfg.signals.outputs.items()},
           **{n: ("instrument", s) for n, s in cfg.signals.instruments.items()}}
    tags = [s.tag for _, s in sig.values()]
    mcap = cfg.source.mcap.model_dump() if cfg.source.mcap else None
    csv = cfg.source.csv.model_dump() if cfg.source.csv else None
    table, report = read_recordings(files, layout=cfg.source.layout,
                                    timezone=cfg.source.timezone, tags=list(dict.fromkeys(tags)),
                                    mcap=mcap, csv=csv, on_truncated=cfg.source.on_truncated,
                                    tick=tick)
    if cfg.source.time_order == "strict":
        _check_time_order(report)
    grid_dt = cfg.source.grid_dt_s or _median_spacing_s(table)
    spec = {}
    for name, (role, s) in sig.items():
        # inputs are continuous (linear); PVs are exception-reported and setpoints
        # (instruments) are step signals: hold
        interp = s.interpolation or ("linear" if role == "input" else "hold")
        spec[s.tag] = {"interpolation": interp,
                       "max_gap_s": s.max_gap_s or max(10 * grid_dt, DEFAULT_MAX_GAP_S)}
    # breaks longer than every signal's max_gap_s are not gridded (all masked there
    # anyway), and an island of stray samples (a year-9999 timestamp) is left out:
    # memory follows the samples, not the span
    grid = to_grid(table, dt_s=grid_dt, signals=spec,
                   break_gap_s=max(v["max_gap_s"] for v in spec.values()),
                   stray_fraction=STRAY_FRACTION)
    order = [grid.names.index(t) for t in tags]
    values = np.asarray(grid.values)[:, order]
    scales = np.array([s.scale for _, s in sig.values()])
    if np.any(scales != 1.0):  # signals.*.scale: the export in the units the job uses
        values = values * scales
    good = np.asarray(grid.good)[:, order]
    spikes = {}
    if cfg.quality.spikes == "mask":
        from pipeline.identification.spikes import find_spikes

        for k, name in enumerate(sig):
            flag = find_spikes(values[:, k], good[:, k], sigmas=cfg.quality.spike_sigmas)
            if flag.any():
                spikes[name] = {"samples": int(flag.sum()),
                                "first": str(np.asarray(grid.time)[flag][0]) + "Z",
                                "largest": float(np.nanmax(np.abs(values[flag, k])))}
                values[flag, k] = np.nan
                good[flag, k] = False
    quality = {}
    ing = report.to_dict()
    tag_name = {s.tag: n for n, (_, s) in sig.items()}
    ing["grid"] = {"islands": grid.islands,
                   "stray_samples": [{**d, "signal": tag_name.get(d["signal"], d["signal"]),
                                      "tag": d["signal"]} for d in grid.dropped]}
    per_signal = {row.get("signal"): row for row in ing.get("signals", [])}
    ing["spikes"] = spikes
    for name, (role, s) in sig.items():
        reasons = dict(grid.mask_reasons.get(s.tag, {}))
        if name in spikes:
            reasons["spike"] = spikes[name]["samples"]
        quality[name] = {"tag": s.tag, "role": role,
                         "grid_samples": int(values.shape[0]),
                         "masked": int((~good[:, list(sig).index(name)]).sum()),
                         "masked_by_reason": reasons,
                         "ingest": per_signal.get(s.tag, {})}
        if good[:, list(sig).index(name)].sum() == 0:
            raise DataQualityError(
                f"signal {name!r} (tag {s.tag}): every sample is bad or missing after ingestion "
                f"({reasons}); check the tag's quality in the export or remove the signal"
            )
    return Recording(tuple(sig), tuple(r for r, _ in sig.values()), tuple(tags),
                     np.asarray(grid.time), float(grid_dt), values, good,
                     tuple(str(f) for f in files), quality, ing)


def _check_time_order(report) -> None:
    bad = [(st.signal, st.duplicates_removed, st.out_of_order) for st in report.signals
           if st.duplicates_removed or st.out_of_order]
    if bad:
        detail = "; ".join(f"tag {t}: {d} duplicate and {o} out-of-order timestamp(s)"
                           for t, d, o in bad[:5])
        raise DataQualityError(
            f"source.time_order is 'strict' but the recording has non-monotonic or "
            f"duplicate times: {detail}; fix the export, or set source.time_order: fix to "
            "resolve them (last value wins, rows sorted) and count them in checks.json"
        )


def _median_spacing_s(table: pl.DataFrame) -> float:
    from pipeline.adapters.grid import median_spacing_s

    med = median_spacing_s(table)
    if med is None:
        raise InsufficientDataError(
            "the recording has fewer than two distinct timestamps per signal; it cannot be "
            "put on a grid — export a longer period"
        )
    # Exception-reported timestamps jitter (1.002 s); two significant figures give the
    # period the historian was configured for, and grids of nightly files line up.
    return max(float(f"{med:.2g}"), 0.001)


def longest_common_good(good: np.ndarray) -> tuple[int, int]:
    """The longest stretch ``(start, stop)`` where every signal is good (``(0, 0)`` if none).

    Parameters
    ----------
    good : ndarray of bool (N, k)
        Quality mask, one column per signal.
    """
    segs = good_segments(good.all(axis=1))
    if not segs:
        return (0, 0)
    return max(segs, key=lambda s: s[1] - s[0])


def configured_decimation(cfg, grid_dt_s: float) -> int | None:
    """The decimation factor of ``sampling.dt_s`` on a grid of ``grid_dt_s`` (``None``
    when the job leaves the sample period to the workflow).

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``sampling.dt_s``).
    grid_dt_s : float
        The recording's grid period (s).

    Raises
    ------
    ConfigError
        ``sampling.dt_s`` is not a whole multiple of the grid period.
    """
    dt_s = cfg.sampling.dt_s
    if dt_s is None:
        return None
    factor = max(1, int(round(dt_s / grid_dt_s)))
    if abs(factor * grid_dt_s - dt_s) > 1e-6 * dt_s:
        raise ConfigError(
            f"sampling.dt_s={dt_s} is not an integer multiple of the grid period "
            f"{grid_dt_s} s; choose a multiple (e.g. {factor * grid_dt_s:g}) or set "
            "source.grid_dt_s")
    return factor
