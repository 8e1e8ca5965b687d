"""``plantdyn export``: a run's model in the files control tools import.

Reads an estimation run directory (``manifest.json``, ``step_responses.parquet`` window
``all``, ``checks.json``), checks the two data files against the manifest's sha256, fits
one continuous transfer function with dead time per pair (:mod:`pipeline.readouts.lti_fit`) and
writes one file, atomically (a temporary file in the target folder, then ``os.replace``):

``csv`` (:data:`SCHEMA_CSV`)
    The DMC-style step-coefficient table: a ``#`` comment header — lines ``# key: value``
    for ``schema``, ``job``, ``run_id``, ``window``, ``dt_s``, ``rows`` (the time
    convention), ``padding`` (the rule and the padded pairs), then the rows
    ``# output_unit,,…``, ``# input_unit,,…``, ``# output_tag,,…``, ``# input_tag,,…``,
    ``# n_p,,…``, ``# tail,,…`` (``hold`` or ``ramp``), ``# settled,,…`` (the settledness
    verdict), ``# grade,,…``, ``# gain,,…``, ``# gain_std,,…`` (the rate for integrating
    pairs; empty when the run reports none) aligned with the columns — then the columns
    ``lag,time_s,<output><-<input>,…``, one row per lag:
    row ``lag = k`` holds coefficient ``k``, the step response at lag ``k`` (lag 1 is the
    same-sample term, ``time_s = (lag - 1/2)·dt_s``).  All pairs share the rows
    ``1..max n_p``; a pair with a shorter ``n_p`` is padded by holding its last value, an
    integrating pair by continuing its last increment (its final slope); ``# n_p`` says
    where padding starts, and the padding is the model only where ``# settled`` says
    ``settled``.  An MPC package's step-response (FSR/DMC) model reads row ``lag = k`` as
    its coefficient ``S_k``: the output change ``k`` samples after a unit input step held
    from sample 0 (``# mpc`` header line).
    Numbers are written with Python's shortest round-trip ``repr``: they read back equal.
``json`` (:data:`SCHEMA_MODEL`)
    Everything: run metadata, signals with units, and per pair the lags, ``time_s``,
    ``step``, ``step_std``, ``delta_h``, gain (or rate) with σ, ``n_k``, warnings and the
    fitted ``transfer_function`` (see below).  Unpadded (each pair its own ``n_p``).
``mat`` (:data:`SCHEMA_MAT`, ``scipy.io.savemat``, MATLAB 5 format)
    ``step``, ``step_std``, ``delta_h`` as ``n_lag × n_y × n_x`` arrays padded like the CSV
    (``step_std`` NaN past ``n_p``), ``lag``/``time_s`` columns, ``dt_s``, ``n_p``,
    ``n_k``, ``gain``, ``gain_std``, ``rate``, ``rate_std`` (``n_y × n_x``), cell arrays
    ``outputs``, ``inputs``, ``output_units``, ``input_units``, and the fits as
    ``tf_kind``, ``tf_num``, ``tf_den`` (row vectors, ``s``), ``tf_delay_s``,
    ``tf_num_z``, ``tf_den_z`` (sampled form at ``dt_s``), ``tf_fit_rms``,
    ``tf_fit_rms_rel``.  In MATLAB: ``tf(tf_num{i,j}, tf_den{i,j}, 'InputDelay',
    tf_delay_s(i,j))``.
``control`` (:data:`SCHEMA_CONTROL`)
    The fitted transfer functions only, for :func:`load_control`, which builds one
    ``control.TransferFunction`` per pair.

The exported model is the reported model: a pair's transfer function is written only
when its DC gain (rate) agrees with the run's reported gain within
``max(2σ, 10 %)`` (:func:`pipeline.readouts.lti_fit.reported_model`); otherwise, and for a pair that reports no gain
(still moving at its horizon), it is left out and ``fit_error`` says why.  Every file
carries units, tags, the settledness verdict, the grade and the gain with its σ.

A pair's ``transfer_function``: ``kind``, ``num``/``den`` of ``G(s)`` without the delay
(highest power first), ``delay_s``, ``parameters``, ``fit_rms`` (RMS of fitted minus stored
step over the lags), ``fit_rms_rel`` (over ``max|step|``), ``noise_rms``, ``tolerance``,
``within_noise``, ``rule``, ``trials``, and ``discrete`` = {``num``, ``den`` (powers of
``z``, highest first), ``dt_s``, ``first_sample_time_s``}: the exact zero-order-hold form
of ``G(s)e^{-θs}`` whose step response at sample ``k`` is the fitted curve at
``(k + 1/2)·dt_s`` — the stored lag ``k + 1``.

Where the file goes: ``--out`` (a file, or an existing folder), default
``./<job>_<run-id>.<ext>`` in the current folder, the name built only from a job name and
run id that pass the store's name check (a manifest naming ``"../../x"`` is refused: give
``--out``).  Never inside a run directory (run directories are the store's immutable
results, every file listed with its sha256 in ``manifest.json``) nor over the catalog; an
existing regular file is replaced only with ``force``, anything else (FIFO, device node,
folder, link) never (:mod:`pipeline.adapters.safe_write`).
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError, DataQualityError

__all__ = [
    "FORMATS",
    "PADE_ORDER",
    "SCHEMA_CONTROL",
    "SCHEMA_CSV",
    "SCHEMA_MAT",
    "SCHEMA_MODEL",
    "ExportResult",
    "PairData",
    "RunData",
    "export_run",
    "fit_pairs",
    "load_control",
    "output_path",
    "read_run",
]

FORMATS = {"csv": ".csv", "json": ".json", "mat": ".mat", "control": ".control.json"}
"""Export formats and their file-name endings."""
SCHEMA_CSV = "plantdyn-step-csv/1"
SCHEMA_MODEL = "plantdyn-model/1"
SCHEMA_MAT = "plantdyn-step-mat/1"
SCHEMA_CONTROL = "plantdyn-control/1"
PADE_ORDER = 6
"""Default order of the Padé approximant of the dead time (``load_control(delay="pade")``)."""
WINDOW = "all"
_FIXES = ("give a run directory printed by `plantdyn run` (<storage>/<job>/<run-id>); "
          "`plantdyn runs JOB` lists them")


@dataclass(frozen=True)
class PairData:
    """One pair's stored step response (window ``all``) and its checks.

    Attributes
    ----------
    output, input : str
        Signal names.
    lag : ndarray of int (n_p,)
        1-based lags (lag 1 is the same-sample term).
    time_s, step, step_std, delta_h : ndarray (n_p,)
        As in ``step_responses.parquet``.
    n_k : int
        Known/forced delay in samples (``checks.json``).
    integrating : bool
        The output is integrating (``rate`` instead of ``gain``).
    gain, gain_std, rate, rate_std : float or None
        From ``checks.json``.
    warnings : list of dict
        ``checks.json`` ``pairs[].warnings``.
    settled : str or None
        ``checks.json`` ``pairs[].settled.verdict`` (``settled``, ``moving``,
        ``insufficient_data``).
    grade : str or None
        The pair's quality grade (:func:`pipeline.identification.quality.grade_from_checks`).
    gain_note : str
        ``checks.json`` ``pairs[].gain_note``.
    gain_extrapolated : dict or None
        ``checks.json`` ``pairs[].gain_extrapolated`` (``rate_extrapolated``).
    transfer_function : dict or None
        ``checks.json`` ``pairs[].transfer_function``: the reported model as the run
        fitted it (None: a run written before runs stored it).
    """

    output: str
    input: str
    lag: np.ndarray
    time_s: np.ndarray
    step: np.ndarray
    step_std: np.ndarray
    delta_h: np.ndarray
    n_k: int
    integrating: bool
    gain: float | None
    gain_std: float | None
    rate: float | None
    rate_std: float | None
    warnings: list = field(default_factory=list)
    settled: str | None = None
    grade: str | None = None
    gain_note: str = ""
    gain_extrapolated: dict | None = None
    transfer_function: dict | None = None

    @property
    def label(self) -> str:
        """``output<-input`` (the CSV column name)."""
        return f"{self.output}<-{self.input}"

    @property
    def n_p(self) -> int:
        """Number of stored lags."""
        return int(self.step.size)


@dataclass(frozen=True)
class RunData:
    """What the export reads from a run directory.

    Attributes
    ----------
    run_dir : Path
        The run directory.
    job, run_id, status, package_version : str
        From ``manifest.json``.
    dt_s : float
        Sample period of the step responses (s).
    outputs, inputs : tuple of str
        Signal names in the job's order.
    units, tags : dict
        Signal name -> unit (``""`` when the job gives none) and historian tag.
    pairs : dict
        ``(output, input)`` -> :class:`PairData`.
    """

    run_dir: Path
    job: str
    run_id: str
    status: str
    package_version: str
    dt_s: float
    outputs: tuple
    inputs: tuple
    units: dict
    tags: dict
    pairs: dict

    def pair_list(self) -> list[PairData]:
        """The pairs, outputs major, in the job's order (the CSV's column order)."""
        return [self.pairs[(o, u)] for o in self.outputs for u in self.inputs
                if (o, u) in self.pairs]


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_run` wrote.

    Attributes
    ----------
    path : Path
        The file written.
    format : str
        One of :data:`FORMATS`.
    fits : dict
        ``(output, input)`` -> :class:`pipeline.readouts.lti_fit.StepModelFit` (or the error text);
        empty for ``csv``.
    notes : list of str
        Lines worth telling the user (run status, poor fits).
    """

    path: Path
    format: str
    fits: dict
    notes: list


