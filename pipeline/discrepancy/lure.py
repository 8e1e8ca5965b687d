"""Saturation candidates simulated exactly for many limit pairs at once (Lur'e form).

A ``saturation`` of block B is a static map ``s -> clip(s, low, high)`` of B's output
``s``.  The augmented model is then the nominal (linear) model plus an injection
``d = clip(s) - s`` at ``s``, and superposition is exact: the outputs are the nominal
outputs plus the injection's response, and ``s`` is its nominal value plus the response
to *earlier* injections (strictly causal: the nominal model has no algebraic loop).  One
pass over time with a state matrix of K columns therefore simulates K limit pairs
exactly (equal to :func:`pipeline.discrepancy.effects.predict_outputs` to rounding) for about the
cost of one per-sample simulation -- which is what makes dense searches over saturation
limits, whose error valleys are narrow when a loop winds up, affordable.

The pass is compiled (numba) and returns the whitened fit-part sum of squares of every
column directly: the (samples, outputs, K) array of output changes is never stored (on
1e5 samples and 297 columns it is 317 MB, whose first touch alone cost 0.04-3.9 s on
these machines).
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from pipeline.discrepancy.problem import Problem
from pipeline.errors import ModelError, PipelineError
from pipeline.models.blocks import Sum, Term
from pipeline.models.model import Model, insert_after, insert_before
from pipeline.models.simulate import discrete_state_space


def inject_model(model: Model, block: str, *, side: str) -> Model:
    """`model` plus an input ``__inject`` added at the output (or input) of `block`.

    Parameters
    ----------
    model : Model
        The nominal model.
    block : str
        Block where the injection is summed in.
    side : {"output", "input"}
        ``"output"``: onto the block's output (its own output is renamed
        ``{block}__inject_upstream``); ``"input"``: onto its input, through a sum
        block ``{block}__inject_sum`` inserted before it.
    """
    base = dataclasses.replace(model, inputs=(*model.inputs, "__inject"))
    if side == "output":
        upstream = f"{block}__inject_upstream"
        return insert_after(base, block, upstream_name=upstream,
                            block=Sum(name=block, inputs=(Term(upstream), Term("__inject"))))
    name = f"{block}__inject_sum"
    with_sum = insert_before(base, block, block=Sum(name=name))
    summed = with_sum.block(name)
    return with_sum.with_block(dataclasses.replace(summed, inputs=(*summed.inputs, Term("__inject"))))


#: States below this magnitude are set to zero in the pass (signals are deviations of
#: order 1e-6..1e6; 1e-150 is far below any and far above the subnormal numbers, on
#: which arithmetic is 10-100x slower, that a state decaying since its last clip reaches).
_FLUSH = 1e-150


class StaticMapPath:
    """The nominal model with a clip on one block's output, exact for many limit pairs.

    Raises ModelError when the nominal model is not linear or too large (the caller then
    simulates each limit pair exactly).

    Parameters
    ----------
    P : Problem
        The analysis problem (model, measured outputs, sample period).
    block : str
        Block whose output is clipped.
    s_nominal : ndarray (N,)
        Nominal simulated output of `block`; the first `stop` samples are used.
    stop : int
        Number of samples simulated, ``[0, stop)`` (the end of the fit part).
    """

    #: Above this many states the K-column state update costs more than simulating.
    MAX_STATES = 200

    def __init__(self, P: Problem, block: str, s_nominal: np.ndarray, stop: int) -> None:
        model = inject_model(P.model, block, side="output")
        system = discrete_state_space(model, dt_s=P.dt_s)
        if system.a.shape[0] > self.MAX_STATES:
            raise ModelError(f"{system.a.shape[0]} states: simulate candidates one by one")
        j = system.input_names.index("__inject")
        name = f"{block}__inject_upstream"
        row = system.signal_names.index(name)
        # the map's own signal must not depend on the current injection
        if abs(system.d[row, j]) > 1e-12:  # pragma: no cover - algebraic loop
            raise ModelError(f"signal {name!r} depends algebraically on the injection")
        rows = [row] + [system.signal_names.index(o) for o in P.outputs]
        # rows [signal, outputs, next state] = [c; a] @ x as a list of nonzero entries
        # (the boiler loop's 10-state a has 13), and the injection's feedthrough
        ca = np.vstack([system.c[rows], system.a])
        self._rows, self._cols = (np.ascontiguousarray(v, dtype=np.int64)
                                  for v in np.nonzero(ca))
        self._vals = np.ascontiguousarray(ca[self._rows, self._cols])
        self._n_rows = ca.shape[0]
        self._bd = np.ascontiguousarray(np.concatenate([system.d[rows[1:], j], system.b[:, j]]),
                                        dtype=float)
        self.n_y = len(rows) - 1
        self.s_nominal = np.ascontiguousarray(s_nominal[:stop], dtype=float)
        self.stop = stop

    def _pass(self, P: Problem, lows, highs, first: int, keep: bool):
        p1 = max(len(a) for a in P.ar)
        ar = np.zeros((self.n_y, p1))
        for i, a in enumerate(P.ar):
            ar[i, :len(a)] = a
        r = np.ascontiguousarray(P.y[:self.stop] - P.y_nominal[:self.stop], dtype=float)
        return _clip_pass(self._rows, self._cols, self._vals, self._n_rows, self._bd,
                          self.s_nominal, np.ascontiguousarray(lows, dtype=float),
                          np.ascontiguousarray(highs, dtype=float), int(first), self.stop,
                          self.n_y, r, ar, 1.0 / np.asarray(P.sigma, dtype=float) ** 2,
                          P.fit_start + p1 - 1, keep)

    def clip_sse(self, P: Problem, lows: np.ndarray, highs: np.ndarray, first: int = 0
                 ) -> np.ndarray:
        """Whitened fit-part sum of squares (K,) of ``y - y_nominal - change`` for the
        clip to ``[lows[j], highs[j]]`` (-inf / inf: no limit) in column j: the numbers
        of ``Fitter.sse`` of each candidate (inf where not finite).

        Parameters
        ----------
        P : Problem
            Measured and nominal outputs, ``fit_start`` and the noise model to whiten
            with (the path itself is the same for every noise model).
        lows, highs : ndarray (K,)
            Lower and upper limit of each column.
        first : int
            No column's clip acts before this sample (:func:`first_crossing`).
        """
        return self._pass(P, lows, highs, first, False)[1]

    def clip_corrections(self, P: Problem, lows: np.ndarray, highs: np.ndarray,
                         first: int = 0) -> np.ndarray:
        """Output changes (stop, n_y, K) caused by the clips; for a few columns only --
        the array is samples x outputs x K.

        Parameters
        ----------
        P : Problem
            The analysis problem (its noise model is not used here).
        lows, highs : ndarray (K,)
            Lower and upper limit of each column (-inf / inf: no limit).
        first : int
            No column's clip acts before this sample (:func:`first_crossing`).
        """
        return self._pass(P, lows, highs, first, True)[0]


# Hand-written and compiled (numba): one pass over time of a sparse K-column state
# update with a clip in the loop, which feeds back through the loop, so the pass cannot
# be vectorised over time; as a NumPy loop it cost ~50 us per sample (3-4 s per location
# for 1e5 samples, 12 locations per two-search analysis).  No library routine simulates
# a Lur'e system over many parameter columns.
# C901: a compiled kernel, one loop nest that numba compiles and inlines as a unit;
# split into functions it would pass arrays across calls per sample.
@numba.njit(cache=True, nogil=True)
def _clip_pass(rows, cols, vals, n_rows, bd, s_nom, lows, highs, first, stop, n_y,  # noqa: C901
               r, ar, inv_var, first_w, keep):  # pragma: no cover - compiled
    k = lows.size
    n_x = n_rows - 1 - n_y
    p1 = ar.shape[1]
    y = np.zeros((stop if keep else 0, n_y, k))
    y_t = np.zeros((n_y, k))
    x = np.zeros((n_x, k))
    x_next = np.zeros((n_x, k))
    s = np.empty(k)
    d = np.empty(k)
    # errors e = r - change of the last p1 samples, e[i, t % p1, j]; zero before sample 0
    e = np.zeros((n_y, p1, k))
    sse = np.zeros(k)
    inject = np.nonzero(bd)[0]  # rows the injection enters (3 of 12 in the boiler loop)
    start = min(max(first, 0), stop)
    # before the first clip every column's error is r: its whitened SS is common
    common = 0.0
    for t in range(first_w, start):
        for i in range(n_y):
            w = 0.0
            for lag in range(min(p1, t + 1)):
                w += ar[i, lag] * r[t - lag, i]
            common += w * w * inv_var[i]
    for t in range(max(start - p1 + 1, 0), start):
        for i in range(n_y):
            for j in range(k):
                e[i, t % p1, j] = r[t, i]
    for t in range(start, stop):
        s[:] = s_nom[t]
        x_next[:, :] = 0.0
        y_t[:, :] = 0.0
        # row 0: the clipped signal; rows 1..n_y: outputs; then the next state
        for n in range(rows.size):
            row, c, v = rows[n], cols[n], vals[n]
            if row == 0:
                for j in range(k):
                    s[j] += v * x[c, j]
            elif row <= n_y:
                for j in range(k):
                    y_t[row - 1, j] += v * x[c, j]
            else:
                for j in range(k):
                    x_next[row - 1 - n_y, j] += v * x[c, j]
        for j in range(k):
            clipped = s[j]
            if clipped < lows[j]:
                clipped = lows[j]
            if clipped > highs[j]:
                clipped = highs[j]
            d[j] = clipped - s[j]
        for row in inject:
            g = bd[row]
            if row < n_y:
                for j in range(k):
                    y_t[row, j] += g * d[j]
            else:
                for j in range(k):
                    x_next[row - n_y, j] += g * d[j]
        for c in range(n_x):
            for j in range(k):
                if abs(x_next[c, j]) < _FLUSH:
                    x_next[c, j] = 0.0
        x, x_next = x_next, x
        slot = t % p1
        for i in range(n_y):
            for j in range(k):
                e[i, slot, j] = r[t, i] - y_t[i, j]
                if keep:
                    y[t, i, j] = y_t[i, j]
        if t >= first_w:
            for i in range(n_y):
                for j in range(k):
                    w = 0.0
                    for lag in range(p1):
                        w += ar[i, lag] * e[i, (t - lag) % p1, j]
                    sse[j] += w * w * inv_var[i]
    for j in range(k):
        sse[j] += common
        if not np.isfinite(sse[j]):
            sse[j] = np.inf
    return y, sse


def saturation_grids(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate low and high limits for the one-sided profiles of a signal `v`.

    Quantiles 0.5 %-50 % (low) and 50 %-99.5 % (high) in steps of 0.5 %, joined with
    values every 1 % of the range: dense where the signal spends its time and in its
    tails.  (A limit outside the range is never met by the nominal signal, and before a
    saturation has acted the plant's signal IS the nominal one, so the limit met first
    lies inside the range.)

    Parameters
    ----------
    v : ndarray
        Nominal signal at the location, samples ``[0, stop)``.
    """
    lo, hi = float(v.min()), float(v.max())
    med = float(np.median(v))
    q = np.arange(0.005, 0.5001, 0.005)
    lows = np.concatenate([np.quantile(v, q), np.linspace(lo, med, 51)[1:]])
    highs = np.concatenate([np.quantile(v, 1.0 - q), np.linspace(med, hi, 51)[:-1]])
    spacing = 1e-6 * max(hi - lo, 1e-300)
    lows = np.unique(np.round(lows / spacing)) * spacing
    highs = np.unique(np.round(highs / spacing)) * spacing
    return lows[(lows > lo) & (lows <= med)], highs[(highs < hi) & (highs >= med)]


