"""Seeded mutation fuzzing of what users feed plantdyn: historian CSV (long and wide),
JSON MCAP and job YAML (issue 10); and, every other seed, the commands around a results
store -- export, runs (--plot), reindex, monitor baselines, discrepancy models, corrupt
catalogs and manifests, special files (issue 33, :mod:`tests.fuzz_surfaces`).

Every case is a folder with a job YAML and its export, built from a valid case by one
to three seeded mutations (bytes, lines, fields, timestamps, numbers, encodings, YAML
values, aliases, nesting, ...).  A case passes when ``plantdyn run --no-prefect JOB``

* ends with exit code 0 or 2 (never 1, an internal error), within the time limit and
  the memory limit;
* prints no traceback, and on exit 2 exactly one ``plantdyn: error:`` line;
* leaves no half-written result: no ``.tmp-*`` folder under the storage root, and every
  run directory has its manifest and every file the manifest lists;
* writes nothing outside what its command may change (a surface case: the case folder is
  listed before and after; a run case: its storage root).

Cases run in-process in a worker subprocess (an import costs 2 s; a case 0.1–0.5 s); the
parent watches each case's wall time and the worker's resident memory and kills the
worker on a hang or a blow-up (an address-space rlimit deadlocks the thread pools of
OpenBLAS and polars instead of failing cleanly).

Use::

    python -m tests.fuzzing --cases 2000 --seed 1 [--out fuzz.json]   # scripts/fuzz.sh

``tests/flows/test_cli_fuzz.py`` runs a CI sample.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
TIME_LIMIT_S = 60.0
MEMORY_LIMIT_MB = 3000.0


# --------------------------------------------------------------------------- bases
def _signals(seed: int, minutes: float = 40.0):
    """Input/output of a first-order plant at 1 s (the suite's test plant)."""
    from tests.conftest import plant_signals

    return plant_signals(seed=seed, hours=minutes / 60.0)


def _job(folder: Path, source: str, **extra) -> dict:
    return {"job": "fuzz", "source": {"path": source, "timezone": "UTC"},
            "signals": {"inputs": {"u": {"tag": "U.PV"}}, "outputs": {"y": {"tag": "Y.PV"}}},
            "storage": "storage", "rerun": {"enabled": False}, **extra}


def base_long_csv(folder: Path, rng: random.Random) -> tuple[Path, dict]:
    from pipeline.adapters.historian_writer import write_long_csv

    sig = _signals(rng.randrange(1000))
    path = folder / "drop" / "export.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_long_csv(path, sig["time"], {"U.PV": sig["u"], "Y.PV": sig["y"]},
                   irregular=np.random.default_rng(rng.randrange(1000)))
    return path, _job(folder, "drop/*.csv")


def base_wide_csv(folder: Path, rng: random.Random) -> tuple[Path, dict]:
    sig = _signals(rng.randrange(1000))
    path = folder / "drop" / "export.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["Time,U.PV,U.PV Quality,Y.PV,Y.PV Quality", ",flow,,pressure,", ",kg/s,,bar,"]
    t = sig["time"].astype("datetime64[s]").astype(str)
    for k in range(t.size):
        lines.append(f"{t[k].replace('T', ' ')},{sig['u'][k]:.6f},G,{sig['y'][k]:.6f},G")
    path.write_text("\n".join(lines) + "\n")
    return path, _job(folder, "drop/*.csv")


def base_mcap(folder: Path, rng: random.Random) -> tuple[Path, dict]:
    from pipeline.adapters.historian_writer import write_json_mcap

    sig = _signals(rng.randrange(1000))
    path = folder / "drop" / "export.mcap"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_mcap(path, sig["time"], {"U.PV": sig["u"], "Y.PV": sig["y"]},
                    samples_per_message=rng.choice([1, 50]))
    return path, _job(folder, "drop/*.mcap")


BASES = {"long_csv": base_long_csv, "wide_csv": base_wide_csv, "mcap": base_mcap}