# --------------------------------------------------------------------- reading a run
def _fail_not_a_run(path: Path) -> None:
    runs = []
    try:
        runs = sorted(p for p in path.iterdir() if (p / "manifest.json").is_file())
    except OSError:
        pass
    if runs:
        raise ConfigError(f"{path} is a job folder, not a run directory; give one of its runs, "
                          f"e.g. {runs[-1]} (`plantdyn runs {path.name}` lists them)")
    raise ConfigError(f"{path} is not a plantdyn run directory (no manifest.json); {_FIXES}")


def _manifest(path: Path) -> dict:
    if not path.exists():
        raise ConfigError(f"run directory {path} does not exist; {_FIXES}")
    if not path.is_dir():
        raise ConfigError(f"{path} is a file, not a run directory; {_FIXES}")
    mpath = path / "manifest.json"
    if not mpath.is_file():
        _fail_not_a_run(path)
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DataQualityError(f"{mpath} cannot be read ({exc}); the run directory is damaged "
                               "— re-run the job") from None
    if not isinstance(manifest, dict) or not {"job", "run_id", "files"} <= set(manifest):
        raise DataQualityError(f"{mpath} is not a plantdyn manifest (no job/run_id/files); "
                               f"{_FIXES}")
    files, config = manifest["files"], manifest.get("config")
    if not isinstance(files, list) or not all(
            isinstance(f, dict) and isinstance(f.get("name"), str) for f in files) or \
            not isinstance(config, (dict, type(None))):
        raise DataQualityError(f"{mpath}: its files list (or config) is not what plantdyn "
                               "writes (a list of {name, sha256, bytes}); the run directory "
                               "is damaged — re-run the job")
    return manifest


