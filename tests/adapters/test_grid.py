"""Tests of pipeline.adapters.grid: irregular canonical samples → uniform grid + masks.

Known answers: linear functions are reproduced exactly by linear interpolation, and a
plain per-point Python reference (written from the rules in the module docstring, no
searchsorted) must agree with the vectorised implementation on random tables.
"""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.adapters.grid import Grid, SignalGridSpec, grid_from_regular, to_grid
from pipeline.adapters.ingest import CANONICAL_SCHEMA, QUALITY_DTYPE
from pipeline.errors import ConfigError, DataQualityError, IngestError

T0 = dt.datetime(2024, 3, 1, 10, 0, 0, tzinfo=dt.UTC)
T0_US = int(T0.timestamp() * 1_000_000)


def make_table(rows: list[tuple[str, float, float | None, str, str | None]]) -> pl.DataFrame:
    """Canonical table from (signal, seconds after T0, value, quality, state) rows."""
    return pl.DataFrame(
        {
            "time": [T0 + dt.timedelta(seconds=r[1]) for r in rows],
            "signal": [r[0] for r in rows],
            "value": [r[2] for r in rows],
            "quality": [r[3] for r in rows],
            "state": [r[4] for r in rows],
        },
        schema=CANONICAL_SCHEMA,
    ).sort(["signal", "time"])


def reference_point(
    t_grid: float, samples: list[tuple[float, float | None, str, str | None]], spec: SignalGridSpec, mask_suspect: bool
) -> tuple[float, str | None]:
    """One grid point by the documented rules, with plain loops (value, reason or None)."""
    times = [s[0] for s in samples]
    if t_grid < times[0]:
        return math.nan, "before_first_sample"
    if t_grid > times[-1]:
        return math.nan, "after_last_sample"
    left = max(k for k, t in enumerate(times) if t <= t_grid)

    def usable(k: int) -> bool:
        _, v, q, _ = samples[k]
        return q == "good" or (q == "suspect" and not mask_suspect)

    def label(k: int) -> str:
        _, _, q, s = samples[k]
        kind = "suspect_quality:" if q == "suspect" else "bad_quality:"
        return kind + (s or "unknown")

    if not usable(left):
        return math.nan, label(left)
    if spec.interpolation == "hold":
        if t_grid - times[left] > spec.max_gap_s:
            return math.nan, "gap>max_gap_s"
        return samples[left][1], None  # type: ignore[return-value]
    if times[left] == t_grid:
        return samples[left][1], None  # type: ignore[return-value]
    right = left + 1
    if not usable(right):
        return math.nan, label(right)
    if times[right] - times[left] > spec.max_gap_s:
        return math.nan, "gap>max_gap_s"
    v0, v1 = samples[left][1], samples[right][1]
    w = (t_grid - times[left]) / (times[right] - times[left])
    return v0 + (v1 - v0) * w, None  # type: ignore[operator]


def test_linear_function_reproduced_exactly_between_irregular_samples() -> None:
    # f(t) = 3 + 0.5 t is linear, so linear interpolation between any samples is exact
    # (up to float rounding ~1e-15 relative).
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 1000, 300))
    t = np.unique(np.round(t, 3))
    rows = [("A", float(x), 3 + 0.5 * float(x), "good", None) for x in t]
    grid = to_grid(make_table(rows), dt_s=1.0)
    assert grid.names == ("A",)
    assert grid.good.all()
    expected = 3 + 0.5 * (grid.t_s + (t[0]))
    np.testing.assert_allclose(grid.values[:, 0], expected, rtol=0, atol=1e-9)
    assert grid.values.shape == (int(np.floor(t[-1] - t[0])) + 1, 1)
    assert grid.time[0] == np.datetime64(T0.replace(tzinfo=None), "us") + np.timedelta64(round(t[0] * 1e6), "us")


def test_linear_matches_numpy_interp_on_a_curve() -> None:
    # np.interp is an independent implementation of the same interpolant.
    rng = np.random.default_rng(2)
    t = np.unique(np.round(np.sort(rng.uniform(0, 600, 200)), 2))
    v = np.sin(t / 37.0) + 0.1 * t
    rows = [("X", float(a), float(b), "good", None) for a, b in zip(t, v, strict=True)]
    grid = to_grid(make_table(rows), dt_s=0.5)
    t_grid = t[0] + grid.t_s
    np.testing.assert_allclose(grid.values[:, 0], np.interp(t_grid, t, v), rtol=0, atol=1e-12)


def test_hold_uses_last_sample_and_max_hold_age() -> None:
    rows = [
        ("SP", 0.0, 1.0, "good", None),
        ("SP", 10.0, 2.0, "good", None),
        ("SP", 40.0, 5.0, "good", None),
    ]
    grid = to_grid(make_table(rows), dt_s=5.0, signals={"SP": {"interpolation": "hold", "max_gap_s": 15.0}})
    # grid 0,5,...,40: held 1,1,2,2,2, 2 (15 s old: allowed), masked at 30 and 35
    # (20 s and 25 s old > 15 s), then 5.
    expected = [1, 1, 2, 2, 2, 2, np.nan, np.nan, 5]
    np.testing.assert_array_equal(grid.values[:, 0], expected)
    assert grid.mask_reasons["SP"] == {"gap>max_gap_s": 2}
    assert grid.interpolation == {"SP": "hold"}


