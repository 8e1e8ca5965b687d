"""Nightly monitoring: has a pair's response moved away from a baseline run's? (issue 13)

Each monitored run compares every input→output pair with the same pair of a pinned
baseline run, on the uncertainty both runs already store (``step_std`` per lag, the
gain's or rate's σ).  The two runs are estimated from disjoint records, so their errors
are independent and the σ of a difference is ``sqrt(σ_base² + σ_run²)``.  Three numbers
per pair, each a z on the same scale (a standard normal deviate under "nothing
changed"), each judged against ``threshold_sigma``:

``gain_z``
    ``|K_run − K_base| / sqrt(σ_K,run² + σ_K,base²)`` with ``K`` the static gain (the
    final step, the FIR model's own gain) — or the rate for an integrating output.
``dead_time_z``
    ``|θ_run − θ_base| / sqrt(σ_θ,run² + σ_θ,base²)``.  The runs store no σ of the dead
    time (it is a read-off, not a parameter), so each run's σ_θ is computed here by a
    parametric bootstrap of the read-off (:func:`dead_time_std`): the step response is
    perturbed by Gaussian random walks scaled to the stored ``step_std`` at every lag
    (a step response is a cumulative sum of increments, so its errors are strongly
    correlated from lag to lag, as a random walk's), and the read-off of
    :mod:`pipeline.readouts.characteristics` is repeated.  The read-off is resolved to one
    sample (its rule is exact on the grid and within a sample between), so σ_θ is at
    least ``T/√12`` (a uniform error over one sample): a change must exceed about 1.2
    samples to count.  The bootstrap perturbs an estimate that is itself noisy, so it
    overstates σ_θ somewhat (measured: z² averages 0.2–0.4 on quiet simulated nights,
    1 if exact) — conservative; a shifted response is caught by ``step_max_z`` anyway
    (a 2-sample extra delay: step z ≈ 11, dead-time z ≈ 2).  ``None`` when either
    run's response is too small to time.
``step_max_z``
    the whole step response, over the ``m`` lags both runs estimate: the largest
    ``|Δ_l| / σ_l`` (``σ_l² = step_std_run,l² + step_std_base,l²``) converted to the
    z of a single comparison with the same false-alarm probability by the Šidák
    correction, ``p = 1 − (1 − p_max)^m``, ``z = Φ⁻¹(1 − p/2)``.

Why the Šidák-corrected maximum and not a Wald statistic: the runs store the marginal σ
of each lag, not the covariance across lags, and the lags of a step response are highly
correlated (cumulative sums), so a χ² of the lags treated as independent would be far
from its nominal distribution.  The maximum with Šidák's correction needs no covariance:
for jointly Gaussian statistics Šidák's inequality ``P(all |Z_l| ≤ c) ≥ Π P(|Z_l| ≤ c)``
holds whatever their correlation, so the false-alarm rate is at most the nominal one
(exactly it for independent lags, below it for correlated ones — the price is some
power against changes of shape only; a gain change is the gain test's).  Bonferroni
would be valid too and very slightly more conservative.

The decision: a pair is ``changed`` when any of the three exceeds ``threshold_sigma``.
Each has a two-sided false-alarm probability ``α = 2(1 − Φ(threshold_sigma))`` (0.27 %
at 3 σ) when the stored σ are calibrated, so a pair's is at most ``3α`` (0.81 %) by the
union bound, and a night with ``P`` pairs at most ``3Pα``.  Measured on an independently
simulated two-pair plant with AR(1) 0.9 noise (``python -m tests.readouts.test_monitor``): 0 of
1000 quiet night-vs-baseline comparisons flagged; a 30 % gain change flagged in 500 of
500, a 10 % one in 79 of 80, a 5 % one in 9 of 80 (the gain's σ is 1.8 % a night).

Lags compared: both runs' common lags.  When the runs' N_p differ, the shorter run's
last lag is left out: the last coefficient of a FIR absorbs the response beyond N_p (the
``end_jump`` warning), so it is that run's gain — compared by the gain test — not the
step at that lag.  When the sample periods differ the finer run's step response (and
σ) is interpolated linearly to the coarser run's lag times over the common span; pin
``sampling.dt_s`` and ``search.n_p`` in a monitored job to compare like with like.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import special, stats

from pipeline.readouts import characteristics as ch
from pipeline.errors import ConfigError, PipelineError

__all__ = [
    "PairResponse",
    "PairChange",
    "MonitorResult",
    "compare_runs",
    "compare_pair",
    "dead_time_std",
    "sidak_z",
    "step_difference_z",
    "monitor_banner",
    "monitor_markdown",
]

#: Bootstrap draws of the dead-time read-off (an integrating pair's read-off is a
#: nonlinear fit, ~0.1 s each, so it gets fewer).
DEAD_TIME_DRAWS = 100
DEAD_TIME_DRAWS_INTEGRATING = 20


@dataclass(frozen=True)
class PairResponse:
    """One pair of one run, as stored: the step response and its uncertainty.

    Attributes
    ----------
    output, input : str
        Signal names.
    integrating : bool
        The output integrates (``value`` is the rate).
    value, value_std : float
        Gain (output per input unit) or, for an integrating output, rate (per second),
        and its standard deviation.
    dead_time_s : float
        The run's dead time read-off (s); NaN when undefined.
    step, step_std : ndarray (n_p,)
        Step response at lags ``1..n_p`` (``time_s = (lag - 1/2)·dt_s``) and its std.
    dt_s : float
        The run's sample period (s).
    """

    output: str
    input: str
    integrating: bool
    value: float
    value_std: float
    dead_time_s: float
    step: np.ndarray
    step_std: np.ndarray
    dt_s: float

    @property
    def pair(self) -> str:
        """``"output<-input"``, the pair's name in checks.json and the catalog."""
        return f"{self.output}<-{self.input}"

    @property
    def time_s(self) -> np.ndarray:
        """Lag times ``(lag - 1/2)·dt_s`` (s), shape (n_p,)."""
        return (np.arange(self.step.size) + 0.5) * self.dt_s


