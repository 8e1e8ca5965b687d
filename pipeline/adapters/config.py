"""Job configuration: the only YAML parser of plantdyn (pydantic v2, ``extra="forbid"``).

A job YAML (design.md) is parsed into :class:`JobConfig`.  Every error is a
:class:`~pipeline.errors.ConfigError` that names the file, the YAML key path, the bad
value and what is allowed.

Path policy (decision): relative paths resolve against the job file's folder.  Source
files and the storage root must lie inside an *allowed root*: the job file's folder,
its parent (so the usual ``../storage`` and ``../exports`` work), and any folder listed
in the environment variable ``PLANTDYN_ALLOWED_ROOTS`` (``os.pathsep``-separated).  A
job file cannot widen its own roots: that is the operator's call, not the author's.
"""

from __future__ import annotations

import glob
import os
from pathlib import Path
from typing import Any, ClassVar, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from pipeline.adapters.ingest.options import CsvOptions as IngestCsvOptions
from pipeline.adapters.ingest.options import McapOptions as IngestMcapOptions
from pipeline.adapters.yaml_text import (  # noqa: F401 - re-exported
    MAX_YAML_BYTES,
    MAX_YAML_DEPTH,
    MAX_YAML_VALUES,
    load_yaml_file,
    parse_yaml_text,
)
from pipeline.errors import ConfigError

__all__ = [
    "JobConfig",
    "SignalConfig",
    "load_job",
    "job_from_dict",
    "resolve_sources",
    "allowed_roots",
    "load_yaml_file",
    "parse_yaml_text",
    "load_model_spec",
    "dump_yaml",
    "DiscrepancySection",
    "MonitorConfig",
    "NightlyConfig",
]


class _Strict(BaseModel):
    # every float finite: .inf / .nan pass a "> 0" check and crash later
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SignalConfig(_Strict):
    """One measured signal: its historian tag and how to put it on the grid."""

    tag: str = Field(min_length=1, max_length=200)
    integrating: bool = False
    interpolation: Literal["linear", "hold"] | None = None
    """Default: linear for inputs, hold for outputs (exception-reported PVs)."""
    max_gap_s: float | None = Field(default=None, gt=0, le=30 * 86_400)
    """Longest span bridged by interpolation/hold; default 10 grid periods."""
    unit: str | None = None
    scale: float = Field(default=1.0, gt=0.0, le=1e9)
    """Multiplies the exported values before anything else uses them: puts a signal in
    the units a model or a reader expects (100 for an OP exported as a fraction 0-1
    where the model works in %)."""


class SignalsConfig(_Strict):
    inputs: dict[str, SignalConfig] = Field(min_length=1)
    outputs: dict[str, SignalConfig] = Field(min_length=1)
    instruments: dict[str, SignalConfig] = Field(default_factory=dict)
    """External signals that move the inputs but are not moved by the outputs' noise
    (setpoints, measured disturbances): with instruments the estimate is
    instrument-based and consistent in closed loop.  Interpolation defaults to hold
    (setpoints are step signals)."""

    @field_validator("inputs", "outputs", "instruments")
    @classmethod
    def _names(cls, v: dict[str, SignalConfig]) -> dict[str, SignalConfig]:
        for name in v:
            if not name.replace("_", "").replace("-", "").isalnum():
                raise ValueError(
                    f"signal name {name!r} must be letters, digits, '_' or '-' "
                    "(it becomes a column and an entity path)"
                )
        return v


# The ingest options own the defaults; these sections add the YAML's types and bounds.
_MCAP, _CSV = IngestMcapOptions(), IngestCsvOptions()


class McapConfig(_Strict):
    """``source.mcap``: how samples are found in MCAP messages (see
    :class:`pipeline.adapters.ingest.McapOptions`, whose defaults these are)."""

    time_field: str | None = _MCAP.time_field
    value_field: str = _MCAP.value_field
    quality_field: str | None = _MCAP.quality_field
    tag_field: str | None = _MCAP.tag_field
    """Field holding the tag; default: the topic name is the tag."""
    time_unit: Literal["s", "ms", "us", "ns"] = _MCAP.time_unit
    """Unit of numeric times (a recorder writing milliseconds needs ``ms``)."""
    topics: list[str] | None = _MCAP.topics
    topic_prefix: str = _MCAP.topic_prefix
    samples_field: str = _MCAP.samples_field


