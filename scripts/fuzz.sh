#!/usr/bin/env bash
# The full seeded fuzz campaign (issues 10 and 33): hostile CSV / MCAP / YAML / numeric
# inputs through `plantdyn run --no-prefect`, and (--surface-share, default 0.5) the
# commands around a results store on a private template store: export, runs --plot,
# reindex, monitor baselines, discrepancy models, corrupt catalogs and manifests, FIFOs,
# sockets and links where plantdyn reads or writes.  Every case has a time limit (a hang
# is a failure) and the case folder is listed before and after (a write outside what the
# command may change is a failure).  Prints the exit-code counts per surface and every
# failing case.
#   scripts/fuzz.sh [--cases 2000] [--seed 1] [--surface-share 0.5] [--time-limit 60]
#                   [--out fuzz.json] [--keep failing-cases/]
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh --test >/dev/null
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1
args=("$@")
[[ " ${args[*]-} " == *" --cases "* ]] || args+=(--cases 2000)
exec nice .venv/bin/python -m tests.fuzzing "${args[@]}"