@dataclass(frozen=True)
class PairChange:
    """A pair compared with its baseline (module notes for the statistics).

    Attributes
    ----------
    output, input : str
        Signal names.
    metric : str
        ``"gain"`` or ``"rate"`` (integrating output): what ``gain_z`` compares.
    baseline, value : float
        The baseline's and this run's gain (rate).
    baseline_std, value_std : float
        Their standard deviations.
    gain_z : float or None
        z of the gain (rate) difference; ``None`` without a finite σ.
    dead_time_baseline_s, dead_time_s : float
        Dead times (s; NaN when undefined).
    dead_time_z : float or None
        z of the dead-time difference; ``None`` when either is undefined.
    step_max_z : float or None
        Šidák-corrected z of the largest lag difference (single-comparison scale).
    step_max_abs_z : float or None
        The largest ``|Δ_l|/σ_l`` itself, at time ``step_max_time_s``.
    step_max_time_s : float or None
        Lag time (s) of that largest difference.
    step_lags : int
        Lags compared.
    changed : bool
        Any of the three z exceeds the threshold.
    reasons : tuple of str
        Which exceeded it: ``"gain"``/``"rate"``, ``"dead_time"``, ``"step"``.
    """

    output: str
    input: str
    metric: str
    baseline: float
    value: float
    baseline_std: float
    value_std: float
    gain_z: float | None
    dead_time_baseline_s: float
    dead_time_s: float
    dead_time_z: float | None
    step_max_z: float | None
    step_max_abs_z: float | None
    step_max_time_s: float | None
    step_lags: int
    changed: bool
    reasons: tuple[str, ...] = ()

    @property
    def pair(self) -> str:
        """``"output<-input"``."""
        return f"{self.output}<-{self.input}"

    @property
    def relative_change(self) -> float | None:
        """``(value - baseline) / |baseline|``; ``None`` for a zero baseline."""
        if not self.baseline or not np.isfinite(self.baseline):
            return None
        return (self.value - self.baseline) / abs(self.baseline)

    def to_dict(self) -> dict:
        """The pair's entry of checks.json ``monitor.pairs`` (JSON-ready, NaN → None)."""
        return {"gain_z": _num(self.gain_z), "dead_time_z": _num(self.dead_time_z),
                "step_max_z": _num(self.step_max_z), "changed": bool(self.changed),
                "reasons": list(self.reasons), "metric": self.metric,
                "baseline": _num(self.baseline), "value": _num(self.value),
                "baseline_std": _num(self.baseline_std), "value_std": _num(self.value_std),
                "relative_change": _num(self.relative_change),
                "dead_time_baseline_s": _num(self.dead_time_baseline_s),
                "dead_time_s": _num(self.dead_time_s),
                "step_max_abs_z": _num(self.step_max_abs_z),
                "step_max_time_s": _num(self.step_max_time_s),
                "step_lags": int(self.step_lags)}