def test_bad_sample_masks_its_brackets_never_interpolates_through_it() -> None:
    rows = [
        ("A", 0.0, 0.0, "good", None),
        ("A", 10.0, 10.0, "good", None),
        ("A", 20.0, None, "bad", "Bad Input"),
        ("A", 30.0, 30.0, "good", None),
        ("A", 40.0, 40.0, "good", None),
    ]
    table = make_table(rows)
    lin = to_grid(table, dt_s=5.0)
    # Linear: every point in (10, 30) uses the bad sample: 15, 20, 25 masked.
    masked = lin.t_s[~lin.good[:, 0]]
    np.testing.assert_array_equal(masked, [15.0, 20.0, 25.0])
    assert lin.mask_reasons["A"] == {"bad_quality:Bad Input": 3}
    np.testing.assert_array_equal(lin.values[lin.good[:, 0], 0], lin.t_s[lin.good[:, 0]])
    hold = to_grid(table, dt_s=5.0, signals={"A": {"interpolation": "hold"}})
    # Hold: the state persists from 20 until the next sample at 30.
    np.testing.assert_array_equal(hold.t_s[~hold.good[:, 0]], [20.0, 25.0])
    assert hold.mask_reasons["A"] == {"bad_quality:Bad Input": 2}


def test_edges_gap_and_suspect_reasons() -> None:
    rows = [
        ("A", 10.0, 1.0, "good", None),
        ("A", 20.0, 2.0, "suspect", "Questionable"),
        ("A", 30.0, 3.0, "good", None),
        ("A", 100.0, 10.0, "good", None),
        ("B", 0.0, 0.0, "good", None),
        ("B", 120.0, 12.0, "good", None),
    ]
    table = make_table(rows)
    grid = to_grid(table, dt_s=10.0, signals={"A": {"max_gap_s": 30.0}, "B": None})
    assert grid.names == ("A", "B")
    assert grid.values.shape == (13, 2)  # 0..120 s every 10 s
    ra = grid.mask_reasons["A"]
    # t=0: before; 10: good; 20 exact suspect; 30 good; 40..90 bracket 70 s > 30 s; 110,120 after.
    assert ra == {
        "after_last_sample": 2,
        "before_first_sample": 1,
        "gap>max_gap_s": 6,
        "suspect_quality:Questionable": 1,
    }
    assert sum(ra.values()) == int((~grid.good[:, 0]).sum())
    lenient = to_grid(table, dt_s=10.0, start=T0, signals={"A": {"max_gap_s": 30.0}}, mask_suspect=False)
    assert lenient.values[2, 0] == 2.0 and lenient.good[2, 0]
    assert grid.good[:, 1].all()
    np.testing.assert_allclose(grid.values[:, 1], np.arange(13.0))


def test_explicit_start_end() -> None:
    rows = [("A", float(k), float(k), "good", None) for k in range(0, 61, 3)]
    grid = to_grid(
        make_table(rows),
        dt_s=6.0,
        start=np.datetime64(T0.replace(tzinfo=None), "us") - np.timedelta64(6, "s"),
        end=(T0 + dt.timedelta(seconds=66)).isoformat(),
    )
    assert grid.values.shape == (13, 1)
    assert grid.mask_reasons["A"] == {"after_last_sample": 1, "before_first_sample": 1}
    assert (~grid.good[:, 0]).sum() == 2 and not grid.good[0, 0] and not grid.good[-1, 0]
    assert grid.time[0] == np.datetime64(T0.replace(tzinfo=None), "us") - np.timedelta64(6, "s")


def test_unsorted_table_with_duplicates_is_sorted_keep_last() -> None:
    table = pl.DataFrame(
        {
            "time": [T0 + dt.timedelta(seconds=s) for s in (10, 0, 10, 20)],
            "signal": ["A", "A", "A", "A"],
            "value": [99.0, 0.0, 10.0, 20.0],
            "quality": ["good"] * 4,
            "state": [None] * 4,
        },
        schema=CANONICAL_SCHEMA,
    )
    grid = to_grid(table, dt_s=5.0)
    np.testing.assert_allclose(grid.values[:, 0], [0, 5, 10, 15, 20])


samples_strategy = st.lists(
    st.tuples(
        st.integers(0, 400),  # time in units of 0.5 s
        st.floats(-100, 100, allow_nan=False),
        st.sampled_from(["good", "good", "good", "bad", "suspect"]),
        st.sampled_from(["S1", "S2", None]),
    ),
    min_size=1,
    max_size=40,
    unique_by=lambda r: r[0],
)