class CsvConfig(_Strict):
    """``source.csv``: overrides for historian-CSV detection; every unset key is detected
    (see :class:`pipeline.adapters.ingest.CsvOptions`, whose defaults these are)."""

    separator: Literal[",", ";", "\t", "|"] | None = _CSV.separator
    decimal: Literal[".", ","] | None = _CSV.decimal
    encoding: str | None = _CSV.encoding
    """A codec name (``cp1252``, ``latin-1``, ``utf-16``); default: UTF-8 or the BOM's."""
    skip_lines: int = Field(default=_CSV.skip_lines, ge=0, le=10_000)
    tag_column: str | None = _CSV.tag_column
    time_column: str | None = _CSV.time_column
    value_column: str | None = _CSV.value_column
    quality_column: str | None = _CSV.quality_column
    header_rows: int | None = Field(default=_CSV.header_rows, ge=1, le=100)
    tag_row: int = Field(default=_CSV.tag_row, ge=0, le=100)
    unit_row: int | None = Field(default=_CSV.unit_row, ge=0, le=100)
    description_row: int | None = Field(default=_CSV.description_row, ge=0, le=100)
    time_format: str | None = _CSV.time_format
    """A strptime format (``"%m-%d-%Y %H:%M:%S"``) or ``epoch_s``."""
    quality_map: dict[str, Literal["good", "suspect", "bad"]] | None = _CSV.quality_map

    @field_validator("encoding")
    @classmethod
    def _codec(cls, v):
        import codecs

        if v is not None:
            try:
                codecs.lookup(v)
            except LookupError:
                raise ValueError(f"{v!r} is not a known text encoding; use e.g. 'utf-8', "
                                 "'cp1252', 'latin-1' or 'utf-16'") from None
        return v


class SourceConfig(_Strict):
    path: str = Field(min_length=1)
    """File or glob, relative to the job file; .csv or .mcap."""
    timezone: str
    """Zone of the export's naive timestamps — required: a wrong guess shifts every
    sample by hours (and DST) without a sign."""
    layout: Literal["auto", "long", "wide", "mcap"] = "auto"
    on_truncated: Literal["error", "warn"] = "error"
    mcap: McapConfig | None = None
    csv: CsvConfig | None = None
    grid_dt_s: float | None = Field(default=None, ge=0.001, le=86_400)
    """Period of the uniform grid before α_T resampling; default: median sample spacing."""
    time_order: Literal["fix", "strict"] = "fix"
    """``fix``: duplicates (last wins) and out-of-order rows are resolved and counted in
    checks.json; ``strict``: any duplicate or out-of-order timestamp is an error (for
    exports that are supposed to be clean, where disorder signals a broken export)."""

    @field_validator("timezone")
    @classmethod
    def _tz(cls, v: str) -> str:
        from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

        if len(v) > 64:  # the longest IANA name has 32 characters
            raise ValueError(f"a time zone of {len(v)} characters ({v[:40]!r}…) is not an IANA "
                             "name; use one such as 'UTC', 'Europe/Berlin' or 'America/Chicago'")
        try:
            ZoneInfo(v)
        except (ZoneInfoNotFoundError, ValueError, OSError) as exc:
            raise ValueError(
                f"unknown time zone {v!r}; use an IANA name such as 'UTC', "
                "'Europe/Berlin' or 'America/Chicago'"
            ) from exc
        return v


class SamplingConfig(_Strict):
    dt_s: float | None = Field(default=None, ge=0.001, le=86_400)
    """Fix the sample period; default: chosen by the α_T criterion."""
    target_input: float = Field(default=0.05, gt=0, lt=1)
    target_output: float = Field(default=0.01, gt=0, lt=1)


class ConditioningConfig(_Strict):
    method: Literal["mean", "detrend", "difference", "highpass"] = "detrend"
    kdiff1: int = Field(default=1, ge=1, le=100_000)
    cutoff_period_s: float | None = Field(default=None, gt=0, le=1e8)
    order: int = Field(default=2, ge=1, le=8)


