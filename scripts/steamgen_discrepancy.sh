#!/usr/bin/env bash
# Discrepancy workflow on the real steam-generator record (issue 4, "It must show" 3).
#   1. convert ../shared/data/steamgen.dat (DaISy 98-003) into a wide historian CSV in
#      demo/steamgen/steamgen.csv (tags STEAMGEN.FUEL ... STEAMGEN.STEAM, UTC times);
#   2. run `plantdyn discrepancy configs/steamgen_discrepancy.yaml` (model
#      configs/models/steamgen.yaml); results go under storage/, the run folder is printed.
# Usage: scripts/steamgen_discrepancy.sh [path/to/steamgen.dat] [plantdyn options, e.g. --no-prefect]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
src="$root/../shared/data/steamgen.dat"
if [[ $# -gt 0 && "$1" != -* ]]; then
  src="$1"
  shift
fi
if [[ ! -f "$src" ]]; then
  echo "error: $src not found; give the path to steamgen.dat (DaISy 98-003) as first argument" >&2
  exit 2
fi
py="$root/.venv/bin/python"
[[ -x "$py" ]] || py=python3
plantdyn="$root/.venv/bin/plantdyn"
[[ -x "$plantdyn" ]] || plantdyn=plantdyn
"$py" -m pipeline.adapters.daisy "$src" "$root/demo/steamgen/steamgen.csv"
"$plantdyn" discrepancy "$root/configs/steamgen_discrepancy.yaml" "$@"
