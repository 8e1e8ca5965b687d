"""Progress on long work (issue 10): bars with rate and ETA for ingest and the search on a
terminal, plain lines when asked for off a terminal, nothing otherwise.

The Prefect path and the nightly file loop are driven through the CLI in
``tests/adapters/test_storage_faults.py`` (they need the Prefect harness).
"""

from __future__ import annotations

import io
import re
import sys

import pytest

from pipeline.adapters.ingest import options as ingest_options
from pipeline.adapters import progress as progress_mod
from tests.conftest import write_job, write_plant_csv
from tests.flows.test_cli_hostile_inputs import cli

LINE = re.compile(r"^(\w+): +(\d+) % ([\d.,]+) of ([\d.,]+) (\w+), ([\d.,]+) \w+/s, ETA (.+)$")


def _bars(err: str, stage: str) -> list[tuple[int, float, float]]:
    out = []
    for ln in err.splitlines():
        m = LINE.match(ln)
        if m and m.group(1) == stage:
            out.append((int(m.group(2)), float(m.group(3).replace(",", "")),
                        float(m.group(4).replace(",", ""))))
    return out


@pytest.fixture
def plant_job(tmp_path):
    write_plant_csv(tmp_path / "drop" / "a.csv", seed=41, hours=2.0)
    return write_job(tmp_path)


def test_asked_for_progress_off_a_terminal_prints_ingest_and_search_lines(
        plant_job, tmp_path, monkeypatch):
    monkeypatch.setenv(progress_mod.ENV, "")
    monkeypatch.setenv(progress_mod.ENV + "_EVERY_S", "0")
    # ~25 chunks: the byte count must advance chunk by chunk, not jump at the end
    monkeypatch.setattr(ingest_options, "CHUNK_CELLS", 2_000)
    rc, out, err = cli("run", "--progress", "always", "--no-prefect", str(plant_job))
    assert rc == 0, err[-3000:]
    size_mb = (tmp_path / "drop" / "a.csv").stat().st_size / 1e6
    lines = _bars(err, "ingest")
    assert len(lines) >= 10, err[-3000:]
    done = [d for _, d, _ in lines]
    assert done == sorted(done) and len(set(done)) >= 3  # advances, never backwards
    assert {t for _, _, t in lines} == {round(size_mb, 2)}  # total = the file's size
    assert lines[-1][0] == 100 and lines[-1][1] == round(size_mb, 2)
    assert "MB/s" in err and "ETA" in err
    steps = _bars(err, "search")
    assert steps and steps[-1][0] == 100 and steps[-1][1] == steps[-1][2]
    assert [d for _, d, _ in steps] == sorted(d for _, d, _ in steps)


def test_no_progress_lines_off_a_terminal_unless_asked(plant_job, monkeypatch):
    monkeypatch.setenv(progress_mod.ENV, "")
    monkeypatch.setenv(progress_mod.ENV + "_EVERY_S", "0")
    rc, _, err = cli("run", "--no-prefect", str(plant_job))
    assert rc == 0, err[-3000:]
    assert not _bars(err, "ingest") and not _bars(err, "search")
    assert "] ingest: start" in err  # the stage lines are always there


def test_never_turns_bars_off_even_on_a_terminal(monkeypatch):
    tty = _Tty()
    monkeypatch.setattr(sys, "stderr", tty)
    monkeypatch.setenv(progress_mod.ENV, "0")
    with progress_mod.bar("ingest", "MB", 1e-6) as tick:
        tick(5e6, 1e7)
    assert tty.getvalue() == ""


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_terminal_bar_shows_rate_and_eta(monkeypatch):
    """On a terminal rich draws the bar: the unit's rate and the time remaining."""
    tty = _Tty()
    monkeypatch.setattr(sys, "stderr", tty)
    monkeypatch.delenv(progress_mod.ENV, raising=False)
    assert progress_mod.mode() == "bar"
    import time

    with progress_mod.bar("ingest", "MB", 1e-6) as tick:
        for k in range(1, 6):
            tick(k * 2e6, 1e7)
            time.sleep(0.15)
    text = tty.getvalue()
    assert "ingest" in text and "MB/s" in text, text[-2000:]
    assert "10.0 of 10.0 MB" in text, text[-2000:]
    assert re.search(r"\d+:\d\d:\d\d|-:--:--", text)  # rich's time-remaining column
