"""Screening: every catalogue effect at every location by its exact (linearised)
sensitivity -- impulse responses for a linear model, responses along its own trajectory
for a nonlinear one (effects accepted earlier in the chain); the saturation static-map
path."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.fft
import scipy.optimize

from pipeline.discrepancy.localise import lag_filter
from pipeline.discrepancy.lure import first_crossing, inject_model, saturation_profile
from pipeline.discrepancy.problem import Problem
from pipeline.discrepancy.effects import (
    Effect,
    applicable_locations,
    original_location,
    predict_outputs,
)
from pipeline.errors import PipelineError
from pipeline.models.blocks import Backlash, Sum, Term
from pipeline.models.model import Model
from pipeline.models.simulate import simulate


#: Relative tolerance under which two candidates' sensitivities count as identical
#: (equivalent locations): rounding of an FFT convolution is ~1e-13 relative.
_EQUIVALENT_RTOL = 1e-7


#: Size of the injection, relative to the injected signal, with which a NONLINEAR model's
#: response along its own trajectory is simulated (:meth:`Screener.response`).  The
#: impulse responses of :meth:`Screener.H` start from rest, where a saturation or a
#: deadband of the model sits in its linear range: they miss how an effect acts while
#: the model is clipped.  A 23 % gain on a drum's integrating mass showed only while the
#: feedwater saturation (accepted first) held the loop open -- its impulse-response score
#: was below 7, while the truth given the saturation closed 74 % of the held-out gap.
#: Simulated along the trajectory: the block-output signal of a gain (and of a dead time,
#: lag or inverse response: their grids delay and filter that response, which is exact
#: for a linear model and keeps at least when the model is clipped otherwise), of an
#: operating-point gain, of an unmodelled input, and the deadband grid.  0.1: the order of
#: the effects sought (a gain of 15-60 %), small enough to be a slope.  A linear model
#: keeps the impulse responses (identical up to rounding, and one FFT per candidate).
_TRAJECTORY_STEP = 0.1


#: One screening grid point: (explained whitened SS, parameters, whitened direction).
_GridPoint = tuple[float, dict[str, Any], np.ndarray]


@dataclass(eq=False)  # identity comparison: the direction arrays make == ambiguous
class Screen:
    """Screening outcome of one candidate (internal)."""

    name: str
    location: str
    score: float  # explained whitened SS minus penalty
    n_parameters: int
    starts: list[dict[str, Any]]  # best grid points first (parameters)
    direction: np.ndarray  # whitened direction at the best point (equivalence test)
    members: list[str] = field(default_factory=list)

    def shares_place(self, other: Screen) -> bool:
        """Whether the two classes act at a common location (their members overlap).

        Parameters
        ----------
        other : Screen
            Another screened class.
        """
        return bool(set(self.members) & set(other.members))


class Screener:
    """First-order (Born) screening of every candidate on the fit part.

    Parameters
    ----------
    P : Problem
        Validated signals, nominal simulation, split and whitening (noise model set).
    resid : ndarray (N, n_y)
        Residual: measured minus nominal simulated outputs; whitened on the fit part.
    h_cache : dict or None
        Cache of impulse responses, exact simulations and saturation paths, shared
        across screenings (None: a new one).
    fixed_basis : ndarray (m, k) or None
        Orthonormal whitened directions that are free alongside every candidate (the
        chain's earlier effects refitted jointly,
        :func:`pipeline.discrepancy.joint.prior_basis`): the residual and every
        candidate's direction are scored orthogonally to them -- the SS a candidate
        removes when those directions are refitted with it, to first order.
    """

    def __init__(self, P: Problem, resid: np.ndarray,
                 h_cache: dict[tuple[str, str], np.ndarray] | None = None,
                 fixed_basis: np.ndarray | None = None) -> None:
        self.P = P
        self.stop = P.holdout_start
        self.nfft = int(scipy.fft.next_fast_len(2 * self.stop))
        self.basis = fixed_basis
        self.r_w = self.perp(P.whiten(resid, P.fit_start, self.stop))
        self.penalty = math.log(self.r_w.size)
        self._h: dict[tuple[str, str], Any] = {} if h_cache is None else h_cache
        sig = P.nominal_signals
        self.v = {b: sig[b][: self.stop] for b in P.model.block_names}
        self.linear = P.model.is_linear
        self.ins = {k: v[: self.stop] for k, v in P.inputs.items()}

    # impulse responses --------------------------------------------------------------
    def H(self, block: str, side: str) -> np.ndarray:
        """rfft of the impulse responses injection -> measured outputs, (nfft//2+1, n_y).

        Parameters
        ----------
        block : str
            Model block where the unit impulse is injected.
        side : {"output", "input"}
            Add the impulse to the block's output, or to its input (through a sum
            inserted before it).
        """
        key = (block, side)
        if key not in self._h:
            m = inject_model(self.P.model, block, side=side)
            u = {k: np.zeros(self.stop) for k in m.inputs}
            u["__inject"][0] = 1.0
            with np.errstate(all="ignore"):
                sim = simulate(m, u, dt_s=self.P.dt_s)
            h = np.column_stack([sim.signals[o] for o in self.P.outputs])
            self._h[key] = scipy.fft.rfft(np.nan_to_num(h), self.nfft, axis=0)
        return self._h[key]

    def conv(self, H: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Response of the outputs to injecting x (stop,): (stop, n_y).

        Parameters
        ----------
        H : ndarray (nfft//2+1, n_y)
            Impulse-response spectra from :meth:`H`.
        x : ndarray (stop,)
            Injected signal on samples ``[0, stop)``.
        """
        X = scipy.fft.rfft(x, self.nfft)
        return scipy.fft.irfft(H * X[:, None], self.nfft, axis=0)[: self.stop]

    def response(self, block: str, x: np.ndarray, tag: str, side: str = "output"
                 ) -> np.ndarray:
        """Response of the outputs to adding `x` (stop,) to `block`'s output (or input):
        (stop, n_y).

        A linear model: the convolution with its impulse responses (:meth:`H`).  A
        nonlinear one (effects accepted earlier in the chain): simulated along the
        model's own trajectory, with the measured inputs, as the change that
        :data:`_TRAJECTORY_STEP` times `x` makes, divided by that step (cached by
        `block` and `tag`, which names `x`).

        Parameters
        ----------
        block : str
            Model block whose output (input) `x` is added to.
        x : ndarray (stop,)
            Injected signal on samples ``[0, stop)``.
        tag : str
            Identity of `x` for the cache (e.g. ``"gain"``).
        side : {"output", "input"}
            As in :meth:`H`.
        """
        if self.linear:
            return self.conv(self.H(block, side), x)
        key = ("trajectory", block, side, tag)
        if key not in self._h:
            self._h[key] = self._trajectory(block, x, side)
        return self._h[key]

    def _trajectory(self, block: str, x: np.ndarray, side: str) -> np.ndarray:
        """:meth:`response` of a nonlinear model (uncached)."""
        P = self.P
        m = inject_model(P.model, block, side=side)
        base_key = ("trajectory", block, side, "")
        if base_key not in self._h:  # the same model with nothing injected
            self._h[base_key] = self._outputs(m, None, {**self.ins,
                                                        "__inject": np.zeros(self.stop)})
        base = self._h[base_key]
        y = self._outputs(m, None, {**self.ins, "__inject": _TRAJECTORY_STEP * x})
        if base is None or y is None:
            return np.zeros((self.stop, P.n_y))
        return (y - base) / _TRAJECTORY_STEP

    def _outputs(self, model: Model, effect: Effect | None, inputs: dict[str, np.ndarray]
                 ) -> np.ndarray | None:
        """Measured outputs (stop, n_y) of `model` with `effect`
        (:func:`pipeline.discrepancy.effects.predict_outputs`) driven by `inputs` on ``[0, stop)``;
        None when the simulation fails or is not finite."""
        try:
            with np.errstate(all="ignore"):
                out = predict_outputs(model, effect, inputs, dt_s=self.P.dt_s,
                                      outputs=self.P.outputs, initial=self.P.config.initial)
        except PipelineError:
            return None
        y = np.column_stack([out[o] for o in self.P.outputs])
        return y if np.all(np.isfinite(y)) else None

    def w(self, d: np.ndarray) -> np.ndarray:
        """Whitened `d` on the fit part (:meth:`Problem.whiten` on ``[fit_start, stop)``).

        Parameters
        ----------
        d : ndarray (stop, n_y)
            Output change or error from sample 0 on.
        """
        return self.P.whiten(d, self.P.fit_start, self.stop)

    def exact(self, effect: Effect) -> np.ndarray | None:
        """Exact outputs with `effect` on the fit part (cached across screenings).

        Parameters
        ----------
        effect : Effect
            Candidate effect, simulated on samples ``[0, stop)``; None is returned when
            the simulation fails or blows up.
        """
        key = ("exact", effect.describe())
        if key not in self._h:
            y = self._outputs(self.P.model, effect, self.ins)
            self._h[key] = y if y is not None and np.max(np.abs(y)) < 1e12 else None
        return self._h[key]

    # scoring helpers -------------------------------------------------------------
    def perp(self, d_w: np.ndarray) -> np.ndarray:
        """`d_w` (a whitened direction, or columns of them) less its part in the
        span of ``fixed_basis`` (unchanged when there is none).

        Parameters
        ----------
        d_w : ndarray (m,) or (m, k)
            Whitened change(s) of the outputs.
        """
        if self.basis is None:
            return d_w
        return d_w - self.basis @ (self.basis.T @ d_w)

    def fixed(self, d_w: np.ndarray) -> float:
        """Whitened SS removed when the direction enters with coefficient 1.

        Parameters
        ----------
        d_w : ndarray
            Whitened change of the outputs (a direction), same length as ``r_w``.
        """
        d_w = self.perp(d_w)
        return float(2.0 * d_w @ self.r_w - d_w @ d_w)

    def project(self, d_w: np.ndarray) -> tuple[float, float]:
        """(SS removed, coefficient) for the best multiple of one direction.

        Parameters
        ----------
        d_w : ndarray
            Whitened change of the outputs (a direction), same length as ``r_w``.
        """
        d_w = self.perp(d_w)
        dd = float(d_w @ d_w)
        if dd <= 0:
            return 0.0, 0.0
        beta = float(d_w @ self.r_w) / dd
        return beta * float(d_w @ self.r_w), beta

    def block_input(self, block: str) -> np.ndarray:
        """Nominal input of `block` on samples ``[0, stop)``: the weighted sum of its terms.

        Parameters
        ----------
        block : str
            Model block name.
        """
        b = self.P.model.block(block)
        total = np.zeros(self.stop)
        for term in b.inputs:
            total = total + term.k * (self.v[term.signal] if term.signal in self.v
                                      else self.ins[term.signal])
        return total

    # candidates -----------------------------------------------------------------
    def screen(self, name: str, loc: str, signal: str | None = None) -> Screen | None:
        """Screen effect `name` at `loc` (``signal``: operating_point_gain's schedule).

        Parameters
        ----------
        name : str
            Catalogue effect name.
        loc : str
            Location: a block name, a measured output (sensor_bias_drift) or
            ``"signal->output"`` (unmodelled_input).
        signal : str or None
            Measured signal scheduling operating_point_gain; unused by other effects.
        """
        P, dt = self.P, self.P.dt_s
        grid: list[_GridPoint] = []
        n_par = 1
        taus = np.geomspace(0.5, max(2.0, P.settling_s / dt), 12)
        if name == "sensor_bias_drift":
            n_par = self._grid_bias_drift(grid, loc)
        elif name == "unmodelled_input":
            n_par = self._grid_unmodelled(grid, loc, taus)
        elif name in ("gain", "dead_time", "extra_lag", "inverse_response", "operating_point_gain",
                      "saturation"):
            n_par = self._grid_block_output(grid, name, loc, signal, taus)
        elif name in ("deadband", "backlash"):
            self._grid_play(grid, name, loc)
        if not grid:
            return None
        grid.sort(key=lambda g: -g[0])
        best = grid[0]
        starts = [g[1] for g in grid[:3]]
        return Screen(name=name, location=loc, score=best[0] - n_par * self.penalty,
                       n_parameters=n_par, starts=starts, direction=best[2], members=[loc])

    def _grid_bias_drift(self, grid: list[_GridPoint], loc: str) -> int:
        """sensor_bias_drift at output `loc`: the exact least-squares point; returns n_par."""
        P, dt = self.P, self.P.dt_s
        i = P.outputs.index(loc)
        t_h = np.arange(self.stop) * dt / 3600.0
        cols = []
        for c in (np.ones(self.stop), t_h):
            d = np.zeros((self.stop, P.n_y))
            d[:, i] = c
            cols.append(self.w(d))
        d_w = np.column_stack(cols)
        d_perp = self.perp(d_w)
        beta, *_ = np.linalg.lstsq(d_perp, self.r_w, rcond=None)
        gain = float(self.r_w @ d_perp @ beta)
        grid.append((gain, {"bias": float(beta[0]), "drift_per_h": float(beta[1])}, d_w @ beta))
        return 2

    def _grid_unmodelled(self, grid: list[_GridPoint], loc: str, taus: np.ndarray) -> int:
        """unmodelled_input ``signal->output``: every delay and lag, k projected; returns n_par."""
        P, dt = self.P, self.P.dt_s
        signal, _, out = loc.partition("->")
        hs = self.response(out, self.ins[signal], f"input:{signal}")
        for d in range(0, P.max_delay + 1):
            shifted = np.zeros_like(hs)
            shifted[d:] = hs[: self.stop - d]
            for tau in taus:
                dw = self.w(lag_filter(shifted, tau))
                g, k = self.project(dw)
                grid.append((g, {"k": k, "tau_s": float(tau * dt), "delay_s": float(d * dt)}, k * dw))
        return 3

    def _grid_block_output(self, grid: list[_GridPoint], name: str, loc: str,
                           signal: str | None, taus: np.ndarray) -> int:
        """Effects acting on block `loc`'s output (gain, delay, lags, saturation); returns n_par."""
        P, dt = self.P, self.P.dt_s
        v = self.v[loc]
        n_par = 1
        if name == "gain":
            dw = self.w(self.response(loc, v, "gain"))
            g, beta = self.project(dw)
            grid.append((g, {"factor": 1.0 + beta}, beta * dw))
        elif name == "dead_time":
            hv = self.response(loc, v, "gain")
            for d in range(1, P.max_delay + 1):
                shifted = np.zeros_like(hv)
                shifted[d:] = hv[: self.stop - d]
                dw = self.w(shifted - hv)
                grid.append((self.fixed(dw), {"delay_s": float(d * dt)}, dw))
        elif name == "extra_lag":
            hv = self.response(loc, v, "gain")
            for tau in taus:
                dw = self.w(lag_filter(hv, tau) - hv)
                grid.append((self.fixed(dw), {"tau_s": float(tau * dt)}, dw))
        elif name == "inverse_response":
            hv = self.response(loc, v, "gain")
            n_par = 2
            for tau in taus:
                dw = self.w(lag_filter(hv, tau) - hv)  # times (1 + magnitude)
                dp = self.perp(dw)
                dd, dr = float(dp @ dp), float(dp @ self.r_w)
                c = max(dr / dd, 1.0) if dd > 0 else 1.0
                grid.append((2 * c * dr - c * c * dd,
                             {"tau_s": float(tau * dt), "magnitude": c - 1.0}, c * dw))
        elif name == "operating_point_gain":
            dw = self.w(self.response(loc, self.ins[signal] * v, f"opg:{signal}"))
            g, beta = self.project(dw)
            grid.append((g, {"slope": beta, "signal": signal}, beta * dw))
        else:  # saturation
            n_par = 2
            self._grid_saturation(grid, loc, v, self.H(loc, "output"))
        return n_par

    def _grid_saturation(self, grid: list[_GridPoint], loc: str, v: np.ndarray,
                         H: np.ndarray) -> None:
        """saturation at `loc`: limits as fractions of the signal's extremes (covariant),
        plus exact one-sided profiles (or exact quantile pairs for a nonlinear model)."""
        P = self.P
        hi_v, lo_v = float(v.max()), float(v.min())
        fractions = (0.35, 0.5, 0.65, 0.8, 0.92, None)
        for fl in fractions:
            for fh in fractions:
                if fl is None and fh is None:
                    continue
                low = -math.inf if fl is None else fl * lo_v
                high = math.inf if fh is None else fh * hi_v
                if not low < high:
                    continue
                dv = np.clip(v, low, high) - v
                dw = self.w(self.conv(H, dv))
                grid.append((self.fixed(dw), {"low": low, "high": high}, dw))
        # A saturation inside a loop with integral action winds up: the first-
        # order picture underestimates it badly, so the one-sided limit profiles
        # are simulated exactly (:func:`saturation_profile`, cached) -- or, for
        # a nonlinear nominal model, five limit pairs (quantiles of the signal).
        profile = saturation_profile(P, self._h, loc, self.stop)
        if profile is not None:
            p_lows, p_highs, p_sse, path = profile
            rr = float(self.r_w @ self.r_w)
            best = np.argsort(p_sse)[:3]
            lows, highs = p_lows[best], p_highs[best]
            y_corr = path.clip_corrections(P, lows, highs,
                                           first=first_crossing(v, lows, highs))
            for m, j in enumerate(best):
                dw = self.w(y_corr[:, :, m])
                # the profile's exact SSE, or -- scored orthogonally to fixed_basis --
                # its correction as a direction
                grid.append((rr - float(p_sse[j]) if self.basis is None else self.fixed(dw),
                             {"low": float(p_lows[j]), "high": float(p_highs[j])}, dw))
        pairs = () if profile is not None else (
            (0.05, 0.95), (0.12, 0.88), (0.25, 0.75), (0.0, 0.9), (0.1, 1.0))
        for ql, qh in pairs:
            low, high = (float(x) for x in np.quantile(v, [ql, qh]))
            low = -math.inf if ql == 0.0 else low
            high = math.inf if qh == 1.0 else high
            if not low < high:
                continue
            y_exact = self.exact(Effect("saturation", loc, {"low": low, "high": high}))
            if y_exact is not None:
                dw = self.w(y_exact - self.P.y_nominal[: self.stop])
                grid.append((self.fixed(dw), {"low": low, "high": high}, dw))

    def _grid_play(self, grid: list[_GridPoint], name: str, loc: str) -> None:
        """deadband or backlash at the input of block `loc`: widths as fractions of the
        input's extreme; the injected signal is the block's map of the nominal input
        less that input (the backlash's by :func:`~pipeline.models.simulate.simulate` of the
        one block, so its memory is the simulator's)."""
        u = self.block_input(loc)
        scale = float(np.max(np.abs(u)))
        if scale > 0:
            for frac in (0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7):
                width = frac * scale
                if name == "deadband":
                    du = -np.clip(u, -width / 2, width / 2)
                else:
                    du = _backlash(u, width, self.P.dt_s) - u
                dw = self.w(self.response(loc, du, f"{name}:{frac}", side="input"))
                grid.append((self.fixed(dw), {"width": width}, dw))


