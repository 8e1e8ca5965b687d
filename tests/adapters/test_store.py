"""Tests of the result store: atomic run directories, manifest, catalog, claims, schema.

The stored tables are synthetic but physical: the step response of a first-order lag
(gain K, time constant tau) sampled at dt, whose value at every lag is known in closed form.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import os
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest

import pipeline
from pipeline.adapters import store as store_mod
from pipeline.adapters.store import ResultSchemaError, ResultStore, to_json_text
from pipeline.errors import ConfigError, DataQualityError

GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "result_schemas.json"
T0_S = 1_795_000_000.0  # 2026-11-18T.. UTC, a fixed "now" for the injected clock


class FakeClock:
    """Settable Unix-seconds clock, so lease expiry and run order need no sleeping."""

    def __init__(self, now_s: float = T0_S) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


# --------------------------------------------------------------------------- synthetic results


def first_order_step(*, gain: float, tau_s: float, dt_s: float, n_p: int) -> np.ndarray:
    """Step response of K/(tau s + 1) at t = lag*dt, lag = 1..n_p (exact, zero-order hold)."""
    t_s = dt_s * np.arange(1, n_p + 1)
    return gain * (1.0 - np.exp(-t_s / tau_s))


def step_frame(windows: tuple[str, ...] = ("all", "w0", "w1"), *, n_p: int = 12, dt_s: float = 5.0) -> pl.DataFrame:
    """step_responses table for two pairs of first-order lags (exact values, windows perturbed)."""
    pairs = {("pressure", "steam_flow"): (-0.8, 40.0), ("level", "feedwater"): (1.5, 20.0)}
    parts = []
    for w_index, window in enumerate(windows):
        for (output, inp), (gain, tau_s) in pairs.items():
            step = first_order_step(gain=gain * (1 + 0.05 * w_index), tau_s=tau_s, dt_s=dt_s, n_p=n_p)
            parts.append(
                pl.DataFrame(
                    {
                        "window": window,
                        "output": output,
                        "input": inp,
                        "lag": np.arange(1, n_p + 1, dtype=np.int32),
                        "time_s": dt_s * np.arange(n_p, dtype=np.float64),
                        "delta_h": np.diff(step, prepend=0.0),
                        "step": step,
                        "step_std": np.full(n_p, 0.02 * abs(gain) * (1 + w_index)),
                        "n_p": np.full(n_p, n_p, dtype=np.int32),
                        "n_d": np.zeros(n_p, dtype=np.int32),
                        "dt_s": np.full(n_p, dt_s),
                    }
                )
            )
    return pl.concat(parts)


def signals_frame(n: int = 50) -> pl.DataFrame:
    start = np.datetime64("2026-03-01T00:00:00", "us")
    times = start + np.arange(n) * np.timedelta64(5, "s")
    rows = []
    for name, role in (("steam_flow", "input"), ("pressure", "output")):
        raw = 100.0 + np.sin(np.arange(n) / 5.0)
        raw[7] = np.nan  # a missing sample: stored as null
        good = np.ones(n, dtype=bool)
        good[[7, 8, 9]] = False
        rows.append(
            pl.DataFrame(
                {
                    "time": times,
                    "signal": name,
                    "role": role,
                    "raw": raw,
                    "conditioned": np.where(good, raw - 100.0, np.nan),
                    "good": good,
                }
            ).with_columns(
                pl.col("time").dt.replace_time_zone("UTC"),
                pl.col("raw").fill_nan(None),
                pl.col("conditioned").fill_nan(None),
            )
        )
    return pl.concat(rows)


def discrepancy_series_frame(n: int = 30) -> pl.DataFrame:
    """A discrepancy run's series: one output, warm-up, fit and held-out parts."""
    t = np.arange(n, dtype=float)
    y = np.sin(t / 5.0)
    return pl.DataFrame({
        "output": ["pressure"] * n, "time_s": t,
        "part": ["warmup"] * 5 + ["fit"] * 15 + ["holdout"] * 10,
        "measured": y, "nominal": 0.9 * y, "augmented": 0.99 * y,
        "residual_before": 0.1 * y, "residual_after": 0.01 * y, "rolling_rms": np.abs(y)})