def _refuse_discrepancy_run(path: Path, manifest: dict) -> None:
    names = {f.get("name") for f in manifest["files"]}
    config = manifest.get("config") or {}
    if "discrepancy.json" in names or config.get("model") or config.get("discrepancy"):
        raise ConfigError(
            f"{path} is a discrepancy run (discrepancy.json, model_augmented.yaml: a model "
            "augmentation, not step responses); export works on estimation runs — run the "
            "job without model:/discrepancy: through `plantdyn run JOB.yaml` and export that run")


def _verified(path: Path, manifest: dict, name: str) -> Path:
    """``path/name`` after checking it against its sha256 in the manifest."""
    from pipeline.adapters.store import file_sha256

    files = {f.get("name"): f for f in manifest["files"]}
    if name not in files:
        raise DataQualityError(f"{path}: the manifest lists no {name}, so there is no step "
                               f"response to export; {_FIXES}")
    file = path / name
    if not file.is_file():
        raise DataQualityError(f"{path}: {name} listed in the manifest is missing; the run "
                               "directory is damaged — re-run the job")
    digest = file_sha256(file)
    if digest != files[name].get("sha256"):
        raise DataQualityError(
            f"{path}: {name} has sha256 {digest[:12]}…, the manifest says "
            f"{str(files[name].get('sha256'))[:12]}…: it was modified after the run was written; "
            "re-run the job (results are exported only as the run wrote them)")
    return file