@dataclass(frozen=True)
class MonitorResult:
    """A run compared with its baseline.

    Attributes
    ----------
    baseline_run : str
        Run id of the baseline (this run's own id when it is the baseline).
    threshold_sigma : float
        The decision threshold, in σ.
    pairs : tuple of PairChange
        One per pair both runs have, in the run's pair order.
    is_baseline : bool
        This run is the baseline (``monitor.baseline: first`` and no earlier run).
    not_compared : dict
        Pair name -> why it was not compared (not in the baseline).
    """

    baseline_run: str
    threshold_sigma: float
    pairs: tuple[PairChange, ...] = ()
    is_baseline: bool = False
    not_compared: dict = field(default_factory=dict)

    @property
    def changed(self) -> tuple[str, ...]:
        """Names (``"y<-u"``) of the pairs flagged ``changed``."""
        return tuple(p.pair for p in self.pairs if p.changed)

    def to_dict(self) -> dict:
        """The checks.json ``monitor`` section (JSON-ready)."""
        return {"baseline_run": self.baseline_run,
                "threshold_sigma": float(self.threshold_sigma),
                "changed": list(self.changed),
                "pairs": {p.pair: p.to_dict() for p in self.pairs},
                "is_baseline": bool(self.is_baseline),
                "not_compared": dict(self.not_compared),
                "false_alarm_per_test": _alpha(self.threshold_sigma)}

    def banner(self) -> str:
        """The one-line markdown verdict for the top of report.md."""
        return monitor_banner(self.to_dict())


def _num(v) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def _alpha(threshold_sigma: float) -> float:
    """Two-sided false-alarm probability of one comparison at ``threshold_sigma``."""
    return float(2.0 * stats.norm.sf(threshold_sigma))


# ----------------------------------------------------------------------- statistics
def sidak_z(max_abs_z: float, m: int) -> float:
    """The single-comparison z with the same false-alarm probability as the largest of
    ``m`` two-sided |z| (Šidák: ``p = 1 - (1 - p_1)^m``), computed in logs so that very
    large z keep their order.

    Parameters
    ----------
    max_abs_z : float
        The largest ``|Δ_l|/σ_l`` over the lags, ≥ 0.
    m : int
        Lags compared, ≥ 1.
    """
    if m < 1:
        raise ConfigError(f"sidak_z: m={m} lags; at least one lag must be compared")
    z = float(abs(max_abs_z))
    log_p1 = math.log(2.0) + float(stats.norm.logsf(z))  # two-sided p of one lag
    if log_p1 >= 0.0:  # z = 0: p = 1, nothing to correct
        return 0.0
    if m * math.exp(log_p1) < 1e-8:  # 1 - (1 - p)^m = m p to relative 1e-8
        log_pm = math.log(m) + log_p1
    else:
        log_pm = math.log(-math.expm1(m * math.log1p(-math.exp(log_p1))))
    return max(0.0, -float(special.ndtri_exp(log_pm - math.log(2.0))))


