"""The issue-10 fuzz findings, one by one, through the CLI as a user runs them.

Each case was an internal error (exit 1 with a traceback), a crash after validation, or a
misleading message. Now each must exit 2 with exactly one ``plantdyn: error:`` line that
names the file / key / topic and message and the fix in job-YAML terms, and leave nothing
under the storage root. (The alias bomb, YAML structure errors, stray timestamps, the
shifted-column file, spikes, the int64 log time and storage faults have their own tests in
``tests/flows/test_cli_hostile_inputs.py`` and ``tests/adapters/test_storage_faults.py``.)
"""

from __future__ import annotations

import json
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest

from tests.conftest import INPUT_TAG, OUTPUT_TAG, plant_signals, write_job, write_plant_csv
from tests.flows.test_cli_hostile_inputs import assert_clean_exit_2, cli


def _csv_job(folder: Path, **extra) -> Path:
    write_plant_csv(folder / "drop" / "export.csv", seed=5, hours=1.0)
    return write_job(folder, **extra)


def _mcap_job(folder: Path, edit: Callable[[list], list]) -> Path:
    """A JSON MCAP export of the test plant (one message per sample), edited."""
    from mcap.writer import Writer

    sig = plant_signals(seed=3, hours=1.0)
    msgs = []
    for k in range(len(sig["u"])):
        for tag, key in ((INPUT_TAG, "u"), (OUTPUT_TAG, "y")):
            msgs.append(["/" + tag, {"t": 1_700_000_000 + k, "value": float(sig[key][k])},
                         (1_700_000_000 + k) * 10**9])
    msgs = edit(msgs)
    path = folder / "drop" / "export.mcap"
    path.parent.mkdir(parents=True)
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        chans = {}
        for topic, payload, log_ns in msgs:
            if topic not in chans:
                chans[topic] = w.register_channel(topic, "json", 0)
            data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
            w.add_message(chans[topic], log_time=log_ns, publish_time=log_ns, data=data)
        w.finish()
    return write_job(folder, source="drop/*.mcap")


def _at(index: int, payload) -> Callable[[list], list]:
    """Replace the payload of message ``index`` (of the merged list; index 101 is the
    output's message 50)."""
    def edit(msgs):
        msgs[index][1] = payload
        return msgs
    return edit


def _ms_as_s(msgs):
    for m in msgs:
        m[1] = {"t": m[1]["t"] * 1000, "value": m[1]["value"]}
    return msgs


def _short(folder: Path) -> Path:
    job = _csv_job(folder)
    p = folder / "drop" / "export.csv"
    lines = p.read_text().splitlines()
    keep = [ln for ln in lines[1:] if ln.startswith(INPUT_TAG)][:100]
    keep += [ln for ln in lines[1:] if ln.startswith(OUTPUT_TAG)][:100]
    p.write_text("\n".join([lines[0], *keep]) + "\n")
    return job


def _without_timezone(folder: Path) -> Path:
    job = _csv_job(folder)
    job.write_text(job.read_text().replace("  timezone: UTC\n", ""))
    return job


@dataclass(frozen=True)
class Repro:
    id: str
    make: Callable[[Path], Path]
    pattern: str
    command: tuple[str, ...] = ("run", "--no-prefect")
    extra: tuple[str, ...] = ()


