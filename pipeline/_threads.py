"""BLAS threading for the estimators (one decision, one place).

The estimators run many small factorisations and products (Cholesky of a few hundred
unknowns, residual products, Wald tests), where multi-threaded BLAS costs more than it
gives on the 2-core machines: the automatic N_p/N_d search with a noise model took
0.53 s per record with OpenBLAS's two threads and 0.22 s with one, and a dot product of
2e4 doubles 50 us against 3.7 us (milliseconds when other processes compete for the
cores).  So every entry point runs with BLAS single-threaded (threadpoolctl).
Parallelism comes from running windows, files and jobs side by side instead.

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

from threadpoolctl import threadpool_limits

__all__ = ["single_threaded_blas"]


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