class SearchConfig(_Strict):
    n_p: int | None = Field(default=None, ge=1, le=5000)
    """Fix N_p for every pair (skips the N_p search)."""
    settling_time_s: float | None = Field(default=None, gt=0, le=1e8)
    """If known: N_p = settling_time_s / T (method.md §5)."""
    n_p_min: int = Field(default=3, ge=1, le=5000)
    n_p_max: int | None = Field(default=None, ge=1, le=5000)
    n_d_start: int | None = Field(default=None, ge=1, le=100_000_000)
    max_windows: int = Field(default=4, ge=2, le=50)

    @model_validator(mode="after")
    def _orders(self):
        if self.n_p_max is not None and self.n_p_min > self.n_p_max:
            raise ValueError(f"search.n_p_min ({self.n_p_min}) is above search.n_p_max "
                             f"({self.n_p_max}); lower n_p_min or raise n_p_max")
        return self


class ChecksConfig(_Strict):
    ljung_box_lags: int = Field(default=20, ge=1, le=1000)
    xcorr_max_lag: int | None = Field(default=None, ge=1, le=5000)
    """Default: the pair's N_p."""


class EstimationConfig(_Strict):
    """How step responses are estimated (method.md §10)."""

    method: Literal["auto", "ls", "correlation", "tc", "dc"] = "auto"
    """``auto`` (the default): least squares when the record holds at least 10 observations
    per unknown and every pair settled within the search's horizon, the kernel-regularised
    FIR otherwise (:mod:`pipeline.identification.method_choice`; checks.json ``estimation.method_choice``
    says which and why); ``ls``: least squares (with the noise model and instruments
    below); ``correlation``: the thesis' older correlation method (method.md §2;
    whole-window auto-correlations, masked samples enter as zeros; white noise; a
    comparison method that degrades with input drift); ``tc`` / ``dc``: kernel-regularised
    least squares with a TC / DC prior whose hyperparameters maximise the marginal
    likelihood, with the noise model below (method.md §11; for short records: one horizon
    for every pair, twice the search's longest).  Only ``ls`` and ``auto`` take
    instruments; the search of N_p/N_d is the least-squares one in every case."""
    noise: str | int = "auto"
    """``auto``: per output a noise model chosen from the data (AR order by BIC; for
    integrating outputs also the differenced or level form); ``white``: the thesis' least
    squares (right only for white noise); an int fixes the AR order (0..40)."""
    n_k: int | dict[str, dict[str, int]] = 0
    """Known delay in samples, ``Δh(1..n_k) = 0``: one int for every pair, or
    ``{output: {input: n_k}}`` (unlisted pairs 0)."""
    feedback: Literal["auto", "report", "off"] = "auto"
    """``auto``: a pair with detected feedback and no instrument gets ``n_k >= 1``;
    ``report``: test and report only; ``off``: no feedback test."""

    @model_validator(mode="before")
    @classmethod
    def _white_for_alternatives(cls, data):
        if isinstance(data, dict) and data.get("method") == "correlation":
            noise = data.get("noise", "white")
            if noise != "white":
                raise ValueError(
                    f"estimation.noise: {noise!r} does not apply to the correlation method: it "
                    "assumes white noise — remove estimation.noise or set it to white (or "
                    "use method: auto, ls, tc or dc for a noise model)")
            data = {**data, "noise": "white"}
        return data

    @field_validator("noise", mode="before")
    @classmethod
    def _order(cls, v):
        if v in ("auto", "white") or (isinstance(v, int) and not isinstance(v, bool)
                                      and 0 <= v <= 40):
            return v
        raise ValueError("must be 'auto', 'white' or an AR order 0..40")

    @field_validator("n_k")
    @classmethod
    def _nk(cls, v):
        vals = [v] if isinstance(v, int) else [n for row in v.values() for n in row.values()]
        if any(isinstance(n, bool) or n < 0 or n > 1000 for n in vals):
            raise ValueError(f"known delays must be integers 0..1000 samples; got {v}")
        return v