REPROS = [
    # values that passed validation and crashed later
    Repro("dt_s-inf", lambda f: _csv_job(f, sampling={"dt_s": float("inf")}),
          r"job\.yaml: sampling\.dt_s: Input should be a finite number \(got inf\)"),
    Repro("settling-1e300", lambda f: _csv_job(f, search={"settling_time_s": 1e300}),
          r"search\.settling_time_s: Input should be less than or equal to 100000000"),
    Repro("n_p-1e30", lambda f: _csv_job(f, search={"n_p": 1e30}),
          r"search\.n_p: .*\(got 1e\+30\)"),
    Repro("xcorr-lag-100000", lambda f: _csv_job(f, checks={"xcorr_max_lag": 100000}),
          r"checks\.xcorr_max_lag: Input should be less than or equal to 5000 \(got 100000\)"),
    Repro("highpass-cutoff-1e300",
          lambda f: _csv_job(f, conditioning={"method": "highpass", "cutoff_period_s": 1e300}),
          r"conditioning\.cutoff_period_s: Input should be less than or equal to 100000000"),
    Repro("job-name-300-chars", lambda f: _csv_job(f, name="j" * 300),
          r"job: String should have at most 64 characters"),
    Repro("run-id-300-chars", _csv_job,
          r"--run-id of 300 characters is too long \(at most 100: it becomes a folder name\)",
          extra=("--run-id", "r" * 300)),
    # misleading messages
    Repro("n_p_min-above-n_p_max", lambda f: _csv_job(f, search={"n_p_min": 50, "n_p_max": 20}),
          r"search\.n_p_min \(50\) is above search\.n_p_max \(20\); lower n_p_min or raise n_p_max"),
    Repro("timezone-missing", _without_timezone,
          r"source\.timezone: required key is missing .* e\.g\. UTC or Europe/Berlin"),
    Repro("200-row-file", _short,
          r"the longest stretch where every signal is good has 100 samples; the α_T criterion "
          r"needs at least 200 — set sampling\.dt_s"),
    Repro("model-file-missing", lambda f: _csv_job(f, model="models/nothere.yaml"),
          r"model file '.*models/nothere\.yaml' does not exist; give the path to a \.yaml model",
          command=("discrepancy", "--no-prefect")),
    # MCAP content errors: topic, message index, log time, the fix
    Repro("mcap-invalid-utf8", lambda f: _mcap_job(f, _at(101, b'{"t": 1700000050, "value": "\xff"}')),
          r"topic '/Y\.PV', message 50 \(log time 1700000050000000000 ns\) is not valid JSON"),
    Repro("mcap-nan-time", lambda f: _mcap_job(f, _at(101, b'{"t": NaN, "value": 1.0}')),
          r"topic '/Y\.PV', message 50 \(log time 1700000050000000000 ns\): time field 't' = nan "
          r"s is not a time between 1900 and 2200 .* set source\.mcap\.time_field: null"),
    Repro("mcap-infinity-time", lambda f: _mcap_job(f, _at(101, b'{"t": Infinity, "value": 1.0}')),
          r"message 50 .*time field 't' = inf s is not a time between 1900 and 2200"),
    Repro("mcap-1e300-time", lambda f: _mcap_job(f, _at(101, {"t": 1e300, "value": 1.0})),
          r"message 50 .*time field 't' = 1e\+300 s is not a time between 1900 and 2200"),
    Repro("mcap-ms-read-as-s", lambda f: _mcap_job(f, _ms_as_s),
          r"topic '/U\.PV', message 0 .*= 1\.7e\+12 s is not a time between 1900 and 2200 "
          r"\(3600 of 3600 sample\(s\) like it\); the recorder writes ms: set "
          r"source\.mcap\.time_unit: ms in the job YAML"),
    Repro("mcap-list-value-on-one-message",
          lambda f: _mcap_job(f, _at(101, {"t": 1700000050, "value": [1.0, 2.0]})),
          r"topic '/Y\.PV', message 50 \(log time 1700000050000000000 ns\): field 'value' is a "
          r"list of 2 values but 't' is one time"),
]


@pytest.mark.parametrize("case", REPROS, ids=[c.id for c in REPROS])
def test_reproduction_exits_2_with_one_specific_message(case, tmp_path):
    job = case.make(tmp_path)
    rc, _, err = cli(*case.command, *case.extra, str(job))
    assert_clean_exit_2(rc, err, case.pattern, tmp_path)


def test_reproductions_cover_every_kind_listed_in_the_issue():
    assert len({c.id for c in REPROS}) == len(REPROS) >= 17
    assert sum(c.id.startswith("mcap-") for c in REPROS) >= 6


def test_a_boolean_input_is_estimated_not_blamed_on_collinearity(tmp_path):
    """An on/off input (a pump, a valve) is a legitimate input: it runs (exit 0)."""
    job = _csv_job(tmp_path)
    p = tmp_path / "drop" / "export.csv"
    rng = random.Random(1)
    rows = []
    for line in p.read_text().splitlines():
        parts = line.split(",")
        if parts[0] == INPUT_TAG:
            parts[2] = str(int(rng.random() < 0.5))
        rows.append(",".join(parts))
    p.write_text("\n".join(rows) + "\n")
    rc, _, err = cli("run", "--no-prefect", str(job))
    assert rc == 0, err[-2000:]
    assert "collinear" not in err