def _finite_or_none(v) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def read_run(run_dir: str | os.PathLike) -> RunData:
    """Read and check an estimation run directory (module notes).

    Parameters
    ----------
    run_dir : str or os.PathLike
        ``<storage>/<job>/<run-id>``.

    Returns
    -------
    RunData

    Raises
    ------
    ConfigError
        Not a run directory (missing, a file, a job folder, no manifest) or a discrepancy
        run.
    DataQualityError
        A file missing, modified after the run, or without window ``all``.
    """
    import polars as pl

    from pipeline.adapters.safe_write import check_path_length

    path = check_path_length(run_dir, "RUN_DIR")
    manifest = _manifest(path)
    _refuse_discrepancy_run(path, manifest)
    steps_file = _verified(path, manifest, "step_responses.parquet")
    checks = json.loads(_verified(path, manifest, "checks.json").read_text(encoding="utf-8"))
    table = pl.read_parquet(steps_file).filter(pl.col("window") == WINDOW).sort(
        "output", "input", "lag")
    if table.height == 0:
        raise DataQualityError(f"{steps_file} has no rows of window '{WINDOW}' (the all-data "
                               "estimate); re-run the job")
    dts = table["dt_s"].unique().to_list()
    if len(dts) != 1:
        raise DataQualityError(f"{steps_file}: window '{WINDOW}' has several dt_s {dts}")
    from pipeline.identification.quality import grade_from_checks

    by_pair = {(p["output"], p["input"]): p for p in checks.get("pairs", [])}
    outputs = tuple(dict.fromkeys(p["output"] for p in checks.get("pairs", [])))
    inputs = tuple(dict.fromkeys(p["input"] for p in checks.get("pairs", [])))
    pairs = {}
    for (o, u), rows in table.group_by(["output", "input"], maintain_order=True):
        c = by_pair.get((o, u), {})
        pairs[(o, u)] = PairData(
            output=o, input=u, lag=rows["lag"].to_numpy().astype(int),
            time_s=rows["time_s"].to_numpy(), step=rows["step"].to_numpy(),
            step_std=rows["step_std"].to_numpy(), delta_h=rows["delta_h"].to_numpy(),
            n_k=int(c.get("n_k") or 0), integrating=bool(c.get("integrating", False)),
            gain=_finite_or_none(c.get("gain")), gain_std=_finite_or_none(c.get("gain_std")),
            rate=_finite_or_none(c.get("rate")), rate_std=_finite_or_none(c.get("rate_std")),
            warnings=list(c.get("warnings") or []),
            settled=(c.get("settled") or {}).get("verdict")
            if isinstance(c.get("settled"), dict) else None,
            grade=grade_from_checks(c, checks).grade if c else None,
            gain_note=str(c.get("gain_note") or ""),
            gain_extrapolated=c.get("rate_extrapolated" if c.get("integrating")
                                    else "gain_extrapolated"),
            transfer_function=c.get("transfer_function"))
    outputs += tuple(o for o, _ in pairs if o not in outputs)
    inputs += tuple(u for _, u in pairs if u not in inputs)
    signals = (manifest.get("config") or {}).get("signals") or {}
    spec = {**(signals.get("inputs") or {}), **(signals.get("outputs") or {})}
    return RunData(
        run_dir=path, job=str(manifest["job"]), run_id=str(manifest["run_id"]),
        status=str(manifest.get("status", "")),
        package_version=str(manifest.get("package_version", "")), dt_s=float(dts[0]),
        outputs=tuple(dict.fromkeys(outputs)), inputs=tuple(dict.fromkeys(inputs)),
        units={n: (spec.get(n) or {}).get("unit") or "" for n in outputs + inputs},
        tags={n: (spec.get(n) or {}).get("tag") or "" for n in outputs + inputs},
        pairs=pairs)


# ------------------------------------------------------------------------ the table
def _padded(run: RunData) -> dict:
    """The step table of every pair on the common lags ``1..max n_p`` (module notes)."""
    n_lag = max(p.n_p for p in run.pairs.values())
    ny, nx = len(run.outputs), len(run.inputs)
    step = np.full((n_lag, ny, nx), np.nan)
    std, dh = np.full_like(step, np.nan), np.full_like(step, np.nan)
    n_p = np.zeros((ny, nx), dtype=np.int32)
    for (o, u), p in run.pairs.items():
        i, j, n = run.outputs.index(o), run.inputs.index(u), p.n_p
        extra = np.arange(1, n_lag - n + 1)
        tail_dh = p.delta_h[-1] if p.integrating else 0.0  # ramp on, or settled
        step[:, i, j] = np.r_[p.step, p.step[-1] + tail_dh * extra]
        dh[:, i, j] = np.r_[p.delta_h, np.full(extra.size, tail_dh)]
        std[:n, i, j] = p.step_std
        n_p[i, j] = n
    lag = np.arange(1, n_lag + 1)
    return {"lag": lag, "time_s": (lag - 0.5) * run.dt_s, "step": step, "step_std": std,
            "delta_h": dh, "n_p": n_p}


