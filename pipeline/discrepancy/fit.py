"""Fitting: prewhitened multi-start nonlinear least squares of the screened candidates."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.fft
import scipy.optimize
import scipy.signal

from pipeline.discrepancy.localise import lag_filter
from pipeline.discrepancy.problem import Problem
from pipeline.discrepancy.lure import (
    first_crossing,
    one_sided,
    saturation_grids,
    saturation_profile,
    static_path,
)
from pipeline.discrepancy.screen import Screen, Screener, near
from pipeline.discrepancy.effects import (
    Effect,
    apply_effect,
    degenerate_forms,
    predict_outputs,
)
from pipeline.errors import ConfigError, PipelineError
from pipeline.models.simulate import simulate


#: Relative tolerances (ftol, xtol) of the least-squares fits.  A whitened sum of squares
#: of a noisy record is ~ its number of samples (1e3-1e5), so 1e-6 stops when a step
#: changes it by < 0.1: far below the BIC margins (3, 10) and, in the parameters, far
#: below their noise-induced spread.  Noise-free records converge quadratically, so
#: the parameters end much closer than 1e-6 (relative) to the truth.
_LSQ_TOL = 1e-6


#: Residual value standing in for a simulation that blew up (unstable parameter trial),
#: in multiples of the nominal model's whitened RMS residual: least squares backs off.
_BLOWUP_RESIDUAL = 1e4


@dataclass
class Fit:
    effect: Effect
    n_parameters: int
    screening_score: float
    y_pred: np.ndarray  # (N, n_y)


class Fitter:
    """Exact fits (simulation of the augmented model) on the fit part.

    Parameters
    ----------
    P : Problem
        Validated signals, nominal simulation, split and whitening (noise model set).
    screener : Screener
        Screener of the same pass: impulse responses and caches reused by the fits.
    """

    def __init__(self, P: Problem, screener: Screener) -> None:
        self.P = P
        self.scr = screener
        self.stop = P.holdout_start
        self.ins_fit = {k: v[: self.stop] for k, v in P.inputs.items()}
        self.n_eval = 0
        self.blew_up = False
        self._blowup: float | None = None

    def predict(self, effect: Effect, *, full: bool = False) -> np.ndarray | None:
        """Outputs with `effect`, (N or holdout_start, n_y); None if the simulation fails/blows up.

        Parameters
        ----------
        effect : Effect
            Candidate effect, added to the nominal model.
        full : bool
            Simulate the whole record (N rows) instead of samples ``[0, holdout_start)``.
        """
        self.n_eval += 1
        return predict_with(self.P, effect, self.P.inputs if full else self.ins_fit)

    def residual(self, effect: Effect) -> np.ndarray:
        """Whitened fit-part residual; a blown-up simulation gives a flat huge vector
        (``self.blew_up`` is then True).

        Parameters
        ----------
        effect : Effect
            Candidate effect, simulated on samples ``[0, holdout_start)``; the residual
            is whitened on ``[fit_start + p_max, holdout_start)``.
        """
        P = self.P
        y = self.predict(effect)
        self.blew_up = y is None
        if y is None:
            if self._blowup is None:
                r0 = P.whiten(P.y[: self.stop] - P.y_nominal[: self.stop], P.fit_start, self.stop)
                self._blowup = _BLOWUP_RESIDUAL * max(1.0, float(np.sqrt(np.mean(r0**2))))
            size = P.n_y * (self.stop - P.fit_start - max(len(a) for a in P.ar) + 1)
            return np.full(size, self._blowup)
        return P.whiten(P.y[: self.stop] - y, P.fit_start, self.stop)

    def sse(self, effect: Effect) -> float:
        """Whitened sum of squares on the fit part (of :meth:`residual`).

        Parameters
        ----------
        effect : Effect
            Candidate effect, added to the nominal model.
        """
        r = self.residual(effect)
        return float(r @ r)

    def _lsq(self, make: Callable[[np.ndarray], Effect], starts: list[np.ndarray],
             lower: np.ndarray, upper: np.ndarray, diff_step: float | None = None,
             n_starts: int = 2) -> Effect:
        """Multi-start bounded least squares.

        Every start is evaluated once; least squares runs from the `n_starts` best that
        do not blow up (an effect that destabilises a loop gives a flat, huge residual
        from which no gradient leads back, so such starts are useless).
        """
        margin = 1e-9 * (upper - lower)
        scored = []
        for x0 in starts:
            x0 = np.clip(np.asarray(x0, dtype=float), lower + margin, upper - margin)
            r = self.residual(make(x0))
            cost = float(r @ r)
            if not self.blew_up:
                scored.append((cost, x0))
        scored.sort(key=lambda cx: cx[0])
        best, best_cost = None, math.inf
        used: list[np.ndarray] = []
        for cost, x0 in scored:
            if len(used) >= n_starts:
                break
            if any(np.allclose(x0, u, rtol=1e-3, atol=1e-6) for u in used):
                continue
            used.append(x0)
            try:
                sol = scipy.optimize.least_squares(
                    lambda x: self.residual(make(x)), x0, bounds=(lower, upper),
                    max_nfev=self.P.config.max_nfev, x_scale="jac", diff_step=diff_step,
                    ftol=_LSQ_TOL, xtol=_LSQ_TOL,
                )
            except (ValueError, PipelineError):
                sol = None
            if sol is not None and 2 * sol.cost < best_cost:
                best, best_cost = make(sol.x), 2 * sol.cost
            if cost < best_cost:
                best, best_cost = make(x0), cost
        if best is None:  # every start blows up: report the first (it will not pass)
            best = make(np.clip(np.asarray(starts[0], dtype=float), lower + margin,
                                upper - margin))
        return best

    def fit(self, s: Screen, warm: Effect | None = None) -> Effect:
        """Fit class `s` exactly.

        Parameters
        ----------
        s : Screen
            Screened class: effect name, canonical location, equivalent locations
            (``members``) and the screening's best parameter points (``starts``).
        warm : Effect or None
            This class's fit under the previous noise model.  It is added as a start
            and least squares then runs from the best start only (the multi-start search
            was done in the previous pass; only the weighting changed).
        """
        name, loc = s.name, s.location
        eq = tuple(m for m in s.members if m != loc)
        mk = lambda params: Effect(name, loc, params, eq)  # noqa: E731
        w = warm.parameters if warm is not None and warm.name == name else None
        n_starts = 1 if w is not None else 2
        if name == "sensor_bias_drift":
            return self._fit_bias_drift(loc, mk)
        if name == "unmodelled_input":
            return self._fit_unmodelled(s, mk)
        if name == "dead_time":
            return self._fit_dead_time(s, mk, w)
        if name in ("gain", "extra_lag", "inverse_response", "operating_point_gain",
                    "deadband", "backlash"):
            return self._fit_by_lsq(s, mk, w, n_starts)
        if name == "saturation":
            return self._fit_saturation_limits(s, mk, w, n_starts)
        raise ConfigError(f"effect {name!r} is not in the catalogue")  # pragma: no cover

    def _fit_bias_drift(self, loc: str, mk: Callable[[dict], Effect]) -> Effect:
        """sensor_bias_drift: linear in both parameters, exact closed form on the whitened residual."""
        P, dt = self.P, self.P.dt_s
        i = P.outputs.index(loc)
        stop = self.stop
        r = P.whiten(P.y[:stop] - P.y_nominal[:stop], P.fit_start, stop)
        cols = []
        for c in (np.ones(stop), np.arange(stop) * dt / 3600.0):
            d = np.zeros((stop, P.n_y))
            d[:, i] = c
            cols.append(P.whiten(d, P.fit_start, stop))
        beta, *_ = np.linalg.lstsq(np.column_stack(cols), r, rcond=None)
        return mk({"bias": float(beta[0]), "drift_per_h": float(beta[1])})

    def _fit_dead_time(self, s: Screen, mk: Callable[[dict], Effect],
                       w: Mapping[str, Any] | None) -> Effect:
        """dead_time: exact sums of squares on a coarse integer grid plus the screening's
        best delays, then an integer walk downhill from the best."""
        P, dt = self.P, self.P.dt_s
        tried: dict[int, float] = {}
        grid = {int(round(st["delay_s"] / dt)) for st in s.starts}
        if w is not None:
            grid.add(int(round(w["delay_s"] / dt)))
        grid |= {int(round(v)) for v in np.geomspace(1, P.max_delay, 10)}
        for d in sorted(grid):
            if 1 <= d <= P.max_delay:
                tried[d] = self.sse(mk({"delay_s": float(d * dt)}))
        d_best = min(tried, key=tried.get)
        while True:
            moved = False
            for d in (d_best - 1, d_best + 1):
                if 1 <= d <= P.max_delay and d not in tried:
                    tried[d] = self.sse(mk({"delay_s": float(d * dt)}))
                    if tried[d] < tried[d_best]:
                        d_best, moved = d, True
            if not moved:
                break
        return mk({"delay_s": float(d_best * dt)})

    def _fit_by_lsq(self, s: Screen, mk: Callable[[dict], Effect],
                    w: Mapping[str, Any] | None, n_starts: int) -> Effect:
        """gain, extra_lag, inverse_response, operating_point_gain, deadband, backlash: multi-start
        bounded least squares in a transformed parameter."""
        P, dt = self.P, self.P.dt_s
        name, loc = s.name, s.location
        tau_lo, tau_hi = 0.05 * dt, 20.0 * max(P.settling_s, dt)
        tau_grid = np.geomspace(0.5 * dt, max(dt, 0.5 * P.settling_s), 6)
        if name == "gain":
            starts = [np.array([math.log(max(st["factor"], 0.05))]) for st in s.starts[:1]]
            starts += [np.array([math.log(f)]) for f in (0.5, 0.7, 0.85, 1.2, 1.45, 1.8)]
            if w is not None:
                starts.insert(0, np.array([math.log(max(w["factor"], 0.05))]))
            return self._lsq(lambda x: mk({"factor": float(math.exp(x[0]))}), starts,
                             np.array([math.log(0.05)]), np.array([math.log(20.0)]),
                             n_starts=n_starts)
        if name == "extra_lag":
            starts = [np.array([math.log(st["tau_s"])]) for st in s.starts[:2]]
            starts += [np.array([math.log(t)]) for t in tau_grid]
            if w is not None:
                starts.insert(0, np.array([math.log(max(w["tau_s"], tau_lo))]))
            return self._lsq(lambda x: mk({"tau_s": float(math.exp(x[0]))}), starts,
                             np.array([math.log(tau_lo)]), np.array([math.log(tau_hi)]),
                             n_starts=n_starts)
        if name == "inverse_response":
            starts = [np.array([math.log(st["tau_s"]), max(st["magnitude"], 0.05)])
                      for st in s.starts[:2]]
            starts += [np.array([math.log(t), m]) for t in tau_grid[::2] for m in (0.3, 1.0)]
            if w is not None:
                starts.insert(0, np.array([math.log(max(w["tau_s"], tau_lo)), w["magnitude"]]))
            return self._lsq(
                lambda x: mk({"tau_s": float(math.exp(x[0])), "magnitude": float(x[1])}), starts,
                np.array([math.log(tau_lo), 0.0]), np.array([math.log(tau_hi), 50.0]),
                n_starts=n_starts)
        if name == "operating_point_gain":
            signal = s.starts[0]["signal"]
            spread = float(np.std(P.inputs[signal])) or 1.0
            starts = [np.array([st["slope"] * spread]) for st in s.starts[:1]]
            starts += [np.array([v]) for v in (-0.4, -0.2, 0.2, 0.4)]
            if w is not None and w["signal"] == signal:
                starts.insert(0, np.array([w["slope"] * spread]))
            return self._lsq(lambda x: mk({"slope": float(x[0] / spread), "signal": signal}),
                             starts, np.array([-5.0]), np.array([5.0]), n_starts=n_starts)
        # deadband, backlash: the width as a fraction of the input's extreme
        u = self._screener().block_input(loc)
        scale = float(np.max(np.abs(u))) or 1.0
        starts = [np.array([st["width"] / scale]) for st in s.starts[:2]]
        starts += [np.array([v]) for v in (0.05, 0.15, 0.3, 0.5)]
        if w is not None:
            starts.insert(0, np.array([w["width"] / scale]))
        return self._lsq(lambda x: mk({"width": float(x[0] * scale)}), starts,
                         np.array([0.0]), np.array([2.0]), diff_step=1e-2,
                         n_starts=n_starts)

    def _fit_saturation_limits(self, s: Screen, mk: Callable[[dict], Effect],
                               w: Mapping[str, Any] | None, n_starts: int) -> Effect:
        """saturation: fitted limits, a limit the fitted signal never reaches reported as absent."""
        low, high = self._fit_saturation(s, mk, w, n_starts)
        # a limit the fitted signal never reaches is not identified: report it as
        # absent (+-inf), which simulates identically
        best = mk({"low": low, "high": high})
        up = self._upstream_signal(best)
        if up is not None:
            if low <= float(up.min()):
                low = -math.inf
            if high >= float(up.max()):
                high = math.inf
        return mk({"low": low, "high": high})

    def _fit_saturation(self, s: Screen, mk: Callable[[dict], Effect],
                        warm: Mapping[str, Any] | None, n_starts: int) -> tuple[float, float]:
        """Saturation limits by a global search on exact simulations.

        Inside a loop with integral action a saturation winds the loop up, and the sum
        of squares is a narrow valley in the limits (a 1 % change of a limit can
        multiply it), and the two limits interact (one limit alone can make the fit
        much worse than none while both together explain the data): gradient steps
        from a few starts miss it.  So candidates are simulated exactly, many limit
        pairs per pass (:class:`StaticMapPath`):

        1. one-sided profiles: each limit alone on a dense grid (:func:`saturation_grids`);
        2. coordinate descent from the best limit of each side: the other limit scanned
           over its grid extended half a range beyond the nominal extremes, with this
           one fixed, then the first one rescanned, until nothing changes (at most
           three scans);
        3. the best `n_starts` pairs (also among pairs of the profiles' local minima,
           the screening's best points and the previous pass's fit) refined on
           shrinking 7 x 7 grids (the centre is kept, so the sum of squares never
           rises) down to 1e-4 of the signal's range;
        4. for two finite limits, a scan along the common shift of both (the valley an
           integrating loop leaves) and a last shrinking-grid refinement.
        """
        P, stop, loc = self.P, self.stop, s.location
        v = P.nominal_signals[loc][:stop]
        span = float(v.max() - v.min()) or 1.0
        search = _SaturationSearch(self, mk, v, span, static_path(P, self.scr._h, loc, stop))
        p_lows, p_highs, p_sse, scan_lo, scan_hi = search.profiles(loc)
        one_low = np.isfinite(p_lows)
        lows_min = _local_minima(p_lows[one_low], p_sse[one_low])
        highs_min = _local_minima(p_highs[~one_low], p_sse[~one_low])
        # 2. coordinate descent on the grids from the best one-sided limit of each side
        search.coordinate_descent(lows_min, highs_min, scan_lo, scan_hi)
        # 3. pairs of local minima, the screening's best points and the previous fit
        pairs = [(a, b) for a in [*lows_min, -math.inf] for b in [*highs_min, math.inf]]
        for st in ([warm] if warm is not None else []) + list(s.starts[:2]):
            pairs.append((float(st["low"]), float(st["high"])))
        search.run(pairs)
        centres = search.centres(n_starts)
        if not centres:
            return -math.inf, math.inf
        search.refine(centres, scan_lo, scan_hi)
        (low, high), _ = min(search.tried.items(), key=lambda kv: kv[1])
        if math.isfinite(low) and math.isfinite(high):
            low, high = search.shift_scan(low, high)
        return low, high

    def _screener(self) -> Screener:
        return self.scr

    def _upstream_signal(self, effect: Effect) -> np.ndarray | None:
        """The signal entering an inserted saturation block (fit part)."""
        P = self.P
        model = apply_effect(P.model, effect, dt_s=P.dt_s)
        sat = model.block(effect.location)
        up = sat.inputs[0].signal
        try:
            with np.errstate(all="ignore"):
                sim = simulate(model, {k: self.ins_fit[k] for k in model.inputs}, dt_s=P.dt_s,
                               initial=P.config.initial)
        except PipelineError:
            return None
        return sim.signals[up][P.fit_start:]

    def _fit_unmodelled(self, s: Screen, mk: Callable[[dict], Effect]) -> Effect:
        """k, tau_s, delay_s of an unmodelled input: exact for a linear model, because
        the injection at the output is linear (a nonlinear one: along its trajectory,
        :meth:`Screener.response`); k in closed form, delay on the integer grid, tau
        refined by a bounded scalar search around the best grid point."""
        P, dt = self.P, self.P.dt_s
        scr = self._screener()
        signal, _, out = s.location.partition("->")
        hs = scr.response(out, scr.ins[signal], f"input:{signal}")

        def sse_k(d: int, tau_samples: float) -> tuple[float, float]:
            shifted = np.zeros_like(hs)
            shifted[d:] = hs[: scr.stop - d]
            dw = scr.w(lag_filter(shifted, tau_samples))
            g, k = scr.project(dw)
            return -g, k

        best = None
        for st in s.starts[:3]:
            d = int(round(st["delay_s"] / dt))
            t0 = math.log(st["tau_s"] / dt)
            for dd in (d - 1, d, d + 1):
                if not 0 <= dd <= P.max_delay:
                    continue
                res = scipy.optimize.minimize_scalar(
                    lambda lt: sse_k(dd, math.exp(lt))[0],
                    bounds=(max(math.log(0.05), t0 - 1.5), t0 + 1.5), method="bounded",
                    options={"xatol": 1e-3})
                val, k = sse_k(dd, math.exp(res.x))
                if best is None or val < best[0]:
                    best = (val, k, math.exp(res.x) * dt, dd * dt)
        assert best is not None
        return mk({"k": float(best[1]), "tau_s": float(best[2]), "delay_s": float(best[3])})


def predict_with(P: Problem, effect: Effect, inputs: Mapping[str, np.ndarray]
                 ) -> np.ndarray | None:
    """Outputs (rows of `inputs`, n_y) of the search's model with `effect` added as it is,
    measurement offsets and the free outputs' profiled constants
    (:meth:`Problem.with_free_offsets`) included; None if the simulation fails or blows
    up.

    Parameters
    ----------
    P : Problem
    effect : Effect
        Added to ``P.model``.
    inputs : mapping of str -> ndarray
        ``P.inputs`` or a leading part of them.
    """
    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            # parameter trials near a null value (magnitude ~ 0) give transfer
            # functions scipy calls badly conditioned; the simulation is still exact
            warnings.simplefilter("ignore", scipy.signal.BadCoefficients)
            out = predict_outputs(P.model, effect, inputs, dt_s=P.dt_s, outputs=P.outputs,
                                  initial=P.config.initial)
    except PipelineError:
        return None
    y = np.column_stack([out[o] for o in P.outputs])
    if not (np.all(np.isfinite(y)) and np.max(np.abs(y)) < 1e12):
        return None
    return P.with_free_offsets(y)


def _local_minima(values: np.ndarray, sse: np.ndarray, m: int = 3) -> list[float]:
    """The (up to) `m` lowest local minima of `sse` over sorted `values`, best first."""
    order = np.argsort(values)
    x, e = values[order], sse[order]
    local = [i for i in range(e.size)
             if (i == 0 or e[i] <= e[i - 1]) and (i == e.size - 1 or e[i] <= e[i + 1])]
    return [float(x[i]) for i in sorted(local, key=lambda i: e[i])[:m]]


def _grid_gap(grid: np.ndarray, x: float) -> float:
    """Twice the spacing of the profile grid around x."""
    g = np.sort(grid)
    if not math.isfinite(x) or g.size < 2:
        return 0.0
    i = int(np.clip(np.searchsorted(g, x), 1, g.size - 1))
    return 2.0 * float(max(g[i] - g[i - 1], g[min(i + 1, g.size - 1)] - g[i]))


@dataclass
class _SaturationSearch:
    """State of :meth:`Fitter._fit_saturation`: limit pairs tried and their exact sums of squares."""

    fitter: Fitter
    mk: Callable[[dict], Effect]
    v: np.ndarray  # nominal signal at the location, samples [0, stop)
    span: float
    path: Any  # StaticMapPath or None (nonlinear nominal model)
    tried: dict[tuple[float, float], float] = field(default_factory=dict)

    def evaluate(self, lows: Sequence[float], highs: Sequence[float]) -> np.ndarray:
        """Exact whitened sums of squares of the limit pairs (lows[j], highs[j])."""
        f = self.fitter
        P, v, path = f.P, self.v, self.path
        lo, hi = np.asarray(lows, dtype=float), np.asarray(highs, dtype=float)
        if lo.size == 0:
            return np.zeros(0)
        if path is None:  # nonlinear nominal model: one exact simulation each
            return np.array([f.sse(self.mk({"low": float(a), "high": float(b)}))
                             for a, b in zip(lo, hi, strict=True)])
        f.n_eval += 1  # one pass simulates the whole batch
        return path.clip_sse(P, lo, hi, first=first_crossing(v, lo, hi))

    def run(self, pairs: Sequence[tuple[float, float]]) -> None:
        """Evaluate the new valid pairs (low < high) and record them in `tried`."""
        tried = self.tried
        new = [pq for pq in dict.fromkeys(pairs) if pq not in tried and pq[0] < pq[1]]
        for pq, e in zip(new, self.evaluate([a for a, _ in new], [b for _, b in new]),
                         strict=True):
            tried[pq] = float(e)

    def profiles(self, loc: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          np.ndarray]:
        """1. one-sided profiles: (lows, highs, sse, scan_lo, scan_hi); fills `tried`."""
        f, v, span = self.fitter, self.v, self.span
        P, stop, inf = f.P, f.stop, math.inf
        profile = saturation_profile(P, f.scr._h, loc, stop)
        grid_lo, grid_hi = saturation_grids(v)
        if profile is None:  # exact simulations one by one: coarser grids
            grid_lo, grid_hi = grid_lo[::6], grid_hi[::6]
            p_lows, p_highs = one_sided(grid_lo, grid_hi)
            p_sse = self.evaluate(p_lows, p_highs)
        else:
            p_lows, p_highs, p_sse, _ = profile
        self.tried.update({(float(a), float(b)): float(e)
                           for a, b, e in zip(p_lows, p_highs, p_sse, strict=True)})
        self.tried[(-inf, inf)] = f.sse(self.mk({"low": -inf, "high": inf}))
        # each chain: [low, high, side scanned next].  The SECOND limit of a pair may lie
        # outside the nominal signal's range: once the first limit acts, a loop can
        # drive the signal beyond where it ever went nominally (a drum level clipped
        # high is refilled low by its controller).  So the scans of the other limit
        # reach half a range beyond the nominal extremes, every 2 %.
        scan_lo = np.concatenate([np.linspace(v.min() - 0.5 * span, v.min(), 26)[:-1], grid_lo])
        scan_hi = np.concatenate([grid_hi, np.linspace(v.max(), v.max() + 0.5 * span, 26)[1:]])
        return p_lows, p_highs, p_sse, scan_lo, scan_hi

    def coordinate_descent(self, lows_min: list[float], highs_min: list[float],
                           scan_lo: np.ndarray, scan_hi: np.ndarray) -> None:
        """2. alternate scans of the other limit from the best one-sided limit of each side."""
        tried, inf = self.tried, math.inf
        chains: list[list[Any]] = [[lows_min[0], inf, "high"]] if lows_min else []
        chains += [[-inf, highs_min[0], "low"]] if highs_min else []
        for sweep in range(3):
            self.run([(float(x), c[1]) if c[2] == "low" else (c[0], float(x))
                      for c in chains for x in (scan_lo if c[2] == "low" else scan_hi)])
            moved = False
            for c in chains:
                if c[2] == "low":
                    options = [(float(x), c[1]) for x in scan_lo] + [(c[0], c[1])]
                else:
                    options = [(c[0], float(x)) for x in scan_hi] + [(c[0], c[1])]
                low, high = min((pq for pq in options if pq in tried), key=lambda pq: tried[pq])
                moved |= (low, high) != (c[0], c[1])
                c[:] = [low, high, "high" if c[2] == "low" else "low"]
            if not moved and sweep:
                break

    def centres(self, n_starts: int) -> list[list[float]]:
        """The best `n_starts` distinct pairs tried, not both limits infinite."""
        span = self.span
        centres: list[list[float]] = []
        for (a, b), _ in sorted(self.tried.items(), key=lambda kv: kv[1]):
            if len(centres) >= n_starts:
                break
            if math.isinf(a) and math.isinf(b):
                continue
            if not any(near(a, c[0], 1e-3 * span) and near(b, c[1], 1e-3 * span)
                       for c in centres):
                centres.append([a, b])
        return centres

    def refine(self, centres: list[list[float]], scan_lo: np.ndarray,
               scan_hi: np.ndarray) -> None:
        """3. shrinking 7 x 7 grids around the centres (the best valley only after 3 rounds)."""
        tried, span = self.tried, self.span
        widths = [[max(_grid_gap(scan_lo, a), 1e-3 * span), max(_grid_gap(scan_hi, b), 1e-3 * span)]
                  for a, b in centres]
        offsets = np.linspace(-1.0, 1.0, 7)
        for round_ in range(40):
            batch = []
            for (a, b), (wa, wb) in zip(centres, widths, strict=True):
                grid_a = [a] if math.isinf(a) else [a + wa * o for o in offsets]
                grid_b = [b] if math.isinf(b) else [b + wb * o for o in offsets]
                batch.append([(x, y_) for x in grid_a for y_ in grid_b if x < y_])
            self.run([pq for part in batch for pq in part])
            for j, part in enumerate(batch):
                centres[j] = list(min(part, key=lambda pq: tried[pq]))
                widths[j] = [0.4 * widths[j][0], 0.4 * widths[j][1]]
            if round_ == 2 and len(centres) > 1:  # keep refining the best valley only
                k = int(np.argmin([tried[tuple(c)] for c in centres]))
                centres, widths = [centres[k]], [widths[k]]
            if max(max(wa, wb) for wa, wb in widths) < 1e-4 * span:
                break

    def shift_scan(self, low: float, high: float) -> tuple[float, float]:
        """4. scan along the common shift of two finite limits, then a shrinking grid."""
        # with integral action, shifting both limits together changes little (the
        # integrator re-centres the loop): the valley runs along the shift, and its
        # floor is rugged (episodes start and end on whole samples).  Scan it.
        tried, span = self.tried, self.span
        offsets = np.linspace(-1.0, 1.0, 7)
        shifts = np.linspace(-0.08, 0.08, 41) * span
        spreads = np.linspace(-0.01, 0.01, 9) * span
        self.run([(low + d - e, high + d + e) for d in shifts for e in spreads])
        (low, high), _ = min(tried.items(), key=lambda kv: kv[1])
        widths_l = [0.005 * span, 0.005 * span]
        for _ in range(8):
            part = [(low + widths_l[0] * x, high + widths_l[1] * y_)
                    for x in offsets for y_ in offsets]
            self.run(part)  # (pairs with low >= high are skipped: not in `tried`)
            low, high = min((pq for pq in part if pq in tried), key=lambda pq: tried[pq])
            widths_l = [0.4 * w_ for w_ in widths_l]
        (low, high), _ = min(tried.items(), key=lambda kv: kv[1])
        return low, high


def refit_nested_lags(fitter: Fitter, preds: list[tuple[Screen, Effect, np.ndarray]]) -> None:
    """Restart extra_lag fits from the tau of an inverse_response at the same class.

    inverse_response nests extra_lag (magnitude 0); when the data want no wrong-way
    part both should reach the same fit and the BIC penalty picks extra_lag.  A lag
    fit that stopped slightly short of the optimum would otherwise lose by more than
    the penalty on a long, clean record.

    Parameters
    ----------
    fitter : Fitter
        Fitter of the current pass (its noise model weights the refits).
    preds : list of (Screen, Effect, ndarray (N, n_y))
        Fitted classes with their full-record predictions; modified in place: an
        extra_lag entry is replaced when the refit lowers its fit-part sum of squares.
    """
    for c_inv, e_inv, _ in [p for p in preds if p[1].name == "inverse_response"]:
        for j, (c_lag, e_lag, _) in enumerate(preds):
            if e_lag.name != "extra_lag" or not c_lag.shares_place(c_inv):
                continue
            mk = lambda x, e=e_lag: Effect("extra_lag", e.location,  # noqa: E731
                                           {"tau_s": float(math.exp(x[0]))},
                                           e.equivalent_locations)
            dt = fitter.P.dt_s
            lower = np.array([math.log(0.05 * dt)])
            upper = np.array([math.log(20.0 * max(fitter.P.settling_s, dt))])
            starts = [np.array([math.log(e_inv.parameters["tau_s"])]),
                      np.array([math.log(e_lag.parameters["tau_s"])])]
            refit = fitter._lsq(mk, starts, lower, upper)
            if fitter.sse(refit) < fitter.sse(e_lag):
                y_pred = fitter.predict(refit, full=True)
                if y_pred is not None:
                    preds[j] = (c_lag, refit, y_pred)


def pade_delay_partners(fitter: Fitter, preds: list[tuple[Screen, Effect, np.ndarray]]
                        ) -> list[tuple[Screen, Effect, np.ndarray | None]]:
    """The dead times an inverse response among `preds` approximates, fitted as their
    own class where no dead time of that place was fitted.

    The catalogue declares the all-pass of magnitude ~1 a delay's Padé approximant
    (:func:`pipeline.discrepancy.effects.degenerate_forms`); selection names the delay
    unless the inverse response predicts held-out data distinguishably better, and it
    can only compare the two when both were fitted.  Screening may keep the inverse
    response alone (zoo heat exchanger 8 101 005: a 14 s steam-valve dead time at 2 s,
    named an inverse response of magnitude 0.99, tau 5.2 s, with no dead time fitted),
    and the form as it maps (``tau (1 + magnitude)`` = 10.25 s) is no whole number of
    samples, so it cannot even be simulated: the class's own fit (integer grid and walk,
    :meth:`Fitter.fit`) starts from it instead.

    Parameters
    ----------
    fitter : Fitter
        Fitter of the current pass.
    preds : list of (Screen, Effect, ndarray (N, n_y))
        Fitted classes with their full-record predictions.

    Returns
    -------
    list of (Screen, Effect, ndarray or None)
        The partners with their full-record predictions (None: the simulation diverges).
    """
    out: list[tuple[Screen, Effect, np.ndarray | None]] = []
    for c_inv, e_inv, _ in [p for p in preds if p[1].name == "inverse_response"]:
        for form in degenerate_forms(e_inv):
            if form.name != "dead_time" or any(
                    e.name == "dead_time" and c.shares_place(c_inv)
                    for c, e, _ in [*preds, *out]):
                continue
            screen = Screen("dead_time", c_inv.location, c_inv.score, 1,
                            [dict(form.parameters)], c_inv.direction, list(c_inv.members))
            effect = fitter.fit(screen)
            out.append((screen, effect, fitter.predict(effect, full=True)))
    return out
