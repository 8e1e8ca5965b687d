"""Lint is part of the suite: ``ruff check`` (pinned in the test extras; rules in
pyproject.toml's ``[tool.ruff]``: pyflakes, syntax errors, McCabe complexity) finds
nothing in the project."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_ruff_finds_nothing():
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache",
                        "--output-format", "concise", "."],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-2000:]
    assert "All checks passed" in r.stdout