def _csv_bytes(run: RunData) -> bytes:
    tab, pairs = _padded(run), run.pair_list()
    idx = [(run.outputs.index(p.output), run.inputs.index(p.input)) for p in pairs]
    short = [f"{p.label} (n_p {p.n_p})" for p in pairs if p.n_p < tab["lag"].size]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for line in (
        f"schema: {SCHEMA_CSV} (plantdyn step-response coefficients, DMC-style)",
        f"job: {run.job}", f"run_id: {run.run_id}", f"window: {WINDOW}",
        f"dt_s: {run.dt_s!r}",
        "rows: row lag = k holds coefficient k, the response of the output to a unit step of "
        "the input at time_s = (lag - 1/2) * dt_s after it (lag 1 is the same-sample term), "
        "in output unit per input unit",
        "padding: rows past a pair's n_p repeat its last value; integrating pairs (tail "
        "ramp) continue their last increment. That is the model only where the pair's "
        "'settled' row says settled: a 'moving' pair's response had not settled at its n_p "
        "(its gain is empty; see the gain_note in checks.json). Padded: "
        + (", ".join(short) if short else "none"),
        "mpc: an MPC package's step-response model (DMC, e.g. a FSR matrix S_1..S_N) takes "
        "row lag = k as S_k: the output change k samples after a unit input step applied "
        "at sample 0 (sample-and-hold), i.e. lag 1 is the same-sample coefficient; pairs "
        "graded C or D or not settled should not go into a controller as they are",
    ):
        buf.write(f"# {line}\n")
    for name, values in (("output_unit", [run.units[p.output] for p in pairs]),
                         ("input_unit", [run.units[p.input] for p in pairs]),
                         ("output_tag", [run.tags[p.output] for p in pairs]),
                         ("input_tag", [run.tags[p.input] for p in pairs]),
                         ("n_p", [p.n_p for p in pairs]),
                         ("tail", ["ramp" if p.integrating else "hold" for p in pairs]),
                         ("settled", [p.settled or "" for p in pairs]),
                         ("grade", [p.grade or "" for p in pairs]),
                         ("gain", [_text(p.rate if p.integrating else p.gain) for p in pairs]),
                         ("gain_std", [_text(p.rate_std if p.integrating else p.gain_std)
                                       for p in pairs])):
        row = io.StringIO()
        csv.writer(row, lineterminator="").writerow([name, "", *values])
        buf.write(f"# {row.getvalue()}\n")
    w.writerow(["lag", "time_s", *(p.label for p in pairs)])
    for k, lag in enumerate(tab["lag"]):
        w.writerow([int(lag), repr(float(tab["time_s"][k])),
                    *(repr(float(tab["step"][k, i, j])) for i, j in idx)])
    return buf.getvalue().encode("utf-8")


def _text(v: float | None) -> str:
    return "" if v is None else repr(float(v))


# ----------------------------------------------------------------------------- fits
def fit_pairs(run: RunData, progress: Callable[[str, str], None] | None = None) -> dict:
    """Every pair's transfer function with dead time: as the run stored it, or fitted
    for a run written before runs stored it (:func:`pipeline.readouts.lti_fit.reported_model`).

    Parameters
    ----------
    run : RunData
        From :func:`read_run`.
    progress : callable, optional
        ``progress(stage, message)``, called once per pair.

    Returns
    -------
    dict
        ``(output, input)`` -> ``StepModelFit``, or the error text when a pair cannot be fitted.
    """
    from pipeline.readouts.lti_fit import reported_model

    fits = {}
    for p in run.pair_list():
        value, std = (p.rate, p.rate_std) if p.integrating else (p.gain, p.gain_std)
        fits[(p.output, p.input)] = reported_model(
            p.step, dt_s=run.dt_s, step_std=p.step_std, integrating=p.integrating,
            value=value, std=std, stored=p.transfer_function, pair=p.label,
            settled=p.settled)
        msg = str(fits[(p.output, p.input)])
        if progress is not None:
            progress("export", f"{p.label}: {msg}")
    return fits


