"""Tests of MCAP ingestion (pipeline.adapters.ingest.mcap_reader) for JSON, protobuf and ROS 2.

Files are written with the mcap writers (our JSON writer, mcap_protobuf.writer.Writer,
mcap_ros2.writer.Writer); the known answer is what was written.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool
from google.protobuf import timestamp_pb2  # noqa: F401  (loads Timestamp into the default pool)
from google.protobuf.message_factory import GetMessageClass
from google.protobuf.wrappers_pb2 import DoubleValue
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_protobuf.writer import Writer as ProtobufWriter
from mcap_ros2.writer import Writer as Ros2Writer

from pipeline.adapters.grid import to_grid
from pipeline.adapters.historian_writer import write_json_mcap
from pipeline.adapters.ingest import McapOptions, read_recording, read_recordings
from pipeline.adapters.ingest.mcap_reader import JsonDecoderFactory
from pipeline.errors import IngestError
from tests.helpers_steamgen import STEAMGEN_DT_S, load_steamgen, steamgen_to_mcap

T0_NS = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z


def t_utc(ns: int) -> dt.datetime:
    return dt.datetime.fromtimestamp(ns // 1000 / 1e6, tz=dt.UTC).replace(microsecond=(ns // 1000) % 1_000_000)


def json_mcap(path: Path, messages: list[tuple[str, dict | str, int]]) -> Path:
    """Write (topic, payload, log_time_ns) JSON messages with the core mcap writer."""
    with path.open("wb") as f:
        w = McapWriter(f)
        w.start()
        channels: dict[str, int] = {}
        for topic, payload, log_ns in messages:
            if topic not in channels:
                channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=0)
            data = payload.encode() if isinstance(payload, str) else json.dumps(payload).encode()
            w.add_message(channel_id=channels[topic], log_time=log_ns, data=data, publish_time=log_ns)
        w.finish()
    return path


# ----------------------------------------------------------------------------- JSON
@pytest.mark.parametrize("samples_per_message", [1, 50])
def test_steamgen_json_mcap_round_trip_is_exact(tmp_path: Path, samples_per_message: int) -> None:
    path = tmp_path / "sg.mcap"
    written = steamgen_to_mcap(path, samples_per_message=samples_per_message)
    assert written.rows == 8 * int(np.ceil(9600 / samples_per_message))
    table, report = read_recording(path)
    assert report.layout == "mcap" and report.encoding == "json"
    times, values = load_steamgen()
    grid = to_grid(table, dt_s=STEAMGEN_DT_S)
    np.testing.assert_array_equal(grid.time, times)
    assert grid.good.all()
    for tag, v in values.items():
        # JSON floats are written with repr and read back exactly.
        np.testing.assert_array_equal(grid.series(tag), v)


def test_samples_layout_with_states_and_tag_field(tmp_path: Path) -> None:
    times = np.datetime64("2024-01-01T00:00:00", "us") + np.arange(10).astype("timedelta64[s]")
    values = {"A": np.arange(10.0), "B": -np.arange(10.0)}
    path = tmp_path / "s.mcap"
    write_json_mcap(
        path, times, values, samples_per_message=7, layout="samples", states={"B": [(4, "I/O Timeout")]}
    )
    table, report = read_recording(path)
    assert report.signal_names == ("A", "B")
    b = table.filter(pl.col("signal") == "B")
    assert b["value"].to_list() == [-float(k) if k != 4 else None for k in range(10)]
    assert b["state"][4] == "I/O Timeout" and b["quality"][4] == "bad"
    assert report.signal("B").bad_by_state == {"I/O Timeout": 1}
    np.testing.assert_array_equal(b["time"].dt.replace_time_zone(None).to_numpy(), times)


def test_json_field_variants(tmp_path: Path) -> None:
    path = json_mcap(
        tmp_path / "v.mcap",
        [
            # ISO text times (naive = the given zone), quality flags, tag from a field.
            ("/plant", {"meta": {"tag": "FIC-1"}, "ts": "2024-01-01T01:00:00", "v": 1.0, "q": "good"}, T0_NS),
            ("/plant", {"meta": {"tag": "FIC-1"}, "ts": "2024-01-01T01:00:01", "v": 2.0, "q": 64}, T0_NS),
            ("/plant", {"meta": {"tag": "FIC-2"}, "ts": "2024-01-01T01:00:00", "v": "Shutdown", "q": "bad"}, T0_NS),
        ],
    )
    opts = McapOptions(time_field="ts", value_field="v", quality_field="q", tag_field="meta.tag")
    table, _ = read_recording(path, mcap=opts, timezone="Europe/Berlin")
    assert [tuple(r) for r in table.iter_rows()] == [
        (dt.datetime(2024, 1, 1, 0, 0, 0, tzinfo=dt.UTC), "FIC-1", 1.0, "good", None),
        (dt.datetime(2024, 1, 1, 0, 0, 1, tzinfo=dt.UTC), "FIC-1", 2.0, "suspect", "64"),
        (dt.datetime(2024, 1, 1, 0, 0, 0, tzinfo=dt.UTC), "FIC-2", None, "bad", "Shutdown"),
    ]


def test_json_without_time_field_uses_log_time_and_ms_units(tmp_path: Path) -> None:
    path = json_mcap(
        tmp_path / "l.mcap",
        [("/A", {"value": float(k)}, T0_NS + k * 1_500_000_000) for k in range(4)]
        + [("/B", {"t": 1_700_000_000_000 + 250, "value": 9.0}, 0)],
    )
    table, _ = read_recording(path, mcap={"time_unit": "ms"})
    a = table.filter(pl.col("signal") == "A")
    assert a["time"].to_list() == [t_utc(T0_NS + k * 1_500_000_000) for k in range(4)]
    assert table.filter(pl.col("signal") == "B")["time"].to_list() == [t_utc(T0_NS + 250_000_000)]


def test_many_sample_message_with_mixed_numbers_and_states(tmp_path: Path) -> None:
    # A list holding numbers and a state text: polars cannot infer one type, the
    # json-module fallback reads it.
    path = json_mcap(
        tmp_path / "m.mcap",
        [("/A", {"t": [1.7e9, 1.7e9 + 1, 1.7e9 + 2], "value": [1.0, "Bad Input", 3.0]}, T0_NS)],
    )
    table, report = read_recording(path)
    assert table["value"].to_list() == [1.0, None, 3.0]
    assert table["state"].to_list() == [None, "Bad Input", None]
    assert report.signal("A").bad == 1


def test_json_decoder_factory_with_mcap_reader(tmp_path: Path) -> None:
    path = json_mcap(tmp_path / "d.mcap", [("/A", {"t": 1.0, "value": 2.5}, 5)])
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        decoded = [m.decoded_message for m in reader.iter_decoded_messages()]
    assert decoded == [{"t": 1.0, "value": 2.5}]
    assert JsonDecoderFactory().decoder_for("cdr", None) is None


def test_topics_filter_and_read_recordings(tmp_path: Path) -> None:
    p1 = json_mcap(tmp_path / "1.mcap", [("/A", {"value": 1.0}, T0_NS), ("/B", {"value": 2.0}, T0_NS)])
    p2 = json_mcap(tmp_path / "2.mcap", [("/A", {"value": 3.0}, T0_NS + 1_000_000_000)])
    table, report = read_recordings([p1, p2], mcap={"topics": ["/A"]})
    assert report.signal_names == ("A",)
    assert table["value"].to_list() == [1.0, 3.0]


# ----------------------------------------------------------------------------- protobuf
def _sample_message_class():
    """A protobuf message ``Sample {Timestamp t; double value; string quality}``."""
    pool = descriptor_pool.Default()
    try:
        return GetMessageClass(pool.FindMessageTypeByName("plantdyn_test.Sample"))
    except KeyError:
        pass
    fdp = descriptor_pb2.FileDescriptorProto(
        name="plantdyn_test/sample.proto",
        package="plantdyn_test",
        syntax="proto3",
        dependency=["google/protobuf/timestamp.proto"],
    )
    m = fdp.message_type.add(name="Sample")
    F = descriptor_pb2.FieldDescriptorProto
    m.field.add(name="t", number=1, type=F.TYPE_MESSAGE, type_name=".google.protobuf.Timestamp", label=F.LABEL_OPTIONAL)
    m.field.add(name="value", number=2, type=F.TYPE_DOUBLE, label=F.LABEL_OPTIONAL)
    m.field.add(name="quality", number=3, type=F.TYPE_STRING, label=F.LABEL_OPTIONAL)
    pool.Add(fdp)
    return GetMessageClass(pool.FindMessageTypeByName("plantdyn_test.Sample"))


def test_protobuf_double_value_and_timestamp_message(tmp_path: Path) -> None:
    path = tmp_path / "pb.mcap"
    Sample = _sample_message_class()
    with path.open("wb") as f:
        w = ProtobufWriter(f)
        for k in range(20):
            ns = T0_NS + k * 2_000_000_000
            w.write_message("/FI-101.PV", DoubleValue(value=0.5 * k), log_time=ns, publish_time=ns)
            s = Sample(value=float(k), quality="bad" if k == 3 else "good")
            s.t.seconds = 1_700_000_000 + k
            s.t.nanos = 250_000_000
            w.write_message("/TI-7.PV", s, log_time=T0_NS, publish_time=T0_NS)
        w.finish()
    table, report = read_recording(path)
    assert report.encoding == "protobuf"
    fi = table.filter(pl.col("signal") == "FI-101.PV")
    # DoubleValue has no time field: the log time is the sample time.
    assert fi["time"].to_list() == [t_utc(T0_NS + k * 2_000_000_000) for k in range(20)]
    assert fi["value"].to_list() == [0.5 * k for k in range(20)]
    ti = table.filter(pl.col("signal") == "TI-7.PV")
    assert ti["time"].to_list() == [t_utc(T0_NS + k * 1_000_000_000 + 250_000_000) for k in range(20)]
    assert ti["value"].to_list() == [None if k == 3 else float(k) for k in range(20)]
    assert report.signal("TI-7.PV").bad_by_state == {"bad": 1}


# ----------------------------------------------------------------------------- ROS 2
STAMPED = """std_msgs/Header header
float64 data
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""