def residuals_frame(n: int = 40) -> pl.DataFrame:
    start = np.datetime64("2026-03-01T00:00:00", "us")
    rng = np.random.default_rng(7)
    return pl.DataFrame(
        {
            "window": "all",
            "time": start + np.arange(n) * np.timedelta64(5, "s"),
            "output": "pressure",
            "residual": rng.normal(0.0, 0.1, n),
        }
    ).with_columns(pl.col("time").dt.replace_time_zone("UTC"))


def write_input(tmp_path: Path, name: str = "export.csv", text: str = "time,tag,value\n0,FI-101,1.0\n") -> Path:
    path = tmp_path / "inputs" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def make_run(store: ResultStore, job: str, *, value: float, tmp_path: Path, run_id: str | None = None) -> str:
    """One complete run with a static-gain metric ``value`` for pressure <- steam_flow."""
    with store.new_run(job, run_id=run_id, config={"job": job}, inputs=[write_input(tmp_path)]) as run:
        run.write_step_responses(step_frame(("all",)))
        run.add_metrics(
            [
                {"window": "all", "output": "pressure", "input": "steam_flow", "metric": "static_gain", "value": value},
                {"window": "all", "output": "pressure", "input": "steam_flow", "metric": "agreement_verdict", "value": "pass"},
            ]
        )
    return run.run_id


def dirs_under(path: Path) -> list[str]:
    return sorted(p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_dir())


# --------------------------------------------------------------------------- golden schema


def test_storage_format_matches_golden_file(tmp_path):
    """The declared schemas, manifest keys and catalog tables equal the golden file.

    A deliberate format change must update tests/golden/result_schemas.json (and bump
    FORMAT_VERSION); an accidental one fails here.
    """
    golden = json.loads(GOLDEN.read_text())
    declared = store_mod.schema_description()
    assert declared == {k: golden[k] for k in ("format_version", "parquet", "json", "manifest_keys",
                                               "catalog")}

    # The files as written (read back by an independent reader: pyarrow) have the same
    # columns, polars dtypes and parquet physical types.
    store = ResultStore(tmp_path / "storage")
    with store.new_run("golden", config={}, inputs=[]) as run:
        run.write_step_responses(step_frame())
        run.write_signals(signals_frame())
        run.write_residuals(residuals_frame())
        run.write_parquet("discrepancy_series.parquet", discrepancy_series_frame())
    for name, spec in golden["parquet"].items():
        path = run.path / name
        read_back = pl.read_parquet_schema(path)
        assert [[c, str(t)] for c, t in read_back.items()] == [[c, t] for c, t, _ in spec["columns"]]
        parquet_schema = pq.ParquetFile(path).schema
        physical = {parquet_schema.column(i).name: parquet_schema.column(i).physical_type for i in range(len(parquet_schema))}
        assert physical == golden["parquet_physical"][name]
    manifest = json.loads((run.path / "manifest.json").read_text())
    assert sorted(manifest) == golden["manifest_keys"]


# --------------------------------------------------------------------------- runs


