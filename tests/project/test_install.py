"""plantdyn installed from its wheel, run from a folder that is not the checkout.

Users install the package and run ``plantdyn demo`` wherever they work; nothing may assume
the checkout's layout (the shipped jobs and models travel inside the wheel).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _build_wheel(tmp: Path) -> Path:
    # a copy of the source tree (the build writes build/ and *.egg-info next to the sources)
    src = tmp / "src"
    keep = ["pyproject.toml", "README.md", "pipeline", "flows", "configs"]
    src.mkdir()
    for name in keep:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(p, src / name)
    out = tmp / "dist"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                        "--no-build-isolation", "-w", str(out), str(src)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    (wheel,) = out.glob("plantdyn-*.whl")
    return wheel


def test_wheel_carries_the_shipped_jobs_and_runs_the_demo_from_an_empty_folder(tmp_path):
    wheel = _build_wheel(tmp_path)
    names = set(zipfile.ZipFile(wheel).namelist())
    for shipped in ("demo_boiler.yaml", "demo_discrepancy.yaml", "demo_discrepancy_two.yaml",
                    "models/boiler_pressure.yaml"):
        assert f"pipeline/_shipped/{shipped}" in names, sorted(names)[:20]
    # a fresh venv with the wheel installed by pip (console script and all); its
    # dependencies come from this venv's site-packages through a plain path entry, which does
    # not process that folder's .pth files, so the checkout's editable install stays out
    fresh = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(fresh)], check=True,
                   timeout=120)
    (fresh_site,) = fresh.glob("lib/python*/site-packages")
    (fresh_site / "deps.pth").write_text(
        next(p for p in sys.path if p.endswith("site-packages")) + "\n")
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(fresh / "bin" / "python"),
                        "install", "-q", "--no-deps", str(wheel)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    plantdyn = str(fresh / "bin" / "plantdyn")

    work = tmp_path / "work"  # an empty folder, nothing of the checkout in reach
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    probe = subprocess.run([str(fresh / "bin" / "python"), "-c",
                            "import pipeline; print(pipeline.__file__)"],
                           cwd=work, env=env, capture_output=True, text=True, timeout=60)
    assert probe.stdout.strip().startswith(str(fresh_site)), probe.stdout + probe.stderr
    r = subprocess.run([plantdyn, "demo", "--no-prefect"],
                       cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = dict(line.split(":", 1) for line in r.stdout.splitlines() if ":" in line)
    run_dir = Path(lines["results"].strip())
    # the demo folder and results root are made where the user stands
    assert (work / "demo" / "demo_boiler.yaml").is_file()
    assert (work / "demo" / "exports" / "boiler_export.csv").is_file()
    assert run_dir.is_relative_to(work / "storage") and (run_dir / "manifest.json").is_file()
    # and the runs listing finds it with the default results root, from the same folder
    r2 = subprocess.run([plantdyn, "runs", "demo_boiler"],
                        cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert r2.returncode == 0 and run_dir.name in r2.stdout, r2.stdout + r2.stderr