def test_ros2_float64_and_header_stamp(tmp_path: Path) -> None:
    path = tmp_path / "ros.mcap"
    with path.open("wb") as f:
        w = Ros2Writer(f)
        plain = w.register_msgdef("std_msgs/msg/Float64", "float64 data")
        stamped = w.register_msgdef("plant_msgs/msg/StampedFloat64", STAMPED)
        for k in range(10):
            w.write_message("/PI-102.PV", plain, {"data": 1.25 * k}, log_time=T0_NS + k * 1_000_000_000)
            msg = {"header": {"stamp": {"sec": 1_700_000_100 + k, "nanosec": 5_000}, "frame_id": ""}, "data": -float(k)}
            w.write_message("/LI-3.PV", stamped, msg, log_time=T0_NS)
        w.finish()
    table, report = read_recording(path, mcap={"topics": ["/PI-102.PV"], "value_field": "data"})
    assert report.encoding == "cdr"
    assert table["value"].to_list() == [1.25 * k for k in range(10)]
    assert table["time"].to_list() == [t_utc(T0_NS + k * 1_000_000_000) for k in range(10)]
    table, _ = read_recording(
        path, mcap=McapOptions(topics=["/LI-3.PV"], value_field="data", time_field="header.stamp")
    )
    assert table["time"].to_list() == [t_utc(T0_NS + (100 + k) * 1_000_000_000 + 5_000) for k in range(10)]
    assert table["value"].to_list() == [-float(k) for k in range(10)]