class QualityConfig(_Strict):
    """Data-quality steps on the grid before anything is estimated."""

    spikes: Literal["mask", "off"] = "mask"
    """``mask``: isolated samples far from their neighbours are masked and reported
    (:mod:`pipeline.identification.spikes`); ``off`` keeps every sample."""
    spike_sigmas: float = Field(default=20.0, ge=3.0, le=1e6, allow_inf_nan=False)
    """Deviation from the running median, in robust noise s.d., that makes a spike."""


class RerunConfig(_Strict):
    enabled: bool = True


class DiscrepancySection(_Strict):
    """The job's optional ``discrepancy:`` section (discrepancy jobs only).

    Workflow keys are read by :mod:`pipeline.jobs.discrepancy`; every other key is a
    setting of :class:`pipeline.discrepancy.DiscrepancyConfig` (same name, same meaning;
    unset keys keep the core's automatic defaults).  A test keeps the two lists equal.
    """

    # --- workflow keys
    simulator_outputs: dict[str, str] | None = None
    """External simulator: ``{measured_output: recorded_signal}`` where the recorded
    signal (listed under ``signals.inputs``) holds a simulator's prediction of that
    output.  Replaces ``model:``; effects then apply at the outputs only."""
    operating_point: Literal["mean", "none"] | dict[str, float] = "mean"
    """Models are in deviation variables: subtract each signal's mean over the analysed
    stretch (``mean``), nothing (``none``), or given values ``{signal: value}`` (others
    by their mean).  A sensor bias is only identifiable against given values."""
    seed: int = Field(default=0, ge=0)
    """Seeds the localisation bootstrap (the only random step)."""
    # --- settings of pipeline.discrepancy.DiscrepancyConfig
    effects: list[str] | None = None
    holdout_fraction: float | None = None
    warmup_s: float | None = None
    initial: Literal["rest", "steady"] | None = None
    ar_order_max: int | None = None
    bic_margin: float | None = None
    holdout_z_min: float | None = None
    holdout_rms_alpha: float | None = None
    lookalike_margin: float | None = None
    n_fit_candidates: int | None = None
    max_delay_s: float | None = None
    n_bootstrap: int | None = None
    load_signal: str | None = None
    n_load_bins: int | None = None
    max_nfev: int | None = None
    max_effects: int | None = None
    min_gap_reduction: float | None = None
    lookalike_gap: float | None = None
    max_time_s: float | None = None
    """Time budget of the search chain, s (default 600); ``null`` for none."""
    open_loops: bool | None = None
    """Drive the actuator path with each measured controller output (default true)."""

    WORKFLOW_KEYS: ClassVar[tuple[str, ...]] = ("simulator_outputs", "operating_point", "seed")

    def core_settings(self) -> dict[str, Any]:
        """The keys set in the YAML that belong to ``DiscrepancyConfig``."""
        out = {}
        for key in self.model_fields_set - set(self.WORKFLOW_KEYS):
            value = getattr(self, key)
            if value is not None or key in ("warmup_s", "max_delay_s", "load_signal",
                                            "max_time_s"):
                out[key] = tuple(value) if key == "effects" else value
        return out


class MonitorConfig(_Strict):
    """``monitor:``: compare every run with a pinned baseline run (:mod:`pipeline.readouts.monitor`)."""

    baseline: str = Field(default="first", min_length=1, max_length=64)
    """A run id of this job, or ``first``: the job's first run in the catalog (with no
    earlier run, the run itself becomes the baseline)."""
    threshold_sigma: float = Field(default=3.0, ge=1.0, le=50.0)
    """A pair is ``changed`` when its gain (rate), dead time or step response differs
    from the baseline's by more than this many σ (both runs' σ combined)."""

    @field_validator("baseline")
    @classmethod
    def _run_id(cls, v: str) -> str:
        import re

        if v != "first" and not re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*", v):
            raise ValueError("must be 'first' or a run id of this job (letters, digits, "
                             "'_', '-', '.'; as `plantdyn runs JOB` lists them)")
        return v


class DaskConfig(_Strict):
    address: str | None = None
    """Dask scheduler address (``tcp://host:8786``); absent runs in-process."""

    @model_validator(mode="before")
    @classmethod
    def _address_given(cls, data: Any) -> Any:
        # `dask: {address: }` parses as null: a forgotten address, not "run locally"
        if isinstance(data, dict) and "address" in data and \
                not str(data["address"] or "").strip():
            raise ValueError("address is empty; give the Dask scheduler's address, e.g. "
                             "dask: {address: tcp://10.0.0.5:8786}, or remove the dask: "
                             "section to run on this machine")
        return data