def _tf_dict(fit, dt_s: float) -> dict | None:
    """A fit as the files store it, with its exact sampled form."""
    from pipeline.readouts.lti_fit import zoh_with_delay

    if isinstance(fit, str):
        return None
    num_z, den_z = zoh_with_delay(fit.num, fit.den, delay_s=fit.delay_s - dt_s / 2, dt_s=dt_s)
    return {**fit.to_dict(),
            "discrete": {"num": num_z.tolist(), "den": den_z.tolist(), "dt_s": dt_s,
                         "first_sample_time_s": dt_s / 2}}


def _header(run: RunData, schema: str) -> dict:
    import pipeline

    return {
        "schema": schema, "job": run.job, "run_id": run.run_id, "run_status": run.status,
        "run_dir": str(run.run_dir), "run_package_version": run.package_version,
        "exported_by": f"plantdyn {pipeline.__version__}", "window": WINDOW, "dt_s": run.dt_s,
        "time_convention": "time_s = (lag - 1/2) * dt_s; lag 1 is the same-sample term",
        "inputs": [{"name": n, "unit": run.units[n], "tag": run.tags[n]} for n in run.inputs],
        "outputs": [{"name": n, "unit": run.units[n], "tag": run.tags[n],
                     "integrating": any(p.integrating for (o, _), p in run.pairs.items()
                                        if o == n)} for n in run.outputs],
    }


def _pair_head(run: RunData, p: PairData) -> dict:
    return {"output": p.output, "input": p.input, "label": p.label,
            "output_unit": run.units[p.output], "input_unit": run.units[p.input],
            "output_tag": run.tags[p.output], "input_tag": run.tags[p.input],
            "dt_s": run.dt_s, "n_p": p.n_p, "n_k": p.n_k, "integrating": p.integrating,
            "gain": p.gain, "gain_std": p.gain_std, "rate": p.rate, "rate_std": p.rate_std,
            "settled": p.settled, "grade": p.grade}


def _json_text(obj: dict) -> bytes:
    from pipeline.adapters.store.files import json_ready

    return (json.dumps(json_ready(obj), indent=1, ensure_ascii=False, allow_nan=False)
            + "\n").encode("utf-8")


def _json_bytes(run: RunData, fits: dict) -> bytes:
    pairs = []
    for p in run.pair_list():
        fit = fits[(p.output, p.input)]
        pairs.append({
            **_pair_head(run, p), "lag": p.lag.tolist(), "time_s": p.time_s.tolist(),
            "step": p.step.tolist(), "step_std": p.step_std.tolist(),
            "delta_h": p.delta_h.tolist(), "gain_note": p.gain_note,
            "gain_extrapolated": p.gain_extrapolated, "warnings": p.warnings,
            "transfer_function": _tf_dict(fit, run.dt_s),
            **({"fit_error": fit} if isinstance(fit, str) else {})})
    return _json_text({**_header(run, SCHEMA_MODEL), "pairs": pairs})


def _control_bytes(run: RunData, fits: dict) -> bytes:
    pairs = []
    for p in run.pair_list():
        fit = fits[(p.output, p.input)]
        pairs.append({**_pair_head(run, p), "transfer_function": _tf_dict(fit, run.dt_s),
                      **({"fit_error": fit} if isinstance(fit, str) else {})})
    return _json_text({**_header(run, SCHEMA_CONTROL), "pairs": pairs})


def _cells(values, shape) -> np.ndarray:
    out = np.empty(shape, dtype=object)
    for k, v in enumerate(values):
        out.flat[k] = v
    return out