@settings(max_examples=60, deadline=None)
@given(
    samples=samples_strategy,
    interpolation=st.sampled_from(["linear", "hold"]),
    max_gap=st.sampled_from([math.inf, 3.0, 20.0]),
    dt_steps=st.integers(1, 7),
    offset=st.integers(-10, 10),
    mask_suspect=st.booleans(),
)
def test_vectorised_grid_matches_per_point_reference(
    samples: list, interpolation: str, max_gap: float, dt_steps: int, offset: int, mask_suspect: bool
) -> None:
    samples = sorted(samples)
    rows = [
        ("S", k * 0.5, None if q == "bad" else v, q, s if q != "good" else None)
        for k, v, q, s in samples
    ]
    spec = SignalGridSpec(interpolation, max_gap)  # type: ignore[arg-type]
    dt_s = dt_steps * 0.5
    start = T0 + dt.timedelta(seconds=offset * 0.5)
    end = T0 + dt.timedelta(seconds=205.0)
    grid = to_grid(make_table(rows), dt_s=dt_s, start=start, end=end, signals={"S": spec}, mask_suspect=mask_suspect)
    ref_samples = [(k * 0.5 - offset * 0.5, None if q == "bad" else v, q, s if q != "good" else None) for k, v, q, s in samples]
    expected_reasons: dict[str, int] = {}
    for i, t in enumerate(grid.t_s):
        value, reason = reference_point(float(t), ref_samples, spec, mask_suspect)
        if reason is None:
            assert grid.good[i, 0]
            assert grid.values[i, 0] == pytest.approx(value, abs=1e-9)
        else:
            assert not grid.good[i, 0]
            assert math.isnan(grid.values[i, 0])
            expected_reasons[reason] = expected_reasons.get(reason, 0) + 1
    assert grid.mask_reasons["S"] == dict(sorted(expected_reasons.items()))


def test_per_signal_slices_do_not_mix_signals() -> None:
    # Two signals with different sample times; each grid column must only use its own.
    rows = [("A", float(k), 1.0, "good", None) for k in range(0, 11)] + [
        ("B", float(k), -1.0, "good", None) for k in range(5, 16)
    ]
    grid = to_grid(make_table(rows), dt_s=1.0)
    assert grid.values.shape == (16, 2)
    np.testing.assert_array_equal(grid.good[:, 0], np.arange(16) <= 10)
    np.testing.assert_array_equal(grid.good[:, 1], np.arange(16) >= 5)
    assert set(np.unique(grid.values[grid.good[:, 0], 0])) == {1.0}
    assert set(np.unique(grid.values[grid.good[:, 1], 1])) == {-1.0}


def test_grid_from_regular() -> None:
    values = np.arange(12.0).reshape(6, 2)
    values[3, 1] = np.nan
    grid = grid_from_regular(values, ["u", "y"], 2.5, "2024-01-01T00:00:00Z")
    assert isinstance(grid, Grid)
    np.testing.assert_array_equal(grid.t_s, [0, 2.5, 5, 7.5, 10, 12.5])
    assert grid.time[1] == np.datetime64("2024-01-01T00:00:02.500", "us")
    assert grid.good.sum() == 11 and not grid.good[3, 1]
    assert grid.mask_reasons == {"u": {}, "y": {"nonfinite_value": 1}}
    np.testing.assert_array_equal(grid.series("u"), values[:, 0])


def test_quality_dtype_is_enum_of_three() -> None:
    assert QUALITY_DTYPE == pl.Enum(["good", "suspect", "bad"])


def test_errors() -> None:
    table = make_table([("A", 0.0, 1.0, "good", None), ("A", 1.0, 2.0, "good", None)])
    with pytest.raises(IngestError, match=r"signal\(s\) \['Z'\] are not in the recording; it has \['A'\]"):
        to_grid(table, dt_s=1.0, signals=["Z"])
    with pytest.raises(ConfigError, match=r"dt_s=0 must be a positive number of seconds"):
        to_grid(table, dt_s=0)
    with pytest.raises(ConfigError, match=r"whole number of microseconds"):
        to_grid(table, dt_s=1e-7)
    with pytest.raises(ConfigError, match=r"end .* is before start"):
        to_grid(table, dt_s=1.0, start="2024-03-01T11:00:00Z", end="2024-03-01T10:00:00Z")
    with pytest.raises(ConfigError, match=r"signals\['A'\]: unknown key\(s\) \['max_gap'\]"):
        to_grid(table, dt_s=1.0, signals={"A": {"max_gap": 3}})
    with pytest.raises(ConfigError, match=r"interpolation='cubic' is not 'linear' or 'hold'"):
        to_grid(table, dt_s=1.0, signals={"A": {"interpolation": "cubic"}})
    with pytest.raises(ConfigError, match=r"max_gap_s=-1.0 must be > 0"):
        SignalGridSpec("linear", -1.0)
    with pytest.raises(DataQualityError, match=r"missing columns \['quality'\]"):
        to_grid(table.drop("quality"), dt_s=1.0)
    with pytest.raises(IngestError, match=r"signal 'Q' is not on the grid; it has \['A'\]"):
        to_grid(table, dt_s=1.0).column("Q")
    with pytest.raises(ConfigError, match=r"2 names for 3 columns"):
        grid_from_regular(np.zeros((4, 3)), ["a", "b"], 1.0, T0)