class NightlyConfig(_Strict):
    """``nightly:``: how ``plantdyn nightly`` takes the files of the drop folder
    (:mod:`pipeline.jobs.nightly`)."""

    max_parallel: int | None = Field(default=None, ge=1, le=256)
    """Files processed at the same time; default from the cores and the free memory
    (:func:`pipeline.adapters.drop_folder.default_max_parallel`)."""
    settle_s: float = Field(default=60.0, ge=0, le=7 * 86_400)
    """A file is taken once unchanged (size and modification time) for this long;
    ``$PLANTDYN_SETTLE_S`` overrides it."""
    marker: str | None = Field(default=None, min_length=1, max_length=32,
                               pattern=r"^\.[A-Za-z0-9_.-]+$")
    """A suffix such as ``.done``: a file is taken only once ``<file><marker>`` exists
    (the exporter writes it when the file is complete); the settle time is not used."""


class JobConfig(_Strict):
    """A validated estimation (or discrepancy) job."""

    job: str = Field(pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$", min_length=1, max_length=64)
    source: SourceConfig
    signals: SignalsConfig
    storage: str = "../storage"
    sampling: SamplingConfig = SamplingConfig()
    conditioning: ConditioningConfig = ConditioningConfig()
    search: SearchConfig = SearchConfig()
    checks: ChecksConfig = ChecksConfig()
    estimation: EstimationConfig = EstimationConfig()
    quality: QualityConfig = QualityConfig()
    rerun: RerunConfig = RerunConfig()
    dask: DaskConfig = DaskConfig()
    nightly: NightlyConfig = NightlyConfig()
    monitor: MonitorConfig | None = None
    """Compare each run with a baseline run (nightly monitoring); off when absent."""
    schedule: str | None = None
    """Cron string for the nightly deployment (e.g. ``"0 2 * * *"``)."""
    model: Any = None
    """Discrepancy jobs: path to a model YAML (relative to the job file) or the mapping."""
    discrepancy: DiscrepancySection | None = None
    base_dir: str = "."
    """Folder of the job file (set by :func:`load_job`; not a YAML key users write)."""

    @field_validator("signals")
    @classmethod
    def _disjoint(cls, v: SignalsConfig) -> SignalsConfig:
        both = set(v.inputs) & set(v.outputs)
        if both:
            raise ValueError(f"signal names {sorted(both)} appear as both input and output")
        twice = (set(v.inputs) | set(v.outputs)) & set(v.instruments)
        if twice:
            raise ValueError(f"signal names {sorted(twice)} appear as instruments and as "
                             "inputs or outputs; an instrument is an extra signal — give it "
                             "its own name (the same tag may appear twice)")
        return v

    @model_validator(mode="after")
    def _method_takes_no_instruments(self) -> JobConfig:
        m = self.estimation.method
        if m not in ("ls", "auto") and self.signals.instruments:
            raise ValueError(
                f"estimation.method: {m} takes no instruments, but signals.instruments lists "
                f"{sorted(self.signals.instruments)}; use method: ls (instrumental variables) "
                "or remove signals.instruments")
        return self

    @model_validator(mode="after")
    def _n_k_names(self) -> JobConfig:
        nk = self.estimation.n_k
        top = nk if isinstance(nk, int) else max((v for r in nk.values() for v in r.values()),
                                                 default=0)
        if self.search.n_p is not None and top >= self.search.n_p:
            raise ValueError(f"estimation.n_k ({top}) must be smaller than search.n_p "
                             f"({self.search.n_p}): n_k fixes the first n_k of the n_p "
                             "step-response increments at zero")
        if isinstance(nk, dict):
            for out, row in nk.items():
                if out not in self.signals.outputs:
                    raise ValueError(f"estimation.n_k: {out!r} is not an output "
                                     f"(signals.outputs: {sorted(self.signals.outputs)})")
                for inp in row:
                    if inp not in self.signals.inputs:
                        raise ValueError(f"estimation.n_k.{out}: {inp!r} is not an input "
                                         f"(signals.inputs: {sorted(self.signals.inputs)})")
        return self

    def n_k_matrix(self):
        """``estimation.n_k`` as an int array (n_outputs, n_inputs)."""
        import numpy as np

        outs, ins = list(self.signals.outputs), list(self.signals.inputs)
        nk = self.estimation.n_k
        if isinstance(nk, int):
            return np.full((len(outs), len(ins)), nk, dtype=int)
        m = np.zeros((len(outs), len(ins)), dtype=int)
        for out, row in nk.items():
            for inp, v in row.items():
                m[outs.index(out), ins.index(inp)] = v
        return m

    @model_validator(mode="after")
    def _simulator_or_model(self) -> JobConfig:
        sim = self.discrepancy.simulator_outputs if self.discrepancy else None
        if sim is None:
            return self
        if self.model is not None:
            raise ValueError("give either model: (a block-diagram model) or "
                             "discrepancy.simulator_outputs (an external simulator's recorded "
                             "outputs), not both")
        for out, sig in sim.items():
            if out not in self.signals.outputs:
                raise ValueError(f"discrepancy.simulator_outputs: {out!r} is not a measured "
                                 f"output (signals.outputs: {sorted(self.signals.outputs)})")
            if sig not in self.signals.inputs:
                raise ValueError(f"discrepancy.simulator_outputs: {out!r} -> {sig!r}: list the "
                                 f"simulator's recorded signal {sig!r} under signals.inputs "
                                 f"(inputs: {sorted(self.signals.inputs)})")
        return self

    # --- resolved paths
    @property
    def base(self) -> Path:
        return Path(self.base_dir)

    @property
    def storage_root(self) -> Path:
        root = (self.base / self.storage).resolve()
        _check_allowed(root, self.base, "storage")
        if root.exists() and not root.is_dir():
            raise ConfigError(f"storage: {str(root)!r} is a file, not a folder; point "
                              "storage at a folder for the results (it is created if missing)")
        return root

    def tags(self) -> dict[str, str]:
        """Signal name -> tag, inputs first, then outputs and instruments."""
        return {n: s.tag for n, s in {**self.signals.inputs, **self.signals.outputs,
                                      **self.signals.instruments}.items()}


def allowed_roots(base: Path) -> list[Path]:
    """Folders that job paths (storage, sources, model) must lie under.

    Parameters
    ----------
    base : Path
        The job file's folder; it and its parent are allowed, and so is every folder in
        the ``PLANTDYN_ALLOWED_ROOTS`` environment variable (``os.pathsep``-separated).
        All are resolved.
    """
    roots = [base.resolve(), base.resolve().parent]
    extra = os.environ.get("PLANTDYN_ALLOWED_ROOTS", "")
    roots += [Path(p).resolve() for p in extra.split(os.pathsep) if p]
    return roots


def _check_allowed(path: Path, base: Path, key: str) -> None:
    roots = allowed_roots(base)
    if not any(path == r or r in path.parents for r in roots):
        raise ConfigError(
            f"{key}: {str(path)!r} is outside the allowed roots "
            f"{[str(r) for r in roots]}; move the data under the job's folder or its parent, "
            "or add its folder to the PLANTDYN_ALLOWED_ROOTS environment variable"
        )


_MISSING_HINTS = {
    "source.timezone": "the zone of the export's naive timestamps, e.g. UTC or Europe/Berlin "
                       "(a wrong zone shifts every sample by hours)",
    "source.path": "the export file or glob, relative to the job file",
    "signals.inputs": "the manipulated or measured inputs, {name: {tag: ...}}",
    "signals.outputs": "the outputs, {name: {tag: ...}}",
}


def _format_validation_error(exc: ValidationError, where: str) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "<top level>"
        if err["type"] == "extra_forbidden":
            parts.append(f"{loc}: unknown key (not allowed here; check the spelling)")
            continue
        if err["type"] == "missing":
            hint = _MISSING_HINTS.get(loc)
            parts.append(f"{loc}: required key is missing" + (f" — {hint}" if hint else ""))
            continue
        val = err.get("input")
        text = repr(val) if not isinstance(val, dict) else "{...}"
        if len(text) > 80:
            text = text[:77] + "..."
        msg = err["msg"].removeprefix("Value error, ")
        parts.append(f"{loc}: {msg} (got {text})")
    return f"invalid job configuration in {where}: " + "; ".join(parts)


def job_from_dict(data: Any, *, base_dir: Path | str = ".", where: str = "<dict>") -> JobConfig:
    """Validate a parsed job mapping.  ``base_dir`` resolves relative paths.

    Parameters
    ----------
    data : mapping
        The parsed job YAML (top-level keys job, source, signals, storage, ...); it must
        not hold ``base_dir``.
    base_dir : Path or str
        Folder that relative paths resolve against (the job file's folder); stored
        resolved.
    where : str
        Name of the configuration's origin (e.g. the file path), for error messages.
    """
    if not isinstance(data, dict):
        raise ConfigError(
            f"invalid job configuration in {where}: the top level must be a mapping with keys "
            f"job, source, signals, storage; got {type(data).__name__}"
        )
    if "base_dir" in data:
        raise ConfigError(f"invalid job configuration in {where}: base_dir: unknown key "
                          "(not allowed here; paths resolve against the job file's folder)")
    try:
        return JobConfig.model_validate({**data, "base_dir": str(Path(base_dir).resolve())})
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, where)) from None