def test_run_is_written_atomically_with_verified_manifest(tmp_path):
    clock = FakeClock()
    store = ResultStore(tmp_path / "storage", clock=clock)
    input_path = write_input(tmp_path, text="time,tag,value\n" + "".join(f"{i},FI-101,{i * 0.5}\n" for i in range(100)))
    steps = step_frame()
    checks = {
        "dt_s": np.float64(5.0),
        "alpha_t": {"steam_flow": np.float32(0.25), "pressure": float("nan")},
        "n_p": np.int64(12),
        "trace": np.array([1.0, np.inf, -np.inf, 2.5]),
        "verdict": "pass",
        "masked": {"pressure": np.int32(3)},
    }
    with store.new_run("boiler", config={"job": "boiler", "dt_s": 5.0}, inputs=[input_path]) as run:
        tmp_dir = run.path
        assert tmp_dir.name.startswith(f".tmp-{run.run_id}-") and tmp_dir.parent == store.root / "boiler"
        run.write_step_responses(steps)
        run.record_timing("estimate", 0.5)
        run.record_timing("estimate", 0.25)  # a stage timed twice adds up
        run.write_signals(signals_frame())
        run.write_residuals(residuals_frame())
        run.write_checks(checks)
        run.write_report("# boiler\nall pairs pass\n")
        run.record_timing("ingest", 1.25)
        # Nothing is visible under the final name while the run is being written.
        assert not (store.root / "boiler" / run.run_id).exists()
        assert store.list_runs("boiler").height == 0

    final = store.root / "boiler" / run.run_id
    assert run.path == final and final.is_dir() and not tmp_dir.exists()
    assert dirs_under(store.root) == ["boiler", f"boiler/{run.run_id}"]
    # run id: sortable UTC timestamp of the (fake) clock + 6 hex digits
    stamp, suffix = run.run_id.split("-")
    assert stamp == time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(T0_S))
    assert len(suffix) == 6 and int(suffix, 16) >= 0

    manifest = json.loads((final / "manifest.json").read_text())
    assert manifest["job"] == "boiler" and manifest["run_id"] == run.run_id and manifest["status"] == "ok"
    assert manifest["package_version"] == pipeline.__version__
    assert manifest["config"] == {"job": "boiler", "dt_s": 5.0}
    assert manifest["timings_s"]["ingest"] == 1.25 and manifest["timings_s"]["estimate"] == 0.75
    assert manifest["inputs"] == [
        {
            "path": str(input_path),
            "sha256": hashlib.sha256(input_path.read_bytes()).hexdigest(),
            "bytes": len(input_path.read_bytes()),
        }
    ]
    # every file in the run dir except the manifest, with its hashlib sha256
    on_disk = sorted(p.name for p in final.iterdir() if p.name != "manifest.json")
    assert [f["name"] for f in manifest["files"]] == on_disk
    assert on_disk == ["checks.json", "report.md", "residuals.parquet", "signals.parquet", "step_responses.parquet"]
    for entry in manifest["files"]:
        data = (final / entry["name"]).read_bytes()
        assert entry["sha256"] == hashlib.sha256(data).hexdigest() and entry["bytes"] == len(data)

    stored = store.read_run("boiler", run.run_id)
    assert stored.step_responses.equals(steps)
    assert stored.signals.equals(signals_frame()) and stored.residuals.equals(residuals_frame())
    assert stored.report == "# boiler\nall pairs pass\n"
    assert stored.checks == {
        "alpha_t": {"pressure": None, "steam_flow": 0.25},
        "dt_s": 5.0,
        "masked": {"pressure": 3},
        "n_p": 12,
        "trace": [1.0, None, None, 2.5],
        "verdict": "pass",
    }
    # the first-order lag survives the round trip exactly: step(lag) = K (1 - exp(-lag dt / tau))
    pair = stored.step_responses.filter(window="all", output="level", input="feedwater")
    np.testing.assert_array_equal(pair["step"].to_numpy(), 1.5 * (1 - np.exp(-5.0 * np.arange(1, 13) / 20.0)))

    runs = store.list_runs("boiler")
    assert runs.select("job", "run_id", "status", "n_inputs").rows() == [("boiler", run.run_id, "ok", 1)]
    assert runs["path"][0] == str(final)
    assert runs["input_sha256s"][0].to_list() == [manifest["inputs"][0]["sha256"]]
    assert runs["created_utc"][0].timestamp() == pytest.approx(T0_S, abs=1e-6)


def test_checks_json_is_sorted_pretty_and_strict():
    text = to_json_text({"b": np.float32(np.nan), "a": [np.int64(3), np.inf, np.bool_(True)], "c": {2: "x"}})
    assert text == '{\n  "a": [\n    3,\n    null,\n    true\n  ],\n  "b": null,\n  "c": {\n    "2": "x"\n  }\n}\n'
    with pytest.raises(TypeError, match=r"\$\.obj: value of type object is not JSON-serialisable"):
        to_json_text({"obj": object()})


def test_exception_inside_run_leaves_no_directory(tmp_path):
    store = ResultStore(tmp_path / "storage")
    with pytest.raises(RuntimeError, match="estimator blew up"):
        with store.new_run("boiler", config={}, inputs=[]) as run:
            run.write_step_responses(step_frame())
            run.write_report("partial")
            raise RuntimeError("estimator blew up")
    assert dirs_under(store.root) == ["boiler"]  # neither the run dir nor the temp dir
    assert store.list_runs("boiler").height == 0
    with pytest.raises(ConfigError, match="no run boiler/"):
        store.read_run("boiler", run.run_id)


