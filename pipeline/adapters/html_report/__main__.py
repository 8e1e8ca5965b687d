"""Rebuild a run's report from its stored files, without refitting:

    python -m pipeline.adapters.html_report RUN_DIR [-o OUT.html]

Writes ``OUT.html`` (default ``report-<job>-<run_id>.html`` in the current folder: the
result store is the only writer under the storage root) and prints its path.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.adapters.html_report import write_report_html
from pipeline.errors import UserInputError


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit code (2: not a run directory).

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).
    """
    parser = argparse.ArgumentParser(prog="python -m pipeline.adapters.html_report",
                                     description="Rebuild report.html of a stored run.")
    parser.add_argument("run_dir", type=Path, help="<storage>/<job>/<run-id>")
    parser.add_argument("-o", "--out", type=Path, default=None, help="the HTML file to write")
    args = parser.parse_args(argv)
    try:
        out = args.out
        if out is None:
            manifest = args.run_dir / "manifest.json"
            m = json.loads(manifest.read_text(encoding="utf-8")) if manifest.is_file() else {}
            out = Path(f"report-{m.get('job', 'run')}-{m.get('run_id', args.run_dir.name)}.html")
        print(write_report_html(args.run_dir, out))
    except UserInputError as exc:
        print(f"plantdyn: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