def load_job(path: Path | str) -> JobConfig:
    """Read and validate a job YAML file.

    Parameters
    ----------
    path : Path or str
        The job YAML; relative paths in it resolve against its folder.
    """
    p = Path(path)
    return job_from_dict(load_yaml_file(p), base_dir=p.resolve().parent, where=str(p))


def resolve_sources(cfg: JobConfig, *, skip_suffix: str | None = None) -> list[Path]:
    """Files matched by ``source.path`` (sorted), checked against the allowed roots.

    Parameters
    ----------
    cfg : JobConfig
        The validated job; ``source.path`` (a path or glob) is relative to its folder.
    skip_suffix : str, optional
        Leave out files whose name ends so (the nightly's marker files, ``nightly.marker``).
    """
    pattern = str(cfg.base / cfg.source.path)
    files = sorted(Path(f).resolve() for f in glob.glob(pattern)
                   if not (skip_suffix and f.endswith(skip_suffix)))
    files = [f for f in files if f.is_file()]
    if not files:
        raise ConfigError(
            f"source.path: no file matches {cfg.source.path!r} (looked for {pattern}); "
            "check the path (relative to the job file) and the glob"
        )
    for f in files:
        _check_allowed(f, cfg.base, "source.path")
        if f.suffix.lower() not in (".csv", ".txt", ".mcap"):
            raise ConfigError(
                f"source.path: {f.name!r} has suffix {f.suffix!r}; allowed: .csv, .txt, .mcap"
            )
    return files


