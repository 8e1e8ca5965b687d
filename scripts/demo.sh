#!/usr/bin/env bash
# One command: set everything up and run the bundled demo job (local files, embedded Prefect).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/plantdyn demo "$@"