def one_sided(grid_lo: np.ndarray, grid_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lows, highs) of the one-sided limit pairs: each low with no high, then each high
    with no low.

    Parameters
    ----------
    grid_lo, grid_hi : ndarray
        Candidate low and high limits (:func:`saturation_grids`).
    """
    return (np.concatenate([grid_lo, np.full(grid_hi.size, -np.inf)]),
            np.concatenate([np.full(grid_lo.size, np.inf), grid_hi]))


def saturation_profile(P: Problem, cache: dict, loc: str, stop: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, StaticMapPath] | None:
    """One-sided limit profiles at `loc`: (lows, highs, whitened fit-part SSE (K,), path).

    Column j has limits ``(lows[j], highs[j])`` with one of them infinite.  Cached per
    location and noise model.  None when the nominal model is not linear.

    Parameters
    ----------
    P : Problem
        Nominal signals and model, measured outputs and noise model.
    cache : dict
        The screening cache (:class:`Screener`'s ``h_cache``), shared across passes.
    loc : str
        Block whose output is saturated.
    stop : int
        End of the fit part (exclusive), a sample index.
    """
    noise = (tuple(tuple(map(float, a)) for a in P.ar), tuple(map(float, P.sigma)))
    key = ("saturation_profile", loc, stop, noise)
    if key not in cache:
        v = P.nominal_signals[loc][:stop]
        lows, highs = one_sided(*saturation_grids(v))
        path = static_path(P, cache, loc, stop)
        if path is None or lows.size == 0:
            cache[key] = None
        else:
            sse = path.clip_sse(P, lows, highs, first=first_crossing(v, lows, highs))
            cache[key] = (lows, highs, sse, path)
    return cache[key]


def static_path(P: Problem, cache: dict, loc: str, stop: int
                ) -> StaticMapPath | None:
    """The cached :class:`StaticMapPath` at the output of `loc` (None: not available).

    Parameters
    ----------
    P : Problem
        Nominal signals and model.
    cache : dict
        The screening cache (:class:`Screener`'s ``h_cache``), shared across passes.
    loc : str
        Block whose output the map acts on.
    stop : int
        End of the fit part (exclusive), a sample index.
    """
    key = ("static_path", loc, stop)
    if key not in cache:
        try:
            cache[key] = StaticMapPath(P, loc, P.nominal_signals[loc], stop)
        except PipelineError:
            cache[key] = None
    return cache[key]


def first_crossing(v: np.ndarray, lows: np.ndarray, highs: np.ndarray) -> int:
    """First sample where the nominal `v` leaves any of the intervals [low, high] (before
    it, no clip acts, so every simulated signal is still the nominal one).

    Parameters
    ----------
    v : ndarray (stop,)
        Nominal signal at the location, samples ``[0, stop)``.
    lows, highs : ndarray (K,)
        Limits of each column; ``v.size`` is returned when there are none.
    """
    if not lows.size:
        return v.size
    out = np.flatnonzero((v < np.max(lows)) | (v > np.min(highs)))
    return int(out[0]) if out.size else v.size