def test_schema_violation_aborts_the_run(tmp_path):
    store = ResultStore(tmp_path / "storage")
    bad_dtype = step_frame().with_columns(pl.col("lag").cast(pl.Int64))
    with pytest.raises(ResultSchemaError, match=r"lag: Int64 \(expected Int32\).*pl\.col\('lag'\)\.cast\(pl\.Int32\)"):
        with store.new_run("boiler", config={}, inputs=[]) as run:
            run.write_step_responses(bad_dtype)
    assert dirs_under(store.root) == ["boiler"]

    cases = [
        (step_frame().drop("dt_s"), r"missing \['dt_s'\], unexpected \[\]"),
        (step_frame().with_columns(extra=pl.lit(1.0)), r"missing \[\], unexpected \['extra'\]"),
        (step_frame().with_columns(window=pl.lit("window-3")), r"column 'window' must be 'all' or 'w<k>'"),
        (step_frame().with_columns(lag=pl.lit(0, pl.Int32)), r"column 'lag' must be >= 1"),
        (pl.concat([step_frame(), step_frame().head(1)]), r"1 duplicate row\(s\) for the key"),
        (step_frame().with_columns(step=pl.lit(None, pl.Float64)), r"column 'step' has 72 null value\(s\) of 72"),
    ]
    with store.new_run("boiler", config={}, inputs=[]) as run:
        for frame, message in cases:
            with pytest.raises(ResultSchemaError, match=message):
                run.write_step_responses(frame)
        with pytest.raises(ResultSchemaError, match=r"column 'role' must be 'input', 'output' or 'instrument'"):
            run.write_signals(signals_frame().with_columns(role=pl.lit("disturbance")))
        # column order is normalised, dtypes are not
        run.write_step_responses(step_frame().select(reversed(step_frame().columns)))
    assert pl.read_parquet(run.path / "step_responses.parquet").columns == list(store_mod.STEP_RESPONSES_SCHEMA)


@pytest.mark.parametrize("job", ["..", ".", "../evil", "a/b", ".hidden", "", "x y", "catalog.sqlite"])
def test_job_names_cannot_escape_the_root(tmp_path, job):
    store = ResultStore(tmp_path / "storage")
    with pytest.raises(ConfigError, match="is not allowed|collides with the catalog"):
        with store.new_run(job, config={}, inputs=[]):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["storage"]
    assert sorted(p.name for p in store.root.iterdir() if p.is_dir()) == []


def test_symlinked_job_dir_pointing_outside_is_refused(tmp_path):
    store = ResultStore(tmp_path / "storage")
    outside = tmp_path / "outside"
    outside.mkdir()
    (store.root / "sneaky").symlink_to(outside)
    with pytest.raises(ConfigError, match="outside the storage root"):
        with store.new_run("sneaky", config={}, inputs=[]):
            pass
    assert list(outside.iterdir()) == []


def test_discrepancy_files_are_schema_checked_and_a_bad_one_leaves_no_run(tmp_path):
    """discrepancy.json needs its top-level keys and a known verdict, and
    discrepancy_series.parquet its schema; a refused file aborts the whole run."""
    from pipeline.adapters.store import ResultSchemaError

    store = ResultStore(tmp_path / "storage")
    good = {k: None for k in ("job", "run_id", "kind", "model", "inputs", "outputs", "data",
                              "effect", "candidates", "gap", "localization", "dt_s",
                              "effects", "minor_effects")}
    with pytest.raises(ResultSchemaError, match=r"missing top-level key\(s\) \['verdict'\]"):
        with store.new_run("disc", run_id="r1", config={}, inputs=[]) as run:
            run.write_json("discrepancy.json", good)
    with pytest.raises(ResultSchemaError, match=r"verdict 'found_it' is not one of"):
        with store.new_run("disc", run_id="r2", config={}, inputs=[]) as run:
            run.write_json("discrepancy.json", {**good, "verdict": "found_it"})
    with pytest.raises(ResultSchemaError, match=r"column 'part' must be 'warmup', 'fit' or"):
        with store.new_run("disc", run_id="r3", config={}, inputs=[]) as run:
            frame = discrepancy_series_frame().with_columns(pl.lit("later").alias("part"))
            run.write_parquet("discrepancy_series.parquet", frame)
    assert store.list_runs("disc").height == 0
    assert not any((store.root / "disc").glob("r*"))
    with store.new_run("disc", run_id="ok", config={}, inputs=[]) as run:
        run.write_json("discrepancy.json", {**good, "verdict": "no_significant_effect"})
        run.write_parquet("discrepancy_series.parquet", discrepancy_series_frame())
    assert store.list_runs("disc")["run_id"].to_list() == ["ok"]