def _backlash(u: np.ndarray, width: float, dt_s: float) -> np.ndarray:
    """`u` through a ``backlash`` block of `width` (memory at rest at the start)."""
    one = Model(name="backlash", inputs=("u",), outputs=("b",),
                blocks=(Backlash(name="b", inputs=(Term("u"),), width=width),))
    return simulate(one, {"u": u}, dt_s=dt_s).outputs[:, 0]


def near(a: float, b: float, tol: float) -> bool:
    """a and b equal (also both the same infinity) or within tol.

    Parameters
    ----------
    a, b : float
        Values compared (may be infinite).
    tol : float
        Absolute tolerance.
    """
    return a == b or abs(a - b) <= tol


def screen_all(P: Problem, resid: np.ndarray,
                h_cache: dict[tuple[str, str], np.ndarray] | None = None,
                fixed_basis: np.ndarray | None = None) -> tuple[list[Screen], Screener]:
    """Screen every candidate; merge identical sensitivities into classes (best first).

    Parameters
    ----------
    P : Problem
        Validated signals, nominal simulation, split and whitening; ``P.config.effects``
        are screened.
    resid : ndarray (N, n_y)
        Residual: measured minus nominal simulated outputs.
    h_cache : dict or None
        Cache shared across screenings (:class:`Screener`; None: a new one).
    fixed_basis : ndarray (m, k) or None
        Directions free alongside every candidate (:class:`Screener`).
    """
    scr = Screener(P, resid, h_cache, fixed_basis)
    results: list[Screen] = []
    for name in P.config.effects:
        locations = applicable_locations(P.model, name, measured_outputs=P.outputs,
                                         signals=P.extra_signals)
        if P.location_names is not None:
            locations = [loc for loc in locations
                         if original_location(loc, P.location_names) is not None]
        # operating_point_gain: one candidate per scheduling signal (part of its identity)
        signals = list(P.inputs) if name == "operating_point_gain" else [None]
        for loc in locations:
            for signal in signals:
                with np.errstate(all="ignore"):
                    s = scr.screen(name, loc, signal)
                if s is not None and np.all(np.isfinite(s.direction)):
                    results.append(s)
    # Equivalence classes: same effect, same whitened change of the outputs.
    classes: list[Screen] = []
    block_order = {b.name: i for i, b in enumerate(P.model.blocks)}
    for s in results:
        norm = float(np.linalg.norm(s.direction))
        for c in classes:
            if c.name != s.name or norm == 0.0:
                continue
            if np.linalg.norm(c.direction - s.direction) <= _EQUIVALENT_RTOL * max(norm, 1e-300):
                c.members.append(s.location)
                # canonical location: a non-sum block if there is one, else model order
                def rank(loc: str) -> tuple[int, int]:
                    is_sum = loc in block_order and isinstance(P.model.block(loc), Sum)
                    return (int(is_sum), block_order.get(loc, 0))
                if rank(s.location) < rank(c.location):
                    c.location = s.location
                    c.starts = s.starts
                break
        else:
            classes.append(s)
    classes = _merge_saturation_chains(P.model, classes)
    classes.sort(key=lambda c: -c.score)
    return classes, scr