# ----------------------------------------------------------------------------- corrupt
def test_truncated_file_error_and_warn(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    times, values = load_steamgen()
    # Small chunks so a cut keeps several complete chunks.
    write_json_mcap(full, times, values, samples_per_message=10, chunk_size=16_384)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(IngestError, match=r"cut\.mcap: MCAP reading failed at byte offset \d+ of \d+ .*truncated or corrupt.*on_truncated='warn'"):
        read_recording(cut)
    table, report = read_recording(cut, on_truncated="warn")
    assert report.truncated and len(report.warnings) == 1
    offset = int(report.warnings[0].split("byte offset ")[1].split(" ")[0])
    assert 0 < offset <= len(data) // 2
    assert 0 < len(table) < 8 * 9600
    # What was read is exactly the original samples at those times.
    for tag, v in values.items():
        part = table.filter(pl.col("signal") == tag)
        idx = ((part["time"].dt.replace_time_zone(None).to_numpy() - times[0]) // np.timedelta64(3, "s")).astype(int)
        np.testing.assert_array_equal(part["value"].to_numpy(), v[idx])
    # Cut inside the summary section: every message is readable.
    tail_cut = tmp_path / "tail.mcap"
    tail_cut.write_bytes(data[:-20])
    with pytest.raises(IngestError, match=r"after the data section"):
        read_recording(tail_cut)
    whole, rep2 = read_recording(tail_cut, on_truncated="warn")
    assert len(whole) == 8 * 9600 and rep2.truncated


def test_error_paths(tmp_path: Path) -> None:
    not_mcap = tmp_path / "x.mcap"
    not_mcap.write_bytes(b"tag,time,value\n")
    with pytest.raises(IngestError, match=r"x\.mcap: not an MCAP file \(bad magic bytes at offset 0\)"):
        read_recording(not_mcap)
    p = json_mcap(tmp_path / "a.mcap", [("/A", {"t": 1.7e9, "reading": 1.0}, T0_NS)])
    with pytest.raises(IngestError, match=r"topic '/A': no value field 'value' in its messages \(fields: \['t', 'reading'"):
        read_recording(p)
    table, _ = read_recording(p, mcap={"value_field": "reading"})
    assert table["value"].to_list() == [1.0]
    with pytest.raises(IngestError, match=r"tag\(s\) \['B'\] requested but not in the recording; it has 1 tags: \['A'\]"):
        read_recording(p, mcap={"value_field": "reading"}, tags=["B"])
    bad_json = json_mcap(tmp_path / "b.mcap", [("/A", "{not json", T0_NS)])
    with pytest.raises(IngestError, match=r"topic '/A', message 0 \(log time \d+ ns\) is not valid JSON"):
        read_recording(bad_json)
    lists = json_mcap(tmp_path / "c.mcap", [("/A", {"t": [1.7e9, 1.7e9 + 1], "value": [1.0]}, T0_NS)])
    with pytest.raises(IngestError, match=r"lists of different lengths in \['time', 'value'\]"):
        read_recording(lists)
    no_time = json_mcap(tmp_path / "n.mcap", [("/A", {"samples": [{"tag": "A", "value": 1.0}, {"tag": "A", "value": 2.0}]}, T0_NS)])
    with pytest.raises(IngestError, match=r"samples without a time field 't' in many-sample messages"):
        read_recording(no_time)
