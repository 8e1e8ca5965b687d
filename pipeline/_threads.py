"""BLAS threading for the estimators (one decision, one place).

The estimators run many small factorisations and products (Cholesky of a few hundred
unknowns, residual products, Wald tests), where multi-threaded BLAS costs more than it
gives on the 2-core machines: the automatic N_p/N_d search with a noise model took
0.53 s per record with OpenBLAS's two threads and 0.22 s with one, and a dot product of
2e4 doubles 50 us against 3.7 us (milliseconds when other processes compete for the
cores).  So every entry point runs with BLAS single-threaded (threadpoolctl).
Parallelism comes from running windows, files and jobs side by side instead, and within
one estimate from fitting its outputs side by side (:func:`thread_map`).  Measured at
20 inputs x 20 outputs, N_p 60, N 1e5 (2 cores): the noise-model estimate 1.31 -> 1.08 s
(CPU 4.7 s for 3.6 s of wall over three), the search's nested factors 1.29 -> 0.75 s;
the pieces are mostly passes over 10-30 MB matrices and small per-lag updates, so two
threads share the memory bandwidth and the GIL, and the gain is 1.2-1.7x, not 2x.

Decision: the limit is set on every entry and never restored.  A result must not depend
on which runner computed it (the estimate flow and the Dask runner are compared bit for
bit with a plain run), and restoring raced: with the task runner's threads estimating
windows side by side, one thread restoring two BLAS threads while another still
computed changed results in the last bits (and the OpenBLAS builds here do not behave
alike in every thread).  The cost: after an estimate, BLAS stays single-threaded in the
process — large matrix products of a caller's own may then run up to 2x slower.
"""

from __future__ import annotations

import functools
import threading

from threadpoolctl import threadpool_limits

__all__ = ["single_threaded_blas", "thread_map", "worker_count"]


def single_threaded_blas(fn):
    """Run ``fn`` with BLAS limited to one thread (module docstring: not restored).

    Parameters
    ----------
    fn : callable
        Function to wrap; each call of the wrapper sets the BLAS limit, then calls it
        with the same arguments.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        threadpool_limits(limits=1, user_api="blas")
        return fn(*args, **kwargs)

    return wrapper


_MAPPING = threading.local()  # set in the threads of a thread_map


def worker_count() -> int:
    """Threads :func:`thread_map` uses at most: the cores this process may run on."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def thread_map(fn, items) -> list:
    """``[fn(item) for item in items]``, the items spread over :func:`worker_count`
    threads.

    For the estimators' independent pieces (one output's fit, one window's estimate):
    each is large BLAS/LAPACK work on its own arrays, which releases the GIL, while BLAS
    itself stays single-threaded (:func:`single_threaded_blas`), so the cores are used
    by pieces side by side instead of by threads inside small products.  Every piece
    computes exactly what it would alone, so results do not depend on the thread count.
    The first exception in item order is raised (after the pieces already started end).

    Parameters
    ----------
    fn : callable
        Called once per item, from a worker thread (or this one for a single item).
    items : iterable
        The pieces, in order.

    Returns
    -------
    list
        ``fn(item)`` in item order.
    """
    from concurrent.futures import ThreadPoolExecutor

    items = list(items)
    workers = min(len(items), worker_count())
    # a piece of a thread_map (a window) maps its own pieces (its outputs) serially:
    # the cores are taken already
    if workers <= 1 or getattr(_MAPPING, "inside", False):
        return [fn(item) for item in items]

    def piece(item):
        _MAPPING.inside = True
        try:
            return fn(item)
        finally:
            _MAPPING.inside = False

    # (the BLAS limit is process-wide for the OpenBLAS builds here: set by the caller)
    with ThreadPoolExecutor(workers) as pool:
        futures = [pool.submit(piece, item) for item in items]
        return [f.result() for f in futures]
