"""Estimates on a lag Gram: noise models (prediction error), instruments, the level form."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline._threads import thread_map
from pipeline.errors import (
    ConfigError,
    DataQualityError,
    InstrumentError,
    InsufficientDataError,
    SingularSystemError,
)
from pipeline.estimation.normal_equations import (
    NormalEquations,
    as_2d,
    check_finite,
    combined_good,
    good_segments,
    integrating_flags,
    n_p_matrix,
)
from pipeline.estimation.solve import singular, unknown_index
from pipeline.estimation.step_result import (
    PairArrays,
    StepResponseEstimate,
    diagnostics_of,
    fill_output,
    n_k_matrix,
)


NOISE_AUTO = "auto"


def noise_order(noise) -> int | None:
    """``noise`` keyword -> fixed AR order (0 = white) or None (chosen by BIC).

    Parameters
    ----------
    noise : ``"white"``, ``"auto"`` or int
        The estimators' ``noise`` setting; an int must be a non-negative AR order.
    """
    if isinstance(noise, str):
        if noise == "white":
            return 0
        if noise == NOISE_AUTO:
            return None
        raise ConfigError(f"noise={noise!r} is not allowed; use 'white', 'auto' or an AR "
                          "order (a non-negative integer)")
    if isinstance(noise, (bool, np.bool_)) or not float(noise).is_integer() or noise < 0:
        raise ConfigError(f"noise={noise!r} is not allowed; use 'white', 'auto' or an AR "
                          "order (a non-negative integer)")
    return int(noise)


def lags_needed(npm: np.ndarray, iv: bool, order: int | None, leads: int = 0) -> int:
    """Lags a lag Gram must hold: the FIR (and ``leads`` future lags of a feedback test,
    or the ``2 n_p`` instrument lags of an IV fit), plus the noise filter's order (the
    largest BIC may pick when ``order`` is None), plus one.

    Parameters
    ----------
    npm : int array (n_y, n_x)
        Per-pair orders N_p.
    iv : bool
        Whether the fit is instrument-based (``2 max(N_p)`` instrument lags).
    order : int or None
        AR order of the noise model; None for the largest BIC may pick
        (:data:`pipeline.estimation.noise_model.DEFAULT_AR_ORDER_MAX`).
    leads : int
        Future input lags of a feedback test.
    """
    from pipeline.estimation.noise_model import DEFAULT_AR_ORDER_MAX

    p = DEFAULT_AR_ORDER_MAX if order is None else order
    P = int(npm.max())
    return max(P + leads, 2 * P if iv else 0) + p + 1


@dataclass(frozen=True)
class GramContext:
    """A lag Gram of ``[x, y_fit, y_level, S, r]`` with its column layout.

    ``y_fit`` is ``y`` (self-regulating) or ``Δy`` (integrating); ``y_level`` the level of
    each integrating output and ``S`` the inputs cumulated from each segment's start (the
    level form); ``r`` the instruments.
    """

    lg: object  # pipeline.estimation.lag_products.LagGram
    n_x: int
    n_y: int
    n_r: int
    integrating: tuple[bool, ...]
    level_col: dict
    s_lo: int | None
    r_lo: int | None

    @property
    def y_col(self) -> range:
        return range(self.n_x, self.n_x + self.n_y)

    def white_normal_equations(self, P: int) -> NormalEquations:
        """The thesis' (unfiltered) normal equations at ``P`` lags, from the Gram.

        Parameters
        ----------
        P : int
            Number of lags (at most the Gram's ``n_lags``).
        """
        from pipeline.estimation.lag_products import signal_gram

        n_x = self.n_x
        # from the contiguous sub-Grams the fits share (the same numbers as slices of G)
        Gxx = signal_gram(self.lg, 0, (0, n_x), (0, n_x))
        A = Gxx[:P, :, :P, :].reshape(P * n_x, P * n_x)
        C = np.stack([signal_gram(self.lg, 0, (c, c + 1), (0, n_x))[0, 0, :P, :].reshape(-1)
                      for c in self.y_col])
        yy = np.array([signal_gram(self.lg, 0, (c, c + 1), (c, c + 1))[0, 0, 0, 0]
                       for c in self.y_col])
        return NormalEquations(A, C, yy, self.lg.n_d, n_x, P, self.integrating,
                               self.lg.n_segments)


def lag_gram_context(x, y, *, integrating=False, mask=None, instruments=None,
                     n_lags: int, level_form: bool = True) -> GramContext:
    """Build the lag Gram every non-white estimate, the search and the feedback test use.

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs.
    y : array (N, n_y)
        Conditioned outputs (not differenced: integrating outputs are differenced here).
    integrating : bool or sequence of bool (n_y,)
        Non-self-regulating outputs.
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good; samples with a non-finite instrument are bad too.
    instruments : array (N, n_r), optional
        Instrument signals, added as the last columns of the Gram.
    n_lags : int
        Lags the Gram holds (:func:`lags_needed`).
    level_form : bool
        With integrating outputs, also hold their levels and the cumulated inputs, with
        the profiled Grams, so that the level form can be fitted.
    """
    from pipeline.estimation.lag_products import ROW_GROUPS, build_lag_gram

    x = as_2d(x, "x")
    y = as_2d(y, "y")
    if x.shape[0] != y.shape[0]:
        raise DataQualityError(
            f"x has {x.shape[0]} samples but y has {y.shape[0]}; inputs and outputs must "
            "cover the same sample times (resample them onto one grid first)")
    n, n_x = x.shape
    n_y = y.shape[1]
    flags = integrating_flags(integrating, n_y)
    good = combined_good(mask, n, n_x + n_y)
    check_finite(x, good, "x")
    check_finite(y, good, "y")
    r = None
    if instruments is not None:
        r = as_2d(instruments, "instruments")
        if r.shape[0] != n:
            raise DataQualityError(
                f"instruments have {r.shape[0]} samples but x and y have {n}; give the "
                "instruments on the same sample times")
        fin = np.isfinite(r).all(axis=1)
        good = fin if good is None else good & fin
        r = np.where(np.isfinite(r), r, 0.0)
    ints = [i for i, f in enumerate(flags) if f]
    use_level = level_form and bool(ints)
    segs = [(0, n)] if good is None else good_segments(good)

    def segments():
        for s0, s1 in segs:
            xs = x[s0:s1]
            ys = y[s0:s1].copy()
            lev = ys[:, ints].copy()
            if ints:
                ys[1:, ints] = np.diff(ys[:, ints], axis=0)
                ys[0, ints] = 0.0  # never used: observations start one sample later
            parts = [xs, ys]
            if use_level:
                parts += [lev, np.cumsum(xs, axis=0)]
            if r is not None:
                parts.append(r[s0:s1])
            yield np.concatenate(parts, axis=1)

    lg = build_lag_gram(segments(), n_lags=n_lags, k0_extra=1 if ints else 0,
                        centred=use_level)
    if lg is not None:  # the outputs' sub-Grams are asked for one output at a time
        lg.cache[ROW_GROUPS] = (((n_x, n_x + n_y), (0, n_x)),)
    if lg is None:
        longest = max((b - a for a, b in segs), default=0)
        raise InsufficientDataError(
            f"no usable observation: {n_lags} lags (n_p, noise-model order and delays) need "
            f"contiguous good segments of at least {n_lags + (1 if ints else 0)} samples, "
            f"the longest has {longest} (of {n} samples); lower n_p or supply more data")
    col = n_x + n_y
    level_col = {}
    s_lo = None
    if use_level:
        level_col = {i: col + k for k, i in enumerate(ints)}
        col += len(ints)
        s_lo = col
        col += n_x
    r_lo = col if r is not None else None
    return GramContext(lg, n_x, n_y, 0 if r is None else r.shape[1], flags, level_col,
                       s_lo, r_lo)


def output_design(ctx: GramContext, i: int, n_p_row: np.ndarray, n_k_row: np.ndarray,
                  form: str, *, leads: int = 0):
    """Regression of output ``i`` in a form, optionally with ``leads`` future input lags.

    With ``leads = M`` the output enters at lag ``M`` and the inputs at lags ``0..M-1``
    are its future (the non-causal part of a feedback test); causal lags shift by ``M``.
    Returns ``(design, inp_of, lag_of, is_lead)``; ``lag_of`` is the causal lag.

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`lag_gram_context`).
    i : int
        Output index.
    n_p_row : int array (n_x,)
        The output's N_p per input.
    n_k_row : int array (n_x,)
        The output's known delay per input, in samples (lags fixed at zero).
    form : str
        ``"direct"``, ``"differenced"`` or ``"level"`` (the last needs a context built
        with ``level_form``).
    leads : int
        Future input lags ``M`` added to the regression (0: a causal fit).
    """
    from pipeline.estimation.lag_products import Block
    from pipeline.estimation.output_fit import Design

    n_x = ctx.n_x
    P = int(n_p_row.max())
    M = int(leads)
    lead_idx = np.arange(M * n_x)
    if form == "level":
        lo = int(n_p_row.min()) - 1
        blocks = []
        xs = np.array([], dtype=int)
        if P - 1 + M > 0:
            blocks.append(Block(0, n_x, 0, P - 1 + M))
            xs = unknown_index(n_p_row - 1 + M, n_x, n_k_row + M, n_lags=P - 1 + M)
        off = P - 1 + M
        off_u = off * n_x if P - 1 + M > 0 else 0
        blocks.append(Block(ctx.s_lo, ctx.s_lo + n_x, lo + M, P + M))
        ss = np.array([off_u + (int(n_p_row[j]) - 1 - lo) * n_x + j for j in range(n_x)])
        sel = np.concatenate([lead_idx, xs, ss]) if M else np.concatenate([xs, ss])
        inp = np.concatenate([lead_idx % n_x, xs % n_x, np.arange(n_x)]) if M else \
            np.concatenate([xs % n_x, np.arange(n_x)])
        lag = np.concatenate([lead_idx // n_x - M, xs // n_x - M, n_p_row - 1]) if M else \
            np.concatenate([xs // n_x, n_p_row - 1])
        yb = Block(ctx.level_col[i], ctx.level_col[i] + 1, M, M + 1)
        design = Design(yb, tuple(blocks), sel.astype(int), nuisance=3)
    else:
        c = ctx.n_x + i
        idx = unknown_index(n_p_row + M, n_x, n_k_row + M, n_lags=P + M)
        sel = np.concatenate([lead_idx, idx]) if M else idx
        # differenced form under a noise model: a constant and a trend per segment (the
        # level's drift and what detrending leaves; the thesis' eq. 3.15 has none, so the
        # white path keeps none)
        nuis = 2 if (form == "differenced" and ctx.s_lo is not None) else 0
        design = Design(Block(c, c + 1, M, M + 1), (Block(0, n_x, 0, P + M),), sel,
                        nuisance=nuis)
        inp = sel % n_x
        lag = sel // n_x - M
    return design, inp.astype(int), lag.astype(int), lag < 0


def _forms_for(ctx: GramContext, i: int, instruments: bool) -> list[str]:
    if not ctx.integrating[i]:
        return ["direct"]
    if instruments or ctx.s_lo is None:
        return ["differenced"]
    return ["differenced", "level"]


def fit_output(ctx: GramContext, i: int, n_p_row, n_k_row, *, noise=NOISE_AUTO,
               form: str | None = None, d_fixed: np.ndarray | None = None,
               sigma2_fixed: float | None = None, instruments: bool = False):
    """Fit output ``i`` (every candidate form; the lowest BIC wins).

    Returns ``(fit, design, inp_of, lag_of, form, selection)``.  (The instruments'
    strength is checked once per estimate by :func:`check_instruments`.)

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`lag_gram_context`).
    i : int
        Output index.
    n_p_row : int array (n_x,)
        The output's N_p per input.
    n_k_row : int array (n_x,)
        The output's known delay per input, in samples.
    noise : ``"white"``, ``"auto"`` or int
        Noise model: white, AR order chosen by BIC, or a fixed AR order.
    form : str, optional
        Fit only this form; default every candidate (``"direct"`` for a self-regulating
        output; ``"differenced"``, and ``"level"`` when the context holds it and no
        instruments are used, for an integrating one).
    d_fixed : ndarray (p + 1,), optional
        Noise filter ``[1, d_1..d_p]`` to use as known (generalised least squares, no
        noise-model fit).
    sigma2_fixed : float, optional
        Innovation variance reported with ``d_fixed``; default the fit's own.
    instruments : bool
        Fit by instrumental variables on instrument lags ``0..2 max(n_p_row) - 1``
        (ignored when ``d_fixed`` is given).
    """
    from pipeline.estimation.lag_products import Block
    from pipeline.estimation.prediction_error import (
        fit_fixed_noise,
        fit_instrumental,
        fit_prediction_error,
    )

    order = noise_order(noise)
    what = f"output {i}"
    best = None
    by_form = {}
    forms = [form] if form is not None else _forms_for(ctx, i, instruments)
    for fm in forms:
        design, inp, lag, _ = output_design(ctx, i, np.asarray(n_p_row), np.asarray(n_k_row), fm)
        try:
            if d_fixed is not None:
                fit = fit_fixed_noise(ctx.lg, design, d_fixed, what=what, sigma2=sigma2_fixed)
            elif instruments:
                rb = Block(ctx.r_lo, ctx.r_lo + ctx.n_r, 0, 2 * int(np.max(n_p_row)))
                fit = fit_instrumental(ctx.lg, design, rb, what=what, order=order)
            else:
                fit = fit_prediction_error(ctx.lg, design, what=what, order=order)
        except SingularSystemError as exc:
            P = int(np.max(n_p_row))
            detail = str(exc).removeprefix(f"normal equations of {what} are singular")
            raise singular(what, ctx.white_normal_equations(P).A, ctx.n_x,
                            detail.split(":")[0] if detail.startswith(" (") else "") from None
        by_form[fm] = fit.bic
        if best is None or fit.bic < best[0].bic:
            best = (fit, design, inp, lag, fm)
    selection = {"form_bic": by_form} if len(forms) > 1 else {}
    return (*best, selection)


def estimate_from_context(ctx: GramContext, *, n_p, n_k, dt: float, noise=NOISE_AUTO,
                          forms: Sequence[str] | None = None,
                          d_fixed: Sequence[np.ndarray] | None = None,
                          sigma2_fixed: Sequence[float] | None = None,
                          use_instruments: bool | None = None) -> StepResponseEstimate:
    """Noise-model or instrument-based estimate of every pair from a :class:`GramContext`.

    ``forms``/``d_fixed``/``sigma2_fixed`` (per output) fix the output form, noise filter
    and innovation variance (the search judges candidate orders with the noise model
    found at ``n_p_max``).

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`lag_gram_context`).
    n_p : int or int array (n_y, n_x)
        Per-pair orders; ``ctx`` must hold the lags they need (:func:`lags_needed`).
    n_k : int or int array (n_y, n_x)
        Known delay in samples: ``delta_h[:n_k]`` fixed at zero.
    dt : float
        Sample period (s).
    noise : ``"white"``, ``"auto"`` or int
        Noise model of every output (as in :func:`estimate_step_responses`).
    forms : sequence of str, optional
        Per output, the form to fit; default the lowest-BIC candidate.
    d_fixed : sequence of ndarray, optional
        Per output, a noise filter ``[1, d_1..d_p]`` taken as known.
    sigma2_fixed : sequence of float, optional
        Per output, the innovation variance reported with ``d_fixed``.
    use_instruments : bool, optional
        Instrument-based fit; default whenever ``ctx`` holds instruments.
    """
    from pipeline.estimation.noise_model import NoiseModel

    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt must be a positive number of seconds; got {dt!r}")
    n_x, n_y = ctx.n_x, ctx.n_y
    npm = n_p_matrix(n_p, n_y, n_x)
    nkm = n_k_matrix(n_k, npm)
    iv = ctx.r_lo is not None if use_instruments is None else use_instruments
    P = int(npm.max())
    arr = PairArrays(n_y, n_x, P)
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    models = []
    first_stage = check_instruments(ctx, P) if iv else {}
    method = "instrumental_variables" if iv else "prediction_error"

    def one(i: int):
        fit, design, inp, lag, form, sel = fit_output(
            ctx, i, npm[i], nkm[i], noise=noise,
            form=None if forms is None else forms[i],
            d_fixed=None if d_fixed is None else d_fixed[i],
            sigma2_fixed=None if sigma2_fixed is None else sigma2_fixed[i], instruments=iv)
        # the output's rows of the result arrays (no other output writes there)
        fill_output(arr, i, fit.b, fit.cov_factor, fit.sigma2, inp, lag, npm[i], form, dt)
        return fit, design, form, sel

    for i, (fit, design, form, sel) in enumerate(_by_output(one, n_y)):
        sigma2[i] = fit.sigma2
        rms[i] = np.sqrt(fit.V / fit.n_d)
        models.append(NoiseModel("white" if fit.order == 0 else "ar", form, fit.order,
                                 tuple(float(v) for v in fit.d[1:]), float(np.sqrt(fit.sigma2)),
                                 {**fit.selection, **sel, "iterations": fit.iterations},
                                 design.nuisance))
    ne = ctx.white_normal_equations(P)
    return StepResponseEstimate(
        delta_h=arr.delta_h, step=arr.step, step_std=arr.step_std, delta_h_std=arr.dh_std,
        delta_g=arr.delta_g, rate=arr.rate, rate_std=arr.rate_std, n_p=npm,
        n_d=ctx.lg.n_d, dt=float(dt), residual_rms=rms, sigma2=sigma2,
        integrating=ctx.integrating, method=method,
        diagnostics=diagnostics_of(ne, _shared_white_factor(ctx, P)),
        extra={"first_stage": first_stage} if first_stage else {},
        noise_model=tuple(models), n_k=nkm, step_cov=arr.step_cov)


def _by_output(fn, n_y: int) -> list:
    """``[fn(i) for i in range(n_y)]``: output 0 first (it puts what every output shares
    -- the white factor, the inputs' inverse factor -- in the Gram's cache), the others
    side by side (:func:`pipeline._threads.thread_map`)."""
    if n_y == 0:
        return []
    first = fn(0)
    return [first, *thread_map(fn, range(1, n_y))]


def _shared_white_factor(ctx: GramContext, P: int):
    """The scaled Cholesky factor of the white normal equations at ``P`` lags (every
    unknown) when a fit on ``ctx`` has already computed it (:class:`pipeline.
    prediction_error._Problem` shares it on the Gram) — the factor
    :func:`pipeline.estimation.step_result.diagnostics_of` would compute again — else None."""
    from pipeline.estimation.lag_products import Block

    key = ("white", 0, (Block(0, ctx.n_x, 0, P),), np.arange(P * ctx.n_x).tobytes(),
           "factor")
    fac = ctx.lg.cache.get(key)
    return None if fac is None else (fac[0][0], True)


def check_instruments(ctx: GramContext, P: int) -> dict:
    """Every instrument moves, and together they move every input (first stage).

    Returns ``{input index: {"F", "r2", "n_instruments"}}``: the F statistic of each input
    regressed on the instruments' lags ``0..2P-1`` (the instrument set of the estimate).

    Parameters
    ----------
    ctx : GramContext
        Lag Gram built with instruments.
    P : int
        Largest N_p of the estimate (instrument lags ``0..2P-1``, capped at the Gram's).

    Raises
    ------
    InstrumentError
        An instrument is constant over the used observations, or an input's
        first-stage F is below :data:`pipeline.estimation.prediction_error.WEAK_INSTRUMENT_F`.
    """
    from pipeline.estimation.lag_products import Block
    from pipeline.estimation.prediction_error import WEAK_INSTRUMENT_F, first_stage_strength

    G = ctx.lg.gram(0)
    for k in range(ctx.n_r):
        c = ctx.r_lo + k
        v0 = G[0, c, 0, c]
        v1 = G[0, c, 1, c] if G.shape[0] > 1 else 0.0
        if v0 <= 0 or v1 > (1 - 1e-9) * v0:
            raise InstrumentError(
                f"instrument {k} does not move over the used observations (constant or "
                "zero); an instrument must vary to explain the inputs — choose a signal "
                "that moves (a setpoint with steps) or drop it from the instruments",
                instrument=k)
    zb = Block(ctx.r_lo, ctx.r_lo + ctx.n_r, 0, min(2 * P, ctx.lg.n_lags))
    first = first_stage_strength(G, [Block(0, ctx.n_x, 0, 1)], zb, ctx.lg.n_d,
                                 "the instruments")
    for s, v in first.items():
        if v["F"] < WEAK_INSTRUMENT_F:
            raise InstrumentError(
                f"instruments are weak for input {s}: first-stage F = {v['F']:.3g} "
                f"(R^2 = {v['r2']:.3g} with {v['n_instruments']} instrument lags) is "
                f"below {WEAK_INSTRUMENT_F:g}; the instruments barely move that input, "
                "so an instrument-based estimate would be biased and its uncertainty "
                "unreliable — use an instrument that moves the input (a setpoint "
                "with steps, a measured disturbance), or drop the instruments",
                input=s, numbers=v)
    return {int(s): v for s, v in first.items()}


def nested_fixed_noise(ctx: GramContext, *, P: int, n_k: np.ndarray, dt: float, forms,
                       d_fixed, sigma2_fixed):
    """Generalised least squares at every order ``m <= P`` from one factor per output.

    With the noise filter and the form of each output fixed (the search's stage 1),
    unknowns ordered lag-major and known delays below every order tried, the filtered
    normal equations of order ``m`` are the leading block of those of order ``P``, whose
    Cholesky factor and inverse factor hold those of every ``m`` as leading blocks —
    one factorisation per output instead of one per output and order.

    Returns ``est_at(m, cov_lags=None)`` -> :class:`StepResponseEstimate`, the same
    estimate as :func:`estimate_from_context` with ``n_p=m`` and the given filters, or
    None when an output cannot be nested (level form, a failed factorisation: the caller
    then uses :func:`estimate_from_context`, which raises what it must).

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record.
    P : int
        Largest order.
    n_k : int array (n_y, n_x)
        Known delays (samples), below every order asked for.
    dt : float
        Sample period (s).
    forms : sequence of str
        Per output, its form.
    d_fixed : sequence of ndarray
        Per output, the noise filter ``[1, d_1..d_p]``.
    sigma2_fixed : sequence of float
        Per output, the innovation variance reported.
    """
    import scipy.linalg

    from pipeline.estimation.noise_model import NoiseModel
    from pipeline.estimation.prediction_error import NestedGLS

    n_x, n_y = ctx.n_x, ctx.n_y
    if "level" in forms:
        return None

    def part(i: int):
        design, _, _, _ = output_design(ctx, i, np.full(n_x, P), n_k[i], forms[i])
        return design, NestedGLS(ctx.lg, design, d_fixed[i], what=f"output {i}")

    try:
        parts = _by_output(part, n_y)
        ne_P = ctx.white_normal_equations(P)
        sc = np.sqrt(np.clip(np.diag(ne_P.A), 1e-300, None))
        As = ne_P.A / np.outer(sc, sc)
        shared = _shared_white_factor(ctx, P)  # the fit at n_p_max factored it already
        white = shared[0] if shared is not None else \
            scipy.linalg.cho_factor(As, lower=True, check_finite=False)[0]
    except (SingularSystemError, np.linalg.LinAlgError, InsufficientDataError):
        return None
    diagnostics_at = _diagnostics_by_order(ne_P, As, white)
    # outputs whose candidate orders take their covariance from the nested moments
    nested_direct = [forms[i] == "direct" and design.sel.size == P * n_x
                     for i, (design, _) in enumerate(parts)]

    moments: dict = {}

    def est_at(m: int, cov_lags=None):
        if np.any(n_k >= m):
            return None
        npm = np.full((n_y, n_x), m)
        arr = PairArrays(n_y, n_x, m)
        sigma2, rms, models = np.zeros(n_y), np.zeros(n_y), []
        if cov_lags is not None:  # each output's moments once, the outputs side by side
            todo = [i for i in range(n_y) if nested_direct[i] and i not in moments]
            done = thread_map(lambda i: _nested_moments(parts[i][1].F, P, n_x, cov_lags),
                              todo)
            moments.update(zip(todo, done, strict=True))
        for i, (design, nested) in enumerate(parts):
            k = int(np.searchsorted(design.sel, m * n_x))
            fit = nested.fit(k, sigma2_fixed[i])  # a product: not worth a thread
            if fit is None:
                return None
            sigma2[i] = fit.sigma2
            rms[i] = np.sqrt(fit.V / fit.n_d)
            sel = design.sel[:k]
            if cov_lags is not None and nested_direct[i]:
                _fill_nested(arr, i, fit.b, fit.sigma2, m, moments[i], cov_lags)
            else:
                fill_output(arr, i, fit.b, fit.cov_factor, fit.sigma2, sel % n_x, sel // n_x,
                            npm[i], forms[i], dt, cov_lags)
            models.append(NoiseModel("white" if fit.order == 0 else "ar", forms[i], fit.order,
                                     tuple(float(v) for v in fit.d[1:]),
                                     float(np.sqrt(fit.sigma2)), {"iterations": 0},
                                     design.nuisance))
        return StepResponseEstimate(
            delta_h=arr.delta_h, step=arr.step, step_std=arr.step_std, delta_h_std=arr.dh_std,
            delta_g=arr.delta_g, rate=arr.rate, rate_std=arr.rate_std, n_p=npm,
            n_d=ctx.lg.n_d, dt=float(dt), residual_rms=rms, sigma2=sigma2,
            integrating=ctx.integrating, method="prediction_error",
            diagnostics=diagnostics_at(m * n_x),
            noise_model=tuple(models), n_k=n_k.copy(), step_cov=arr.step_cov)

    return est_at


def _diagnostics_by_order(ne_P: NormalEquations, As: np.ndarray, white: np.ndarray):
    """``diagnostics_of`` the white normal equations of every order from those at the
    largest: everything but the condition number reads the first lag block only (the
    same at every order), and the condition number of order ``m`` is LAPACK's estimate
    from the leading ``k = m n_x`` block of the scaled matrix ``As`` and of its Cholesky
    factor ``white`` — no copy of the order's normal equations per order.

    Returns ``diagnostics_at(k)`` -> :class:`pipeline.estimation.step_result.Diagnostics`.
    """
    import dataclasses

    import scipy.linalg

    base = diagnostics_of(ne_P, (white, True))
    K, n_x = As.shape[0], ne_P.n_x
    # column sums of |As| over the first m n_x rows, every m: one running sum over the
    # rows (the same sums, row by row, as each order's own column sums)
    abs_As = np.abs(As)
    acc = np.zeros(K)
    col_sums = {}
    for row in range(K):
        acc += abs_As[row]
        if (row + 1) % n_x == 0:
            col_sums[row + 1] = acc.copy()

    def diagnostics_at(k: int):
        norm = col_sums[k][:k].max() if k in col_sums else abs_As[:k, :k].sum(axis=0).max()
        rcond, _ = scipy.linalg.lapack.dpocon(white[:k, :k], norm, uplo="L")
        cond = float(1.0 / rcond) if rcond > 0 else float("inf")
        return dataclasses.replace(base, condition_number=cond)

    return diagnostics_at


def _nested_moments(F: np.ndarray, P: int, n_x: int, cov_lags):
    """Every order's step-response variances and tail covariances from the inverse factor
    at ``P`` (direct form, every unknown): the order-``m`` factor is ``F[:m n_x, :m n_x]``,
    so its cumulative sums over lags are the first ``m n_x`` rows of those of ``F``, and
    variances are sums of their squares over those rows — prefix sums over row blocks.

    Returns ``(dh_var, step_var, tail)``: ``dh_var[m-1, l, j]`` and ``step_var`` (unit
    innovation variance) at order ``m``, and ``tail[m-1] = (lags, C)`` with ``C`` (n_x,
    |lags|, |lags|) the step covariance at ``cov_lags(m)``.
    """
    K = P * n_x
    # FT[l, j, k] = F[k, l n_x + j]: F's transpose, a view of the Fortran-ordered factor
    # (a copy otherwise), so that the sums over lags and rows run along contiguous memory
    FT = np.ascontiguousarray(F.T).reshape(P, n_x, K)
    CS = FT.copy()
    for lag in range(1, P):  # np.cumsum(FT, axis=0) (the same sums), 5x faster
        CS[lag] += CS[lag - 1]
    dh_var = np.cumsum((FT ** 2).reshape(P, n_x, P, n_x).sum(axis=3), axis=2)
    step_var = np.cumsum((CS ** 2).reshape(P, n_x, P, n_x).sum(axis=3), axis=2)
    tail = []
    for m in range(1, P + 1):
        lags = np.asarray(cov_lags(m), dtype=int)
        sub = np.ascontiguousarray(CS[lags, :, : m * n_x].transpose(1, 0, 2))  # (n_x, |lags|, k)
        tail.append((lags, sub @ sub.transpose(0, 2, 1)))
    return dh_var.transpose(2, 0, 1), step_var.transpose(2, 0, 1), tail


def _fill_nested(arr: PairArrays, i: int, b: np.ndarray, sigma2: float, m: int, moments,
                 cov_lags) -> None:
    """:func:`pipeline.estimation.step_result.fill_output` of a direct-form candidate order from
    :func:`_nested_moments`: increments, step and their standard deviations at every lag,
    the step covariance at ``cov_lags(m)`` only."""
    dh_var, step_var, tail = moments
    n_x = arr.n_x
    theta = b.reshape(m, n_x).T  # (n_x, m)
    arr.delta_h[i, :, :m] = theta
    arr.step[i, :, :m] = np.cumsum(theta, axis=1)
    arr.dh_std[i, :, :m] = np.sqrt(sigma2 * dh_var[m - 1, :m, :]).T
    arr.step_std[i, :, :m] = np.sqrt(sigma2 * step_var[m - 1, :m, :]).T
    lags, C = tail[m - 1]
    arr.step_cov[i][:, lags[:, None], lags[None, :]] = sigma2 * C  # every input at once
