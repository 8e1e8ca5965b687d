#!/usr/bin/env bash
# Discrepancy workflow on the real steam-generator record (issue 4, "It must show" 3):
# scripts/steamgen.sh discrepancy (convert DaISy 98-003, run configs/steamgen_discrepancy.yaml).
# Usage: scripts/steamgen_discrepancy.sh [path/to/steamgen.dat] [plantdyn options, e.g. --no-prefect]
exec "$(dirname "$0")/steamgen.sh" discrepancy "$@"
