"""Continuous transfer functions with dead time fitted to an estimated step response,
and their exact sampled form (what ``plantdyn export`` hands to control tools).

Time axis (the estimator's, :mod:`pipeline.estimation.estimate`): the stored ``step`` at lag
``l = 1..n_p`` is ``h((l - 1/2)·dt_s)``, ``h`` the continuous step response (lag 1 is the
same-sample term).  Every fit here compares the model's step response at exactly those
times with the stored values.

Candidates, fewest parameters first (``G(s)·e^{-θs}``, ``θ >= 0``)::

    zero              G = 0                                   (0 parameters)
    fopdt             K / (τ s + 1)                            (3: K, τ, θ)
    sopdt             K / ((τ1 s + 1)(τ2 s + 1))  or           (4: K, τ1 >= τ2, θ)
                      K / (T² s² + 2ζT s + 1), ζ < 1           (4: K, T, ζ, θ)
    rational (n, m)   N(s)/D(s), (n, m) = (2,1) (3,0) (2,2) (3,1) (3,2) (3,3)  (m + n + 2)

FOPDT and SOPDT are fitted directly to the step response (``scipy.optimize.least_squares``,
analytic step responses, a few starts read off the response; the SOPDT is the better of
its over- and underdamped forms).  A rational candidate starts from the
least-squares-distance fit of method.md §7 (:func:`pipeline.readouts.frequency.fit_transfer_function`)
to the FIR's frequency response with the FOPDT/SOPDT dead time removed, and from the best
fit so far (extra degrees as cancelling factors ``(σ + 1)``), and is refined on the step
response together with ``θ`` (coefficients of ``σ = s/ω_ref``, ``ω_ref`` that of the §7
fit).  Every fit minimises the plain sum of squared step errors over the lags — the
quantity reported as its error.

Choice rule. ``noise_rms`` is the RMS of ``step_std`` over the lags; the tolerance is
``2·noise_rms``. Candidates are tried in the order above and the first whose RMS misfit is
within the tolerance is taken: it reproduces the estimate within its own uncertainty, and a
model with more parameters would fit the noise. When none is, the simplest candidate whose
misfit is within 20 % of the smallest is taken (a more complex model must buy a clear
improvement). Rational fits with a pole in the closed right half plane are never taken for a
self-regulating pair. Integrating pairs (outputs declared ``integrating``) get the one model
of :func:`pipeline.readouts.characteristics.integrating_characteristics`, ``K (1 - T_a s) e^{-T_d s}
/ (s (1 + T_1 s)(1 + T_2 s))`` (its time axis shifted by ``dt/2``; time constants under
``1e-3·dt`` set to 0).

Error of a fit: ``fit_rms = sqrt(mean((model - step)²))`` over the stored lags (output units
per input unit), evaluated by the exact sampled form below, and ``fit_rms_rel = fit_rms /
max|step|`` — relative to the largest value of the response rather than its final value,
which is zero for a response that returns (a controlled pressure's response to a load) and
equals it for a monotone response.

Exact sampled form (:func:`zoh_with_delay`).  For a piecewise-constant input the
zero-order-hold discretisation of ``N/D·e^{-θs}`` is exact at the sample instants also for a
delay that is not a multiple of ``dt``: with ``θ = d·dt + δ``, ``0 <= δ < dt`` (d >= -1)::

    x[k+1] = Φ x[k] + Γ0 u[k-d] + Γ1 u[k-d-1]
    Φ = e^{A dt},  Γ0 = ∫_0^{dt-δ} e^{Aη} dη B,  Γ1 = e^{A(dt-δ)} ∫_0^δ e^{Aη} dη B
    G(z) = C (zI - Φ)^{-1} (Γ0 z + Γ1) z^{-(d+1)}  (+ the direct term D at its delay)

The exported discrete model uses ``θ - dt/2`` so that its sample ``k`` is the continuous
response at ``(k + 1/2)·dt`` — the stored lag ``k + 1``: its step response is the fitted
curve at the estimator's own lags, coefficient for coefficient.  ``d = -1`` (``θ < dt/2``)
gives a biproper ``G(z)``, the same-sample term of block-averaged data.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.signal

from pipeline.readouts.characteristics import finite_or_none, integrating_characteristics
from pipeline.errors import ConfigError, DataQualityError, PipelineError
from pipeline.readouts.frequency import fit_transfer_function, frequency_response_from_step

__all__ = ["RATIONAL_DEGREES", "StepModelFit", "fit_step_model", "gain_mismatch",
           "reported_model", "model_record", "fopdt_step", "sopdt_step", "rational_step",
           "zoh_with_delay", "sampled_step"]

RATIONAL_DEGREES = ((2, 1), (3, 0), (2, 2), (3, 1), (3, 2), (3, 3))
"""(n, m) of the rational candidates, in the order they are tried."""
NOISE_FACTOR = 2.0
"""A fit within ``NOISE_FACTOR·noise_rms`` reproduces the estimate within its uncertainty."""
CLEAR_IMPROVEMENT = 1.2
"""Without a fit within the noise: the simplest one within this factor of the best."""
_TAIL = 0.2


@dataclass(frozen=True)
class StepModelFit:
    """A continuous transfer function with dead time fitted to a step response.

    Attributes
    ----------
    kind : str
        ``"zero"``, ``"fopdt"``, ``"sopdt"``, ``"rational"`` or ``"integrating"``.
    num, den : ndarray
        ``G(s)`` without the delay, highest power of ``s`` first, ``den`` monic.
    delay_s : float
        Dead time ``θ`` (s).
    parameters : dict
        Physical parameters of the kind: ``gain`` (or ``rate``), ``time_constant_s``,
        ``time_constants_s``, ``natural_period_s``, ``damping``, ``m``/``n``, ...
    fit_rms : float
        RMS of model minus stored step over the lags (output units per input unit).
    fit_rms_rel : float
        ``fit_rms / max|step|`` (NaN for an all-zero step).
    noise_rms : float
        RMS of ``step_std`` over the lags (NaN when not given).
    tolerance : float
        ``NOISE_FACTOR · noise_rms`` (at least ``1e-9·max|step|``: round-off is no misfit).
    within_noise : bool
        ``fit_rms <= tolerance``.
    rule : str
        Why this candidate was taken.
    trials : tuple of dict
        Every candidate tried: ``kind``, ``n``, ``m``, ``fit_rms``, ``stable``.
    """

    kind: str
    num: np.ndarray
    den: np.ndarray
    delay_s: float
    parameters: dict
    fit_rms: float
    fit_rms_rel: float
    noise_rms: float
    tolerance: float
    within_noise: bool
    rule: str
    trials: tuple = field(default_factory=tuple)

    def to_dict(self) -> dict:
        """JSON-ready dict (numbers as floats, NaN as None)."""
        return {
            "kind": self.kind, "num": [float(v) for v in self.num],
            "den": [float(v) for v in self.den], "delay_s": float(self.delay_s),
            "parameters": self.parameters, "fit_rms": finite_or_none(self.fit_rms),
            "fit_rms_rel": finite_or_none(self.fit_rms_rel),
            "noise_rms": finite_or_none(self.noise_rms), "tolerance": float(self.tolerance),
            "within_noise": bool(self.within_noise), "rule": self.rule,
            "trials": list(self.trials),
        }

    @classmethod
    def from_dict(cls, d: dict) -> StepModelFit:
        """The fit :meth:`to_dict` wrote (None read as NaN).

        Parameters
        ----------
        d : dict
        """
        nan = {k: math.nan if d.get(k) is None else float(d[k])
               for k in ("fit_rms", "fit_rms_rel", "noise_rms")}
        return cls(kind=str(d["kind"]), num=np.asarray(d["num"], dtype=float),
                   den=np.asarray(d["den"], dtype=float), delay_s=float(d["delay_s"]),
                   parameters=dict(d["parameters"]), tolerance=float(d["tolerance"]),
                   within_noise=bool(d["within_noise"]), rule=str(d["rule"]),
                   trials=tuple(d.get("trials") or ()), **nan)

    def __str__(self) -> str:
        extra = "" if self.kind != "rational" else \
            f"({self.parameters['n']},{self.parameters['m']})"
        return (f"{self.kind}{extra}: delay {self.delay_s:.4g} s, fit RMS {self.fit_rms:.3g} "
                f"({100 * self.fit_rms_rel:.2g} % of the peak), "
                f"{'within' if self.within_noise else 'outside'} 2σ noise {self.tolerance:.3g}")


# ------------------------------------------------------------------ model step responses
DELAY_RESOLUTION = 0.01
"""A fitted dead time shorter than this share of the sample period is reported as 0: at the
data's resolution it cannot be told from none (it moves the sampled step by under 1 % of a
sample's change), and its Padé approximant (poles near 2·order/θ) would make the exported
continuous-time model numerically stiff — a 3e-4 s delay at 1 s gave a python-control step
response of NaN (the demo's pressure<-steam pair)."""


def _lag_after(t, delay_s: float) -> np.ndarray:
    return np.maximum(np.asarray(t, dtype=float) - float(delay_s), 0.0)


def fopdt_step(t, *, gain: float, time_constant_s: float, delay_s: float) -> np.ndarray:
    """Step response of ``K e^{-θs} / (τ s + 1)``.

    Parameters
    ----------
    t : array_like
        Times after the step (s).
    gain : float
        ``K`` (output units per input unit).
    time_constant_s : float
        ``τ`` (s, > 0).
    delay_s : float
        ``θ`` (s, >= 0).

    Returns
    -------
    ndarray
        ``K (1 - e^{-(t-θ)/τ})`` after ``θ``, zero before.
    """
    tp = _lag_after(t, delay_s)
    return gain * -np.expm1(-tp / max(float(time_constant_s), 1e-300))


def _overdamped_unit(tp: np.ndarray, t1: float, t2: float) -> np.ndarray:
    a, b = max(t1, t2), min(t1, t2)
    a = max(a, 1e-300)
    if a - b <= 1e-6 * a:  # double pole: the limit
        return 1.0 - (1.0 + tp / a) * np.exp(-tp / a)
    b = max(b, 1e-300)
    with np.errstate(under="ignore"):
        return 1.0 - (a * np.exp(-tp / a) - b * np.exp(-tp / b)) / (a - b)


def _underdamped_unit(tp: np.ndarray, period_s: float, zeta: float) -> np.ndarray:
    root = math.sqrt(max(1.0 - zeta * zeta, 0.0))
    wd = root / period_s
    # sin(wd t)/root -> t/T as root -> 0 (critical damping) without dividing by zero
    sinc_term = (tp / period_s) * np.sinc(wd * tp / np.pi)
    return 1.0 - np.exp(-zeta * tp / period_s) * (np.cos(wd * tp) + zeta * sinc_term)


def sopdt_step(t, *, gain: float, delay_s: float, time_constants_s=None,
               natural_period_s: float | None = None, damping: float | None = None) -> np.ndarray:
    """Step response of a second-order lag with dead time.

    Parameters
    ----------
    t : array_like
        Times after the step (s).
    gain : float
        ``K`` (output units per input unit).
    delay_s : float
        ``θ`` (s, >= 0).
    time_constants_s : pair of float, optional
        ``(τ1, τ2)`` of ``K/((τ1 s + 1)(τ2 s + 1))`` (overdamped or critical).
    natural_period_s : float, optional
        ``T`` of ``K/(T² s² + 2ζT s + 1)`` (with ``damping``; ``ζ >= 1`` is overdamped).
    damping : float, optional
        ``ζ``.

    Returns
    -------
    ndarray
    """
    tp = _lag_after(t, delay_s)
    if time_constants_s is not None:
        t1, t2 = (float(v) for v in time_constants_s)
        return gain * _overdamped_unit(tp, t1, t2)
    if natural_period_s is None or damping is None:
        raise ConfigError("give time_constants_s, or natural_period_s and damping")
    T, z = float(natural_period_s), float(damping)
    if z >= 1.0:
        r = math.sqrt(z * z - 1.0)
        return gain * _overdamped_unit(tp, T * (z + r), T * (z - r))
    return gain * _underdamped_unit(tp, T, z)


def rational_step(t, num, den, *, delay_s: float = 0.0) -> np.ndarray:
    """Step response of ``N(s)/D(s)·e^{-θs}`` at arbitrary times (partial fractions).

    Parameters
    ----------
    t : array_like
        Times after the step (s).
    num, den : array_like
        Coefficients, highest power of ``s`` first, ``deg num <= deg den``.
    delay_s : float
        ``θ`` (s).

    Returns
    -------
    ndarray
        Real step response.  Fast (used inside the fits); accurate unless poles nearly
        coincide — then :func:`sampled_step` (exact, on the lag grid) is used instead.
    """
    num, den = _normalised(num, den)
    tp = _lag_after(t, delay_s)
    direct = num[0] if num.size == den.size else 0.0
    rest = np.polysub(num, direct * den) if direct else num
    p = np.roots(den)
    if p.size == 0:
        return np.where(np.asarray(t, float) >= delay_s, direct, 0.0)
    dprime = np.polyval(np.polyder(den), p)
    if np.min(np.abs(dprime)) <= 1e-9 * max(1.0, float(np.max(np.abs(p))) ** (p.size - 1)):
        raise _NearlyRepeated
    r = np.polyval(rest, p) / dprime
    pt = np.outer(tp, p)
    with np.errstate(over="ignore", invalid="ignore"):
        small = np.abs(p) < 1e-12
        ratio = np.where(small, tp[:, None] * (1 + pt / 2),
                         np.expm1(pt) / np.where(small, 1.0, p))
    out = direct * (tp >= 0) + (ratio @ r).real
    return np.where(np.asarray(t, float) >= delay_s, out, 0.0)


class _NearlyRepeated(ArithmeticError):
    """Partial fractions are ill-conditioned: use the exact sampled path."""


def _normalised(num, den) -> tuple[np.ndarray, np.ndarray]:
    num = np.atleast_1d(np.asarray(num, dtype=float))
    den = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), "f")
    if den.size == 0:
        raise ConfigError("den must have a nonzero coefficient")
    num = np.trim_zeros(num, "f") if np.any(num) else np.zeros(1)
    if num.size > den.size:
        raise ConfigError(f"improper transfer function: deg num {num.size - 1} > deg den "
                          f"{den.size - 1}")
    return num / den[0], den / den[0]