# ------------------------------------------------------------------ data mutations
def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def m_truncate(data: bytes, rng: random.Random) -> bytes:
    return data[: rng.randrange(len(data) + 1)]


def m_flip_bytes(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 20)):
        if b:
            b[rng.randrange(len(b))] = rng.randrange(256)
    return bytes(b)


def m_insert_bytes(data: bytes, rng: random.Random) -> bytes:
    k = rng.randrange(len(data) + 1)
    junk = rng.choice([b"\x00", b"\xff\xfe", b"\xef\xbb\xbf", b"\r", b'"', b",,,", b";",
                       bytes(rng.randrange(256) for _ in range(rng.randint(1, 40)))])
    return data[:k] + junk + data[k:]


def m_delete_lines(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    for _ in range(rng.randint(1, 50)):
        if len(ls) > 1:
            del ls[rng.randrange(len(ls))]
    return b"\n".join(ls)


def m_duplicate_lines(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    for _ in range(rng.randint(1, 50)):
        k = rng.randrange(len(ls))
        ls.insert(rng.randrange(len(ls)), ls[k])
    return b"\n".join(ls)


def m_shuffle_lines(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    a = rng.randrange(len(ls))
    b = min(len(ls), a + rng.randint(2, 200))
    part = ls[a:b]
    rng.shuffle(part)
    ls[a:b] = part
    return b"\n".join(ls)


_FIELD_VALUES = [b"", b"nan", b"NaN", b"inf", b"-inf", b"1e300", b"-1e300", b"1e-320",
                 b"99999999999999999999999999", b"0x1F", b"1,5", b"12.5.3", b"--1", b"+",
                 b"#N/A", b"Bad Input", b"I/O Timeout", b"\xc3\x28", b"null", b"true",
                 b'"quoted, value"', b" 1 ", b"\t", b"9999-12-31 23:59:59",
                 b"1970-01-01 00:00:00", b"2026-02-30 12:00:00", b"2026-13-01 00:00:00",
                 b"24:61:00", b"yesterday", b"2026-05-04T00:00:00+05:00",
                 b"-0", b"1e5", b"0.0000001", b"Good", b"Bad", b"192", b"\xe2\x80\x8b"]


def m_replace_field(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    for _ in range(rng.randint(1, 30)):
        k = rng.randrange(len(ls))
        sep = b";" if b";" in ls[k] else b","
        f = ls[k].split(sep)
        f[rng.randrange(len(f))] = rng.choice(_FIELD_VALUES)
        ls[k] = sep.join(f)
    return b"\n".join(ls)


def m_extra_fields(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    for _ in range(rng.randint(1, 30)):
        k = rng.randrange(len(ls))
        ls[k] = ls[k] + rng.choice([b",", b",x", b",1,2", b";", b",,"])
    return b"\n".join(ls)


def m_decimal_commas(data: bytes, rng: random.Random) -> bytes:
    """Decimal commas in a comma-separated file: rows gain fields (a classic export)."""
    ls = _lines(data)
    for k in range(len(ls)):
        if rng.random() < 0.5:
            parts = ls[k].split(b",")
            ls[k] = b",".join(p.replace(b".", b",", 1) if i >= 2 else p
                              for i, p in enumerate(parts))
    return b"\n".join(ls)


def m_stray_time(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    if len(ls) < 2:
        return data
    for _ in range(rng.randint(1, 3)):
        k = rng.randrange(1, len(ls))
        for old in (b"2026-03-0", b"2026-03-"):
            if old in ls[k]:
                ls[k] = ls[k].replace(old, rng.choice([b"9999-03-0", b"1970-03-0", b"2026-04-0",
                                                       b"2027-03-0", b"1900-03-0"]), 1)
                break
    return b"\n".join(ls)


def m_spikes(data: bytes, rng: random.Random) -> bytes:
    ls = _lines(data)
    if len(ls) < 2:
        return data
    for _ in range(rng.randint(1, 10)):
        k = rng.randrange(1, len(ls))
        f = ls[k].split(b",")
        if len(f) >= 3:
            try:
                f[2] = repr(float(f[2]) * rng.choice([1e6, -1e6, 1e3])).encode()
            except ValueError:
                pass
            ls[k] = b",".join(f)
    return b"\n".join(ls)


def m_encoding(data: bytes, rng: random.Random) -> bytes:
    text = data.decode("utf-8", errors="replace")
    enc = rng.choice(["utf-16", "utf-16-le", "latin-1", "cp1252", "utf-8-sig", "utf-32"])
    return text.encode(enc, errors="replace")


def m_line_endings(data: bytes, rng: random.Random) -> bytes:
    return data.replace(b"\n", rng.choice([b"\r\n", b"\r", b"\n\n"]))


def m_empty(data: bytes, rng: random.Random) -> bytes:
    return rng.choice([b"", b"\n", b"tag,timestamp,value,status\n", data[:200]])


CSV_MUTATIONS = [m_truncate, m_flip_bytes, m_insert_bytes, m_delete_lines,
                 m_duplicate_lines, m_shuffle_lines, m_replace_field, m_extra_fields,
                 m_decimal_commas, m_stray_time, m_spikes, m_encoding, m_line_endings,
                 m_empty]


_HOSTILE_PAYLOADS = [
    b"\xff\xfe not utf-8", b'{"t": NaN, "value": 1}', b'{"t": Infinity, "value": 1}',
    b'{"t": 1e300, "value": 1}', b'{"t": 1.7e9, "value": [1, 2]}',
    b'{"t": 1.7e9, "value": {"a": 1}}', b'{"t": "soon", "value": 1}',
    b'{"value": 1}', b'{"t": 1.7e12, "value": 1}', b"[]", b"{}", b"null",
    b'{"t": -1e9, "value": 1}', b'{"t": 1.7e9, "value": "1,5"}']


def _mcap_one_hostile(data: bytes, rng: random.Random) -> bytes:
    """Exactly one hostile payload (so its own error is the one that surfaces)."""
    return _mcap_mutate_payloads(data, rng, one=True)


def _mcap_mutate_payloads(data: bytes, rng: random.Random, one: bool = False) -> bytes:
    """Rewrite the file with mutated JSON payloads (valid framing, hostile content)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    try:
        reader = make_reader(io.BytesIO(data))
        msgs = list(reader.iter_messages())
    except Exception:  # noqa: BLE001 - an unreadable base: mutate the bytes instead
        return m_flip_bytes(data, rng)
    out = io.BytesIO()
    w = Writer(out)
    w.start()
    schemas, channels = {}, {}
    target = rng.randrange(len(msgs)) if one and msgs else -1
    for i, (schema, channel, msg) in enumerate(msgs):
        if schema is not None and schema.id not in schemas:
            schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
        if channel.id not in channels:
            channels[channel.id] = w.register_channel(
                channel.topic, channel.message_encoding,
                schemas.get(schema.id, 0) if schema is not None else 0)
        payload, log_time = msg.data, msg.log_time
        if (i == target) if one else rng.random() < 0.02:
            payload = rng.choice(_HOSTILE_PAYLOADS)
        if not one and rng.random() < 0.005:
            log_time = rng.choice([0, 2**63 + 5, 2**64 - 1, log_time * 1000])
        w.add_message(channels[channel.id], log_time=min(log_time, 2**64 - 1),
                      data=payload, publish_time=min(log_time, 2**64 - 1))
    w.finish()
    return out.getvalue()


MCAP_MUTATIONS = [m_truncate, m_flip_bytes, m_insert_bytes, _mcap_mutate_payloads,
                  _mcap_mutate_payloads, _mcap_one_hostile, _mcap_one_hostile, m_empty]


# ------------------------------------------------------------------ YAML mutations
_YAML_VALUES = [None, "", "x" * 300, -1, 0, 1, 2.5, 1e30, -1e30, float("inf"),
                float("nan"), True, [], [1, 2], {}, {"a": 1}, "auto", "white", 40, 100000,
                "../../../../etc/passwd", "/tmp", "storage/../..", "Mars/Olympus", ".inf",
                "1e300", "UTC", "drop/*.csv", 3, 10, 1e300]

_KEY_PATHS = [
    ("job",), ("source", "path"), ("source", "timezone"), ("source", "layout"),
    ("source", "grid_dt_s"), ("source", "on_truncated"), ("source", "time_order"),
    ("signals", "inputs", "u", "tag"), ("signals", "outputs", "y", "tag"),
    ("signals", "outputs", "y", "integrating"), ("signals", "outputs", "y", "max_gap_s"),
    ("signals", "inputs", "u", "interpolation"), ("storage",), ("sampling", "dt_s"),
    ("sampling", "target_input"), ("conditioning", "method"), ("conditioning", "kdiff1"),
    ("conditioning", "cutoff_period_s"), ("conditioning", "order"), ("search", "n_p"),
    ("search", "n_p_min"), ("search", "n_p_max"), ("search", "settling_time_s"),
    ("search", "n_d_start"), ("search", "max_windows"), ("checks", "ljung_box_lags"),
    ("checks", "xcorr_max_lag"), ("estimation", "noise"), ("estimation", "n_k"),
    ("estimation", "feedback"), ("rerun", "enabled"), ("dask", "address"), ("schedule",),
    ("model",), ("discrepancy",), ("signals", "instruments"), ("unknown_key",),
]


def _set(d: dict, path: tuple, value) -> None:
    for k in path[:-1]:
        if not isinstance(d.get(k), dict):
            d[k] = {}
        d = d[k]
    d[path[-1]] = value


def y_value(job: dict, rng: random.Random) -> str:
    for _ in range(rng.randint(1, 3)):
        _set(job, rng.choice(_KEY_PATHS), rng.choice(_YAML_VALUES))
    return yaml.safe_dump(job, sort_keys=False)


def y_delete(job: dict, rng: random.Random) -> str:
    path = rng.choice(_KEY_PATHS)
    d = job
    for k in path[:-1]:
        d = d.get(k, {}) if isinstance(d, dict) else {}
    if isinstance(d, dict):
        d.pop(path[-1], None)
    return yaml.safe_dump(job, sort_keys=False)


def y_alias_bomb(job: dict, rng: random.Random) -> str:
    depth = rng.randint(3, 9)
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for k in range(1, depth):
        lines.append(f"a{k}: &a{k} [" + ",".join([f"*a{k - 1}"] * 9) + "]")
    key = rng.choice(["model", "discrepancy", "schedule", "source"])
    bomb = "\n".join("  " + ln for ln in lines)
    return yaml.safe_dump(job, sort_keys=False) + f"{key}:\n{bomb}\n"


def y_deep(job: dict, rng: random.Random) -> str:
    depth = rng.choice([50, 500, 5000])
    return yaml.safe_dump(job, sort_keys=False) + "model: " + "[" * depth + "]" * depth + "\n"


def y_duplicate_key(job: dict, rng: random.Random) -> str:
    text = yaml.safe_dump(job, sort_keys=False)
    return text + rng.choice(["job: other\n", "storage: elsewhere\n",
                              "search: {n_p: 5}\n"])


def y_text(job: dict, rng: random.Random) -> str:
    text = yaml.safe_dump(job, sort_keys=False)
    return m_flip_bytes(text.encode(), rng).decode("utf-8", errors="replace") \
        if rng.random() < 0.5 else rng.choice(
            ["", "- a\n- b\n", "!!python/object/apply:os.system ['true']\n", "job: [\n",
             "\t" + text, text.replace(":", "=", 1), "job: fuzz\n" * 3])


YAML_MUTATIONS = [y_value, y_value, y_value, y_delete, y_alias_bomb, y_deep,
                  y_duplicate_key, y_text]


# --------------------------------------------------------------------------- cases
def make_case(folder: Path, seed: int, template: Path | None = None,
              surface_share: float = 0.5) -> dict:
    """Write case ``seed`` into ``folder``; return what was done (for the report).  With a
    template store, a share ``surface_share`` of the seeds (drawn per seed) are store
    surfaces (:mod:`tests.fuzz_surfaces`)."""
    if template is not None and random.Random(seed ^ 0x5EED).random() < surface_share:
        from tests.fuzz_surfaces import make_surface_case

        return make_surface_case(folder, seed, template)
    rng = random.Random(seed)
    kind = rng.choice(list(BASES))
    path, job = BASES[kind](folder, rng)
    done = {"seed": seed, "base": kind, "mutations": []}
    target = rng.choices(["data", "yaml", "both"], weights=[6, 3, 1])[0]
    if target in ("data", "both"):
        data = path.read_bytes()
        pool = MCAP_MUTATIONS if kind == "mcap" else CSV_MUTATIONS
        for _ in range(rng.randint(1, 3)):
            m = rng.choice(pool)
            data = m(data, rng)
            done["mutations"].append(m.__name__)
        path.write_bytes(data)
    if target in ("yaml", "both"):
        m = rng.choice(YAML_MUTATIONS)
        text = m(json.loads(json.dumps(job)), rng)
        done["mutations"].append(m.__name__)
    else:
        text = yaml.safe_dump(job, sort_keys=False)
    (folder / "job.yaml").write_text(text, encoding="utf-8", errors="replace")
    return done


def leftovers(folder: Path, before: set[str] = frozenset()) -> list[str]:
    """Half-written results under the case's storage root (the pass criteria); run
    folders in ``before`` (a surface case's own corrupt store) are not judged."""
    bad = []
    storage = folder / "site" / "storage" if (folder / "site").is_dir() else folder / "storage"
    if not storage.is_dir() or storage.is_symlink():
        return bad
    for p in storage.rglob("*"):
        if p.is_dir() and p.name.startswith(".tmp") and str(p) not in before:
            bad.append(f"temp folder {p.relative_to(folder)}")
    job_root = storage / "fuzz"
    if job_root.is_dir() and not job_root.is_symlink():
        for run in job_root.iterdir():
            if not run.is_dir() or run.name.startswith(".") or str(run) in before:
                continue
            man = run / "manifest.json"
            if not man.is_file():
                bad.append(f"run {run.name} without manifest")
                continue
            try:
                files = json.loads(man.read_text()).get("files", [])
            except (ValueError, OSError):
                bad.append(f"run {run.name}: unreadable manifest")
                continue
            for entry in files:
                if not (run / entry["name"]).is_file():
                    bad.append(f"run {run.name}: {entry['name']} missing")
    return bad


def run_in_process(folder: Path) -> dict:
    """``plantdyn run --no-prefect job.yaml`` (or a surface case's ``argv.json``) in this
    process, output captured."""
    from flows.cli import main

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    cwd = os.getcwd()
    spec = {"argv": ["run", "--no-prefect", str(folder / "job.yaml")], "cwd": str(folder)}
    if (folder / "argv.json").is_file():
        spec = json.loads((folder / "argv.json").read_text())
    try:
        os.chdir(spec["cwd"])
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = main(spec["argv"])
            except SystemExit as exc:  # argparse
                rc = exc.code if isinstance(exc.code, int) else 2
    finally:
        os.chdir(cwd)
    return {"rc": rc, "stderr": err.getvalue()[-4000:], "seconds": time.perf_counter() - t0}


@dataclass
class Outcome:
    seed: int
    base: str
    mutations: list
    rc: int | None
    seconds: float
    problem: str  # "" when the case passed
    stderr_tail: str


def storage_of(folder: Path) -> Path:
    """The storage root a run case's (possibly mutated) job names: where it may write."""
    try:
        doc = yaml.safe_load((folder / "job.yaml").read_text(encoding="utf-8"))
        value = doc.get("storage", "storage") if isinstance(doc, dict) else "storage"
        return (folder / str(value)).resolve() if isinstance(value, str) and value \
            and "\0" not in value else folder / "storage"
    except Exception:  # noqa: BLE001 - any unreadable job: its default
        return folder / "storage"


def judge(done: dict, res: dict | None, folder: Path, killed: str = "",
          before: dict | None = None) -> Outcome:
    """The outcome of one case (``before``: the case folder's listing before it ran)."""
    from tests.fuzz_surfaces import listing, writes_outside

    if res is None:
        return Outcome(done["seed"], done["base"], done["mutations"], None, 0.0, killed, "")
    err = res["stderr"]
    problem = ""
    if res["rc"] not in (0, 2):
        problem = f"exit {res['rc']}"
    elif "Traceback" in err:
        problem = "traceback"
    elif res["rc"] == 2 and err.count("plantdyn: error: ") != 1:
        problem = "exit 2 without exactly one error line"
    left = leftovers(folder, set(before or ()))
    if left:
        problem = (problem + "; " if problem else "") + "half-written: " + ", ".join(left[:3])
    if before is not None:
        spec = json.loads((folder / "argv.json").read_text()) \
            if (folder / "argv.json").is_file() else {"may_change": [str(storage_of(folder))]}
        outside = writes_outside(before, listing(folder), spec["may_change"])
        if outside:
            problem = (problem + "; " if problem else "") + "wrote outside: " + \
                ", ".join(outside[:3])
    tail = err[-600:] if problem else err.strip().splitlines()[-1][:300] if err.strip() else ""
    return Outcome(done["seed"], done["base"], done["mutations"], res["rc"], res["seconds"],
                   problem, tail)


# ------------------------------------------------------------------ worker / parent
def _worker() -> None:
    """Read case folders from stdin, run each, write one JSON line per result."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ["PLANTDYN_FUZZ"] = "1"
    for line in sys.stdin:
        folder = Path(line.strip())
        res = run_in_process(folder)
        sys.stdout.write(json.dumps(res) + "\n")
        sys.stdout.flush()


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for ln in fh:
                if ln.startswith("VmRSS:"):
                    return float(ln.split()[1]) / 1024.0
    except OSError:
        return 0.0
    return 0.0


class _Worker:
    def __init__(self):
        self.p = subprocess.Popen([sys.executable, "-m", "tests.fuzzing", "--worker"],
                                  cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True, bufsize=1)
        os.set_blocking(self.p.stdout.fileno(), False)

    def run(self, folder: Path, time_limit: float, mem_limit: float):
        self.p.stdin.write(str(folder) + "\n")
        self.p.stdin.flush()
        t0 = time.perf_counter()
        peak = 0.0
        buf = ""
        while True:
            try:
                chunk = self.p.stdout.read()
            except (BlockingIOError, TypeError):
                chunk = None
            if chunk:
                buf += chunk
                if buf.endswith("\n"):
                    res = json.loads(buf)
                    res["peak_mb"] = peak
                    return res, ""
            if self.p.poll() is not None:
                return None, f"worker died (exit {self.p.returncode})"
            peak = max(peak, _rss_mb(self.p.pid))
            if peak > mem_limit:
                self.kill()
                return None, f"memory > {mem_limit:.0f} MB"
            if time.perf_counter() - t0 > time_limit:
                self.kill()
                return None, f"hang > {time_limit:.0f} s"
            time.sleep(0.02)

    def kill(self):
        self.p.kill()
        self.p.wait()

    def close(self):
        if self.p.poll() is None:
            self.p.stdin.close()
            self.p.wait(timeout=30)


def campaign(cases: int, seed: int, *, time_limit: float = TIME_LIMIT_S,
             mem_limit: float = MEMORY_LIMIT_MB, keep: Path | None = None,
             progress=None, surface_share: float = 0.5) -> list[Outcome]:
    """Run ``cases`` cases (seeds ``seed .. seed + cases - 1``) and judge each; a share
    ``surface_share`` of them are store-surface cases on a template store made first."""
    from tests.fuzz_surfaces import build_template, listing

    outcomes = []
    base = Path(tempfile.mkdtemp(prefix="plantdyn-fuzz-"))
    template = build_template(base / "template") if surface_share > 0 else None
    outside = listing(base)
    worker = _Worker()
    try:
        for k in range(cases):
            folder = base / f"case{seed + k}"
            folder.mkdir()
            try:
                done = make_case(folder, seed + k, template, surface_share)
            except Exception as exc:  # noqa: BLE001 - the generator's own fault: say, go on
                print(f"seed {seed + k}: case generator failed ({exc!r}); skipped",
                      file=sys.stderr)
                shutil.rmtree(folder, ignore_errors=True)
                continue
            before = listing(folder)
            res, killed = worker.run(folder, time_limit, mem_limit)
            if res is None:
                worker = _Worker()
            out = judge(done, res, folder, killed, before)
            now = {p: v for p, v in listing(base).items() if not p.startswith(str(folder))}
            if now != outside and storage_of(folder).is_relative_to(folder):
                out.problem += "; wrote outside the case folder: " + ", ".join(
                    sorted(set(now) ^ set(outside))[:3])
            outside = now
            outcomes.append(out)
            if out.problem and keep is not None:
                shutil.copytree(folder, keep / folder.name, dirs_exist_ok=True)
            shutil.rmtree(folder, ignore_errors=True)
            if progress:
                progress(k + 1, cases, out)
    finally:
        worker.close()
        shutil.rmtree(base, ignore_errors=True)
    return outcomes


def summary(outcomes: list[Outcome]) -> dict:
    rcs: dict = {}
    for o in outcomes:
        rcs[str(o.rc)] = rcs.get(str(o.rc), 0) + 1
    bad = [o for o in outcomes if o.problem]
    return {"cases": len(outcomes), "exit_codes": rcs, "problems": len(bad),
            "median_s": float(np.median([o.seconds for o in outcomes])) if outcomes else 0.0,
            "by_base": {b: sum(o.base == b for o in outcomes)
                        for b in sorted({o.base for o in outcomes})},
            "by_base_exit": {b: {str(rc): sum(o.base == b and o.rc == rc for o in outcomes)
                                 for rc in sorted({o.rc for o in outcomes if o.base == b},
                                                  key=str)}
                             for b in sorted({o.base for o in outcomes})},
            "problems_by_base": {b: sum(o.base == b and bool(o.problem) for o in outcomes)
                                 for b in sorted({o.base for o in outcomes})}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="JSON report of every case")
    ap.add_argument("--keep", type=Path, default=None, help="copy failing cases here")
    ap.add_argument("--surface-share", type=float, default=0.5,
                    help="share of cases on store surfaces (export, runs, reindex, ...)")
    ap.add_argument("--time-limit", type=float, default=TIME_LIMIT_S,
                    help="seconds a case may take before it counts as a hang")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        _worker()
        return 0
    t0 = time.perf_counter()

    lines = args.out.with_suffix(".jsonl").open("w") if args.out else None

    def show(k, n, out):
        if lines is not None:  # every outcome as it comes (a stopped campaign keeps them)
            lines.write(json.dumps(asdict(out)) + "\n")
            lines.flush()
        if out.problem:
            print(f"[{k}/{n}] seed {out.seed} {out.base} {out.mutations}: {out.problem}\n"
                  f"    {out.stderr_tail[-300:]}", file=sys.stderr)
        elif k % 50 == 0 or k == n:
            el = time.perf_counter() - t0
            print(f"[{k}/{n}] {el:.0f} s elapsed, ETA {el / k * (n - k):.0f} s",
                  file=sys.stderr)

    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
    outs = campaign(args.cases, args.seed, keep=args.keep, progress=show,
                    surface_share=args.surface_share, time_limit=args.time_limit)
    s = summary(outs)
    s["seconds"] = time.perf_counter() - t0
    print(json.dumps(s, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"summary": s, "cases": [asdict(o) for o in outs]},
                                       indent=1))
    return 1 if s["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
