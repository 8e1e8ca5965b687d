"""Fuzz surfaces beyond ``plantdyn run`` on an export (issue 33, must-show 4): ``export``,
``runs`` (with ``--plot``), ``reindex``, monitor baselines, discrepancy models, a corrupt
catalog or manifest, and special files where plantdyn reads or writes.

Every case starts from a copy of one template store (job ``fuzz``, two runs made once per
campaign by :func:`build_template`), mutates it one to three times and names one command
(``argv.json``: the argv, the working directory and the paths the command may change).
Besides the checks of :mod:`tests.fuzzing` (exit 0 or 2, no traceback, one error line,
no hang, no half-written run), a case fails when anything outside the paths it may
change was written, replaced or removed: the whole case folder is listed (path, kind,
size, mtime; links not followed, FIFOs never opened) before and after.

Special files are made in the case's private folder only: FIFOs (``os.mkfifo``), Unix
sockets (a bound ``AF_UNIX`` socket, closed at once: the node stays), symbolic links to
a FIFO and to a decoy file, folders where a file is expected.  No device node is made
(that needs root and a real device number; the rule under test decides on
``stat.S_ISREG`` alone, which a FIFO and a socket exercise).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import shutil
import socket
import sqlite3
import stat
from pathlib import Path
from types import SimpleNamespace

import yaml

SURFACES = ("export", "runs", "reindex", "monitor", "discrepancy")
IGNORED = ("catalog.sqlite-wal", "catalog.sqlite-shm", "catalog.sqlite-journal")
LONG = "n" * 300


# ------------------------------------------------------------------------ template
def build_template(folder: Path, minutes: float = 20.0) -> Path:
    """A store with two runs of job ``fuzz`` (the suite's first-order plant, ``minutes``
    long), made with the CLI in a subprocess; the folder holds ``job.yaml``, ``drop/`` and
    ``storage/``."""
    from pipeline.adapters.historian_writer import write_long_csv
    from tests.fuzzing import _job, _signals

    sig = _signals(7, minutes=minutes)
    (folder / "drop").mkdir(parents=True, exist_ok=True)
    write_long_csv(folder / "drop" / "export.csv", sig["time"],
                   {"U.PV": sig["u"], "Y.PV": sig["y"]})
    job = _job(folder, "drop/*.csv")
    (folder / "job.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    from flows.cli import main

    for _ in range(2):
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            rc = main(["run", "--no-prefect", str(folder / "job.yaml")])
        if rc != 0:
            raise RuntimeError(f"the fuzz template's run failed (exit {rc}):\n{err.getvalue()}")
    return folder


def _runs(site: Path) -> list[Path]:
    return sorted(p for p in (site / "storage" / "fuzz").iterdir()
                  if p.is_dir() and not p.name.startswith("."))


# --------------------------------------------------------------------- specials
def remove(path: Path) -> None:
    """Remove whatever is at ``path`` (file, special file, link or folder)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.is_symlink() or path.exists():
        path.unlink()