def _merge_saturation_chains(model: Model, classes: list[Screen]) -> list[Screen]:
    """Merge saturation classes at B1 and B2 when B2 = k * B1 (delayed) is B1's only reader.

    A saturation commutes with a static gain and a dead time once its limits are
    scaled by k (swapped when k < 0), so the two locations are indistinguishable; the
    sensitivity test cannot see it because the limits differ.  The class keeps the
    downstream block (the physical actuator signal) and the better screening score.
    """
    readers: dict[str, list[str]] = {}
    for block in model.blocks:
        for ref in block.references():
            readers.setdefault(ref, []).append(block.name)
    by_loc = {c.location: c for c in classes if c.name == "saturation"}
    for block in model.blocks:
        if not isinstance(block, (Sum,)) and block.TYPE != "gain":
            continue
        if len(block.inputs) != 1:
            continue
        up = block.inputs[0].signal
        if up not in by_loc or block.name not in by_loc or up in model.outputs:
            continue
        if readers.get(up, []) != [block.name]:
            continue
        down_cls, up_cls = by_loc[block.name], by_loc[up]
        if down_cls is up_cls:
            continue
        keep, drop = (down_cls, up_cls)
        keep.members = list(dict.fromkeys(keep.members + drop.members))
        if drop.score > keep.score:
            keep.score = drop.score
        classes = [c for c in classes if c is not drop]
        for loc in drop.members:
            by_loc[loc] = keep
    return classes


