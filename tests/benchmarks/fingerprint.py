"""Numeric fingerprints of the reference runs, to show a refactoring changed no number.

Runs, through the ``plantdyn`` CLI in a scratch folder (``--no-prefect``):

* the demo (``plantdyn demo``) and the discrepancy demo (``plantdyn demo --discrepancy``);
* the real steam generator (DaISy 98-003 converted as ``scripts/steamgen.sh`` does):
  ``configs/steamgen.yaml`` and ``configs/steamgen_discrepancy.yaml``;
* the fractionator export (``../shared/data/frac2_historian_export.csv``, the job of
  ``tests/jobs/test_frac2_job.py``),

and prints, per run, a SHA-256 of every numeric column of ``step_responses.parquet``
(rows sorted by window, output, input, lag; float64 bytes, so bit-for-bit) and of every
number in ``checks.json`` / ``discrepancy.json`` (keys about wall-clock time excluded).

Use::

    .venv/bin/python -m tests.benchmarks.fingerprint --out before.json
    ... refactor ...
    .venv/bin/python -m tests.benchmarks.fingerprint --out after.json --compare before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import polars as pl
import yaml

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"
_CLOCK = re.compile(r"timing|elapsed|seconds|duration|wall|created|started|finished|run_id|"
                    r"path|file|version|host")


def _numbers(obj, key: str = "", digits: int | None = None) -> list:
    """Every number of a JSON document in key order (``digits``: significant digits kept,
    None: bit-exact)."""
    if _CLOCK.search(key.lower()):
        return []
    if isinstance(obj, dict):
        return [x for k in sorted(obj) for x in _numbers(obj[k], f"{key}.{k}", digits)]
    if isinstance(obj, list):
        return [x for v in obj for x in _numbers(v, key, digits)]
    if isinstance(obj, bool) or obj is None:
        return [repr(obj)]
    if isinstance(obj, (int, float)):
        return [repr(float(obj)) if digits is None else f"{float(obj):.{digits}g}"]
    return []


CHECKS_DIGITS = 12
"""checks.json is compared to 12 significant digits: its excitation condition number
(LAPACK dpocon on a factor of sums formed by SIMD reductions) differs run to run in the
last bits on the same code (2567.575437828475 vs ...477, measured); step_responses.parquet
and discrepancy.json are compared bit for bit."""


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def fingerprint_run(run_dir: Path) -> dict[str, str]:
    out = {}
    sr = run_dir / "step_responses.parquet"
    if sr.exists():
        df = pl.read_parquet(sr).sort(["window", "output", "input", "lag"])
        for c, dt in df.schema.items():
            if dt.is_numeric():
                out[f"step_responses.{c}"] = _sha(np.ascontiguousarray(
                    df[c].cast(pl.Float64).fill_null(float("nan")).to_numpy()).tobytes())
    for name, digits in (("checks.json", CHECKS_DIGITS), ("discrepancy.json", None)):
        p = run_dir / name
        if p.exists():
            out[name] = _sha("\n".join(_numbers(json.loads(p.read_text()), digits=digits))
                             .encode())
    return out


def _cli(args: list[str], cwd: Path, env: dict | None = None) -> Path:
    # the CLI of the tree this file is in (run on an older checkout it runs that code)
    module = "flows.cli" if (ROOT / "flows" / "cli.py").exists() else "pipeline.cli"
    r = subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})
    if r.returncode != 0:
        raise SystemExit(f"plantdyn {' '.join(args)} failed ({r.returncode}):\n{r.stderr[-3000:]}")
    return Path(r.stdout.strip().splitlines()[-1])


def _newest_run(storage: Path, job: str) -> Path:
    runs = sorted((p for p in (storage / job).iterdir() if not p.name.startswith(".")),
                  key=lambda p: p.stat().st_mtime)
    return runs[-1]


def run_all(work: Path) -> dict[str, dict[str, str]]:
    res = {}
    _cli(["demo", "--no-prefect", "--dir", "demo"], work)
    res["demo"] = fingerprint_run(_newest_run(work / "storage", "demo_boiler"))
    _cli(["demo", "--discrepancy", "--no-prefect", "--dir", "demo"], work)
    res["demo_discrepancy"] = fingerprint_run(_newest_run(work / "storage", "demo_discrepancy"))
    if not SHARED.is_dir():
        return res
    shutil.copytree(ROOT / "configs", work / "configs")
    subprocess.run([sys.executable, "-m", "pipeline.adapters.daisy", str(SHARED / "steamgen.dat"),
                    str(work / "demo" / "steamgen" / "steamgen.csv")], check=True, cwd=ROOT,
                   capture_output=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    for key, job in (("steamgen", "steamgen.yaml"),
                     ("steamgen_discrepancy", "steamgen_discrepancy.yaml")):
        cmd = "run" if key == "steamgen" else "discrepancy"
        res[key] = fingerprint_run(_cli([cmd, "--no-prefect", str(work / "configs" / job)], work))
    from tests.jobs.test_frac2_job import INPUTS, OUTPUTS, _name

    job = {"job": "frac2",
           "source": {"path": str(SHARED / "frac2_historian_export.csv"),
                      "timezone": "America/Chicago"},
           "signals": {"inputs": {_name(t): {"tag": t} for t in INPUTS},
                       "outputs": {_name(t): {"tag": t} for t in OUTPUTS}},
           "storage": "storage", "rerun": {"enabled": False}}
    (work / "frac2.yaml").write_text(yaml.safe_dump(job, sort_keys=False))
    res["frac2"] = fingerprint_run(_cli(["run", "--no-prefect", str(work / "frac2.yaml")], work,
                                        env={"PLANTDYN_ALLOWED_ROOTS": str(SHARED)}))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--compare", type=Path, default=None, help="an earlier --out file")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="plantdyn-fp-"))
    try:
        res = run_all(work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    text = json.dumps(res, indent=1, sort_keys=True)
    print(text)
    if args.out:
        args.out.write_text(text)
    if args.compare:
        old = json.loads(args.compare.read_text())
        diff = [(run, k) for run in sorted(set(old) | set(res))
                for k in sorted(set(old.get(run, {})) | set(res.get(run, {})))
                if old.get(run, {}).get(k) != res.get(run, {}).get(k)]
        for run, k in diff:
            print(f"DIFFERS {run}: {k}", file=sys.stderr)
        print(f"{len(diff)} difference(s) against {args.compare}", file=sys.stderr)
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