def make_special(path: Path, kind: str, decoy: Path) -> None:
    """Put a special file of ``kind`` at ``path`` (removing what is there)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    remove(path)
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "socket":
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.bind(str(path))
        finally:
            s.close()
    elif kind == "link_fifo":
        fifo = path.with_name(path.name + ".fifo")
        os.mkfifo(fifo)
        path.symlink_to(fifo)
    elif kind == "link_decoy":
        path.symlink_to(decoy)
    elif kind == "folder":
        path.mkdir()
    elif kind == "empty":
        path.write_bytes(b"")


SPECIALS = ("fifo", "socket", "link_fifo", "link_decoy", "folder")


# ------------------------------------------------------------------ corruptions
def _json_mutation(doc, rng: random.Random):
    if not isinstance(doc, dict) or not doc:
        return rng.choice([[], None, 1, "x", {}])
    key = rng.choice(sorted(doc))
    choice = rng.randrange(9)
    if choice == 0:
        doc.pop(key)
    elif choice == 1:
        doc[key] = rng.choice([None, 1e308, -1, "", "../../x", [], {}, True, "x" * 5000])
    elif choice == 2:
        doc["job"] = rng.choice(["../../x", "a/b", "", ".hidden", "x" * 300, 5])
    elif choice == 3:
        doc["run_id"] = rng.choice(["../esc", ".", "..", "x" * 300, None])
    elif choice == 4:
        doc["created_utc"] = rng.choice(["yesterday", "2026-01-01T00:00:00Z", 5, "",
                                         "2026-13-45T99:99:99Z", "2026-01-01T00:00:00"])
    elif choice == 5 and isinstance(doc.get("metrics"), list) and doc["metrics"]:
        doc["metrics"].append(dict(doc["metrics"][0]) if isinstance(doc["metrics"][0], dict)
                              else 1)
    elif choice == 6 and isinstance(doc.get("files"), list) and doc["files"]:
        entry = doc["files"][0]
        if isinstance(entry, dict):
            entry["name"] = rng.choice(["../../outside.txt", "/etc/passwd", "", "x" * 300])
    elif choice == 7:
        doc["status"] = rng.choice([None, 1, [], "x" * 1000])
    else:
        doc[key] = {"deep": json.loads("[" * 200 + "]" * 200)}
    return doc


def corrupt_file(path: Path, rng: random.Random, decoy: Path) -> str:
    """Corrupt one store file (catalog, manifest, parquet, checks); returns what."""
    what = rng.choice(["zero", "garbage", "truncate", "flip", "special", "delete", "json"])
    if what == "special":
        kind = rng.choice(SPECIALS)
        make_special(path, kind, decoy)
        return f"{path.name}:{kind}"
    if not path.is_file():
        return f"{path.name}:absent"
    data = path.read_bytes()
    if what == "zero":
        data = b""
    elif what == "garbage":
        data = bytes(rng.randrange(256) for _ in range(rng.randint(1, 4000)))
    elif what == "truncate":
        data = data[: rng.randrange(len(data) + 1)]
    elif what == "flip":
        b = bytearray(data)
        for _ in range(rng.randint(1, 30)):
            if b:
                b[rng.randrange(len(b))] = rng.randrange(256)
        data = bytes(b)
    elif what == "delete":
        remove(path)
        return f"{path.name}:deleted"
    elif what == "json" and path.suffix == ".json":
        try:
            data = json.dumps(_json_mutation(json.loads(data), rng)).encode()
        except (ValueError, RecursionError):
            data = b"{"
    path.write_bytes(data)
    return f"{path.name}:{what}"


def corrupt_catalog(storage: Path, rng: random.Random, decoy: Path) -> str:
    catalog = storage / "catalog.sqlite"
    choice = rng.randrange(4)
    if choice == 0:
        for p in storage.glob("catalog.sqlite*"):
            remove(p)
        con = sqlite3.connect(catalog)
        try:
            con.execute(rng.choice(["CREATE TABLE books (title TEXT)",
                                    "CREATE TABLE runs (a INTEGER)",
                                    "CREATE TABLE runs (job TEXT, run_id TEXT)"]))
            con.commit()
        finally:
            con.close()
        return "catalog:foreign"
    if choice == 1:
        if not catalog.is_file() or catalog.is_symlink():
            return "catalog:not_a_file"
        con = sqlite3.connect(catalog)
        try:
            tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master "
                                                "WHERE type='table'")]
            table = rng.choice(tables) if tables else "runs"
            cols = [r[1] for r in con.execute(f"PRAGMA table_info({table})")]
            if cols:
                col = rng.choice(cols)
                value = rng.choice(["yesterday", "", None, -1, "../../x", 1e308, "x" * 2000])
                con.execute(f"UPDATE {table} SET {col} = ?", (value,))
                con.commit()
        except sqlite3.Error:
            pass
        finally:
            con.close()
        return "catalog:values"
    for p in storage.glob("catalog.sqlite-*"):
        remove(p)
    return corrupt_file(catalog, rng, decoy)


def corrupt_store(site: Path, rng: random.Random, decoy: Path) -> list[str]:
    """One to three corruptions of the store in ``site/storage``."""
    storage = site / "storage"
    done = []
    for _ in range(rng.randint(1, 3)):
        runs = _runs(site)
        target = rng.choice(["catalog", "manifest", "manifest", "file", "junk"])
        if target == "catalog" or not runs:
            done.append(corrupt_catalog(storage, rng, decoy))
        elif target == "manifest":
            done.append(corrupt_file(rng.choice(runs) / "manifest.json", rng, decoy))
        elif target == "file":
            run = rng.choice(runs)
            files = sorted(p for p in run.iterdir() if p.name != "manifest.json")
            if files:
                done.append(corrupt_file(rng.choice(files), rng, decoy))
        else:
            junk = rng.choice([storage / "fuzz" / ".tmp-zz", storage / "other" / "r1",
                               storage / "fuzz" / "x" / "y", storage / "fuzz" / "trend.png"])
            if rng.random() < 0.5:
                make_special(junk, rng.choice(SPECIALS + ("empty",)), decoy)
            else:
                remove(junk)
                junk.mkdir(parents=True)
            done.append(f"junk:{junk.relative_to(storage)}")
    return done


# ------------------------------------------------------------------------ targets
def out_target(folder: Path, rng: random.Random, site: Path, decoy: Path,
               suffix: str) -> tuple[str, str]:
    """A file the user names (``--out``/``--plot``): ``(path, what)``."""
    out = folder / "out"
    choice = rng.choice(["new", "existing", "special", "special", "long", "in_run",
                         "catalog", "missing_dir", "folder", "nul", "decoy"])
    path = out / f"model{suffix}"
    if choice == "existing":
        path.write_bytes(b"old")
    elif choice == "special":
        kind = rng.choice(SPECIALS)
        make_special(path, kind, decoy)
        choice = kind
    elif choice == "long":
        path = out / (LONG + suffix)
    elif choice == "in_run":
        runs = _runs(site)
        path = (runs[-1] if runs else out) / f"model{suffix}"
    elif choice == "catalog":
        path = site / "storage" / "catalog.sqlite"
    elif choice == "missing_dir":
        path = out / "no" / "such" / f"model{suffix}"
    elif choice == "folder":
        path = out
    elif choice == "decoy":
        path = decoy
    text = str(path) if choice != "nul" else str(out / "a\0b.csv")
    return text, choice


# ------------------------------------------------------------------------ models
_BLOCK_TYPES = ["gain", "first_order", "second_order", "transfer", "integrator", "pi",
                "pid", "sum", "deadband", "saturation", "operating_point_gain", "nonesuch"]
_HOSTILE_NUMBERS = [0, -1, 1e12, -1e12, 1e308, float("inf"), float("nan"), 1e-300, "x",
                    None, True, [], {}, 2.5, 20, -20, 0.5, 65]


def random_model(rng: random.Random) -> dict:
    """A random, often hostile, model on input ``u`` with output ``y``."""
    n = rng.choice([1, 2, 3, 5, 8, 150, 10_000]) if rng.random() < 0.3 else rng.randint(1, 4)
    names = [f"b{i}" for i in range(n - 1)] + ["y"]
    blocks = []
    for i, name in enumerate(names):
        kind = rng.choice(_BLOCK_TYPES) if rng.random() < 0.5 else "first_order"
        source = rng.choice(["u", *names[:i]] + (names if rng.random() < 0.2 else []))
        b = {"name": name, "type": kind,
             "input": source if rng.random() < 0.9 else rng.choice(["-u", "nosuch", 5])}
        b.update({"first_order": {"k": 2.0, "tau_s": 20.0}, "gain": {"k": 1.0},
                  "second_order": {"k": 1.0, "wn": 0.1, "zeta": 0.7},
                  "transfer": {"num": [2.0], "den": [20.0, 1.0]},
                  "integrator": {"k": 0.01}, "pi": {"kp": 0.5, "ti_s": 60.0},
                  "pid": {"kp": 0.5, "ti_s": 60.0, "td_s": 5.0},
                  "deadband": {"width": 0.1}, "saturation": {"low": -1.0, "high": 1.0},
                  "operating_point_gain": {"slope": 0.1, "signal": "u"}}.get(kind, {}))
        if kind == "sum":
            b.pop("input")
            b["inputs"] = [source, {"signal": rng.choice(["u", *names]), "k": rng.choice(
                [1.5, -0.5, 3.0, 1e6])}]
        for _ in range(rng.choice([0, 0, 1, 2])):
            key = rng.choice(["k", "tau_s", "delay_s", "den", "num", "wn", "zeta", "kp",
                              "ti_s", "width", "low", "high", "bogus"])
            b[key] = rng.choice(_HOSTILE_NUMBERS) if key not in ("den", "num") else \
                rng.choice([[-20.0, 1.0], [1.0, -1.0], [0.0], [], [1.0, 2.0, 3.0], [1e300, 1]])
        blocks.append(b)
    model = {"name": rng.choice(["m", "", 5]) if rng.random() < 0.1 else "m",
             "inputs": ["u"], "outputs": ["y"], "blocks": blocks}
    if rng.random() < 0.1:
        model[rng.choice(["inputs", "outputs", "blocks"])] = rng.choice(
            [None, "u", [], [5], {"a": 1}])
    return model


# ------------------------------------------------------------------------ cases
def _case_export(c) -> tuple[list[str], list[str]]:
    run = c.rng.choice(c.runs)
    fmt = c.rng.choice(["csv", "json", "mat", "control"])
    if c.rng.random() < 0.6:
        c.done["mutations"].append(corrupt_file(run / c.rng.choice(
            ["manifest.json", "manifest.json", "step_responses.parquet", "checks.json"]),
            c.rng, c.decoy))
    argv = ["export", str(run), "--format", fmt]
    if c.rng.random() < 0.8:
        text, what = out_target(c.folder, c.rng, c.site, c.decoy, "." + fmt)
        argv += ["--out", text]
        c.done["mutations"].append(f"out:{what}")
        may_change = [str(c.folder / "out"), text]  # the file the user named
    else:
        c.done["mutations"].append("out:default")
        may_change = [str(c.folder / "out")]
    if c.rng.random() < 0.5:
        argv.append("--force")
    return argv, may_change


def _case_runs(c) -> tuple[list[str], list[str]]:
    may_change = [str(c.storage)]
    if c.rng.random() < 0.7:
        c.done["mutations"] += corrupt_store(c.site, c.rng, c.decoy)
    argv = ["runs", c.rng.choice(["fuzz", "fuzz", "nosuch", "../x", str(c.site / "job.yaml")]),
            "--storage", str(c.storage)]
    plot = c.rng.random()
    if plot < 0.5:
        text, what = out_target(c.folder, c.rng, c.site, c.decoy, ".png")
        argv += ["--plot", text]
        c.done["mutations"].append(f"plot:{what}")
        may_change += [str(c.folder / "out"), text]
    elif plot < 0.7:
        argv.append("--no-plot")
    if c.rng.random() < 0.5:
        argv.append("--force")
    return argv, may_change


def _case_reindex(c) -> tuple[list[str], list[str]]:
    target = c.storage
    choice = c.rng.random()
    if choice < 0.6:
        c.done["mutations"] += corrupt_store(c.site, c.rng, c.decoy)
    elif choice < 0.8:
        target = c.folder / "etc"
        (target / "ssh").mkdir(parents=True)
        (target / "hosts").write_text("127.0.0.1 localhost\n")
        c.done["mutations"].append("not_a_store")
    else:
        target = c.folder / "out" / "thing"
        make_special(target, c.rng.choice(SPECIALS + ("empty",)), c.decoy)
        c.done["mutations"].append("special_root")
    argv = ["reindex", str(target)] + (["--force"] if c.rng.random() < 0.3 else [])
    return argv, [str(target)]


def _case_monitor(c) -> tuple[list[str], list[str]]:
    job = yaml.safe_load((c.site / "job.yaml").read_text())
    job["monitor"] = {"baseline": c.rng.choice(["first", "first", c.runs[0].name, "nosuch",
                                                "../x", 5, None, ""])}
    (c.site / "job.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    c.done["mutations"].append(f"baseline:{job['monitor']['baseline']!r}")
    if c.rng.random() < 0.8:
        c.done["mutations"].append(corrupt_file(c.runs[0] / c.rng.choice(
            ["manifest.json", "checks.json", "step_responses.parquet"]), c.rng, c.decoy))
    if c.rng.random() < 0.3:
        c.done["mutations"] += corrupt_store(c.site, c.rng, c.decoy)
    return ["run", "--no-prefect", str(c.site / "job.yaml")], [str(c.storage)]


def _case_model(c) -> tuple[list[str], list[str]]:
    job = yaml.safe_load((c.site / "job.yaml").read_text())
    model = random_model(c.rng)
    if c.rng.random() < 0.2:
        (c.site / "model.yaml").write_text(yaml.safe_dump({"model": model}))
        job["model"] = "model.yaml"
        if c.rng.random() < 0.3:
            make_special(c.site / "model.yaml", c.rng.choice(SPECIALS), c.decoy)
            c.done["mutations"].append("model_file:special")
    else:
        job["model"] = model
    job["discrepancy"] = {"max_effects": 1}
    (c.site / "job.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    blocks = model.get("blocks")
    c.done["mutations"].append(f"blocks:{len(blocks) if isinstance(blocks, list) else '?'}")
    return ["discrepancy", "--no-prefect", str(c.site / "job.yaml")], [str(c.storage)]


#: How each surface's case is made (every other surface is a discrepancy model).
_CASES = {"export": _case_export, "runs": _case_runs, "reindex": _case_reindex,
          "monitor": _case_monitor}


def make_surface_case(folder: Path, seed: int, template: Path) -> dict:
    """Write case ``seed`` of a surface into ``folder`` (``argv.json`` + a private copy
    of the template); returns what was done."""
    rng = random.Random(seed)
    surface = SURFACES[seed % len(SURFACES)]
    site = folder / "site"
    shutil.copytree(template, site, symlinks=True)
    (folder / "out").mkdir()
    decoy = folder / "decoy.txt"
    decoy.write_text("the user's own file\n")
    done: dict = {"seed": seed, "base": surface, "mutations": []}
    ctx = SimpleNamespace(rng=rng, folder=folder, site=site, decoy=decoy, done=done,
                          storage=site / "storage", runs=_runs(site))
    argv, may_change = _CASES.get(surface, _case_model)(ctx)
    (folder / "argv.json").write_text(json.dumps({"argv": argv, "cwd": str(folder / "out"),
                                                  "may_change": may_change}))
    return done


# ------------------------------------------------------------------------ judging
def listing(folder: Path) -> dict[str, tuple]:
    """Every entry under ``folder``: kind, size, mtime (links not followed)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            if name.endswith(IGNORED):
                continue
            try:
                st = p.lstat()
            except OSError:
                continue
            kind = stat.S_IFMT(st.st_mode)
            out[str(p)] = (kind,) if stat.S_ISDIR(kind) else (kind, st.st_size, st.st_mtime_ns)
    return out


def writes_outside(before: dict, after: dict, may_change: list[str]) -> list[str]:
    """Paths added, removed or changed outside the ``may_change`` paths."""
    allowed = [p.rstrip("/") for p in may_change]

    def inside(path: str) -> bool:
        return any(path == a or path.startswith(a + "/") for a in allowed)

    bad = []
    for path in sorted(set(before) | set(after)):
        if before.get(path) != after.get(path) and not inside(path):
            state = "added" if path not in before else "removed" if path not in after \
                else "changed"
            bad.append(f"{state} {path}")
    return bad
