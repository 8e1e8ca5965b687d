"""Tests of pipeline.windows: disjoint windows and the sample accounting."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError
from pipeline.normal_equations import normal_equations
from pipeline.windows import (
    Window,
    n_d_for,
    samples_for,
    split_windows,
    split_windows_masked,
)


def _assert_disjoint_ordered(windows: list[Window], n: int) -> None:
    for w in windows:
        assert 0 <= w.start < w.stop <= n
    for a, b in zip(windows, windows[1:]):
        assert a.stop <= b.start  # no shared sample


@pytest.mark.parametrize("n_p,integrating", [(1, False), (1, True), (5, False), (5, True)])
def test_sample_accounting_matches_the_estimator(n_p, integrating):
    """samples_for/n_d_for agree with the observation count of the least-squares code."""
    n_d = 37
    n = samples_for(n_d, n_p, integrating)
    rng = np.random.default_rng(0)
    ne = normal_equations(
        rng.standard_normal((n, 1)), rng.standard_normal((n, 1)), n_p_max=n_p,
        integrating=integrating,
    )
    assert ne.n_d == n_d == n_d_for(n, n_p, integrating)
    assert n == n_d + max(n_p - 1, int(integrating))
    assert n_d_for(3, 10) == 0


def test_equal_windows_cover_the_record():
    ws = split_windows(1003, n_windows=4, n_p=10)
    assert [(w.start, w.stop) for w in ws] == [(0, 251), (251, 502), (502, 753), (753, 1003)]
    assert [w.n_d for w in ws] == [242, 242, 242, 241]
    assert [w.index for w in ws] == [0, 1, 2, 3]
    _assert_disjoint_ordered(ws, 1003)
    x = np.arange(1003)
    assert sum(x[w.slice].size for w in ws) == 1003


def test_window_len_and_gap():
    ws = split_windows(1000, window_len=300, n_p=10, gap=51)
    assert [(w.start, w.stop) for w in ws] == [(0, 300), (351, 651)]  # a third would end at 1002
    ws3 = split_windows(1000, window_len=300, n_windows=3, n_p=10, gap=50)
    assert [(w.start, w.stop) for w in ws3][-1] == (700, 1000)
    wg = split_windows(1000, n_windows=2, n_p=3, gap=100, integrating=True)
    assert [(w.start, w.stop) for w in wg] == [(0, 450), (550, 1000)]
    assert wg[0].n_d == 448 and wg[0].n_samples == 450
    assert wg[1].to_dict() == {"index": 1, "start": 550, "stop": 1000, "n_d": 448}


def test_errors_say_the_numbers_and_the_fix():
    msg = r"record of 100 samples cannot hold 3 disjoint windows.*each needs 60 samples.*use fewer"
    with pytest.raises(InsufficientDataError, match=msg):
        split_windows(100, n_windows=3, n_p=10, min_n_d=51)
    msg = "window_len=15 samples gives n_d=6 observations with n_p=10"
    with pytest.raises(InsufficientDataError, match=msg):
        split_windows(100, window_len=15, n_p=10)
    with pytest.raises(InsufficientDataError, match=r"cannot hold 5 window\(s\) of 30 samples"):
        split_windows(100, window_len=30, n_windows=5, n_p=10)
    with pytest.raises(ConfigError, match="give n_windows, window_len, or both"):
        split_windows(100, n_p=10)
    with pytest.raises(ConfigError, match="n_p must be a positive integer"):
        split_windows(100, n_windows=2, n_p=0)
    with pytest.raises(ConfigError, match="gap must be a non-negative integer"):
        split_windows(100, n_windows=2, n_p=2, gap=-1)


def test_masked_windows_balance_usable_observations():
    """Half the first half of the record is bad: the first window must stretch."""
    n, n_p = 2000, 11
    good = np.ones(n, bool)
    good[100:600] = False
    ws = split_windows_masked(good, n_windows=2, n_p=n_p)
    _assert_disjoint_ordered(ws, n)
    assert ws[0].start == 0 and ws[-1].stop == n
    # usable observations: (100 - 10) + (1400 - 10) = 1480 -> 740 each (± k0 at the cut)
    assert ws[0].stop > 1000
    assert abs(ws[0].n_d - ws[1].n_d) <= n_p
    # n_d counted by brute force: observation k usable if samples k-10..k are all good
    for w in ws:
        g = good[w.slice]
        brute = sum(g[k - n_p + 1 : k + 1].all() for k in range(n_p - 1, g.size))
        assert w.n_d == brute


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_windows=st.integers(2, 4),
    n_p=st.integers(1, 8),
    gap=st.integers(0, 5),
    integrating=st.booleans(),
)
def test_masked_windows_property(seed, n_windows, n_p, gap, integrating):
    rng = np.random.default_rng(seed)
    n = 3000
    good = np.ones(n, bool)
    for start in rng.integers(0, n, 8):  # 8 random outages of up to 60 samples
        good[start : start + rng.integers(1, 60)] = False
    ws = split_windows_masked(good, n_windows=n_windows, n_p=n_p, integrating=integrating, gap=gap)
    _assert_disjoint_ordered(ws, n)
    k0 = max(n_p - 1, int(integrating))
    total = sum(
        good[k - k0 : k + 1].all() for k in range(k0, n)
    )
    share = total / n_windows
    for w in ws:
        # cut rounding (1), observations needing samples before the window (k0), gap
        assert share - 1 - k0 - gap <= w.n_d <= share + 1


def test_masked_windows_errors():
    good = np.zeros(500, bool)
    good[:50] = True
    msg = "has 41 usable observations for n_p=10; 2 windows of n_d >= 25 need 50"
    with pytest.raises(InsufficientDataError, match=msg):
        split_windows_masked(good, n_windows=2, n_p=10, min_n_d=25)
    # 41 in total is enough for 2 x 20, but the cut costs window 1 its first 9 observations
    msg = r"window 1 \(samples 30..500\) has only 11 usable"
    with pytest.raises(InsufficientDataError, match=msg):
        split_windows_masked(good, n_windows=2, n_p=10, min_n_d=20)
    with pytest.raises(DataQualityError, match="good must be a 1-D mask"):
        split_windows_masked(np.ones((10, 2), bool), n_windows=2, n_p=1)
