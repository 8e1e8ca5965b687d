"""BLAS threading for the estimators (one decision, one place).

The estimators run many small factorisations and products (Cholesky of a few hundred
unknowns, residual products, Wald tests), where multi-threaded BLAS costs more than it
gives on the 2-core machines: the automatic N_p/N_d search with a noise model took
0.53 s per record with OpenBLAS's two threads and 0.22 s with one, and a dot product of
2e4 doubles 50 us against 3.7 us (milliseconds when other processes compete for the
cores).  So the entry points run with BLAS single-threaded (threadpoolctl; restored
after).  Parallelism comes from running windows, files and jobs side by side instead.
"""

from __future__ import annotations

import functools

from threadpoolctl import threadpool_limits

__all__ = ["single_threaded_blas"]


def single_threaded_blas(fn):
    """Run ``fn`` with BLAS limited to one thread (module docstring)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
