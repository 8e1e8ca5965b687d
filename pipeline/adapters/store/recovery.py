"""Is a folder a results store, is its catalog ours, is a manifest fit to catalogue —
what ``plantdyn reindex`` and every open of the store check before they write.

* :func:`catalog_fault` says why ``catalog.sqlite`` is not a usable plantdyn catalog: not
  a regular file (a FIFO, a folder: never touched), empty (0 bytes or no tables: what a
  first run that failed on a full disk leaves), not an SQLite database (or a damaged
  one), or a database of another schema (tables or columns that are not the catalog's).
* :func:`store_evidence` says what makes a folder a results store: a plantdyn catalog
  (or an empty one), or the ``<job>/<run-id>/manifest.json`` layout of run folders.
  ``reindex`` refuses any other folder unless forced, so ``plantdyn reindex /etc`` does not
  turn ``/etc`` into a store.
* :func:`move_aside` renames a catalog that is not ours (with its ``-wal``/``-shm``) to
  ``catalog.sqlite.<UTC time>.bad`` — never deleted — so the catalog can be rebuilt.
* :func:`read_manifest` and :func:`catalog_manifest` check one run's manifest before it
  is catalogued: a manifest that is not a regular file, not JSON, names another run,
  has a time that is not ISO 8601 or repeats a metric is skipped with a line naming the
  run folder and the reason, and the other runs are catalogued.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
import json
import os
import secrets
import sqlite3
import stat
from pathlib import Path
from typing import Any

from pipeline.adapters.store.files import iso_utc, parse_iso_utc
from pipeline.adapters.store.schemas import CATALOG_DDL, CATALOG_NAME, MANIFEST_KEYS, \
    MANIFEST_NAME, NAME_RE

__all__ = ["CatalogFault", "catalog_fault", "catalog_manifest", "has_run_folders",
           "move_aside", "read_manifest", "store_evidence"]

MANIFEST_MAX_BYTES = 64 << 20
"""A manifest larger than this is not read (a run's manifest is a few kB to a few MB)."""


@dataclasses.dataclass(frozen=True)
class CatalogFault:
    """Why a ``catalog.sqlite`` is not a usable plantdyn catalog.

    Attributes
    ----------
    kind : str
        ``"special"`` (not a regular file), ``"empty"`` (0 bytes or no tables),
        ``"not_sqlite"`` (not an SQLite database, or a damaged one) or ``"foreign"``
        (another schema).
    detail : str
        In words, for the message ("is empty (0 bytes)").
    """

    kind: str
    detail: str


@functools.lru_cache(maxsize=1)
def _catalog_columns() -> dict[str, frozenset[str]]:
    con = sqlite3.connect(":memory:")
    try:
        for statement in CATALOG_DDL:
            con.execute(statement)
        names = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        return {n: frozenset(r[0] for r in con.execute("SELECT name FROM pragma_table_info(?)",
                                                       (n,))) for n in names}
    finally:
        con.close()


def _tables(path: Path, deep: bool, readonly: bool) -> dict[str, frozenset[str]] | str | None:
    """The tables and their columns; a text when the file is not a (sound) database; None
    when it cannot be read now (locked, unreadable: the caller's own open says why).
    ``immutable`` creates no ``-shm``/``-wal`` (a read-only open leaves no trace)."""
    immutable = "mode=ro&immutable=1"
    for query in (immutable,) if readonly else ("mode=ro", immutable):
        try:
            con = sqlite3.connect(f"{path.as_uri()}?{query}", uri=True, timeout=10.0)
        except sqlite3.Error:
            continue
        try:
            names = [r[0] for r in con.execute(
                "SELECT name FROM sqlite_master WHERE type='table' AND name NOT LIKE 'sqlite_%'")]
            tables = {n: frozenset(r[0] for r in con.execute(
                "SELECT name FROM pragma_table_info(?)", (n,))) for n in names}
            if deep:
                check = con.execute("PRAGMA quick_check").fetchone()[0]
                if check != "ok":
                    return f"is a damaged SQLite database ({check})"
            return tables
        except sqlite3.OperationalError as exc:
            if "unable to open" in str(exc) or "readonly" in str(exc):
                continue  # a read-only folder (no -shm can be made): read it immutable
            return None  # locked or busy: not a verdict (the caller's own open will say)
        except sqlite3.DatabaseError as exc:
            return f"is not an SQLite database ({exc})"
        except UnicodeDecodeError:
            return "is a damaged SQLite database (its schema holds text that is not UTF-8)"
        finally:
            con.close()
    return None


def catalog_fault(path: Path, *, deep: bool = False,
                  readonly: bool = False) -> CatalogFault | None:
    """Why ``path`` is not a usable plantdyn catalog; None when it is one or is absent.

    Parameters
    ----------
    path : Path
        ``<root>/catalog.sqlite``.
    deep : bool
        Also run SQLite's ``quick_check`` (``reindex``: finds damaged pages).
    readonly : bool
        Read without creating anything beside the file (a read-only store).
    """
    try:
        st = path.lstat()
    except (FileNotFoundError, NotADirectoryError):
        return None  # no catalog (the store's open says what is wrong with the folder)
    except OSError as exc:
        return CatalogFault("special", f"cannot be checked ({exc.strerror or exc})")
    if not stat.S_ISREG(st.st_mode):
        from pipeline.adapters.safe_write import file_kind

        return CatalogFault("special", f"is a {file_kind(st.st_mode)}, not a file")
    if st.st_size == 0:
        return CatalogFault("empty", "is empty (0 bytes; left by a run that failed while "
                                     "creating it)")
    tables = _tables(path, deep, readonly)
    if tables is None:
        return None
    if isinstance(tables, str):
        return CatalogFault("not_sqlite", tables)
    ours = _catalog_columns()
    other = sorted(set(tables) - set(ours))
    if other:
        return CatalogFault("foreign", f"is a database of another schema (tables "
                                       f"{', '.join(other[:5])} are not the catalog's)")
    for name, columns in sorted(tables.items()):
        if columns != ours[name]:
            return CatalogFault("foreign", f"is a database of another schema (table {name} "
                                           f"has columns {', '.join(sorted(columns))}; the "
                                           f"catalog's has {', '.join(sorted(ours[name]))})")
    if "runs" not in tables:
        return CatalogFault("empty", "has no tables yet")
    return None


def has_run_folders(root: Path) -> bool:
    """Whether ``root`` holds at least one ``<job>/<run-id>/manifest.json``.

    Parameters
    ----------
    root : Path
        The folder.
    """
    try:
        jobs = [p for p in root.iterdir() if NAME_RE.fullmatch(p.name) and p.is_dir()]
        for job in jobs:
            for run in job.iterdir():
                if NAME_RE.fullmatch(run.name) and (run / MANIFEST_NAME).is_file():
                    return True
    except OSError:
        return False
    return False


def store_evidence(root: Path, fault: CatalogFault | None) -> str | None:
    """What makes ``root`` a results store, in words; None when nothing does.

    Parameters
    ----------
    root : Path
        The folder.
    fault : CatalogFault or None
        :func:`catalog_fault` of its catalog.
    """
    catalog = root / CATALOG_NAME
    if fault is None and catalog.is_file():
        return f"its catalog {CATALOG_NAME}"
    if fault is not None and fault.kind == "empty":
        return f"its empty catalog {CATALOG_NAME}"
    if has_run_folders(root):
        return f"its run folders (<job>/<run-id>/{MANIFEST_NAME})"
    return None


def move_aside(catalog: Path) -> Path:
    """Rename ``catalog`` (and its ``-wal``/``-shm``) to ``catalog.sqlite.<UTC>.bad``.

    Parameters
    ----------
    catalog : Path
        The catalog file; a regular file (:func:`catalog_fault` kind not ``special``).

    Returns
    -------
    Path
        Where it went.
    """
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    aside = catalog.with_name(f"{catalog.name}.{stamp}-{secrets.token_hex(2)}.bad")
    for suffix in ("-wal", "-shm"):  # the journal first: it belongs to the old file
        side = Path(f"{catalog}{suffix}")
        if side.is_file() and not side.is_symlink():
            os.rename(side, f"{aside}{suffix}")
    os.rename(catalog, aside)
    return aside


def read_manifest(path: Path) -> dict[str, Any]:
    """A run folder's ``manifest.json`` as a mapping.

    Parameters
    ----------
    path : Path
        The manifest file.

    Raises
    ------
    ValueError
        Missing, not a regular file, too large, not JSON or not a JSON object (the
        reason, for the skipped line).
    """
    try:
        st = path.lstat()
    except FileNotFoundError:
        raise ValueError(f"no {MANIFEST_NAME}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{MANIFEST_NAME} is not a regular file")
    if st.st_size > MANIFEST_MAX_BYTES:
        raise ValueError(f"{MANIFEST_NAME} is {st.st_size:,} bytes (at most "
                         f"{MANIFEST_MAX_BYTES:,})")
    try:
        doc = json.loads(path.read_bytes())
    except RecursionError:
        raise ValueError(f"{MANIFEST_NAME} is nested too deeply") from None
    except ValueError as exc:
        raise ValueError(f"{MANIFEST_NAME} is not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{MANIFEST_NAME} is not a JSON object")
    return doc


def _utc_text(value: Any) -> str:
    if not isinstance(value, str):
        raise ValueError(f"created_utc {value!r} is not a time")
    try:
        return iso_utc(parse_iso_utc(value))
    except ValueError:
        raise ValueError(f"created_utc {value!r} is not an ISO 8601 time with a zone "
                         "(e.g. 2026-03-01T02:00:00.000000Z)") from None


def catalog_manifest(manifest: dict[str, Any], job: str, run_id: str) -> dict[str, Any]:
    """The manifest as the catalog stores it (``created_utc`` in the catalog's fixed-width
    form), after checking what the catalog needs from it.

    Parameters
    ----------
    manifest : dict
        From :func:`read_manifest`.
    job, run_id : str
        The run folder's job and run id (the manifest must name the same).

    Raises
    ------
    ValueError
        Keys missing, another run named, a field of the wrong type, a time that is not
        ISO 8601, a metric listed twice (the reason, for the skipped line).
    """
    missing = sorted(MANIFEST_KEYS - set(manifest))
    if missing:
        raise ValueError(f"manifest lacks keys {missing}")
    if (manifest["job"], manifest["run_id"]) != (job, run_id):
        raise ValueError(f"manifest names {manifest['job']}/{manifest['run_id']}")
    if not isinstance(manifest["status"], str):
        raise ValueError(f"status {manifest['status']!r} is not a text")
    inputs, metrics = manifest["inputs"], manifest["metrics"]
    if not isinstance(inputs, list) or not all(
            isinstance(i, dict) and isinstance(i.get("sha256"), str) for i in inputs):
        raise ValueError("inputs is not a list of {path, sha256, bytes}")
    if not isinstance(metrics, list):
        raise ValueError("metrics is not a list")
    seen = set()
    for m in metrics:
        key = tuple(m.get(k) for k in ("window", "output", "input", "metric")) \
            if isinstance(m, dict) else None
        if key is None or not all(isinstance(k, str) for k in key):
            raise ValueError(f"metric {m!r} lacks window/output/input/metric")
        if not isinstance(m.get("value"), (int, float, type(None))) or \
                not isinstance(m.get("label"), (str, type(None))):
            raise ValueError(f"metric {'/'.join(key)} has value {m.get('value')!r}, label "
                             f"{m.get('label')!r} (a number and a text expected)")
        if key in seen:
            raise ValueError(f"metric {'/'.join(key)} is listed twice")
        seen.add(key)
    return {**manifest, "created_utc": _utc_text(manifest["created_utc"]),
            "metrics": [{**m, "value": m.get("value"), "label": m.get("label")}
                        for m in metrics]}