def test_extra_files_bad_names_and_duplicate_run_ids(tmp_path):
    store = ResultStore(tmp_path / "storage")
    with store.new_run("disc", run_id="r1", config={}, inputs=[]) as run:
        run.write_json("effects.json", {"effects": [{"name": "dead_time", "delay_s": np.float64(8.0)}]})
        run.write_text("model_augmented.yaml", "model:\n  name: x\n")
        run.write_parquet("extra_table.parquet", pl.DataFrame({"a": [1, 2]}))
        (run.path / "recording.rrd").write_bytes(b"written by another adapter")
        for bad in ("../x.json", "sub/x.json", ".hidden"):
            with pytest.raises(ConfigError, match="result file name"):
                run.write_text(bad, "x")
        with pytest.raises(ConfigError, match="written by the store itself"):
            run.write_json("manifest.json", {})
    manifest = json.loads((run.path / "manifest.json").read_text())
    assert [f["name"] for f in manifest["files"]] == [
        "effects.json",
        "extra_table.parquet",
        "model_augmented.yaml",
        "recording.rrd",
    ]
    assert json.loads((run.path / "effects.json").read_text()) == {"effects": [{"delay_s": 8.0, "name": "dead_time"}]}
    with pytest.raises(ConfigError, match="already exists"):
        with store.new_run("disc", run_id="r1", config={}, inputs=[]):
            pass
    with pytest.raises(Exception, match="writer is closed"):
        run.write_text("late.txt", "x")


KILLED_WRITER = textwrap.dedent(
    """
    import os, sys
    from pipeline.adapters.store import ResultStore
    store = ResultStore(sys.argv[1])
    with store.new_run("boiler", run_id="killed", config={}, inputs=[]) as run:
        run.write_report("half-written")
        os._exit(9)  # like SIGKILL: no exception handler, no cleanup
    """
)


def test_killed_writer_leaves_only_an_ignored_temp_dir(tmp_path):
    root = tmp_path / "storage"
    store = ResultStore(root)
    make_run(store, "boiler", value=1.0, tmp_path=tmp_path, run_id="good")
    proc = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(root)], cwd=Path(pipeline.__file__).parents[1])
    assert proc.returncode == 9
    leftovers = [p.name for p in (root / "boiler").iterdir() if p.name.startswith(".tmp-killed-")]
    assert len(leftovers) == 1
    assert store.list_runs("boiler")["run_id"].to_list() == ["good"]
    assert store.reindex().n_runs == 1 and store.list_runs("boiler")["run_id"].to_list() == ["good"]

    assert store.clean_stale(older_than_s=3600.0) == []  # fresh: could be a live writer
    assert ResultStore(root).root == root  # opening again: still fresh, kept
    assert [p.name for p in (root / "boiler").iterdir() if p.name.startswith(".tmp-")] == leftovers
    # an hour later, opening the store removes what the killed writer left
    ResultStore(root, clock=lambda: time.time() + 7200.0)
    assert sorted(p.name for p in (root / "boiler").iterdir()) == ["good"]


def test_read_run_detects_modified_files(tmp_path):
    store = ResultStore(tmp_path / "storage")
    run_id = make_run(store, "boiler", value=2.0, tmp_path=tmp_path)
    path = store.root / "boiler" / run_id / "step_responses.parquet"
    edited = step_frame(("all",)).with_columns(pl.col("step") * 2.0)  # a valid but edited table
    edited.write_parquet(path)
    with pytest.raises(DataQualityError, match="step_responses.parquet has sha256 .* modified after the run"):
        store.read_run("boiler", run_id)
    assert store.read_run("boiler", run_id, verify=False).step_responses.equals(edited)