def _mat_bytes(run: RunData, fits: dict) -> bytes:
    import scipy.io

    tab = _padded(run)
    ny, nx = len(run.outputs), len(run.inputs)
    grid = [(o, u) for o in run.outputs for u in run.inputs]
    tfs = [_tf_dict(fits.get(k, "no pair"), run.dt_s) if k in run.pairs else None for k in grid]

    def per_pair(get):
        vals = [get(run.pairs[k]) if k in run.pairs else None for k in grid]
        return np.array([np.nan if v is None else v for v in vals], dtype=float).reshape(ny, nx)

    def tf_field(key, default):
        return [np.atleast_2d(np.asarray(t[key] if t else default, dtype=float)) for t in tfs]

    data = {
        "schema": SCHEMA_MAT, "job": run.job, "run_id": run.run_id, "window": WINDOW,
        "dt_s": run.dt_s, "lag": tab["lag"].astype(float)[:, None],
        "time_s": tab["time_s"][:, None], "step": tab["step"], "step_std": tab["step_std"],
        "delta_h": tab["delta_h"], "n_p": tab["n_p"],
        "n_k": per_pair(lambda p: p.n_k), "gain": per_pair(lambda p: p.gain),
        "gain_std": per_pair(lambda p: p.gain_std), "rate": per_pair(lambda p: p.rate),
        "rate_std": per_pair(lambda p: p.rate_std),
        "outputs": _cells(run.outputs, (ny, 1)), "inputs": _cells(run.inputs, (nx, 1)),
        "output_units": _cells([run.units[o] for o in run.outputs], (ny, 1)),
        "input_units": _cells([run.units[u] for u in run.inputs], (nx, 1)),
        "output_tags": _cells([run.tags[o] for o in run.outputs], (ny, 1)),
        "input_tags": _cells([run.tags[u] for u in run.inputs], (nx, 1)),
        "settled": _cells([run.pairs[k].settled or "" if k in run.pairs else ""
                           for k in grid], (ny, nx)),
        "grade": _cells([run.pairs[k].grade or "" if k in run.pairs else "" for k in grid],
                        (ny, nx)),
        "tf_kind": _cells([t["kind"] if t else "none" for t in tfs], (ny, nx)),
        "tf_num": _cells(tf_field("num", []), (ny, nx)),
        "tf_den": _cells(tf_field("den", []), (ny, nx)),
        "tf_delay_s": np.array([t["delay_s"] if t else np.nan for t in tfs]).reshape(ny, nx),
        "tf_num_z": _cells([np.atleast_2d(t["discrete"]["num"] if t else []) for t in tfs],
                           (ny, nx)),
        "tf_den_z": _cells([np.atleast_2d(t["discrete"]["den"] if t else []) for t in tfs],
                           (ny, nx)),
        "tf_fit_rms": np.array([_nan(t, "fit_rms") for t in tfs]).reshape(ny, nx),
        "tf_fit_rms_rel": np.array([_nan(t, "fit_rms_rel") for t in tfs]).reshape(ny, nx),
    }
    buf = io.BytesIO()
    scipy.io.savemat(buf, data, do_compression=True, oned_as="column")
    return buf.getvalue()


def _nan(t: dict | None, key: str) -> float:
    return np.nan if t is None or t.get(key) is None else float(t[key])


# ---------------------------------------------------------------------- writing
def output_path(run: RunData, fmt: str, out: str | os.PathLike | None = None, *,
                force: bool = False) -> Path:
    """Where the export goes, checked before any work (module notes).

    Parameters
    ----------
    run : RunData
        The run being exported (its job, run id and directory).
    fmt : str
        One of :data:`FORMATS`.
    out : str or os.PathLike, optional
        A file, or an existing folder for the default name; default the current folder.
    force : bool
        Replace an existing file.

    Returns
    -------
    Path
        Absolute path of the file to write.

    Raises
    ------
    ConfigError
        The rule of :func:`pipeline.adapters.safe_write.safe_target` (a missing folder, a
        target inside a run directory or over the catalog, a non-regular file, an existing
        file without ``force``, a name too long), or a manifest whose job name or run id
        cannot be part of a file name (default name only).
    StorageError
        The folder is not writable.
    """
    from pipeline.adapters.safe_write import check_path_length, safe_name, safe_target

    given = check_path_length(Path.cwd() if out is None else out, "--out")
    if given.is_dir():  # the default name, from the manifest's names checked as the store does
        given = given / safe_name({"job": run.job, "run_id": run.run_id}, suffix=FORMATS[fmt],
                                  where=f"the run's manifest {run.run_dir / 'manifest.json'}")
    return safe_target(given, force=force, option="--out")


