#!/usr/bin/env bash
# The full seeded fuzz campaign (issue 10): hostile CSV / MCAP / YAML / numeric inputs
# through `plantdyn run --no-prefect`; prints the exit-code counts and every failing case.
#   scripts/fuzz.sh [--cases 2000] [--seed 1] [--out fuzz.json] [--keep failing-cases/]
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh --test >/dev/null
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1
args=("$@")
[[ " ${args[*]-} " == *" --cases "* ]] || args+=(--cases 2000)
exec .venv/bin/python -m tests.fuzzing "${args[@]}"
