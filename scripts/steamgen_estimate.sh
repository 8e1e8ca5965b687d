#!/usr/bin/env bash
# Step responses of the real steam generator with the defaults (issue 9, must-show 6):
# scripts/steamgen.sh run (convert DaISy 98-003, run configs/steamgen.yaml).
# Usage: scripts/steamgen_estimate.sh [path/to/steamgen.dat] [plantdyn options, e.g. --no-prefect]
exec "$(dirname "$0")/steamgen.sh" run "$@"