# --------------------------------------------------------------------------- catalog


def test_trend_returns_values_in_run_order(tmp_path):
    clock = FakeClock()
    store = ResultStore(tmp_path / "storage", clock=clock)
    # written out of time order: insertion order must not leak into the result
    written = [(300.0, "c", 3.0), (100.0, "a", 1.0), (200.0, "b", 2.0)]
    for offset_s, run_id, gain in written:
        clock.now_s = T0_S + offset_s
        make_run(store, "boiler", value=gain, tmp_path=tmp_path, run_id=run_id)
    clock.now_s = T0_S + 400.0
    make_run(store, "other_job", value=99.0, tmp_path=tmp_path)

    trend = store.trend("boiler", output="pressure", input="steam_flow", metric="static_gain")
    assert trend["run_id"].to_list() == ["a", "b", "c"]
    assert trend["value"].to_list() == [1.0, 2.0, 3.0]
    assert [t.timestamp() for t in trend["created_utc"]] == [T0_S + 100.0, T0_S + 200.0, T0_S + 300.0]
    verdicts = store.trend("boiler", metric="agreement_verdict")
    assert verdicts["label"].to_list() == ["pass"] * 3 and verdicts["value"].null_count() == 3
    assert store.trend("boiler", window="w0").height == 0
    assert store.list_runs("boiler")["run_id"].to_list() == ["a", "b", "c"]


def test_reindex_rebuilds_catalog_after_failed_insert_and_loss(tmp_path):
    store = ResultStore(tmp_path / "storage", clock=FakeClock())
    make_run(store, "boiler", value=1.0, tmp_path=tmp_path, run_id="r1")
    # A stale catalog row with the id of the next run makes the insert fail after the rename.
    con = sqlite3.connect(store.catalog_path)
    con.execute("INSERT INTO runs VALUES ('boiler', 'r2', 'ok', '2000-01-01T00:00:00.000000Z', 'x', 0, '[]')")
    con.commit()
    con.close()
    with pytest.raises(sqlite3.IntegrityError, match="UNIQUE") as info:
        make_run(store, "boiler", value=2.0, tmp_path=tmp_path, run_id="r2")
    assert any("plantdyn reindex" in note for note in info.value.__notes__)
    assert (store.root / "boiler" / "r2" / "manifest.json").is_file()  # rename happened first

    before = store.trend("boiler", metric="static_gain")
    assert before["value"].to_list() == [1.0]  # r2's metrics were never inserted
    result = store.reindex()
    assert result.n_runs == 2 and result.skipped == ()
    assert store.trend("boiler", metric="static_gain")["value"].to_list() == [1.0, 2.0]

    # The catalog file can be lost entirely and rebuilt from the manifests.
    expected = store.list_runs("boiler")
    for suffix in ("", "-wal", "-shm"):
        Path(f"{store.catalog_path}{suffix}").unlink(missing_ok=True)
    (store.root / "boiler" / "junk").mkdir()  # not a run: skipped with a reason
    rebuilt = ResultStore(store.root)
    result = rebuilt.reindex()
    assert result.n_runs == 2 and len(result.skipped) == 1 and "junk" in result.skipped[0]
    assert rebuilt.list_runs("boiler").equals(expected)
    assert rebuilt.trend("boiler", metric="static_gain")["value"].to_list() == [1.0, 2.0]


def test_metrics_are_validated(tmp_path):
    store = ResultStore(tmp_path / "storage")
    with store.new_run("boiler", config={}, inputs=[]) as run:
        with pytest.raises(ConfigError, match=r"metrics\[0\]: keys must be .* missing \['window'\]"):
            run.add_metrics([{"output": "p", "input": "f", "metric": "gain", "value": 1.0}])
        row = {"window": "all", "output": "p", "input": "f", "metric": "gain", "value": math.nan}
        run.add_metrics([row])
        with pytest.raises(ConfigError, match="recorded twice"):
            run.add_metrics([row])
    assert store.trend("boiler")["value"].to_list() == [None]  # NaN stored as null


# --------------------------------------------------------------------------- processed files


