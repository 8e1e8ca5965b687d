"""One summary of an estimation run, rendered to every place a person reads it.

Like statsmodels' ``Summary``, one object holds what a run reports and renders it:
:meth:`RunSummary.to_markdown` is ``report.md`` (and the Prefect report artifact),
:meth:`RunSummary.to_text` the terminal's lines, :meth:`RunSummary.pair_records` the
Prefect pairs table, and ``report.html`` takes its header facts, gain cells, window and
feedback verdicts and data notes from the same object.  Every number a report prints is
formatted here once (the gain cell itself by
:func:`pipeline.identification.settledness.gain_cell`, the grade by
:func:`pipeline.identification.quality.grade_from_checks`).

The summary is read from the run's ``checks.json`` document alone, so a stored run —
old or new — renders to the same text without refitting (the HTML report is rebuilt
from the stored files); absent keys are left out, never guessed.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from pipeline.identification.quality import GRADE_MEANING, GRADE_RULE, grade_from_checks
from pipeline.identification.settledness import gain_cell

__all__ = ["METHOD_TEXT", "PairSummary", "RunSummary", "gain_unit", "signal_units"]

METHOD_TEXT = {
    "least_squares": "least squares, white-noise assumption (the thesis)",
    "prediction_error": "least squares with a noise model per output "
                        "(prediction-error method)",
    "instrumental_variables": "instrumental variables",
    "correlation": "the correlation method (method.md §2), white-noise σ",
    "regularized_tc": "kernel-regularised FIR, TC prior (hyperparameters by marginal "
                      "likelihood, noise model per output, posterior σ)",
    "regularized_dc": "kernel-regularised FIR, DC prior (hyperparameters by marginal "
                      "likelihood, noise model per output, posterior σ)",
}
"""What each ``estimation.method`` of checks.json is, in words."""


def _p(p: Any) -> str:
    """A p-value to 2 significant figures (``n/a`` when missing)."""
    return "n/a" if p is None else f"{float(p):.2g}"


@dataclass(frozen=True)
class PairSummary:
    """What the reports say about one input→output pair.

    Attributes
    ----------
    output, input : str
        Signal names.
    grade : str
        The quality grade, ``"A"`` … ``"D"``.
    reasons : tuple of str
        Why the pair is not an A (empty when every check passes).
    n_p : int
        The pair's horizon in samples.
    horizon_s : float or None
        ``n_p · T`` in seconds.
    settled : str
        The settledness verdict.
    integrating : bool
        The output integrates: the pair has a rate, not a gain.
    value, std : float or None
        The reported gain (rate) and its σ; ``None`` when the pair has none.
    value_text : str
        The gain (rate) cell as every report prints it, with its unit.
    value_plain : str
        The same cell without the unit (tables that show the unit apart).
    unit : str
        The gain's unit, ``output/input`` (``""`` when either is unknown).
    criteria : mapping
        The grade's criteria with their values
        (:attr:`pipeline.identification.quality.Grade.criteria`).
    windows : str
        The window-agreement verdict; ``windows_p`` its p-value.
    feedback : bool or None
        Feedback detected (``None``: not tested); ``feedback_p`` its p-value.
    n_k : int or None
        Leading lags left out (feedback).
    warnings : tuple of (str, str)
        ``(code, message)`` of every warning.
    """

    output: str
    input: str
    grade: str
    reasons: tuple[str, ...]
    n_p: int
    horizon_s: float | None
    settled: str
    integrating: bool
    value: float | None
    std: float | None
    value_text: str
    value_plain: str
    unit: str
    criteria: Mapping[str, Any]
    windows: str
    windows_p: float | None
    feedback: bool | None
    feedback_p: float | None
    n_k: int | None
    warnings: tuple[tuple[str, str], ...]

    @classmethod
    def from_pair(cls, p: Mapping, checks: Mapping, unit: str = "") -> PairSummary:
        """The summary of one entry of ``checks["pairs"]``.

        Parameters
        ----------
        p : mapping
            The pair's entry.
        checks : mapping
            The whole checks.json document (the grade reads the output's whiteness and
            the inputs' excitation).
        unit : str
            The gain's unit (``"bar/bar"``), ``""`` when unknown.
        """
        integ = bool(p.get("integrating"))
        key = "rate" if integ else "gain"
        g = grade_from_checks(dict(p), dict(checks))
        agr = p.get("agreement") or {}
        fb = p.get("feedback")
        dt = checks.get("dt_s")
        n_p = int(p.get("n_p") or 0)
        return cls(
            output=str(p.get("output")), input=str(p.get("input")), grade=g.grade,
            reasons=tuple(g.reasons), n_p=n_p,
            horizon_s=None if dt is None else n_p * float(dt),
            settled=str((p.get("settled") or {}).get("verdict", "")), integrating=integ,
            value=p.get(key), std=p.get(f"{key}_std"),
            value_text=gain_cell(dict(p), key, f" {unit}" if unit and not integ else ""),
            value_plain=gain_cell(dict(p), key), unit=unit, criteria=g.criteria,
            windows=str(agr.get("verdict", "")), windows_p=agr.get("p_value"),
            feedback=None if not isinstance(fb, Mapping) else bool(fb.get("detected")),
            feedback_p=None if not isinstance(fb, Mapping) else fb.get("p_value"),
            n_k=p.get("n_k"),
            warnings=tuple((str(w.get("code")), str(w.get("message")))
                           for w in p.get("warnings") or []))

    @property
    def name(self) -> str:
        """``"output<-input"``."""
        return f"{self.output}<-{self.input}"

    @property
    def quantity(self) -> str:
        """``"rate"`` for an integrating output, else ``"gain"``."""
        return "rate" if self.integrating else "gain"

    @property
    def windows_text(self) -> str:
        """``pass (0.56)``: the window verdict with its p-value."""
        return self.windows + (f" ({_p(self.windows_p)})" if self.windows_p is not None
                               else "")

    @property
    def feedback_text(self) -> str:
        """``not tested``, ``no (0.44)`` or ``detected (0.001), n_k = 1``."""
        if self.feedback is None:
            return "not tested"
        if not self.feedback:
            return f"no ({_p(self.feedback_p)})"
        return f"detected ({_p(self.feedback_p)}), n_k = {self.n_k}"

    def record(self) -> dict:
        """The pair as one row of plain values (the Prefect pairs table)."""
        return {"output": self.output, "input": self.input, "grade": self.grade,
                "n_p": self.n_p, self.quantity: self.value_text,
                "settled": self.settled, "windows": self.windows_text,
                "feedback": self.feedback_text,
                "warnings": ", ".join(code for code, _ in self.warnings)}


@dataclass(frozen=True)
class RunSummary:
    """What an estimation run reports, read from its checks.json, with its renderings.

    Attributes
    ----------
    job : str
        The job's name.
    status : str
        The run's status (``ok``, ``windows_disagree``).
    checks : mapping
        The checks.json document the summary was read from.
    pairs : tuple of PairSummary
        Every pair, outputs major.
    units : mapping of str to str
        Unit per signal name (those known).
    """

    job: str
    status: str
    checks: Mapping[str, Any]
    pairs: tuple[PairSummary, ...]
    units: Mapping[str, str]

    @classmethod
    def from_checks(cls, checks: Mapping, *, job: str, status: str,
                    config: Mapping[str, Any] | None = None) -> RunSummary:
        """Read the summary of a run from its checks.json document.

        Parameters
        ----------
        checks : mapping
            checks.json (as written by the run, or read back from a stored run).
        job : str
            The job's name.
        status : str
            The run's status.
        config : mapping, optional
            The resolved job configuration (its ``signals`` give units; see
            :func:`signal_units`).
        """
        units = signal_units(config, (checks.get("data_quality") or {}).get("signals"))
        pairs = tuple(PairSummary.from_pair(
            p, checks, gain_unit(units, str(p.get("output")), str(p.get("input"))))
                      for p in checks.get("pairs") or [])
        return cls(job, status, checks, pairs, units)

    def with_checks(self, checks: Mapping) -> RunSummary:
        """The same run with an extended checks.json (the monitor's section added).

        Parameters
        ----------
        checks : mapping
            The new document.
        """
        return replace(self, checks=checks)

    @property
    def outputs(self) -> list[str]:
        """Output names in the pairs' order (checks.json's mappings are stored with
        sorted keys; the renderings follow the job's order, read from the pairs list)."""
        return list(dict.fromkeys(p.output for p in self.pairs))

    def pair(self, output: str, input: str) -> PairSummary | None:
        """The pair ``output<-input`` (``None`` when the run has no such pair).

        Parameters
        ----------
        output, input : str
            Signal names.
        """
        return next((p for p in self.pairs if (p.output, p.input) == (output, input)), None)

    # ------------------------------------------------------------------ facts
    @property
    def dt_s(self) -> float | None:
        """The sample period T in seconds."""
        return self.checks.get("dt_s")

    @property
    def n_d(self) -> int | None:
        """Samples per disjoint window."""
        return (self.checks.get("search") or {}).get("n_d")

    @property
    def n_windows(self) -> int:
        """Disjoint windows of the window check."""
        return len((self.checks.get("search") or {}).get("windows") or [])

    def method_text(self) -> str:
        """The estimator in words, with the reason it was chosen (when recorded)."""
        est = self.checks.get("estimation") or {}
        method = est.get("method")
        text = METHOD_TEXT.get(method, str(method))
        if method == "instrumental_variables" and est.get("instruments"):
            text += " (" + ", ".join(est["instruments"]) + ")"
        reason = (est.get("method_choice") or {}).get("reason")
        return text + (f" — {reason}" if reason else "")

    def header_facts(self) -> list[str]:
        """The run's facts as short phrases (report.md's opening, report.html's header)."""
        c, facts = self.checks, []
        sampling = c.get("sampling") or {}
        grid = (c.get("data_quality") or {}).get("grid_dt_s")
        if self.dt_s is not None:
            how = [f"decimation {sampling['decimation']}" if "decimation" in sampling else "",
                   f"from the {grid:g} s grid" if grid is not None else "",
                   str(sampling.get("source") or "")]
            how = " ".join(h for h in how[:2] if h) + (f", {how[2]}" if how[2] else "")
            facts.append(f"sample period T = {self.dt_s:g} s" + (f" ({how})" if how else ""))
        if (c.get("conditioning") or {}).get("method"):
            facts.append(f"conditioning: {c['conditioning']['method']}")
        if self.n_d:
            facts.append(f"N_d per window = {self.n_d}, {self.n_windows} disjoint windows")
        if (c.get("estimation") or {}).get("method"):
            facts.append(f"estimator: {self.method_text()}")
        return facts

    def data_notes(self) -> list[str]:
        """Sentences about the record: stretches not gridded, spikes, stray samples."""
        dq = self.checks.get("data_quality") or {}
        ingest = dq.get("ingest") or {}
        grid = ingest.get("grid") or {}
        notes = []
        if len(grid.get("islands") or []) > 1:
            notes.append(f"The record has {len(grid['islands'])} stretches separated by "
                         "breaks longer than every signal's max_gap_s (not gridded).")
        for name, sp in (ingest.get("spikes") or {}).items():
            notes.append(f"Spikes masked in {name}: {sp.get('samples')} sample(s) far from "
                         f"their neighbours (largest |value| {float(sp.get('largest')):.4g}, "
                         f"first at {sp.get('first')}); quality.spikes: off keeps them.")
        for d in grid.get("stray_samples") or []:
            notes.append(f"Stray samples left out: {d.get('samples')} of {d.get('signal')} "
                         f"(tag {d.get('tag')}) between {d.get('first')} and {d.get('last')}, "
                         "far from the rest of the record — check the export's timestamps.")
        return notes

    def window_notes(self) -> list[str]:
        """The window check when it could not run as planned: each window that could not
        be estimated (when, and why), or no two windows at all."""
        search = self.checks.get("search") or {}
        lines = []
        for w in search.get("windows") or []:
            if w.get("status") == "failed":
                lines.append(f"Window {w['window']} ({w['time'][0]} to {w['time'][1]}, "
                             f"samples {w['samples'][0]}–{w['samples'][1]}) could not be "
                             f"estimated: {w.get('error')}.")
        if "windows" in search and not search["windows"]:
            last = next((t for t in reversed(search.get("nd_trace") or []) if "error" in t),
                        {})
            where = ""
            if "failed_window" in last:
                (a, b), span = last["failed_window"], last.get("failed_window_time") or ["?"] * 2
                where = f"the window {span[0]} to {span[1]} (samples {a}–{b}) cannot be " \
                        "estimated: "
            lines.append("No window check: " + where
                         + (last.get("error") or "no two disjoint windows fit") + ".")
        return lines

    # -------------------------------------------------------------- renderings
    def to_text(self) -> list[str]:
        """The terminal's lines: the sample period, N_d, and one line per pair."""
        lines = [f"dt = {self.dt_s:g} s, N_d per window = {self.n_d}"]
        lines += [f"{p.name}: grade {p.grade}, {p.quantity} {p.value_text}, N_p={p.n_p}, "
                  f"windows {p.windows}" for p in self.pairs]
        return lines

    def pair_records(self) -> list[dict]:
        """One row of plain values per pair (the Prefect pairs table)."""
        return [p.record() for p in self.pairs]

    def to_markdown(self) -> str:
        """``report.md``."""
        from pipeline.readouts.monitor import monitor_banner

        lines = [f"# plantdyn run: {self.job}", ""]
        banner = monitor_banner(self.checks["monitor"]) if "monitor" in self.checks else ""
        if banner:
            lines += [banner, ""]
        lines += [f"Status: **{self.status}**. "
                  + "; ".join(f[0].upper() + f[1:] if k == 0 else f
                              for k, f in enumerate(self.header_facts())) + ".", ""]
        lines += self._pair_table_md() + self._noise_md() + self._grades_md()
        warned = [p for p in self.pairs if p.warnings]
        lines += ["", "## When to distrust a pair", ""]
        if not warned:
            graded = [p for p in self.pairs if p.grade in "CD"]
            lines.append("No warnings: residuals white under the noise models, no feedback "
                         "without an instrument, N_p inside its bounds, windows agree."
                         + (f" {len(graded)} pair(s) are graded C or D all the same: the "
                            "quality grades above say why and what to change."
                            if graded else ""))
        lines += _distrust_md(warned)
        windows = self.window_notes()
        if windows:
            lines += ["", "## The window check", ""] + [f"- {w}" for w in windows]
        signals = (self.checks.get("data_quality") or {}).get("signals") or {}
        masked = {n: signals[n]["masked"] for n in sorted(signals) if signals[n].get("masked")}
        lines += ["", f"Masked grid samples per signal: {masked or 'none'}."]
        lines += self.data_notes()
        return "\n".join(lines) + "\n"

    def _pair_table_md(self) -> list[str]:
        lines = ["| output | input | grade | N_p | N_p·T (s) | settled | gain ± σ "
                 "| rate K ± σ (/s) | windows (p) | feedback (p) | warnings |",
                 "|---|---|---|---|---|---|---|---|---|---|---|"]
        for p in self.pairs:
            gain, rate = ("", p.value_text) if p.integrating else (p.value_text, "")
            fb = f"**{p.feedback_text}**" if p.feedback else p.feedback_text
            codes = ", ".join(code for code, _ in p.warnings) or "none"
            horizon = "" if p.horizon_s is None else f"{p.horizon_s:g}"
            lines.append(f"| {p.output} | {p.input} | {p.grade} | {p.n_p} | {horizon} "
                         f"| {p.settled} | {gain} | {rate} | {p.windows_text} | {fb} "
                         f"| {codes} |")
        return lines

    def _noise_md(self) -> list[str]:
        models = self.checks.get("noise_model") or {}
        white = (self.checks.get("residuals") or {}).get("whiteness") or {}
        lines = ["", "Noise models (per output, chosen from the data):", ""]
        for o in self.outputs + sorted(set(models) - set(self.outputs)):
            if o not in models:
                continue
            nm = models[o]
            pole = nm.get("dominant_pole")
            kind = "white" if nm["order"] == 0 else f"AR({nm['order']})" + \
                (f", slowest pole {pole:.3f}" if pole is not None else "")
            w = white.get(o) or {}
            lines.append(f"- {o}: {kind}, {nm['form']} form, innovation σ "
                         f"{nm['innovation_std']:.3g}; prediction errors "
                         f"{'white' if w.get('white') else 'NOT white'}"
                         f" (Ljung–Box p = {_p(w.get('p_value'))})")
        return lines

    def _grades_md(self) -> list[str]:
        lines = ["", "## Quality grades", ""]
        lines += [f"- {p.name}: **{p.grade}**"
                  + (f" — {'; '.join(p.reasons)}" if p.reasons else " — every check passes")
                  for p in self.pairs]
        lines += ["", "Each criterion caps the grade; the grade is the worst cap ("
                  + "; ".join(f"{g} {t}" for g, t in GRADE_MEANING.items()) + "):", "",
                  "| criterion | read from | A | B | C | D |", "|---|---|---|---|---|---|"]
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |"
                  for row in GRADE_RULE]
        return lines


def signal_units(config: Mapping[str, Any] | None,
                 quality: Mapping[str, Any] | None) -> dict[str, str]:
    """Unit per signal name: the job's ``signals.<role>.<name>.unit``, else the unit the
    export's header gave (``data_quality.signals.<name>.ingest.unit``), else none.

    Parameters
    ----------
    config : mapping or None
        The resolved job configuration (``manifest.json`` ``config``).
    quality : mapping or None
        Per-signal data-quality records (checks.json ``data_quality.signals`` or
        discrepancy.json ``data.quality``).
    """
    units: dict[str, str] = {}
    for name, q in (quality or {}).items():
        ingest = q.get("ingest") if isinstance(q, Mapping) else None
        if isinstance(ingest, Mapping) and ingest.get("unit"):
            units[name] = str(ingest["unit"])
    signals = (config or {}).get("signals") or {}
    for role in ("inputs", "outputs", "instruments"):
        for name, spec in (signals.get(role) or {}).items():
            if isinstance(spec, Mapping) and spec.get("unit"):
                units[name] = str(spec["unit"])
    return units


def gain_unit(units: Mapping[str, str], output: str, input: str) -> str:
    """A gain's unit, ``output_unit/input_unit``, when both are known, else ``""``.

    Parameters
    ----------
    units : mapping of str to str
        Unit per signal name (:func:`signal_units`).
    output, input : str
        Signal names.
    """
    uo, ui = units.get(output), units.get(input)
    return f"{uo}/{ui}" if uo and ui else ""


def _distrust_md(warned: list[PairSummary]) -> list[str]:
    """One line per distinct warning: a cause shared by several pairs (the output's
    residuals, say) is said once with every pair it touches and their grades."""
    groups: dict[tuple[str, str], list[str]] = {}
    for p in warned:
        for code, msg in p.warnings:
            groups.setdefault((code, msg), []).append(f"**{p.name}** ({p.grade})")
    return [f"- {', '.join(who)} — {code}: {msg}." for (code, msg), who in groups.items()]
