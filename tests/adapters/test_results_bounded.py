"""Results written in bounded memory and size (issue 33, build 3): long series drawn as
min/max envelopes at display resolution, read back from the stored parquet a row group
at a time, a recording whose size does not grow with the record, and every stage of a
run ending with a done line.

Memory and time targets (a month at 1 Hz) live in ``tests/benchmarks/bench_ingest.py
--job``; these tests use small data.
"""

from __future__ import annotations

import re

import numpy as np
import polars as pl
import pytest
from rerun.chunk import RrdReader

from pipeline.adapters import series_reader
from pipeline.adapters.rerun_sink import render_run
from pipeline.adapters.series_reader import Spec, reduce_series
from pipeline.adapters.store import ResultStore
from pipeline.adapters.store.schemas import ResultSchemaError
from pipeline.readouts.envelope import (
    DISPLAY_POINTS,
    bucket_ids,
    bucket_width,
    envelope_points,
    first_flagged,
)
from pipeline.jobs.job_types import LongTable

# --------------------------------------------------------------------------- the envelope


def _series(n: int, seed: int) -> np.ndarray:
    """A random walk with spikes and NaN stretches (a masked stretch, a whole bucket)."""
    rng = np.random.default_rng(seed)
    v = np.cumsum(rng.normal(0.0, 1.0, n))
    v[rng.integers(0, n, 20)] += rng.choice([-1, 1], 20) * 500.0  # single-sample spikes
    v[rng.integers(0, n, 50)] = np.nan
    v[n // 3: n // 3 + 400] = np.nan
    return v


@pytest.mark.parametrize("n, max_points", [(10_000, 200), (123_457, 5000), (999, 40)])
def test_envelope_keeps_every_buckets_min_and_max_exactly(n, max_points):
    v = _series(n, seed=n)
    t_s = np.arange(n) * 0.5
    width = bucket_width(t_s[-1] - t_s[0], n, max_points)
    b = bucket_ids(t_s, t_s[0], width)
    env = envelope_points(b, v)
    assert env.index.size <= max_points
    assert np.all(np.diff(env.index) > 0)  # time order, each sample once
    point_bucket = b[env.index]
    for k in np.unique(b):
        ref = v[b == k]
        got = env.value[point_bucket == k]
        assert 1 <= got.size <= 2
        if np.isfinite(ref).any():  # the reference: numpy on the bucket's samples
            assert np.nanmin(got) == np.nanmin(ref) and np.nanmax(got) == np.nanmax(ref)
            assert np.isfinite(got).all()
        else:  # no value: one NaN point (a gap)
            assert got.size == 1 and np.isnan(got[0])
    # the points are samples of the series, at their own positions
    finite = np.isfinite(env.value)
    assert np.array_equal(env.value[finite], v[env.index][finite])
    # every spike is drawn
    assert np.nanmax(env.value) == np.nanmax(v) and np.nanmin(env.value) == np.nanmin(v)


def test_short_series_and_flags():
    assert bucket_width(100.0, DISPLAY_POINTS, DISPLAY_POINTS) is None  # every sample drawn
    with pytest.raises(ValueError, match="max_points=1 must be at least 2"):
        bucket_width(10.0, 100, 1)
    with pytest.raises(ValueError, match="non-decreasing"):
        envelope_points(np.array([0, 1, 0]), np.zeros(3))
    b = np.repeat(np.arange(5), 10)
    flag = np.zeros(50, bool)
    flag[[3, 7, 31, 49]] = True
    assert first_flagged(b, flag).tolist() == [3, 31, 49]
    one = envelope_points(np.zeros(4, np.int64), np.full(4, 2.0))  # constant: one point
    assert one.index.tolist() == [0] and one.value.tolist() == [2.0]


# --------------------------------------------------------------------------- stored tables


N_LONG = 60_000


def _signals_table(n: int, names=("u", "y")) -> LongTable:
    """Two signals of ``n`` samples at 1 s, made in chunks of 7,000 rows."""
    time = np.datetime64("2026-01-01T00:00:00", "us") + np.arange(n) * np.timedelta64(1, "s")
    values = {name: _series(n, seed=k) for k, name in enumerate(names)}
    good = np.ones(n, bool)
    good[5000:5100] = False

    def make(rows: int):
        for k, name in enumerate(names):
            for a in range(0, n, rows):
                b = min(a + rows, n)
                yield pl.DataFrame({
                    "time": time[a:b], "signal": name, "role": ("input", "output")[k % 2],
                    "raw": values[name][a:b], "conditioned": values[name][a:b] - 1.0,
                    "good": good[a:b]}).with_columns(
                        pl.col("raw").fill_nan(None), pl.col("conditioned").fill_nan(None),
                        pl.col("time").dt.replace_time_zone("UTC"))

    return LongTable(n * len(names), make, chunk_rows=7_000)


@pytest.fixture(scope="module")
def long_runs(tmp_path_factory):
    """Runs of N_LONG and 4 x N_LONG samples per signal, each with its recording."""
    store = ResultStore(tmp_path_factory.mktemp("bounded") / "storage")
    out = {}
    for n in (N_LONG, 4 * N_LONG):
        with store.new_run("long", config={}, inputs=[]) as run:
            run.write_signals(_signals_table(n))
            render_run(run.path, ident=f"long/{run.run_id}")
            rid = run.run_id
        out[n] = store.run_dir("long", rid)
    return out


def test_a_chunked_table_is_stored_in_row_groups_and_read_back_whole(long_runs):
    import pyarrow.parquet as pq

    path = long_runs[N_LONG] / "signals.parquet"
    assert pq.ParquetFile(path).num_row_groups == 2 * -(-N_LONG // 7_000)
    stored = pl.read_parquet(path)
    assert stored.equals(pl.concat(list(_signals_table(N_LONG))))


def test_a_key_in_two_chunks_is_refused(tmp_path):
    table = _signals_table(100)
    twice = [next(iter(table)), next(iter(table))]
    store = ResultStore(tmp_path / "storage")
    with pytest.raises(ResultSchemaError, match="overlap an earlier chunk"), \
            store.new_run("dup", config={}, inputs=[]) as run:
        run.write_signals(twice)
    assert not list((tmp_path / "storage").glob("dup/*"))


def test_reading_a_row_group_at_a_time_gives_the_envelope_of_the_whole(long_runs, monkeypatch):
    monkeypatch.setattr(series_reader, "BATCH_ROWS", 999)  # buckets straddle batches
    path = long_runs[N_LONG] / "signals.parquet"
    got = {}
    reduce_series(path, ["signal"], {"raw": Spec(pl.col("raw")),
                                     "masked": Spec(pl.lit(0.0), flag=~pl.col("good"))},
                  columns=["raw", "good"], max_points=300,
                  on_key=lambda info, s: got.__setitem__(info.key[0], s))
    whole = pl.read_parquet(path)
    for name in ("u", "y"):
        df = whole.filter(pl.col("signal") == name)
        t_s = (df["time"] - df["time"][0]).dt.total_seconds(fractional=True).to_numpy()
        b = bucket_ids(t_s, 0.0, bucket_width(t_s[-1], df.height, 300))
        env = envelope_points(b, df["raw"].fill_null(np.nan).to_numpy())
        times = df["time"].dt.replace_time_zone(None).cast(pl.Datetime("ns")).to_numpy()
        assert got[name]["raw"].envelope
        assert np.array_equal(got[name]["raw"].time, times[env.index])
        assert np.array_equal(got[name]["raw"].value, env.value, equal_nan=True)
        marks = first_flagged(b, ~df["good"].to_numpy())
        assert np.array_equal(got[name]["masked"].time, times[marks])
        assert np.all(got[name]["masked"].value == 0.0)


def _recorded(path) -> dict[str, np.ndarray]:
    """Entity path -> the values of its temporal scalars."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if "Scalars:scalars" in batch.schema.names:
            out.setdefault(chunk.entity_path, []).extend(
                v[0] if v else np.nan for v in batch.column("Scalars:scalars").to_pylist())
    return {k: np.array(v, dtype=float) for k, v in out.items()}


def test_recording_size_does_not_grow_with_the_record(long_runs):
    sizes = {n: (d / "recording.rrd").stat().st_size for n, d in long_runs.items()}
    # 4x the samples, the same drawing: within 15 %, and far below one float per sample
    assert sizes[4 * N_LONG] < 1.15 * sizes[N_LONG], sizes
    assert sizes[4 * N_LONG] < 4 * N_LONG * 2 * 8 / 4, sizes
    series = _recorded(long_runs[4 * N_LONG] / "recording.rrd")
    stored = pl.read_parquet(long_runs[4 * N_LONG] / "signals.parquet")
    for name in ("u", "y"):
        raw = series[f"/signals/raw/{name}"]
        assert raw.size <= DISPLAY_POINTS
        ref = stored.filter(pl.col("signal") == name)["raw"]
        assert np.nanmax(raw) == ref.max() and np.nanmin(raw) == ref.min()  # spikes drawn
        assert series[f"/signals/masked/{name}"].size <= DISPLAY_POINTS // 2


# --------------------------------------------------------------------------- stage lines


def test_every_stage_of_a_run_ends_with_a_done_line(tmp_path):
    from tests.conftest import write_job, write_plant_csv
    from tests.flows.test_cli_hostile_inputs import cli

    write_plant_csv(tmp_path / "drop" / "a.csv", seed=41, hours=2.0)
    job = write_job(tmp_path, rerun={"enabled": True})
    rc, _, err = cli("run", "--no-prefect", str(job))
    assert rc == 0, err[-3000:]
    lines = re.findall(r"^\[\s*[\d.]+ s\] ([\w/.-]+): (start|done in [\d.]+ s)", err, re.MULTILINE)
    started = [s for s, what in lines if what == "start"]
    done = [s for s, what in lines if what.startswith("done")]
    for stage in ("ingest", "prepare", "search", "estimate", "summarise", "store",
                  "store/tables", "store/html_report", "store/rerun", "store/commit"):
        assert stage in started, err[-3000:]
    assert sorted(started) == sorted(done)  # every stage that starts ends with its done line
    assert "stage times: ingest" in err and "store " in err