def _aligned(base: PairResponse, run: PairResponse) -> tuple[np.ndarray, np.ndarray,
                                                             np.ndarray]:
    """Differences, their σ and the lag times over the compared lags (module notes)."""
    same_grid = math.isclose(base.dt_s, run.dt_s, rel_tol=1e-9)
    nb, nr = base.step.size, run.step.size
    if same_grid:
        m = min(nb, nr) - (1 if nb != nr else 0)
        m = max(m, 1)
        d = run.step[:m] - base.step[:m]
        s = np.hypot(run.step_std[:m], base.step_std[:m])
        return d, s, base.time_s[:m]
    coarse, fine = (base, run) if base.dt_s > run.dt_s else (run, base)
    # last lags left out (each run's last coefficient is its gain)
    tc, tf = coarse.time_s[:-1], fine.time_s[:-1]
    keep = (tc >= tf[0]) & (tc <= tf[-1]) if tf.size else np.zeros(tc.size, bool)
    t = tc[keep]
    step_f = np.interp(t, tf, fine.step[:-1])
    std_f = np.interp(t, tf, fine.step_std[:-1])
    sign = 1.0 if coarse is run else -1.0
    d = sign * (coarse.step[:-1][keep] - step_f)
    return d, np.hypot(coarse.step_std[:-1][keep], std_f), t


def step_difference_z(base: PairResponse, run: PairResponse) -> tuple[float | None,
                                                                      float | None,
                                                                      float | None, int]:
    """The step-response comparison of two runs (module notes).

    Returns ``(step_max_z, step_max_abs_z, step_max_time_s, m)``: the Šidák-corrected
    z, the largest ``|Δ_l|/σ_l``, its lag time and the number of lags compared (lags
    where both σ are zero — increments fixed at zero by ``n_k`` in both — are not
    compared).  ``None`` values when no lag can be compared.

    Parameters
    ----------
    base, run : PairResponse
        The baseline's and this run's pair.
    """
    d, s, t = _aligned(base, run)
    ok = np.isfinite(d) & np.isfinite(s) & (s > 0)
    m = int(ok.sum())
    if m == 0:
        return None, None, None, 0
    z = np.abs(d[ok]) / s[ok]
    k = int(np.argmax(z))
    return sidak_z(float(z[k]), m), float(z[k]), float(t[ok][k]), m


def _read_dead_time(step: np.ndarray, step_std: np.ndarray, dt_s: float, integrating: bool,
                    value: float, value_std: float) -> float:
    """The dead time by the read-off of :mod:`pipeline.readouts.characteristics` (NaN if none)."""
    try:
        if integrating:
            return float(ch.integrating_characteristics(
                step, dt_s=dt_s, step_std=step_std, rate=value,
                rate_std=value_std).dead_time_s)
        return float(ch.self_regulating_characteristics(
            step, dt_s=dt_s, step_std=step_std, gain=float(step[-1]),
            gain_std=float(step_std[-1])).dead_time_s)
    except PipelineError:
        return float("nan")