def load_model_spec(cfg: JobConfig) -> dict:
    """The ``model:`` section as a mapping (reading the YAML file when it is a path).

    Parameters
    ----------
    cfg : JobConfig
        The validated job; its ``model`` is a path (relative to the job's folder) or a
        mapping, either possibly wrapped in a top-level ``model`` key.
    """
    if cfg.model is None:
        raise ConfigError("model: a discrepancy job needs a model (path to a model YAML or "
                          "the mapping inline)")
    if isinstance(cfg.model, str):
        p = (cfg.base / cfg.model).resolve()
        _check_allowed(p, cfg.base, "model")
        data = load_yaml_file(p, what="model file")
        if isinstance(data, dict) and "model" in data:
            data = data["model"]
        return data
    if isinstance(cfg.model, dict):
        return cfg.model.get("model", cfg.model)
    raise ConfigError(f"model: expected a path or a mapping; got {type(cfg.model).__name__}")


def dump_yaml(data: Any, *, header: str = "") -> str:
    """YAML text of plain data (block style, key order kept), with ``#`` header lines.

    Parameters
    ----------
    data : object
        Plain data (mappings, lists, strings, numbers) for :func:`yaml.safe_dump`.
    header : str
        Text written before the YAML, each line as a ``# `` comment (an empty line as
        ``#``); ``""`` writes none.
    """
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, allow_unicode=True,
                          width=100)
    lines = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    return lines + body
