#!/usr/bin/env bash
# The real steam-generator record (DaISy 98-003) through plantdyn:
#   1. convert ../shared/data/steamgen.dat into a wide historian CSV in
#      demo/steamgen/steamgen.csv (tags STEAMGEN.FUEL ... STEAMGEN.STEAM, UTC times);
#   2. run `plantdyn run configs/steamgen.yaml` (step responses with the defaults) or
#      `plantdyn discrepancy configs/steamgen_discrepancy.yaml` (against
#      configs/models/steamgen.yaml); results go under storage/, the run folder is printed.
# Usage: scripts/steamgen.sh run|discrepancy [path/to/steamgen.dat] [plantdyn options, e.g. --no-prefect]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
cmd="${1:-}"
case "$cmd" in
  run) job="$root/configs/steamgen.yaml" ;;
  discrepancy) job="$root/configs/steamgen_discrepancy.yaml" ;;
  *) echo "usage: scripts/steamgen.sh run|discrepancy [path/to/steamgen.dat] [plantdyn options]" >&2; exit 2 ;;
esac
shift
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
"$plantdyn" "$cmd" "$job" "$@"