def class_key(c: Screen) -> tuple[str, str, Any]:
    """Identity of a screened class across passes: effect, location, schedule signal.

    Parameters
    ----------
    c : Screen
        Screened class.
    """
    return (c.name, c.location, c.starts[0].get("signal") if c.starts else None)


def kept_classes(classes: list[Screen], k: int) -> list[Screen]:
    """The `k` best classes.

    Parameters
    ----------
    classes : list of Screen
        Screened classes, best first (:func:`screen_all`).
    k : int
        Number kept (``n_fit_candidates``).
    """
    return list(classes[:k])


def nested_partners(classes: list[Screen], chosen: list[Screen]) -> list[Screen]:
    """The extra_lag class at the location of each chosen inverse_response.

    inverse_response with magnitude 0 is an extra lag: fitting both at a location lets
    the BIC penalty pick the simpler one when the wrong-way part is not needed.

    Parameters
    ----------
    classes : list of Screen
        Every screened class.
    chosen : list of Screen
        Classes already selected for fitting (partners among them are not repeated).
    """
    out: list[Screen] = []
    for c in chosen:
        if c.name != "inverse_response":
            continue
        for other in classes:
            if (other.name == "extra_lag" and other not in chosen and other not in out
                    and other.shares_place(c)):
                out.append(other)
    return out
