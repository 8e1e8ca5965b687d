"""Outputs and windows estimated side by side (``pipeline._threads.thread_map``): the
same numbers whatever the thread count, errors in item order."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import pipeline._threads as threads
from pipeline._threads import thread_map
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.identification.search import search


def test_results_come_in_item_order_and_the_first_failing_item_is_raised():
    def fn(k):
        if k == 1:
            time.sleep(0.2)  # the later failure (item 3) happens first
            raise ValueError("item 1")
        if k == 3:
            raise KeyError("item 3")
        return k * k

    assert thread_map(lambda k: k * k, range(7)) == [0, 1, 4, 9, 16, 25, 36]
    with pytest.raises(ValueError, match="item 1"):
        thread_map(fn, range(5))
    assert thread_map(fn, []) == []


def test_a_piece_maps_its_own_pieces_on_its_own_thread():
    """A window's estimate (a piece of a thread_map) fits its outputs serially: the
    cores are taken by the windows already (two pools of two threads on two cores
    would share them four ways)."""
    def outer(k):
        me = threading.get_ident()
        return thread_map(lambda j: threading.get_ident() == me, range(3))

    assert thread_map(outer, range(2)) == [[True] * 3] * 2
    assert not all(thread_map(lambda j: threading.get_ident() == threading.main_thread().ident,
                              range(4))) or threads.worker_count() == 1


def _record(seed=3, n=20_000, n_x=4, n_y=3):
    """Inputs of random steps through first-order pairs, AR(1) output noise."""
    rng = np.random.default_rng(seed)
    x = np.repeat(rng.normal(0, 1, (n // 40, n_x)), 40, axis=0)
    y = np.zeros((n, n_y))
    for i in range(n_y):
        for j in range(n_x):
            a = np.exp(-1.0 / rng.uniform(3, 12))
            y[1:, i] += np.convolve(x[:, j], (1 - a) * a ** np.arange(60))[: n - 1] \
                * rng.uniform(-2, 2)
        e = rng.normal(0, 0.3, n)
        for k in range(1, n):
            e[k] += 0.8 * e[k - 1]
        y[:, i] += e
    return x, y


def test_estimates_and_the_search_do_not_depend_on_the_thread_count(monkeypatch):
    """Known answer: the same record estimated on one thread (``worker_count`` 1) and
    on two -- the noise-model estimate and the whole search (orders, windows) -- gives
    bit-identical step responses, uncertainties and choices."""
    x, y = _record()
    runs = []
    for workers in (1, 2):
        monkeypatch.setattr(threads, "worker_count", lambda w=workers: w)
        est = estimate_step_responses(x, y, n_p=40, dt=1.0, noise="auto")
        res = search(x, y, dt=1.0, n_p_max=40, noise="auto")
        runs.append((est.step, est.step_std, res.n_p, res.n_d, repr(res.nd_trace)))
    for a, b in zip(*runs, strict=True):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b