# -------------------------------------------------------------- exact sampled form
def _hold_integrals(A: np.ndarray, B: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """``e^{A τ}`` and ``∫_0^τ e^{Aη} dη B`` from one matrix exponential (Van Loan)."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n], M[:n, n:] = A * tau, B * tau
    E = scipy.linalg.expm(M)
    return E[:n, :n], E[:n, n:]


def zoh_with_delay(num, den, *, delay_s: float, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of ``N(s)/D(s)·e^{-θs}`` (module notes).

    Parameters
    ----------
    num, den : array_like
        Continuous coefficients, highest power of ``s`` first.
    delay_s : float
        ``θ`` (s), ``>= -dt_s`` (a negative value advances by less than a sample; the
        result is then biproper).
    dt_s : float
        Sample period (s).

    Returns
    -------
    num_z, den_z : ndarray
        ``G(z)``, highest power of ``z`` first, equal lengths, ``den_z[0] == 1``.  Its step
        response at sample ``k`` is the continuous one at ``k·dt_s`` exactly.
    """
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    if not (np.isfinite(delay_s) and delay_s >= -dt_s * (1 + 1e-12)):
        raise ConfigError(f"delay_s must be >= -dt_s = {-dt_s:g} s; got {delay_s!r}")
    num, den = _normalised(num, den)
    n = den.size - 1
    d = math.floor(delay_s / dt_s + 1e-9)
    delta = max(delay_s - d * dt_s, 0.0)
    if delta <= 1e-9 * dt_s:
        delta = 0.0
    direct = num[0] if num.size == den.size else 0.0
    num_z, den_z = np.zeros(1), np.ones(1)
    if n > 0:
        with warnings.catch_warnings():  # BadCoefficients for tiny leading numerator terms
            warnings.simplefilter("ignore", scipy.signal.BadCoefficients)
            A, B, C, _ = scipy.signal.tf2ss(np.polysub(num, direct * den) if direct else num,
                                            den)
        Phi, _ = _hold_integrals(A, B, dt_s)
        E0, G0 = _hold_integrals(A, B, dt_s - delta)
        _, Gd = _hold_integrals(A, B, delta)
        zero = np.zeros((1, 1))
        n0, den_z = scipy.signal.ss2tf(Phi, G0, C, zero)
        n1, _ = scipy.signal.ss2tf(Phi, E0 @ Gd, C, zero)
        den_z = np.ravel(den_z)
        num_z = np.polyadd(np.polymul(n0[0], [1.0, 0.0]), n1[0])  # C(zI-Φ)^-1 (Γ0 z + Γ1)
    # all of it times z^-(d+1); the direct term D u(k dt - θ) is u[k-d-1] when δ > 0, but
    # u[k-d] when θ falls on a sample (one z more)
    if direct:
        num_z = np.polyadd(num_z, direct * (den_z if delta > 0 else np.polymul(den_z, [1.0, 0.0])))
    den_z = np.polymul(den_z, np.r_[1.0, np.zeros(d + 1)])
    return _equal_length(num_z, den_z)


def _equal_length(num_z: np.ndarray, den_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pad to equal length, drop common leading zeros (z^k factors of both), den monic."""
    L = max(num_z.size, den_z.size)
    num_z = np.r_[np.zeros(L - num_z.size), num_z]
    den_z = np.r_[np.zeros(L - den_z.size), den_z]
    k = int(np.argmax(np.abs(den_z) > 0))
    if np.any(num_z[:k]):
        raise ConfigError("non-causal sampled system (delay below -dt_s)")
    num_z, den_z = num_z[k:], den_z[k:]
    # trailing zeros of both: common factors z^j cancel
    while den_z.size > 1 and den_z[-1] == 0 and num_z[-1] == 0:
        num_z, den_z = num_z[:-1], den_z[:-1]
    return num_z / den_z[0], den_z / den_z[0]


def sampled_step(num, den, *, delay_s: float, dt_s: float, n_lags: int) -> np.ndarray:
    """The continuous step response at the lag times ``(l - 1/2)·dt_s``, ``l = 1..n_lags``,
    computed exactly through :func:`zoh_with_delay` (the exported discrete model's).

    Parameters
    ----------
    num, den : array_like
        Continuous ``G(s)`` without delay, highest power first.
    delay_s : float
        ``θ`` (s, >= -dt_s/2).
    dt_s : float
        Sample period (s).
    n_lags : int
        Number of lags.

    Returns
    -------
    ndarray (n_lags,)
    """
    num_z, den_z = zoh_with_delay(num, den, delay_s=delay_s - dt_s / 2, dt_s=dt_s)
    return scipy.signal.lfilter(num_z, den_z, np.ones(int(n_lags)))


# ------------------------------------------------------------------------- fitting
class _Data:
    """The response being fitted and the quantities the starts are read from."""

    def __init__(self, h: np.ndarray, dt_s: float):
        self.h, self.dt = h, dt_s
        self.t = (np.arange(1, h.size + 1) - 0.5) * dt_s
        tail = h[max(int(h.size * (1 - _TAIL)), 1) - 1:]
        self.final = float(np.mean(tail))
        k_peak = int(np.argmax(np.abs(h)))
        self.peak, self.t_peak = float(h[k_peak]), float(self.t[k_peak])
        ref = self.final if abs(self.final) > 0.05 * abs(self.peak) else self.peak
        self.sign = 1.0 if ref >= 0 else -1.0
        self.theta0 = self._crossing(0.1 * abs(ref)) - 0.5 * dt_s
        self.tau0 = max(self._crossing((1 - math.exp(-1)) * abs(ref)) - self.theta0, dt_s)
        self.span = float(self.t[-1])

    def _crossing(self, level: float) -> float:
        above = np.nonzero(self.sign * self.h >= level)[0]
        return float(self.t[above[0]]) if above.size else float(self.t[-1]) / 2

    def rms(self, model: np.ndarray) -> float:
        return float(np.sqrt(np.mean((model - self.h) ** 2)))


def _least_squares(resid, starts, lower, upper):
    """Best of ``least_squares`` from each start (inside the bounds)."""
    best = None
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    for p0 in starts:
        room = np.where(np.isfinite(hi - lo), 1e-9 * (hi - lo), 0.0)
        p0 = np.clip(np.asarray(p0, float), lo + room, hi - room)
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            try:
                res = scipy.optimize.least_squares(resid, p0, bounds=(lo, hi), x_scale="jac",
                                                   max_nfev=400)
            except (ValueError, np.linalg.LinAlgError):
                continue
        if np.all(np.isfinite(res.fun)) and (best is None or res.cost < best.cost):
            best = res
    return best


def _fit_fopdt(D: _Data) -> dict | None:
    def resid(p):
        return fopdt_step(D.t, gain=p[0], time_constant_s=p[1], delay_s=p[2]) - D.h

    kmax = 10 * max(abs(D.peak), abs(D.final), 1e-300)
    starts = [(D.final, D.tau0, max(D.theta0, 0)), (D.final, D.tau0, 0.0),
              (D.peak, 2 * D.tau0, max(D.theta0, 0) / 2)]
    res = _least_squares(resid, starts, [-kmax, 1e-3 * D.dt, 0.0],
                         [kmax, 100 * D.span, D.span])
    if res is None:
        return None
    K, tau, theta = (float(v) for v in res.x)
    return {"kind": "fopdt", "num": np.array([K / tau]), "den": np.array([1.0, 1.0 / tau]),
            "delay_s": theta, "parameters": {"gain": K, "time_constant_s": tau},
            "rms": D.rms(resid(res.x) + D.h)}


def _fit_sopdt(D: _Data, first: dict | None) -> dict | None:
    """The better of the overdamped (τ1, τ2 = r·τ1) and underdamped (T, ζ < 1) fits."""
    K0 = first["parameters"]["gain"] if first else D.final
    tau = first["parameters"]["time_constant_s"] if first else D.tau0
    th = first["delay_s"] if first else max(D.theta0, 0.0)
    kmax = 10 * max(abs(D.peak), abs(D.final), 1e-300)

    def over(p):
        return sopdt_step(D.t, gain=p[0], time_constants_s=(p[1], p[1] * p[2]), delay_s=p[3]) - D.h

    def under(p):
        return sopdt_step(D.t, gain=p[0], natural_period_s=p[1], damping=p[2], delay_s=p[3]) - D.h

    ro = _least_squares(over, [(K0, tau, 0.2, 0.7 * th), (K0, 0.6 * tau, 0.8, 0.5 * th),
                               (K0, tau, 0.01, th)],
                        [-kmax, 1e-3 * D.dt, 1e-4, 0.0], [kmax, 100 * D.span, 1.0, D.span])
    overshoot = D.sign * D.peak / max(abs(D.final), 1e-300) - 1.0
    z0 = (-math.log(overshoot) / math.hypot(math.pi, math.log(overshoot))
          if 1e-3 < overshoot < 1.0 else 0.5)
    T0 = max((D.t_peak - th) / math.pi * math.sqrt(1 - z0 * z0), D.dt) if overshoot > 1e-3 \
        else tau / 2
    ru = _least_squares(under, [(D.final, T0, z0, th), (D.final, T0, 0.2, 0.5 * th),
                                (K0, tau / 2, 0.7, th)],
                        [-kmax, 1e-3 * D.dt, 0.01, 0.0], [kmax, 100 * D.span, 0.999, D.span])
    if ro is None and ru is None:
        return None
    if ru is None or (ro is not None and ro.cost <= ru.cost):
        K, t1, r, theta = (float(v) for v in ro.x)
        t2 = t1 * r
        return {"kind": "sopdt", "num": np.array([K / (t1 * t2)]),
                "den": np.polymul([1.0, 1.0 / t1], [1.0, 1.0 / t2]), "delay_s": theta,
                "parameters": {"gain": K, "time_constants_s": [t1, t2],
                               "natural_period_s": math.sqrt(t1 * t2),
                               "damping": (t1 + t2) / (2 * math.sqrt(t1 * t2))},
                "rms": D.rms(over(ro.x) + D.h)}
    K, T, z, theta = (float(v) for v in ru.x)
    return {"kind": "sopdt", "num": np.array([K / T**2]),
            "den": np.array([1.0, 2 * z / T, 1.0 / T**2]), "delay_s": theta,
            "parameters": {"gain": K, "time_constants_s": None, "natural_period_s": T,
                           "damping": z},
            "rms": D.rms(under(ru.x) + D.h)}


def _section7_start(D: _Data, n: int, m: int, theta0: float):
    """§7 least-squares-distance fit to the FIR's frequency response with ``θ0`` removed."""
    fr = frequency_response_from_step(step=D.h, dt_s=D.dt)
    w, H = fr.omega_rad_s, fr.response
    keep = np.nonzero((w > 0) & (w <= np.pi / (4 * D.dt)))[0]
    if keep.size < m + n + 2:
        return None
    pick = keep[np.unique(np.geomspace(1, keep.size, 100).astype(int) - 1)]
    return fit_transfer_function(w[pick], H[pick] * np.exp(1j * w[pick] * theta0), m=m, n=n)


def _embed(prev: dict, n: int, m: int, T: float) -> np.ndarray | None:
    """A previous fit as a start of degrees (n, m): coefficients of ``σ = sT`` (ascending
    numerator, then the denominator without its leading 1, then θ/T), extra degrees as
    cancelling factors ``(σ + 1)``; None when it does not fit in (n, m)."""
    num, den = _normalised(prev["num"], prev["den"])
    extra = n - (den.size - 1)
    if extra < 0 or (np.trim_zeros(num, "f").size - 1 if np.any(num) else 0) + extra > m:
        return None
    num_s = num * T ** -np.arange(num.size - 1, -1, -1.0)  # N(σ/T), descending in σ
    den_s = den * T ** -np.arange(den.size - 1, -1, -1.0)
    for _ in range(extra):
        num_s, den_s = np.polymul(num_s, [1.0, 1.0]), np.polymul(den_s, [1.0, 1.0])
    num_s, den_s = num_s / den_s[0], den_s / den_s[0]
    b = np.r_[np.zeros(m + 1 - num_s.size), num_s][::-1] if num_s.size <= m + 1 else None
    if b is None:
        return None
    return np.r_[b, den_s[1:][::-1], prev["delay_s"] / T]


def _fit_rational(D: _Data, n: int, m: int, theta0: float, prev: dict | None) -> dict | None:
    """Rational (n, m) with delay: starts from the §7 fit and from the best fit so far."""
    try:
        start = _section7_start(D, n, m, theta0)
    except PipelineError:
        return None
    if start is None:
        return None
    T = 1.0 / start.omega_ref_rad_s  # coefficients of σ = sT are O(1)
    starts = [np.r_[start.num[::-1] * T ** (n - np.arange(m + 1)),  # ascending b, a
                    start.den[::-1][:n] * T ** (n - np.arange(n)), theta0 / T]]
    warm = _embed(prev, n, m, T) if prev is not None else None
    if warm is not None:
        starts.append(warm)
    tn = D.t / T

    def resid(p):
        try:
            return rational_step(tn, p[: m + 1][::-1], np.r_[1.0, p[m + 1: m + 1 + n][::-1]],
                                 delay_s=p[-1]) - D.h
        except _NearlyRepeated:
            return np.full(D.h.size, 1e6 * max(abs(D.peak), 1.0))

    free = np.full(m + n + 1, np.inf)
    res = _least_squares(resid, starts, np.r_[-free, 0.0], np.r_[free, D.span / T])
    if res is None:
        return None
    b, a = res.x[: m + 1], res.x[m + 1: m + 1 + n]
    num = (b * T ** -(n - np.arange(m + 1)))[::-1]  # back to s: b_k T^{k-n}
    den = np.r_[1.0, (a * T ** -(n - np.arange(n)))[::-1]]
    return {"kind": "rational", "num": num, "den": den, "delay_s": float(res.x[-1]) * T,
            "parameters": {"n": n, "m": m, "gain": _static_gain(num, den),
                           "poles": _complex_list(np.roots(den)),
                           "zeros": _complex_list(np.roots(num))},
            "rms": D.rms(resid(res.x) + D.h), "stable": bool(np.all(np.roots(den).real < 0))}


def _static_gain(num, den) -> float | None:
    return None if den[-1] == 0 else float(num[-1] / den[-1])


def _complex_list(z: np.ndarray) -> list:
    return [[float(v.real), float(v.imag)] for v in np.sort_complex(z)]


def _zero_candidate(D: _Data) -> dict:
    return {"kind": "zero", "num": np.zeros(1), "den": np.ones(1), "delay_s": 0.0,
            "parameters": {"gain": 0.0}, "rms": D.rms(np.zeros_like(D.h))}


def _candidates(D: _Data):
    """Yield candidate fits in the order of the rule (lazily: later ones cost more)."""
    yield _zero_candidate(D)
    first = _fit_fopdt(D)
    yield first
    second = _fit_sopdt(D, first)
    yield second
    done = [f for f in (first, second) if f is not None]
    theta0 = min(done, key=lambda f: f["rms"])["delay_s"] if done else 0.0
    for n, m in RATIONAL_DEGREES:
        if n + m + 2 > D.h.size:
            break
        prev = min((f for f in done if f.get("stable", True)), key=lambda f: f["rms"],
                   default=None)
        fit = _fit_rational(D, n, m, theta0, prev)
        if fit is not None:
            done.append(fit)
        yield fit


def _check_step(step, step_std, dt_s):
    h = np.asarray(step, dtype=float)
    if h.ndim != 1 or h.size < 3 or not np.all(np.isfinite(h)):
        raise DataQualityError(f"step must be a finite 1-D response of at least 3 lags; got "
                               f"shape {h.shape} (pass one pair's lags 1..n_p)")
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    s = None if step_std is None else np.asarray(step_std, dtype=float)
    if s is not None and (s.shape != h.shape or not np.all(np.isfinite(s))):
        raise DataQualityError(f"step_std must be finite with the shape of step {h.shape}; "
                               f"got {s.shape}")
    return h, s


def fit_step_model(step, *, dt_s: float, step_std=None, integrating: bool = False,
                   rate: float | None = None) -> StepModelFit:
    """Fit a continuous transfer function with dead time to one pair's step response
    (module notes: candidates, choice rule, error).

    Parameters
    ----------
    step : array (n_p,)
        The stored step response at lags ``1..n_p`` (times ``(l - 1/2)·dt_s``).
    dt_s : float
        Sample period (s).
    step_std : array (n_p,), optional
        Its standard deviation; sets the noise tolerance of the rule.
    integrating : bool
        The output is integrating: fit the integrating model instead.
    rate : float, optional
        Integrating pairs: the estimate's final slope (``checks.json`` ``rate``).

    Returns
    -------
    StepModelFit
    """
    h, s = _check_step(step, step_std, dt_s)
    noise = float(np.sqrt(np.mean(s**2))) if s is not None else float("nan")
    # a floor for responses known exactly (no step_std, synthetic): round-off is no misfit
    tol = max(NOISE_FACTOR * noise if s is not None else 0.0,
              1e-9 * float(np.max(np.abs(h))))
    if integrating:
        return _fit_integrating(h, s, dt_s, rate, noise, tol)
    D = _Data(h, dt_s)
    trials, taken, rule = [], None, ""
    for cand in _candidates(D):
        if cand is None:
            continue
        trials.append(cand)
        if cand.get("stable", True) and cand["rms"] <= tol:
            taken, rule = cand, f"first candidate within {NOISE_FACTOR:g}·noise_rms"
            break
    if taken is None:
        ok = [c for c in trials if c.get("stable", True)]
        best = min(c["rms"] for c in ok)
        taken = next(c for c in ok if c["rms"] <= CLEAR_IMPROVEMENT * best)
        rule = (f"none within {NOISE_FACTOR:g}·noise_rms: simplest within "
                f"{CLEAR_IMPROVEMENT:g}× the smallest misfit")
    return _result(taken, h, dt_s, noise, tol, rule, trials)


def _result(c: dict, h, dt_s, noise, tol, rule, trials) -> StepModelFit:
    delay = float(c["delay_s"]) if c["delay_s"] >= DELAY_RESOLUTION * dt_s else 0.0
    exact = sampled_step(c["num"], c["den"], delay_s=delay, dt_s=dt_s, n_lags=h.size)
    rms = float(np.sqrt(np.mean((exact - h) ** 2)))
    peak = float(np.max(np.abs(h)))
    summary = tuple({"kind": t["kind"], "n": int(t["parameters"].get("n", t["den"].size - 1)),
                     "m": int(t["parameters"].get("m", t["num"].size - 1)),
                     "fit_rms": float(t["rms"]), "stable": bool(t.get("stable", True))}
                    for t in trials)
    return StepModelFit(kind=c["kind"], num=np.asarray(c["num"], float),
                        den=np.asarray(c["den"], float), delay_s=delay,
                        parameters=c["parameters"], fit_rms=rms,
                        fit_rms_rel=rms / peak if peak > 0 else float("nan"),
                        noise_rms=noise, tolerance=float(tol), within_noise=bool(rms <= tol),
                        rule=rule, trials=summary)


def _fit_integrating(h, s, dt_s, rate, noise, tol) -> StepModelFit:
    ch = integrating_characteristics(h, dt_s=dt_s, step_std=s, rate=rate)
    # a time constant under a thousandth of a sample is invisible at dt_s and would only put
    # a pole at -1e7 rad/s into the continuous model: it is dropped
    T1, T2, Ta = (v if v >= 1e-3 * dt_s else 0.0 for v in
                  (ch.time_constant_1_s, ch.time_constant_2_s, ch.zero_time_constant_s))
    K = ch.rate
    # characteristics.py puts step[0] at t = 0; the lags are at (l - 1/2) dt
    theta = ch.dead_time_s + dt_s / 2
    num = K * np.array([-Ta, 1.0])
    den = np.polymul(np.polymul([T1, 1.0], [T2, 1.0]), [1.0, 0.0])
    num, den = _normalised(num, den)
    c = {"kind": "integrating", "num": num, "den": den, "delay_s": theta,
         "parameters": {"rate": K, "time_constant_1_s": T1, "time_constant_2_s": T2,
                        "zero_time_constant_s": Ta}, "rms": ch.fit_rms}
    return _result(c, h, dt_s, noise, tol, "integrating output: the model of "
                   "characteristics.integrating_characteristics", [c])


GAIN_TOLERANCE_SIGMAS = 2.0
GAIN_TOLERANCE_REL = 0.10
"""An exported transfer function's DC gain (rate) must be within
``max(2 σ, 10 % of |gain|)`` of the reported gain, or the pair's transfer function is
left out with the reason: the exported model is the reported model."""


def gain_mismatch(fit: StepModelFit, *, value: float | None, std: float | None,
                  integrating: bool = False, label: str = "the pair") -> str | None:
    """Why a fitted transfer function is not the reported model (``None``: it is): the
    pair has no reported gain (still moving at its horizon, or not judged), or the fit's
    DC gain (rate, for an integrating pair) differs from it by more than
    ``max(GAIN_TOLERANCE_SIGMAS σ, GAIN_TOLERANCE_REL |gain|)``.

    Parameters
    ----------
    fit : StepModelFit
        The pair's fitted transfer function.
    value, std : float or None
        The reported gain (rate) and its σ.
    integrating : bool
        The output is integrating (compare rates).
    label : str
        The pair in the message.
    """
    what = "rate" if integrating else "gain"
    if value is None:
        return f"the run reports no {what} for {label}, so no transfer function can match it"
    model = fit.parameters.get(what)
    if model is None:  # the fit's static gain from the polynomials
        model = float(fit.num[-1] / fit.den[-1]) if fit.den[-1] != 0 else float("inf")
    sd = std or 0.0
    tol = max(GAIN_TOLERANCE_SIGMAS * sd, GAIN_TOLERANCE_REL * abs(value))
    if not np.isfinite(model) or abs(model - value) > tol:
        return (f"the fitted {fit.kind} transfer function's {what} {model:.4g} differs from "
                f"the reported {what} {value:.4g} ± {sd:.2g} by more than {tol:.2g} "
                f"(max({GAIN_TOLERANCE_SIGMAS:g}σ, {100 * GAIN_TOLERANCE_REL:g} %))")
    return None


def reported_model(step, *, dt_s: float, step_std=None, integrating: bool = False,
                   value: float | None, std: float | None, pair: str = "the pair",
                   settled: str | None = None, stored: dict | None = None
                   ) -> StepModelFit | str:
    """The transfer function ``plantdyn export`` writes for a pair: :func:`fit_step_model`
    when it is the reported model (:func:`gain_mismatch`), else why not (the fit's error
    or the mismatch) — one rule, fitted once by the run and stored in ``checks.json``
    (:func:`model_record`); the export and report.html's overlay pass that record as
    `stored` (runs written before it was stored are fitted here).

    Parameters
    ----------
    step, step_std : array (n_p,)
        The stored step response and its standard deviation.
    dt_s : float
        Sample period (s).
    integrating : bool
        The output is integrating (``value`` is its rate).
    value, std : float or None
        The reported gain (rate) and its σ.
    pair, settled : str
        The pair (``output<-input``) and its settledness verdict, for the message.
    stored : dict, optional
        The run's record (:func:`model_record`), when it has one.
    """
    if stored is not None:
        return stored["left_out"] if "left_out" in stored else StepModelFit.from_dict(stored)
    try:
        fit = fit_step_model(step, dt_s=dt_s, step_std=step_std, integrating=integrating,
                             rate=value if integrating else None)
    except PipelineError as exc:
        return f"no transfer function: {exc}"
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
        # a numeric failure of this auxiliary fit must not stop the run that stores it
        return f"no transfer function: the fit failed ({type(exc).__name__}: {exc})"
    label = f"{pair} ({settled or 'not judged'} at its horizon of {np.size(step)} lags)"
    why = gain_mismatch(fit, value=value, std=std, integrating=integrating, label=label)
    return fit if why is None else f"left out: {why}"


def model_record(fit: StepModelFit | str) -> dict:
    """What a run stores of :func:`reported_model`'s answer (``checks.json``
    ``pairs[].transfer_function``): :meth:`StepModelFit.to_dict` or ``{"left_out": why}``.

    Parameters
    ----------
    fit : StepModelFit or str
    """
    return {"left_out": fit} if isinstance(fit, str) else fit.to_dict()
