"""Writes only where they belong (issue 33, build 4), driven through the CLI as a user
types it (in-process ``flows.cli.main``).

Every case is measured: exit 2, one message saying what, where and the fix, and nothing
written or replaced — the folder's listing (names, kinds, sizes, mtimes) and each
special file's kind (``stat.S_ISFIFO`` / ``S_ISLNK`` / ``S_ISDIR``) are compared before and
after.  Special files are FIFOs (``os.mkfifo``), symbolic links to FIFOs and folders made
in pytest's private ``tmp_path``; a device node cannot be made without root, and the rule
is decided on ``stat.S_ISREG`` alone, so a FIFO stands for it.  Nothing under ``/dev`` or
anywhere outside ``tmp_path`` is touched.

The store: one job (``plant``, a 1-hour first-order plant) run twice once per module with
``plantdyn run --no-prefect``; each test works on its own copy.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import sqlite3
import stat
from pathlib import Path

import pytest

from flows.cli import main
from tests.conftest import write_job, write_plant_csv

LONG = "o" * 300


def cli(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def listing(folder: Path) -> list[tuple]:
    """Every entry under ``folder``: path, kind, size, mtime (links not followed).  SQLite's
    own ``catalog.sqlite-wal``/``-shm`` are left out: any reader of a WAL database makes
    them (a command about to write checks its catalog that way); they hold no data."""
    out = []
    for p in sorted(folder.rglob("*")):
        if p.name.endswith(("catalog.sqlite-wal", "catalog.sqlite-shm")):
            continue
        st = p.lstat()
        out.append((p.relative_to(folder).as_posix(), stat.S_IFMT(st.st_mode), st.st_size,
                    st.st_mtime_ns))
    return out


def refused(rc: int, out: str, err: str, *needles: str) -> None:
    """Exit 2, one message with every needle, no traceback, nothing on stdout."""
    assert rc == 2, err[-3000:]
    assert "Traceback" not in err and err.count("plantdyn: error:") == 1, err[-3000:]
    assert out == "", out[-2000:]
    for needle in needles:
        assert needle in err, err


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("safe_base")
    write_plant_csv(folder / "drop" / "export.csv", seed=21, hours=1.0)
    job = write_job(folder)
    for _ in range(2):
        rc, _, err = cli("run", "--no-prefect", job)
        assert rc == 0, err[-3000:]
    return folder


@pytest.fixture
def site(base, tmp_path) -> Path:
    """A private copy of the job folder (job.yaml, drop/, storage/)."""
    copy = tmp_path / "site"
    shutil.copytree(base, copy, symlinks=True)
    return copy


def runs_of(site: Path) -> list[Path]:
    return sorted(p for p in (site / "storage" / "plant").iterdir() if p.is_dir())


def special_files(folder: Path) -> dict[str, Path]:
    """A FIFO, a symbolic link to it, and a folder, in ``folder``."""
    fifo = folder / "pipe.csv"
    os.mkfifo(fifo)
    link = folder / "link.csv"
    link.symlink_to(fifo)
    directory = folder / "dir.csv"
    directory.mkdir()
    return {"FIFO": fifo, "link": link, "folder": directory}


def kinds(paths: dict[str, Path]) -> dict[str, int]:
    return {k: stat.S_IFMT(p.lstat().st_mode) for k, p in paths.items()}


# ------------------------------------------------------------------- special files
@pytest.mark.parametrize("which, says", [
    ("FIFO", "is a FIFO (named pipe), not a regular file"),
    ("link", "is a symbolic link (to "),
    ("folder", "is a folder, not a regular file")])
def test_export_never_replaces_a_special_file_even_with_force(site, tmp_path, which, says):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    targets = special_files(out_dir)
    if which == "folder":  # a folder given as --out is where the default name goes: make
        name = f"plant_{runs_of(site)[0].name}.csv"  # that name a folder
        (out_dir / name).mkdir()
        targets["folder"], given = out_dir / name, out_dir
    else:
        given = targets[which]
    before, types = listing(out_dir), kinds(targets)
    assert not any(stat.S_ISREG(t) for t in types.values())
    refused(*cli("export", runs_of(site)[0], "--format", "csv", "--out", given, "--force"),
            says, "another --out")
    assert listing(out_dir) == before and kinds(targets) == types
    assert stat.S_ISFIFO(targets["FIFO"].lstat().st_mode)


def test_export_refuses_a_link_to_a_regular_file_and_keeps_it(site, tmp_path):
    real = tmp_path / "real.csv"
    real.write_text("mine")
    link = tmp_path / "model.csv"
    link.symlink_to(real)
    refused(*cli("export", runs_of(site)[0], "--format", "csv", "--out", link, "--force"),
            f"--out {link} is a symbolic link (to {real})")
    assert link.is_symlink() and real.read_text() == "mine"


@pytest.mark.parametrize("which", ["FIFO", "link", "folder"])
@pytest.mark.parametrize("force", [False, True])
def test_runs_plot_never_replaces_a_special_file(site, tmp_path, which, force):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    targets = special_files(out_dir)
    before, types = listing(out_dir), kinds(targets)
    store_before = listing(site / "storage")
    argv = ["runs", "plant", "--storage", site / "storage", "--plot", targets[which]]
    refused(*cli(*argv, *(["--force"] if force else [])), f"--plot {targets[which]} is a ",
            "give another --plot")
    assert listing(out_dir) == before and kinds(targets) == types
    assert listing(site / "storage") == store_before  # not even the default figure


def test_runs_plot_replaces_a_regular_file_only_with_force(site, tmp_path):
    png = tmp_path / "trend.png"
    png.write_bytes(b"old")
    argv = ["runs", "plant", "--storage", site / "storage", "--plot", png]
    refused(*cli(*argv), f"--plot {png} exists; pass --force to replace it")
    assert png.read_bytes() == b"old"
    rc, out, err = cli(*argv, "--force")
    assert rc == 0, err[-2000:]
    assert f"trend plot: {png}" in out and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["site", "trend.png"]


def test_the_default_figure_is_not_written_through_a_fifo(site):
    fig = site / "storage" / "plant" / "trend.png"
    os.mkfifo(fig)
    before = listing(site / "storage")
    refused(*cli("runs", "plant", "--storage", site / "storage"),
            f"the figure {fig} is a FIFO (named pipe)", "give --plot FILE (or --no-plot)")
    assert listing(site / "storage") == before and stat.S_ISFIFO(fig.lstat().st_mode)


# ------------------------------------------------------------------ built names
@pytest.mark.parametrize("key, value", [("job", "../../x"), ("run_id", "../esc"),
                                        ("job", "a/b"), ("run_id", ".hidden")])
def test_default_export_name_is_built_from_safe_parts_only(site, tmp_path, monkeypatch, key,
                                                           value):
    run = runs_of(site)[0]
    manifest = json.loads((run / "manifest.json").read_text())
    manifest[key] = value
    (run / "manifest.json").write_text(json.dumps(manifest))
    here = tmp_path / "a" / "b" / "c"
    here.mkdir(parents=True)
    monkeypatch.chdir(here)
    before = listing(tmp_path)
    refused(*cli("export", run, "--format", "csv"),
            f"has {key} {value!r}, which cannot be part of a file name",
            "give the file with --out FILE")
    assert listing(tmp_path) == before  # nothing in the folder, nothing above it
    rc, out, err = cli("export", run, "--format", "csv", "--out", here / "model.csv")
    assert rc == 0 and out.strip() == str(here / "model.csv"), err[-2000:]


# ------------------------------------------------------------ inside the store
def test_out_inside_another_run_or_over_the_catalog_is_refused(site):
    first, second = runs_of(site)
    catalog = site / "storage" / "catalog.sqlite"
    before = listing(site / "storage")
    refused(*cli("export", first, "--format", "csv", "--out", second / "model.csv"),
            f"is inside the run directory {second}", "immutable")
    refused(*cli("export", first, "--format", "json", "--out", second, "--force"),
            f"is inside the run directory {second}")
    refused(*cli("export", first, "--format", "csv", "--out", catalog, "--force"),
            "would replace the results catalog (catalog.sqlite)")
    refused(*cli("runs", "plant", "--storage", site / "storage", "--plot", catalog,
                 "--force"), "would replace the results catalog")
    assert listing(site / "storage") == before


# --------------------------------------------------------------------- reindex
def test_reindex_refuses_a_folder_that_is_not_a_results_store(tmp_path):
    etc = tmp_path / "etc"
    (etc / "ssh").mkdir(parents=True)
    (etc / "hosts").write_text("127.0.0.1 localhost\n")
    before = listing(etc)
    refused(*cli("reindex", etc), f"storage {etc} is not a results store",
            "no catalog and no <job>/<run-id>/manifest.json run folders",
            f"pass --force to make {etc} one")
    assert listing(etc) == before and not (etc / "catalog.sqlite").exists()
    rc, out, err = cli("reindex", etc, "--force")
    assert rc == 0 and "catalog rebuilt from 0 run folder(s)" in out, err
    assert (etc / "catalog.sqlite").is_file()


def test_reindex_refuses_a_folder_with_only_a_foreign_database(tmp_path):
    folder = tmp_path / "app"
    folder.mkdir()
    con = sqlite3.connect(folder / "catalog.sqlite")
    con.execute("CREATE TABLE books (title TEXT)")
    con.commit()
    con.close()
    before = listing(folder)
    refused(*cli("reindex", folder), "is not a results store",
            "is a database of another schema (tables books", "--force")
    assert listing(folder) == before


def test_zero_byte_catalog_is_a_message_and_reindex_rebuilds_it(site):
    storage = site / "storage"
    for p in storage.glob("catalog.sqlite*"):
        p.unlink()
    (storage / "catalog.sqlite").write_bytes(b"")
    refused(*cli("runs", "plant", "--storage", storage),
            "the catalog is empty (0 bytes", f"run `plantdyn reindex {storage}`")
    before = listing(storage)  # beside run folders, a new run would hide them: refused
    refused(*cli("run", "--no-prefect", site / "job.yaml"), "the catalog is empty (0 bytes",
            f"run `plantdyn reindex {storage}`")
    assert listing(storage) == before
    rc, out, err = cli("reindex", storage)
    assert rc == 0, err[-3000:]
    aside = [p for p in storage.iterdir() if p.name.endswith(".bad")]
    assert len(aside) == 1 and aside[0].stat().st_size == 0
    assert f"moved aside to {aside[0]} (not deleted)" in out
    assert "catalog rebuilt from 2 run folder(s)" in out
    rc, out, err = cli("runs", "plant", "--storage", storage, "--no-plot")
    assert rc == 0 and all(r.name in out for r in runs_of(site)), err


def test_a_first_run_after_a_zero_byte_catalog_just_works(tmp_path):
    """What a first run that failed on a full disk leaves: a 0-byte catalog, no runs."""
    write_plant_csv(tmp_path / "drop" / "export.csv", seed=23, hours=1.0)
    job = write_job(tmp_path)
    (tmp_path / "storage").mkdir()
    (tmp_path / "storage" / "catalog.sqlite").write_bytes(b"")
    rc, out, err = cli("run", "--no-prefect", job)
    assert rc == 0, err[-3000:]
    rc, listed, err = cli("runs", "plant", "--storage", tmp_path / "storage", "--no-plot")
    assert rc == 0 and Path(out.strip().splitlines()[-1]).name in listed, err


def test_foreign_catalog_is_a_message_and_reindex_moves_it_aside(site):
    storage = site / "storage"
    catalog = storage / "catalog.sqlite"
    for p in storage.glob("catalog.sqlite*"):
        p.unlink()
    con = sqlite3.connect(catalog)
    con.execute("CREATE TABLE runs (a INTEGER)")  # the catalog's table name, not its columns
    con.execute("INSERT INTO runs VALUES (42)")
    con.commit()
    con.close()
    refused(*cli("runs", "plant", "--storage", storage),
            "the catalog is a database of another schema (table runs has columns a",
            f"`plantdyn reindex {storage}`")
    before = listing(storage)
    refused(*cli("run", "--no-prefect", site / "job.yaml"),  # before the work, not after
            "the catalog is a database of another schema", "nothing is deleted")
    assert listing(storage) == before
    rc, out, err = cli("reindex", storage)
    assert rc == 0 and "catalog rebuilt from 2 run folder(s)" in out, err[-3000:]
    aside = next(p for p in storage.iterdir() if p.name.endswith(".bad"))
    assert "moved aside to" in out and str(aside) in out
    con = sqlite3.connect(aside)  # the other program's data, whole
    assert con.execute("SELECT a FROM runs").fetchall() == [(42,)]
    con.close()
    rc, out, err = cli("runs", "plant", "--storage", storage, "--no-plot")
    assert rc == 0 and all(r.name in out for r in runs_of(site)), err


def test_a_catalog_that_is_a_fifo_is_never_touched(site):
    storage = site / "storage"
    for p in storage.glob("catalog.sqlite*"):
        p.unlink()
    os.mkfifo(storage / "catalog.sqlite")
    before = listing(storage)
    refused(*cli("reindex", storage), "the catalog is a FIFO (named pipe), not a file",
            "plantdyn does not touch it")
    refused(*cli("runs", "plant", "--storage", storage), "is a FIFO (named pipe)")
    assert listing(storage) == before


def test_reindex_skips_a_bad_manifest_and_catalogues_the_rest(site):
    storage = site / "storage"
    dup, fifo_run = runs_of(site)
    manifest = json.loads((dup / "manifest.json").read_text())
    manifest["metrics"].append(dict(manifest["metrics"][0]))
    (dup / "manifest.json").write_text(json.dumps(manifest))
    rc, out, err = cli("reindex", storage)
    assert rc == 0, err[-3000:]
    metric = "/".join(manifest["metrics"][0][k] for k in ("window", "output", "input",
                                                           "metric"))
    assert f"skipped {dup}: metric {metric} is listed twice" in out
    assert "catalog rebuilt from 1 run folder(s)" in out
    rc, out, _ = cli("runs", "plant", "--storage", storage, "--no-plot")
    assert rc == 0 and fifo_run.name in out and dup.name not in out
    # a manifest that is a FIFO is skipped, never opened (it would block forever)
    (fifo_run / "manifest.json").unlink()
    os.mkfifo(fifo_run / "manifest.json")
    rc, out, err = cli("reindex", storage)
    assert rc == 0 and f"skipped {fifo_run}: manifest.json is not a regular file" in out, err


def test_created_utc_without_fractional_seconds(site):
    storage = site / "storage"
    run = runs_of(site)[0]
    manifest = json.loads((run / "manifest.json").read_text())
    manifest["created_utc"] = manifest["created_utc"].split(".")[0] + "Z"
    (run / "manifest.json").write_text(json.dumps(manifest))
    rc, out, err = cli("reindex", storage)
    assert rc == 0 and "catalog rebuilt from 2 run folder(s)" in out, err[-3000:]
    con = sqlite3.connect(storage / "catalog.sqlite")
    stored = con.execute("SELECT created_utc FROM runs WHERE run_id = ?",
                         (run.name,)).fetchone()[0]
    assert stored == manifest["created_utc"][:-1] + ".000000Z"  # the catalog's fixed width
    con.execute("UPDATE runs SET created_utc = ? WHERE run_id = ?",
                (manifest["created_utc"], run.name))  # as an older reindex stored it
    con.commit()
    con.close()
    rc, out, err = cli("runs", "plant", "--storage", storage, "--no-plot")
    assert rc == 0 and run.name in out, err[-3000:]
    con = sqlite3.connect(storage / "catalog.sqlite")
    con.execute("UPDATE runs SET created_utc = 'yesterday' WHERE run_id = ?", (run.name,))
    con.commit()
    con.close()
    refused(*cli("runs", "plant", "--storage", storage, "--no-plot"),
            "runs of job 'plant', created_utc: 'yesterday' is not an ISO 8601 time",
            f"`plantdyn reindex {storage}`")


# ------------------------------------------------------------------ job inputs
def test_baseline_whose_manifest_is_not_json(site):
    job = write_job(site, monitor={"baseline": "first"})
    first = runs_of(site)[0]
    (first / "manifest.json").write_text("{not json")
    before = listing(site / "storage")
    refused(*cli("run", "--no-prefect", job),
            "monitor.baseline: the baseline run cannot be used",
            f"run plant/{first.name}: manifest.json is not JSON",
            "pin another run (monitor.baseline: RUN_ID)")
    assert listing(site / "storage") == before


@pytest.mark.parametrize("yaml_text, says", [
    ("source:\n  path: drop/*.csv\n  timezone: !!timestamp hello\n",
     "source.timezone: the value 'hello' (line 4, column 13) is tagged !!timestamp but is "
     "not a date or time"),
    ("source:\n  path: drop/*.csv\n  timezone: UTC\nsampling:\n  dt_s: !!float fast\n",
     "sampling.dt_s: the value 'fast' (line 6, column 9) is tagged !!float but is not a "
     "number"),
    (f"source:\n  path: drop/*.csv\n  timezone: {'A' * 300}\n",
     "source.timezone: a time zone of 300 characters"),
    (f"source:\n  path: drop/*.csv\n  timezone: Europe/{'B' * 300}\n",
     "source.timezone: a time zone of 307 characters"),
])
def test_yaml_values_that_raised_os_or_attribute_errors(tmp_path, yaml_text, says):
    job = tmp_path / "job.yaml"
    job.write_text("job: plant\n" + yaml_text + "signals:\n  inputs: {u: {tag: U.PV}}\n"
                   "  outputs: {y: {tag: Y.PV}}\nstorage: storage\n")
    refused(*cli("run", "--no-prefect", job), f"{job}", says)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["job.yaml"]


@pytest.mark.parametrize("argv, option", [
    (["export", "{run}", "--format", "csv", "--out", "{tmp}/" + LONG + ".csv"], "--out"),
    (["export", "{run}", "--format", "csv", "--out", "{tmp}/" + LONG + "/m.csv"], "--out"),
    (["export", "{tmp}/" + LONG, "--format", "csv"], "RUN_DIR"),
    (["runs", "plant", "--storage", "{storage}", "--plot", "{tmp}/" + LONG + ".png"],
     "--plot"),
    (["runs", "plant", "--storage", "{tmp}/" + LONG], "--storage"),
    (["reindex", "{tmp}/" + LONG], "STORAGE"),
])
def test_300_character_names_name_the_option(site, tmp_path, argv, option):
    values = {"run": runs_of(site)[0], "tmp": tmp_path, "storage": site / "storage"}
    before = listing(tmp_path)
    refused(*cli(*[a.format(**values) for a in argv]),
            f"{option}: the name '{LONG[:40]}'… is 30", "at most 255 bytes",
            f"give a shorter {option}")
    assert listing(tmp_path) == before


def test_demo_never_writes_through_a_special_file(tmp_path):
    """``plantdyn demo --dir`` replaces its own files each time, through the same rule."""
    demo = tmp_path / "demo"
    demo.mkdir()
    os.mkfifo(demo / "demo_boiler.yaml")
    before = listing(tmp_path)
    rc, out, err = cli("demo", "--no-prefect", "--dir", demo)
    assert rc == 2 and "Traceback" not in err and err.count("plantdyn: error:") == 1, err
    assert f"--dir {demo / 'demo_boiler.yaml'} is a FIFO (named pipe)" in err
    assert listing(tmp_path) == before
