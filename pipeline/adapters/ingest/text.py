"""The text of a CSV export: its encoding (byte-order mark, else UTF-8, else
``source.csv.encoding``), the decoded head, a UTF-8 copy for polars' reader, and the tail
rows for the format sample."""

from __future__ import annotations

import codecs
import csv as _csv
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.adapters.ingest.options import CsvOptions
from pipeline.errors import ConfigError, IngestError

SAMPLE_ROWS = 200
"""Rows of the head (and of the tail) the format detection looks at."""


def detect_encoding(head: bytes, options: CsvOptions, path: str, complete: bool) -> str:
    """Python codec of the file: forced, from the byte-order mark, or UTF-8.

    Raises IngestError when there is no BOM and the bytes are not UTF-8.

    Parameters
    ----------
    head : bytes
        The first bytes of the file (64 KiB).
    options : CsvOptions
        ``encoding`` forces the codec.
    path : str
        The file, for messages.
    complete : bool
        ``head`` is the whole file (a character cut at its end is an error then).
    """
    if options.encoding is not None:
        try:
            return codecs.lookup(options.encoding).name
        except LookupError as exc:
            raise ConfigError(
                f"source.csv.encoding: {options.encoding!r} is not a known codec; use e.g. "
                f"'utf-8', 'utf-16', 'cp1252', 'latin-1'"
            ) from exc
    if head.startswith(codecs.BOM_UTF8):
        return "utf-8-sig"
    if head.startswith((codecs.BOM_UTF32_LE, codecs.BOM_UTF32_BE)):
        return "utf-32"
    if head.startswith(codecs.BOM_UTF16_LE):
        return "utf-16-le"
    if head.startswith(codecs.BOM_UTF16_BE):
        return "utf-16-be"
    if head.startswith(b"PK\x03\x04"):
        raise IngestError(
            f"{path}: this is a zip archive (an Excel .xlsx workbook?), not a CSV text "
            f"export; save it as CSV from the historian or spreadsheet"
        )
    window = head[:4096]
    if b"\x00" in window:
        # UTF-16 without a BOM: ASCII text has a NUL in every other byte.
        even, odd = window[0::2], window[1::2]
        if odd.count(0) > 0.3 * len(odd) and even.count(0) < 0.05 * len(even):
            return "utf-16-le"
        if even.count(0) > 0.3 * len(even) and odd.count(0) < 0.05 * len(odd):
            return "utf-16-be"
        raise IngestError(
            f"{path}: unknown encoding — the file holds NUL bytes but no byte-order mark "
            f"and no UTF-16 pattern (a binary file?); export as UTF-8 or UTF-16 text, or "
            f"set source.csv.encoding in the job YAML"
        )
    try:
        codecs.getincrementaldecoder("utf-8")().decode(head, final=complete)
    except UnicodeDecodeError as exc:
        raise IngestError(
            f"{path}: unknown encoding — no byte-order mark and byte 0x{head[exc.start]:02X} "
            f"at offset {exc.start} is not valid UTF-8; set the export's code page in the "
            f"job YAML, e.g. source.csv.encoding: cp1252 (or latin-1)"
        ) from exc
    return "utf-8"


def decode_head(head: bytes, codec: str, complete: bool, path: str) -> str:
    """The head decoded with ``codec``, without a byte-order mark.

    Parameters
    ----------
    head : bytes
        The first bytes of the file.
    codec : str
        From :func:`detect_encoding`.
    complete : bool
        ``head`` is the whole file.
    path : str
        The file, for messages.
    """
    try:
        text = codecs.getincrementaldecoder(codec)().decode(head, final=complete)
    except UnicodeDecodeError as exc:
        raise IngestError(
            f"{path}: cannot decode the first bytes as {codec} (offset {exc.start}); set "
            f"the right source.csv.encoding in the job YAML"
        ) from exc
    return text.lstrip("\ufeff")


@contextmanager
def as_utf8(path: Path, codec: str, name: str) -> Iterator[Path]:
    """The file itself when it is UTF-8, else a temporary UTF-8 copy (transcoded in
    blocks, so memory stays small; removed afterwards) — polars reads UTF-8 only.

    Parameters
    ----------
    path : Path
        The export.
    codec : str
        Its codec (:func:`detect_encoding`).
    name : str
        The file as named in messages.
    """
    if codec in ("utf-8", "utf-8-sig"):
        yield path
        return
    decoder = codecs.getincrementaldecoder(codec)()
    fd, tmp_name = tempfile.mkstemp(prefix="plantdyn-", suffix=".csv")
    tmp = Path(tmp_name)
    try:
        with path.open("rb") as src, open(fd, "wb") as dst:
            consumed, first = 0, True
            while True:
                raw = src.read(16 * 2**20)
                try:
                    text = decoder.decode(raw, final=not raw)
                except UnicodeDecodeError as exc:
                    raise IngestError(
                        f"{name}: bytes near offset {consumed + exc.start} are not valid "
                        f"{codec}; the file is corrupt or in another encoding (set "
                        "source.csv.encoding in the job YAML)") from exc
                if first and text:
                    text, first = text.lstrip("\ufeff"), False
                dst.write(text.encode("utf-8", "surrogatepass"))
                consumed += len(raw)
                if not raw:
                    break
        yield tmp
    finally:
        tmp.unlink(missing_ok=True)


def tail_rows(path: Path, codec: str, sep: str, n_bytes: int = 65536) -> list[list[str]]:
    """Whole rows from the last ``n_bytes`` of the file (for the format sample).

    Parameters
    ----------
    path : Path
        The export.
    codec : str
        Its codec.
    sep : str
        Field separator.
    n_bytes : int
        Bytes read from the end.
    """
    size = path.stat().st_size
    if size <= n_bytes:
        return []
    width = {"utf-16-le": 2, "utf-16-be": 2, "utf-16": 2, "utf-32": 4}.get(codec, 1)
    start = (size - n_bytes) // width * width
    with path.open("rb") as f:
        f.seek(start)
        tail = f.read()
    text = tail.decode(codec.replace("-sig", "") if codec != "utf-16" else "utf-16-le",
                       errors="replace")
    lines = text.splitlines()[1:]  # the first line is cut
    if '"' in text:
        return []  # a cut inside a quoted field would misalign the fields
    return [r for r in _csv.reader(lines[-SAMPLE_ROWS:], delimiter=sep) if r]