def test_claim_lifecycle_and_expiry(tmp_path):
    clock = FakeClock()
    root = tmp_path / "storage"
    first = ResultStore(root, claim_lease_s=60.0, clock=clock)
    second = ResultStore(root, claim_lease_s=60.0, clock=clock)
    sha = hashlib.sha256(b"export 1").hexdigest()

    assert first.claim_file("boiler", sha, "exports/a.csv") is True
    assert second.claim_file("boiler", sha, "exports/a.csv") is False  # live claim
    assert first.claim_file("other_job", sha, "exports/a.csv") is True  # per job

    clock.now_s += 50.0
    assert first.heartbeat_file("boiler", sha) is True
    clock.now_s += 59.0  # 109 s after the claim, 59 s after the heartbeat: still live
    assert second.claim_file("boiler", sha, "exports/a.csv") is False
    clock.now_s += 2.0  # heartbeat 61 s old > lease: the first owner is presumed dead
    assert second.claim_file("boiler", sha, "exports/a.csv") is True
    assert first.heartbeat_file("boiler", sha) is False  # no longer the owner

    row = second.processed("boiler").row(0, named=True)
    assert (row["status"], row["attempts"], row["run_id"]) == ("running", 2, None)

    second.finish_file("boiler", sha, None, "failed", error="IngestError: truncated file")
    row = second.processed("boiler").row(0, named=True)
    assert (row["status"], row["error"]) == ("failed", "IngestError: truncated file")
    assert row["processed_utc"].timestamp() == pytest.approx(clock.now_s, abs=1e-6)
    assert first.claim_file("boiler", sha, "exports/a.csv") is True  # failures are retried
    first.finish_file("boiler", sha, "20261122T031500Z-a1b2c3", "ok")
    clock.now_s += 10 * 86400.0
    assert second.claim_file("boiler", sha, "exports/a.csv") is False  # ok is final
    row = first.processed("boiler").row(0, named=True)
    assert (row["status"], row["run_id"], row["attempts"], row["error"]) == ("ok", "20261122T031500Z-a1b2c3", 3, None)

    with pytest.raises(ConfigError, match="was never claimed"):
        first.finish_file("boiler", "0" * 64, None, "ok")
    with pytest.raises(ConfigError, match="file status 'running'"):
        first.finish_file("boiler", sha, None, "running")


N_FILES = 40


def _claim_all(root: str, barrier, queue) -> None:
    try:
        store = ResultStore(root, busy_timeout_s=60.0)
        won = []
        for i in range(N_FILES):
            barrier.wait()  # both processes go for the same file at the same moment
            if store.claim_file("nightly", f"{i:064x}", f"exports/{i}.csv"):
                won.append(i)
        # and write runs concurrently, to exercise concurrent catalog inserts
        for k in range(3):
            with store.new_run("nightly", config={"k": k}, inputs=[]) as run:
                run.write_report(f"{os.getpid()} {k}")
        queue.put(won)
    except BaseException as exc:  # report, so the parent fails fast instead of waiting
        barrier.abort()
        queue.put(f"{type(exc).__name__}: {exc}")


def test_concurrent_claims_from_two_processes_never_both_win(tmp_path):
    root = tmp_path / "storage"
    ResultStore(root)
    ctx = multiprocessing.get_context("spawn")  # no fork of a process with polars threads
    barrier, queue = ctx.Barrier(2, timeout=60), ctx.Queue()
    procs = [ctx.Process(target=_claim_all, args=(str(root), barrier, queue), daemon=True) for _ in range(2)]
    try:
        for p in procs:
            p.start()
        results = [queue.get(timeout=120) for _ in procs]
        for p in procs:
            p.join(timeout=60)
            assert p.exitcode == 0
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
    errors = [r for r in results if isinstance(r, str)]
    assert not errors, errors
    won_a, won_b = (set(r) for r in results)
    assert won_a.isdisjoint(won_b)
    assert won_a | won_b == set(range(N_FILES))
    store = ResultStore(root)
    processed = store.processed("nightly")
    assert processed.height == N_FILES and set(processed["attempts"]) == {1}
    assert len(set(processed["owner"])) == (2 if won_a and won_b else 1)
    assert store.list_runs("nightly").height == 6
