"""Internal errors the store-surface fuzz campaign found (issue 33, must-show 4), each now
one message with the fix (exit 2):

* seed 43 (monitor surface): a catalog whose ``runs.input_sha256s`` is not JSON made
  ``list_runs`` raise ``JSONDecodeError``;
* seed 426 (runs surface): a catalog whose schema text was damaged (a flipped byte that
  is not UTF-8 in a table's name and its SQL) made the catalog check raise
  ``UnicodeDecodeError`` (SQLite's own "malformed database schema (name)" message could
  not be decoded).
"""

from __future__ import annotations

import json
import sqlite3

import pytest

from tests.conftest import write_job
from tests.adapters.test_safe_writes import base, cli, listing, refused, site  # noqa: F401 - fixtures


def test_catalog_value_that_is_not_json(site):  # noqa: F811 - the imported fixture
    storage = site / "storage"
    con = sqlite3.connect(storage / "catalog.sqlite")
    con.execute("UPDATE runs SET input_sha256s = ''")
    con.commit()
    con.close()
    refused(*cli("runs", "plant", "--storage", storage, "--no-plot"),
            "runs of job 'plant': Expecting value", f"`plantdyn reindex {storage}`")
    job = write_job(site, monitor={"baseline": "first"})
    before = listing(storage)
    refused(*cli("run", "--no-prefect", job), "runs of job 'plant'", "plantdyn reindex")
    assert listing(storage) == before
    rc, out, err = cli("reindex", storage)
    assert rc == 0 and "catalog rebuilt from 2 run folder(s)" in out, err[-2000:]


def test_catalog_with_a_name_that_is_not_utf8(site):  # noqa: F811 - the imported fixture
    storage = site / "storage"
    catalog = storage / "catalog.sqlite"
    con = sqlite3.connect(catalog)
    con.execute("PRAGMA journal_mode=DELETE")
    con.execute("CREATE TABLE caf\u00e9 (a INTEGER)")
    con.commit()
    con.close()
    for p in storage.glob("catalog.sqlite-*"):
        p.unlink()
    data = catalog.read_bytes()
    assert b"caf\xc3\xa9" in data
    catalog.write_bytes(data.replace(b"caf\xc3\xa9", b"caf\xb3\xa9")
                        .replace(b"(a INTEGER)", b"(a INTEGER("))
    before = listing(storage)
    refused(*cli("runs", "plant", "--storage", storage, "--no-plot"),
            "the catalog is a damaged SQLite database (its schema holds text that is not "
            "UTF-8)",
            f"run `plantdyn reindex {storage}`")
    assert listing(storage) == before
    rc, out, err = cli("reindex", storage)
    assert rc == 0 and "moved aside to" in out and "catalog rebuilt from 2 run folder(s)" in out, \
        err[-2000:]


def test_catalog_text_value_that_is_not_utf8(site):  # noqa: F811 - the imported fixture
    storage = site / "storage"
    catalog = storage / "catalog.sqlite"
    con = sqlite3.connect(catalog)
    con.execute("PRAGMA journal_mode=DELETE")
    [(path,)] = con.execute("SELECT path FROM runs LIMIT 1").fetchall()
    # the same bytes with one that is not UTF-8, written as TEXT (what a flipped bit does)
    bad = path.encode()[:-3] + b"\xb3" + path.encode()[-2:]
    con.execute("UPDATE runs SET path = CAST(? AS TEXT) WHERE path = ?", (bad, path))
    con.commit()
    con.close()
    before = listing(storage)
    refused(*cli("runs", "plant", "--storage", storage, "--no-plot"),
            "the catalog is damaged (a text value in it is not UTF-8)",
            f"run `plantdyn reindex {storage}`")
    assert listing(storage) == before
    rc, out, err = cli("reindex", storage)
    assert rc == 0 and "catalog rebuilt from 2 run folder(s)" in out, err[-2000:]


@pytest.mark.parametrize("key, value", [("files", 1e308), ("files", [1]), ("files", None),
                                        ("files", [{"name": 5}]), ("config", "x")])
def test_export_of_a_manifest_whose_files_are_not_a_list(site, tmp_path, key, value):  # noqa: F811
    """Seeds 6355 and 6375 (export surface): ``"files": 1e308`` made export raise
    ``TypeError`` before any --out check."""
    run = min(p for p in (site / "storage" / "plant").iterdir() if p.is_dir())
    manifest = json.loads((run / "manifest.json").read_text())
    manifest[key] = value
    (run / "manifest.json").write_text(json.dumps(manifest))
    before = listing(tmp_path)
    refused(*cli("export", run, "--format", "csv", "--out", tmp_path / "m.csv"),
            "is not what plantdyn writes", "re-run the job")
    assert listing(tmp_path) == before
