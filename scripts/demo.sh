#!/usr/bin/env bash
# One command: set everything up and run the bundled demo job (local files; the project's
# Prefect server, started on first use and kept for the next command:
# .venv/bin/plantdyn server stop stops it).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/plantdyn demo "$@"