def export_run(run_dir: str | os.PathLike, *, fmt: str, out: str | os.PathLike | None = None,
               force: bool = False,
               progress: Callable[[str, str], None] | None = None) -> ExportResult:
    """Export a run's model as ``fmt`` (module notes).

    Parameters
    ----------
    run_dir : str or os.PathLike
        An estimation run directory.
    fmt : str
        ``"csv"``, ``"json"``, ``"mat"`` or ``"control"``.
    out : str or os.PathLike, optional
        Target file or existing folder (:func:`output_path`).
    force : bool
        Replace an existing target file.
    progress : callable, optional
        ``progress(stage, message)`` for one line per fitted pair.

    Returns
    -------
    ExportResult

    Raises
    ------
    ConfigError, DataQualityError, StorageError
        Errors the user can fix (exit 2 in the CLI); nothing is written then.
    """
    if fmt not in FORMATS:
        raise ConfigError(f"format {fmt!r} is not an export format; allowed: "
                          f"{', '.join(FORMATS)}")
    run = read_run(run_dir)
    path = output_path(run, fmt, out, force=force)
    notes = []
    if run.status != "ok":
        notes.append(f"note: run status is {run.status!r} (see {run.run_dir / 'report.md'}); "
                     "exported as stored")
    fits = {} if fmt == "csv" else fit_pairs(run, progress)
    for key, fit in fits.items():
        if isinstance(fit, str):
            notes.append(f"note: {key[0]}<-{key[1]}: {fit}")
        elif fit.fit_rms_rel > 0.1:
            notes.append(f"note: {key[0]}<-{key[1]}: the best {fit.kind} fit misses the step "
                         f"response by {100 * fit.fit_rms_rel:.0f} % RMS of its peak; use the "
                         "step coefficients (csv) for this pair")
    from pipeline.adapters.safe_write import write_atomically

    writer = {"csv": lambda: _csv_bytes(run), "json": lambda: _json_bytes(run, fits),
              "mat": lambda: _mat_bytes(run, fits), "control": lambda: _control_bytes(run, fits)}
    write_atomically(path, writer[fmt](), option="--out")
    return ExportResult(path=path, format=fmt, fits=fits, notes=notes)


# -------------------------------------------------------------------------- loading
def load_control(path: str | os.PathLike, *, delay: str = "discrete",
                 pade_order: int = PADE_ORDER) -> dict:
    """The python-control objects of an exported model (``control`` or ``json`` format).

    Parameters
    ----------
    path : str or os.PathLike
        A file written by ``plantdyn export --format control`` (or ``json``).
    delay : {"discrete", "pade"}
        ``"discrete"`` (default): the exact sampled model at the run's ``dt_s`` (a
        discrete-time ``TransferFunction``, the dead time as powers of ``z^-1``, fractional
        delays included); its step response at sample ``k`` is the fitted curve at
        ``(k + 1/2)·dt_s``, the stored lag ``k + 1``.  ``"pade"``: continuous time, the
        dead time replaced by its Padé approximant of order ``pade_order`` (for s-domain
        design; approximate near the dead time).
    pade_order : int
        Order of the Padé approximant (``delay="pade"``).

    Returns
    -------
    dict
        ``(output, input)`` -> ``control.TransferFunction`` named ``output<-input``; pairs
        that could not be fitted are left out.

    Raises
    ------
    ConfigError
        Not such a file, or an unknown ``delay``.
    """
    from pipeline.adapters.control_lti import pade_transfer_function, sampled_transfer_function

    if delay not in ("discrete", "pade"):
        raise ConfigError(f"delay {delay!r} must be 'discrete' or 'pade'")
    file = Path(path)
    try:
        doc = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{file} cannot be read as an exported model ({exc}); export one "
                          "with `plantdyn export RUN_DIR --format control`") from None
    if not isinstance(doc, dict) or doc.get("schema") not in (SCHEMA_CONTROL, SCHEMA_MODEL):
        raise ConfigError(f"{file} is not a plantdyn control/json export (schema "
                          f"{doc.get('schema') if isinstance(doc, dict) else None!r}; allowed "
                          f"{SCHEMA_CONTROL}, {SCHEMA_MODEL})")
    out = {}
    for p in doc["pairs"]:
        tf = p.get("transfer_function")
        if not tf:
            continue
        names = {"output": p["output"], "input": p["input"]}
        if delay == "discrete":
            d = tf["discrete"]
            out[(p["output"], p["input"])] = sampled_transfer_function(
                d["num"], d["den"], dt_s=d["dt_s"], **names)
        else:
            out[(p["output"], p["input"])] = pade_transfer_function(
                tf["num"], tf["den"], delay_s=tf["delay_s"], order=pade_order, **names)
    return out