def dead_time_std(pair: PairResponse, *, n_draws: int | None = None, seed: int = 0) -> float:
    """σ of a run's dead-time read-off by a parametric bootstrap (module notes).

    Each draw adds ``step_std_l · W_l / sqrt(l)`` to the step response, ``W`` a standard
    Gaussian random walk over the lags (so every lag has exactly its stored σ and
    neighbouring lags are correlated as a cumulative sum's), and reads the dead time
    off again.  Returns the draws' std, at least ``dt_s/√12`` (the read-off resolves one
    sample), or NaN when fewer than half the draws have a dead time.

    Parameters
    ----------
    pair : PairResponse
        The run's pair (step, step_std, dt_s, integrating, value).
    n_draws : int, optional
        Bootstrap draws; default :data:`DEAD_TIME_DRAWS` (self-regulating) or
        :data:`DEAD_TIME_DRAWS_INTEGRATING`.
    seed : int
        Seeds the draws (the σ of a stored run is then reproducible).
    """
    n = pair.step.size
    if n < 2 or not np.isfinite(pair.dead_time_s):
        return float("nan")
    if n_draws is None:
        n_draws = DEAD_TIME_DRAWS_INTEGRATING if pair.integrating else DEAD_TIME_DRAWS
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.standard_normal((n_draws, n)), axis=1) / np.sqrt(np.arange(1, n + 1))
    std = np.nan_to_num(pair.step_std, nan=0.0)
    times = np.array([_read_dead_time(pair.step + std * w, std, pair.dt_s, pair.integrating,
                                      pair.value, pair.value_std) for w in walk])
    times = times[np.isfinite(times)]
    if times.size < max(2, n_draws // 2):
        return float("nan")
    return float(max(np.std(times, ddof=1), pair.dt_s / math.sqrt(12.0)))


def _z(a: float, b: float, sa: float, sb: float) -> float | None:
    s = math.hypot(sa, sb)
    if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(s)) or s <= 0:
        return None
    return abs(a - b) / s


def compare_pair(base: PairResponse, run: PairResponse, *, threshold_sigma: float,
                 base_dead_time_std: float | None = None,
                 run_dead_time_std: float | None = None) -> PairChange:
    """Compare one pair of a run with the baseline's (module notes).

    Parameters
    ----------
    base, run : PairResponse
        The baseline's and this run's pair (same output and input).
    threshold_sigma : float
        A z above this flags the pair.
    base_dead_time_std, run_dead_time_std : float, optional
        σ of the dead times if already known; default :func:`dead_time_std`.
    """
    if (base.output, base.input) != (run.output, run.input):
        raise ConfigError(f"compare_pair: baseline pair {base.pair} is not the run's "
                          f"{run.pair}; compare the same output and input")
    gz = _z(run.value, base.value, run.value_std, base.value_std)
    sb = dead_time_std(base) if base_dead_time_std is None else base_dead_time_std
    sr = dead_time_std(run) if run_dead_time_std is None else run_dead_time_std
    dz = _z(run.dead_time_s, base.dead_time_s, sr, sb)
    sz, sabs, st, m = step_difference_z(base, run)
    metric = "rate" if run.integrating else "gain"
    reasons = tuple(name for name, z in ((metric, gz), ("dead_time", dz), ("step", sz))
                    if z is not None and z > threshold_sigma)
    return PairChange(run.output, run.input, metric, float(base.value), float(run.value),
                      float(base.value_std), float(run.value_std), gz, float(base.dead_time_s), float(run.dead_time_s), dz, sz, sabs, st,
                      m, bool(reasons), reasons)


def compare_runs(baseline: Sequence[PairResponse], run: Sequence[PairResponse], *,
                 baseline_run: str, threshold_sigma: float = 3.0) -> MonitorResult:
    """Compare every pair of a run with the baseline run's same pair.

    Parameters
    ----------
    baseline : sequence of PairResponse
        The baseline run's pairs.
    run : sequence of PairResponse
        This run's pairs (their order is the result's).
    baseline_run : str
        The baseline's run id (recorded in the result).
    threshold_sigma : float
        A z above this flags a pair (> 0; default 3).
    """
    if not (np.isfinite(threshold_sigma) and threshold_sigma > 0):
        raise ConfigError(f"monitor.threshold_sigma: {threshold_sigma!r} must be a positive "
                          "number of standard deviations, e.g. 3")
    base = {p.pair: p for p in baseline}
    out, missing = [], {}
    for p in run:
        if p.pair not in base:
            missing[p.pair] = f"the baseline run {baseline_run} has no pair {p.pair}"
            continue
        out.append(compare_pair(base[p.pair], p, threshold_sigma=threshold_sigma))
    return MonitorResult(baseline_run, float(threshold_sigma), tuple(out), False, missing)


