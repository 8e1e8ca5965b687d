"""Lag products of a set of signals: the one pass over the data every estimator shares.

For signals ``w`` (columns: inputs, outputs, and for some estimators cumulated inputs and
instruments) and ``L`` lags, the *lag Gram* is

    G = sum_k Z(k) Z(k)',   Z(k) = [w(k); w(k-1); ...; w(k-L+1)]   (lag-major)

summed over the observations ``k`` of every contiguous good segment (from its
``L - 1 (+1)``-th sample on).  The thesis' normal equations (method.md §2) are a corner
of ``G``; so are the normal equations of the same problem with inputs and output filtered
by any FIR ``D(q)`` of order ``p <= L - 1 - max lag`` (method.md §10):

    sum_k (D a)(k) (D b)(k) = sum_{i,j} d_i d_j G[a shifted by i, b shifted by j],

and so are residual autocovariances, the non-causal terms of a feedback test (an output
at lag ``M`` regressed on inputs at lags ``0..M-1``) and the cross products of an
instrumental-variable estimate.  So ``G`` is formed once (block FFT for its first block
row, the diagonal recursion for the rest: :func:`pipeline.estimation.estimate._lag_products`,
:func:`pipeline.estimation.estimate._assemble_A`) and everything else is arithmetic on it.

Integrating outputs under a noise model carry polynomial nuisance terms per segment:
a constant and a trend in the differenced form, a constant, a trend and a quadratic in
the level form (what linear detrending of inputs and level leaves: the cumulated
detrended input has a quadratic part).  They use the *profiled* Grams
``G_d = sum_seg (G_seg - M' (B'B)^-1 M)`` with ``M = sum_k b(k) Z(k)'`` for the first
``d`` terms ``b`` of ``1, t, t^2``: polynomials of degree < d are mapped onto themselves by
any filter ``D(q)``, and filtering is linear, so the profiled Gram of filtered signals is
``t' G_d t`` — the nuisances are profiled out exactly.

Regressors are addressed as :class:`Block`\\ s — a contiguous range of signals over a
contiguous range of lags — whose unknowns are ordered lag-major inside the block.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import math

import numpy as np
import scipy.fft

__all__ = ["Block", "LagGram", "build_lag_gram", "filtered_gram", "shifted_products", "take",
           "first_block_row", "assemble_gram", "assemble_lag_gram", "assemble_block",
           "assemble_parts", "signal_gram", "ROW_GROUPS"]


@dataclass(frozen=True)
class Block:
    """Signals ``sig_lo..sig_hi-1`` at lags ``lag_lo..lag_hi-1`` (unknowns lag-major)."""

    sig_lo: int
    sig_hi: int
    lag_lo: int
    lag_hi: int

    @property
    def n_sig(self) -> int:
        return self.sig_hi - self.sig_lo

    @property
    def n_lag(self) -> int:
        return self.lag_hi - self.lag_lo

    @property
    def size(self) -> int:
        return self.n_sig * self.n_lag

    def shifted(self, s: int) -> "Block":
        """The same signals with the lag range moved by ``s``.

        Parameters
        ----------
        s : int
            Lags added to ``lag_lo`` and ``lag_hi`` (negative moves to earlier lags).
        """
        return Block(self.sig_lo, self.sig_hi, self.lag_lo + s, self.lag_hi + s)


@dataclass(frozen=True)
class LagGram:
    """Lag products of ``n_w`` signals over ``n_lags`` lags (see the module docstring).

    Attributes
    ----------
    G : ndarray (n_lags, n_w, n_lags, n_w)
        ``G[l1, s1, l2, s2] = sum_k w_s1(k - l1) w_s2(k - l2)``.  Built from ``seeds`` on
        first use when the Gram was built lazily: a fit that reads only contiguous
        sub-Grams (:func:`signal_gram`) never needs the whole of it.
    profiled : tuple of ndarray
        The same with the first 1, 2, 3 terms of ``1, t, t^2`` per segment profiled out
        (empty when not built).
    n_d : int
        Observations summed.
    n_segments : int
    seeds : tuple
        Per segment, its first block row and head and tail samples
        (:func:`assemble_block`); empty when ``G`` was given.
    """

    _G: np.ndarray | None
    n_d: int
    n_segments: int
    profiled: tuple = ()
    cache: dict = field(default_factory=dict, compare=False, repr=False)
    """Arithmetic shared by every fit on this Gram (contiguous sub-Grams, the white
    factor); :func:`signal_gram` fills it."""
    seeds: tuple = field(default=(), compare=False, repr=False)

    @property
    def G(self) -> np.ndarray:
        if self._G is None:  # the whole Gram, as the eager build sums it
            G = None
            for seed in self.seeds:
                Gs = assemble_block(*seed, (0, self.n_w), (0, self.n_w))
                G = Gs if G is None else G + Gs
            object.__setattr__(self, "_G", G)
        return self._G

    @property
    def n_lags(self) -> int:
        return self._G.shape[0] if self._G is not None else self.seeds[0][0].shape[0]

    @property
    def n_w(self) -> int:
        return self._G.shape[1] if self._G is not None else self.seeds[0][0].shape[1]

    def __add__(self, other: "LagGram") -> "LagGram":
        prof = tuple(a + b for a, b in zip(self.profiled, other.profiled)) \
            if self.profiled and other.profiled else ()
        return LagGram(self.G + other.G, self.n_d + other.n_d,
                       self.n_segments + other.n_segments, prof)

    def gram(self, nuisance: int = 0) -> np.ndarray:
        """``G`` (``nuisance=0``), or with the first ``nuisance`` terms of ``1, t, t^2``
        per segment profiled out.

        Parameters
        ----------
        nuisance : int
            Number of terms of ``1, t, t^2`` profiled out per segment, 0..3; above 0
            needs the profiled Grams (``build_lag_gram(..., centred=True)``).
        """
        if nuisance == 0:
            return self.G
        if nuisance > len(self.profiled):
            raise ValueError("the profiled lag Gram was not built (pass centred=True)")
        return self.profiled[nuisance - 1]


ROW_GROUPS = "row_groups"
"""Key of ``LagGram.cache`` holding ``(group, cols)`` pairs of signal ranges ``(lo, hi)``:
the signals of ``group`` (the outputs) are asked for one at a time, against ``cols`` (the
inputs) and against themselves, and ``cols`` against themselves — a lazily built Gram
assembles those three parts together, once (:func:`signal_gram`)."""


def signal_gram(lg: LagGram, nuisance: int, s1: tuple[int, int],
                s2: tuple[int, int]) -> np.ndarray:
    """Contiguous copy ``G[:, s1, :, s2]`` of a lag Gram, cached on ``lg``.

    Every fit on the Gram slices the same signal ranges (the inputs against themselves
    for every output, one output against the inputs); strided 4-D slices of the full
    Gram cost a copy per use, a contiguous copy costs it once.  On a lazily built Gram
    whose whole ``G`` is not formed yet, the sub-Gram is assembled from the seeds
    (the same numbers): one output against the inputs, or against itself, for every
    output of its :data:`ROW_GROUPS` range at once.

    Parameters
    ----------
    lg : LagGram
        The lag Gram.
    nuisance : int
        Which Gram (:meth:`LagGram.gram`).
    s1, s2 : tuple of int
        Signal ranges ``(lo, hi)`` of rows and columns.

    Returns
    -------
    ndarray (n_lags, s1 width, n_lags, s2 width)
    """
    key = ("signal_gram", nuisance, tuple(s1), tuple(s2))
    if key not in lg.cache:
        if nuisance == 0 and lg._G is None:
            lg.cache[key] = _lazy_signal_gram(lg, tuple(s1), tuple(s2))
        else:
            G = lg.gram(nuisance)
            lg.cache[key] = np.ascontiguousarray(G[:, s1[0]:s1[1], :, s2[0]:s2[1]])
    return lg.cache[key]


def _lazy_signal_gram(lg: LagGram, s1: tuple, s2: tuple) -> np.ndarray:
    """:func:`signal_gram` from the seeds (see there)."""
    for group, cols in lg.cache.get(ROW_GROUPS, ()):
        one = s1[1] - s1[0] == 1 and group[0] <= s1[0] < group[1]
        if not (s1 == s2 == cols or (one and (s2 == cols or s1 == s2))):
            continue
        pkey = ("group_parts", group, cols)
        if pkey not in lg.cache:
            parts = None
            for seed in lg.seeds:  # summed over segments in the eager build's order
                ps = assemble_parts(*seed, group, cols)
                parts = ps if parts is None else tuple(a + b for a, b in zip(parts, ps))
            lg.cache[pkey] = parts
        G_cc, G_gc, G_gg = lg.cache[pkey]
        if s1 == s2 == cols:
            return G_cc
        i = s1[0] - group[0]
        if s1 == s2:
            return np.ascontiguousarray(G_gg[:, i, :]).reshape(lg.n_lags, 1, -1, 1)
        return np.ascontiguousarray(G_gc[:, i : i + 1])
    G = None
    for seed in lg.seeds:
        Gs = assemble_block(*seed, s1, s2)
        G = Gs if G is None else G + Gs
    return G


def filtered_gram(G: np.ndarray, d: np.ndarray, b1: Block, b2: Block) -> np.ndarray:
    """``sum_k (D z1)(k) (D z2)(k)'`` for the unknowns of blocks ``b1``, ``b2``.

    ``d = [1, d_1, ..., d_p]`` is the filter ``D(q)``; ``G`` a 4-D lag Gram.  Separable:
    first filter along the lags of ``b1`` (``p + 1`` strided slices), then along ``b2``.
    Cost ``2 (p + 1) |b1| |b2|`` — no data pass, no gather of ``G``.

    Parameters
    ----------
    G : ndarray (n_lags, n_w, n_lags, n_w)
        Lag Gram (:attr:`LagGram.G` or a profiled one); both blocks' lags plus ``p`` must
        lie within ``n_lags``.
    d : ndarray (p + 1,)
        Filter coefficients ``[1, d_1, ..., d_p]``.
    b1, b2 : Block
        Row and column regressors.

    Returns
    -------
    ndarray (b1.size, b2.size)
    """
    p = d.size - 1
    s1 = slice(b1.sig_lo, b1.sig_hi)
    s2 = slice(b2.sig_lo, b2.sig_hi)
    cols = slice(b2.lag_lo, b2.lag_hi + p)
    out = np.empty((b1.n_lag, b1.n_sig, b2.n_lag, b2.n_sig))
    # one row lag at a time: the same products and sums as filtering the whole block
    # along b1's lags and then along b2's, while that lag's slab is in cache (2.5x faster
    # on the Gram of 20 inputs at 60 lags than whole-block passes)
    for lag in range(b1.n_lag):
        q = b1.lag_lo + lag
        h = d[0] * G[q, s1, cols, s2]
        for a in range(1, p + 1):
            h += d[a] * G[q + a, s1, cols, s2]
        o = out[lag]
        np.multiply(d[0], h[:, : b2.n_lag, :], out=o)
        for a in range(1, p + 1):
            o += d[a] * h[:, a : a + b2.n_lag, :]
    return out.reshape(b1.size, b2.size)


def shifted_products(G: np.ndarray, blocks: list[Block], coef: list[np.ndarray],
                     shifts: int) -> np.ndarray:
    """``q[a] = sum_k Z(k) e(k - a)`` for ``a = 0..shifts-1``, ``e(k) = sum_b coef_b' z_b(k)``.

    Returns ndarray (shifts, n_lags, n_w): the products of the residual-like combination
    ``e`` (a fixed linear combination of block unknowns, e.g. ``y - U'b``) at shift ``a``
    with every signal at every lag — from which residual autocovariances and the
    Jacobian products of a prediction-error fit follow by indexing.

    Parameters
    ----------
    G : ndarray (n_lags, n_w, n_lags, n_w)
        Lag Gram.
    blocks : list of Block
        Blocks whose unknowns make up ``e``; their lags plus ``shifts - 1`` must lie
        within ``n_lags``.
    coef : list of ndarray
        Per block, its coefficients (``blk.size`` values, lag-major).
    shifts : int
        Number of shifts ``a`` of ``e``.
    """
    L, n_w = G.shape[0], G.shape[1]
    q = np.zeros((shifts, L, n_w))
    for a in range(shifts):
        for blk, c in zip(blocks, coef):
            sub = G[:, :, blk.lag_lo + a : blk.lag_hi + a, blk.sig_lo : blk.sig_hi]
            q[a] += np.tensordot(sub, c.reshape(blk.n_lag, blk.n_sig), axes=([2, 3], [0, 1]))
    return q


def take(q: np.ndarray, blk: Block, shift: int = 0) -> np.ndarray:
    """Entries of a ``(n_lags, n_w)`` product vector at a block's unknowns (lag-major).

    Parameters
    ----------
    q : ndarray (n_lags, n_w)
        Products with every signal at every lag (one shift of :func:`shifted_products`).
    blk : Block
        Unknowns to pick.
    shift : int
        Lags added to the block's lag range.
    """
    return q[blk.lag_lo + shift : blk.lag_hi + shift, blk.sig_lo : blk.sig_hi].reshape(-1)


# ------------------------------------------------- the data pass (block FFT + recursion)
def first_block_row(w: np.ndarray, x: np.ndarray, k0: int, n_lags: int) -> np.ndarray:
    """``r[p, n, j] = sum_{k=k0}^{N-1} w[k, n] * x[k-p, j]`` for ``p < n_lags``.

    Block FFT (overlap-save): each block of ``B`` observations is correlated against
    the ``B + n_lags - 1`` input samples it needs, the cross-spectra are summed over
    blocks and a single inverse FFT per pair returns every lag.  Hand-written because
    scipy.signal.correlate has no "sum over observation range with lag window" form and
    would need one full-length FFT per pair.

    Parameters
    ----------
    w : ndarray (N, n_w)
        Signals at the current sample ``k``.
    x : ndarray (N, n_x)
        Signals at the lagged sample ``k - p`` (the same samples as ``w``).
    k0 : int
        Index of the first observation; at least ``n_lags - 1``.
    n_lags : int
        Number of lags ``p = 0..n_lags-1``.
    """
    n, n_w = w.shape
    n_x = x.shape[1]
    n_obs = n - k0
    P = n_lags
    L = scipy.fft.next_fast_len(max(8 * P, 512), real=True)
    B = L - P + 1
    nb = -(-n_obs // B)
    # x padded so every block's segment [s - P + 1, s - P + 1 + L) exists.
    first = k0 - P + 1
    need = first + (nb - 1) * B + L
    xp = x[first:] if need <= n else np.concatenate([x[first:], np.zeros((need - n, n_x))])
    wp = w[k0:]
    if wp.shape[0] < nb * B:
        wp = np.concatenate([wp, np.zeros((nb * B - wp.shape[0], n_w))])
    F = L // 2 + 1
    S = np.zeros((F, n_w, n_x), dtype=complex)
    # chunk of blocks per pass: bounds memory to ~ chunk * L * (n_w + n_x) complex numbers
    chunk = max(1, int(4_000_000 // (L * (n_w + n_x))))
    for b0 in range(0, nb, chunk):
        b1 = min(nb, b0 + chunk)
        nbc = b1 - b0
        seg = np.lib.stride_tricks.sliding_window_view(
            xp[b0 * B : (b1 - 1) * B + L], L, axis=0
        )[::B]  # (nbc, n_x, L)
        X = scipy.fft.rfft(seg, axis=2)  # (nbc, n_x, F)
        wb = np.zeros((nbc, n_w, L))
        wb[:, :, P - 1 : P - 1 + B] = wp[b0 * B : b1 * B].reshape(nbc, B, n_w).transpose(0, 2, 1)
        W = scipy.fft.rfft(wb, axis=2)  # (nbc, n_w, F)
        # S[f] += W[:, :, f]^T @ conj(X[:, :, f])  — a batched GEMM over frequencies
        S += np.matmul(W.transpose(2, 1, 0), X.conj().transpose(2, 0, 1))
    r = scipy.fft.irfft(S, n=L, axis=0)[:P]
    return r


def assemble_gram(r_xx: np.ndarray, x: np.ndarray, k0: int, n: int, P: int) -> np.ndarray:
    """Full lag-major A from its first block row by the diagonal recursion (method.md §2).

    Parameters
    ----------
    r_xx : ndarray (P, n_x, n_x)
        First block row, ``r_xx[p] = sum_k x(k) x(k-p)'`` (:func:`first_block_row` of
        ``x`` with itself).
    x : ndarray (N, n_x)
        The signals ``r_xx`` was computed from.
    k0 : int
        Index of the first observation (at least ``P - 1``).
    n : int
        Number of samples; observations are ``k = k0..n-1``.
    P : int
        Number of lags.
    """
    n_x = x.shape[1]
    # one diagonal recursion for both layouts: the 4-D lag Gram, flattened lag-major
    return assemble_lag_gram(r_xx, x, k0, n, P).reshape(P * n_x, P * n_x)




def assemble_lag_gram(r: np.ndarray, w: np.ndarray, k0: int, n: int, L: int) -> np.ndarray:
    """The lag Gram ``G[q, :, p, :]`` (4-D, ``(L, n_w, L, n_w)``) from its first block row,
    one block diagonal at a time.

    Along a block diagonal ``p = q + s`` the diagonal recursion of method.md §2 is a
    cumulative sum of the head and tail products, so each diagonal is one vectorised
    pass; the lower diagonals are the upper ones transposed (exactly symmetric, no
    averaging pass), written in place in the 4-D layout the estimators read.  Same
    numbers as the block-row recursion it replaced to rounding, about 5x faster on the
    full Gram of inputs and outputs (no lag-major transpose copy, no symmetrisation over
    the whole matrix); :func:`assemble_gram` is this Gram flattened.

    Parameters
    ----------
    r : ndarray (L, n_w, n_w)
        First block row, ``r[p] = sum_k w(k) w(k-p)'`` (:func:`first_block_row` of ``w``
        with itself).
    w : ndarray (N, n_w)
        The signals.
    k0 : int
        Index of the first observation (at least ``L - 1``).
    n : int
        Number of samples; observations are ``k = k0..n-1``.
    L : int
        Number of lags.
    """
    n_w = w.shape[1]
    G = np.empty((L, n_w, L, n_w))
    back = np.arange(L - 1)
    head = w[k0 - 1 - back]  # w(k0-1-q): enters block (q+1, p+1)
    tail = w[n - 1 - back]  # w(N-1-q): leaves it
    every = slice(0, n_w)
    for s in range(L):
        m = L - s
        vals = _diagonal_values(r, head, tail, s, m, every, every)
        q = np.arange(m)
        G[q, :, q + s, :] = vals
        if s:
            G[q + s, :, q, :] = vals.transpose(0, 2, 1)
    return G


def _diagonal_values(r, head, tail, s: int, m: int, rows: slice, cols: slice):
    """``G[q, rows, q + s, cols]`` for ``q < m``: the diagonal recursion along block
    diagonal ``s`` (every lag Gram here is built from it: :func:`assemble_lag_gram`,
    :func:`assemble_block`, :func:`assemble_parts`)."""
    vals = np.empty((m, rows.stop - rows.start, cols.stop - cols.start))
    vals[0] = r[s][rows, cols]
    if m > 1:
        inc = head[: m - 1, rows, None] * head[s : s + m - 1, None, cols]
        inc -= tail[: m - 1, rows, None] * tail[s : s + m - 1, None, cols]
        np.cumsum(inc, axis=0, out=inc)
        vals[1:] = r[s][rows, cols] + inc
    return vals


def assemble_block(r: np.ndarray, head: np.ndarray, tail: np.ndarray, a: tuple,
                   b: tuple) -> np.ndarray:
    """The sub-Gram ``G[:, a, :, b]`` of one segment from its first block row — the
    diagonal recursion of :func:`assemble_lag_gram` restricted to rows ``a`` and columns
    ``b`` (the same operations on the same numbers, entry by entry).

    Parameters
    ----------
    r : ndarray (L, n_w, n_w)
        First block row (:func:`first_block_row` of the segment's signals with
        themselves).
    head, tail : ndarray (L - 1, n_w)
        ``w(k0 - 1 - q)`` and ``w(N - 1 - q)``, ``q = 0..L-2``: the samples entering and
        leaving the sums along a diagonal.
    a, b : tuple of int
        Signal ranges ``(lo, hi)`` of rows and columns.

    Returns
    -------
    ndarray (L, |a|, L, |b|)
    """
    L = r.shape[0]
    sa, sb = slice(*a), slice(*b)
    G = np.empty((L, a[1] - a[0], L, b[1] - b[0]))
    for s in range(L):
        m = L - s
        q = np.arange(m)
        vals = _diagonal_values(r, head, tail, s, m, sa, sb)
        G[q, :, q + s, :] = vals
        if s:  # the lower diagonal: G[q + s, a, q, b] = G[q, b, q + s, a]'
            low = vals if a == b else _diagonal_values(r, head, tail, s, m, sb, sa)
            G[q + s, :, q, :] = low.transpose(0, 2, 1)
    return G


def assemble_parts(r: np.ndarray, head: np.ndarray, tail: np.ndarray, group: tuple,
                   cols: tuple) -> tuple:
    """The three sub-Grams a fit of each ``group`` signal on the ``cols`` signals reads,
    of one segment, in one diagonal recursion over both ranges (:func:`assemble_block`'s
    numbers): ``cols`` against themselves ``(L, |c|, L, |c|)``, every ``group`` signal
    against ``cols`` ``(L, |g|, L, |c|)``, and each ``group`` signal against itself
    ``(L, |g|, L)`` (``[q, i, p] = G[q, i, p, i]``).

    Parameters
    ----------
    r : ndarray (L, n_w, n_w)
        First block row.
    head, tail : ndarray (L - 1, n_w)
        Samples entering and leaving the sums (:func:`assemble_block`).
    group, cols : tuple of int
        Signal ranges ``(lo, hi)``.
    """
    L = r.shape[0]
    lo, hi = min(group[0], cols[0]), max(group[1], cols[1])
    c = slice(cols[0] - lo, cols[1] - lo)
    g = slice(group[0] - lo, group[1] - lo)
    gi = np.arange(g.start, g.stop)
    nc, ng = c.stop - c.start, g.stop - g.start
    G_cc = np.empty((L, nc, L, nc))
    G_gc = np.empty((L, ng, L, nc))
    G_gg = np.empty((L, ng, L))
    for s in range(L):
        m = L - s
        q = np.arange(m)
        vals = _diagonal_values(r, head, tail, s, m, slice(lo, hi), slice(lo, hi))
        G_cc[q, :, q + s, :] = vals[:, c, c]
        G_gc[q, :, q + s, :] = vals[:, g, c]
        G_gg[q, :, q + s] = vals[:, gi, gi]
        if s:  # lower diagonals: the transposes
            G_cc[q + s, :, q, :] = vals[:, c, c].transpose(0, 2, 1)
            G_gc[q + s, :, q, :] = vals[:, c, g].transpose(0, 2, 1)
            G_gg[q + s, :, q] = vals[:, gi, gi]
    return G_cc, G_gc, G_gg


NUISANCE_DEGREES = 3
"""Profiled Grams are built for polynomials of 1, 2 and 3 terms per segment (a constant,
plus a trend, plus a quadratic)."""


def _segment_gram(w: np.ndarray, k0: int, L: int, centred: bool):
    """Lag Gram of one segment and, when ``centred``, its versions with the first 1, 2, 3
    terms of ``1, t, t^2`` per segment profiled out (``t`` the scaled time)."""
    n, n_w = w.shape
    r = first_block_row(w, w, k0, L)  # (L, n_w, n_w): r[p, a, b] = sum_k w_a(k) w_b(k-p)
    G2 = assemble_lag_gram(r, w, k0, n, L).reshape(L * n_w, L * n_w)  # lag-major
    if not centred:
        return G2, []
    n_obs = n - k0
    lags = np.arange(L)
    # scaled time tau(k) = (k - centre) / n_obs, |tau| <= 1/2 over the observations; the
    # products sum_k tau(k)^p w(k - l) expand binomially in tau(j) = tau(k) - l / n_obs,
    # j = k - l, so cumulative sums of tau(j)^a w(j) give every lag at once
    centre = 0.5 * (k0 + n - 1)
    tau = (np.arange(n, dtype=float) - centre) / n_obs
    cs = [np.concatenate([np.zeros((1, n_w)), np.cumsum(tau[:, None] ** a * w, axis=0)])
          for a in range(NUISANCE_DEGREES)]
    win = [c[n - lags] - c[k0 - lags] for c in cs]  # (L, n_w): sum_j tau(j)^a w(j)
    shift = lags[:, None] / n_obs
    M = []
    for p in range(NUISANCE_DEGREES):
        acc = np.zeros((L, n_w))
        for a in range(p + 1):
            acc += math.comb(p, a) * win[a] * shift ** (p - a)
        M.append(acc.reshape(-1))  # sum_k tau(k)^p Z(k)
    M = np.array(M)
    tk = tau[k0:]
    B = np.array([[np.sum(tk ** (p + q)) for q in range(NUISANCE_DEGREES)]
                  for p in range(NUISANCE_DEGREES)])
    profiled = []
    for d in range(1, NUISANCE_DEGREES + 1):
        Md = M[:d]
        Gd = G2 - Md.T @ np.linalg.solve(B[:d, :d], Md)
        profiled.append(0.5 * (Gd + Gd.T))
    return G2, profiled


def build_lag_gram(segments, *, n_lags: int, k0_extra: int = 0,
                   centred: bool = False) -> LagGram:
    """Lag Gram summed over segments (each an array (n_seg, n_w) of contiguous good data).

    Observations start at ``n_lags - 1 + k0_extra`` in each segment (``k0_extra = 1``
    when a signal is a first difference whose first sample is undefined); shorter
    segments are skipped.  ``centred`` also builds the Grams with a constant, and with a
    constant and a linear trend, per segment profiled out.

    Parameters
    ----------
    segments : iterable of ndarray (n_seg, n_w)
        Contiguous good data, the same ``n_w`` signal columns in each.
    n_lags : int
        Lags ``L`` of the Gram.
    k0_extra : int
        Samples skipped at each segment's start beyond the ``L - 1`` lags need.
    centred : bool
        Also build the profiled Grams (the first 1, 2 and 3 terms of ``1, t, t^2`` per
        segment profiled out; :meth:`LagGram.gram`).

    Returns
    -------
    LagGram or None when no segment is long enough.  Without ``centred`` the Gram is
    lazy: each segment's first block row is computed here (the data pass) and the
    recursion runs when ``G`` or a sub-Gram is first asked for.
    """
    L = int(n_lags)
    k0 = L - 1 + int(k0_extra)
    if not centred:
        seeds, n_d = [], 0
        back = np.arange(L - 1)
        for w in segments:
            if w.shape[0] > k0:
                seeds.append((first_block_row(w, w, k0, L), w[k0 - 1 - back],
                              w[w.shape[0] - 1 - back]))
                n_d += w.shape[0] - k0
        return LagGram(None, n_d, len(seeds), (), seeds=tuple(seeds)) if seeds else None
    total = None
    for w in segments:
        if w.shape[0] <= k0:
            continue
        G2, profiled = _segment_gram(w, k0, L, centred)
        n_w = w.shape[1]
        shape = (L, n_w, L, n_w)
        part = LagGram(G2.reshape(shape), w.shape[0] - k0, 1,
                       tuple(g.reshape(shape) for g in profiled))
        total = part if total is None else total + part
    return total