# ------------------------------------------------------------------------ rendering
def _largest(entry: Mapping) -> tuple[str, float]:
    """The quantity of a pair entry with the largest z and that z."""
    cands = [(k, entry.get(k)) for k in ("gain_z", "dead_time_z", "step_max_z")]
    cands = [(k, float(v)) for k, v in cands if v is not None]
    return max(cands, key=lambda kv: kv[1]) if cands else ("gain_z", float("nan"))


def _describe(entry: Mapping) -> str:
    """``gain +31 %, 6.2 σ`` — what moved, in the quantity's own terms: the gain (rate)
    when it moved, else the dead time, else the step response (``reasons`` order)."""
    first = {"gain": "gain_z", "rate": "gain_z", "dead_time": "dead_time_z",
             "step": "step_max_z"}
    reasons = [first[r] for r in entry.get("reasons") or () if r in first]
    key, z = (reasons[0], float(entry[reasons[0]])) if reasons else _largest(entry)
    if key == "gain_z":
        rel = entry.get("relative_change")
        what = entry.get("metric", "gain")
        size = f"{100 * rel:+.0f} %" if rel is not None else \
            f"{entry.get('value')} vs {entry.get('baseline')}"
        return f"{what} {size}, {z:.1f} σ"
    if key == "dead_time_z":
        a, b = entry.get("dead_time_s"), entry.get("dead_time_baseline_s")
        return f"dead time {a - b:+.3g} s, {z:.1f} σ" if a is not None and b is not None \
            else f"dead time, {z:.1f} σ"
    t = entry.get("step_max_time_s")
    at = f" largest at {t:.3g} s" if t is not None else ""
    return f"step response{at}, {z:.1f} σ (Šidák over {entry.get('step_lags')} lags)"


def monitor_banner(section: Mapping) -> str:
    """The one-line markdown verdict of a checks.json ``monitor`` section.

    Parameters
    ----------
    section : mapping
        ``checks["monitor"]`` (:meth:`MonitorResult.to_dict`).
    """
    run = section["baseline_run"]
    thr = f"{float(section['threshold_sigma']):g}"
    if section.get("is_baseline"):
        return (f"**Baseline:** this run ({run}) is the job's monitoring baseline "
                "(monitor.baseline: first, and no earlier run of the job).")
    changed = section.get("changed") or []
    if not section.get("pairs") and section.get("not_compared"):
        return (f"**Not compared with baseline {run}:** it has none of this run's pairs "
                f"({', '.join(section['not_compared'])}).")
    if not changed:
        return f"No pair moved beyond {thr} σ of baseline {run}."
    parts = [f"{p} ({_describe(section['pairs'][p])})" for p in changed]
    return f"**Changed vs baseline {run}:** " + "; ".join(parts)


def monitor_markdown(section: Mapping) -> str:
    """The monitoring result as markdown: the banner and a table of every pair's z
    (report artifacts; the same numbers as checks.json).

    Parameters
    ----------
    section : mapping
        ``checks["monitor"]`` (:meth:`MonitorResult.to_dict`).
    """
    lines = [monitor_banner(section), ""]
    pairs = section.get("pairs") or {}
    if pairs:
        lines += [f"Threshold {float(section['threshold_sigma']):g} σ on each z (false "
                  f"alarm {100 * float(section.get('false_alarm_per_test', float('nan'))):.2g} "
                  "% per comparison).", "",
                  "| pair | changed | baseline | this run | gain/rate z | dead time z "
                  "| step max z |", "|---|---|---|---|---|---|---|"]
        for name, e in pairs.items():
            def f(v, fmt=".4g"):
                return "—" if v is None else format(v, fmt)
            lines.append(f"| {name} | {'**yes**' if e['changed'] else 'no'} | "
                         f"{f(e.get('baseline'))} | {f(e.get('value'))} | "
                         f"{f(e['gain_z'], '.2f')} | {f(e['dead_time_z'], '.2f')} | "
                         f"{f(e['step_max_z'], '.2f')} |")
    for name, why in (section.get("not_compared") or {}).items():
        lines.append(f"- {name}: not compared ({why})")
    return "\n".join(lines) + "\n"
