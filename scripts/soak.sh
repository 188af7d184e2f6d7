#!/usr/bin/env bash
# Soak and fault injection of the production runtime (README "Soak test"): builds cellsight (Release), sets up a
# small simulated cell (scripts/sim_cell.sh: calibration and a 3-part model database, cached in WORK), and runs
# tests/soak.py: SIGTERM mid-pass with restarts, then `cellsight run --sim` for PARTS parts with an acknowledging
# PLC, a polling client, a client abusing the port, camera stalls and hiccups, encoder glitches, photo-eye chatter
# and a teach into a full disk; checked against the simulator's truth. Exit 0 only when every check passed.
#
# usage: scripts/soak.sh [--ci | --full] [--parts N] [--work DIR] [--json FILE] [--keep DIR]
#   --ci        the CI size (default): 500 parts, 2 restarts, one disk-full teach
#   --full      the acceptance run: 10 000 parts, 3 restarts, two disk-full teaches
# environment: CELLSIGHT_SOAK_BUILD  build folder (default build-soak); CELLSIGHT_BIN  use this executable instead
set -euo pipefail
cd "$(dirname "$0")/.."

PARTS=500
RESTARTS=2
WORK=out/soak
JSON=
KEEP=
while [ $# -gt 0 ]; do
  case "$1" in
    --ci) PARTS=500; RESTARTS=2 ;;
    --full) PARTS=10000; RESTARTS=3 ;;
    --parts) PARTS=${2:?--parts needs a number}; shift ;;
    --work) WORK=${2:?--work needs a folder}; shift ;;
    --json) JSON=${2:?--json needs a file}; shift ;;
    --keep) KEEP=${2:?--keep needs a folder}; shift ;;
    -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
    *) echo "soak.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done

scripts/setup.sh >/dev/null
if [ -z "${CELLSIGHT_BIN:-}" ]; then
  BUILD=${CELLSIGHT_SOAK_BUILD:-build-soak}
  cmake -S . -B "$BUILD" -DCMAKE_BUILD_TYPE=Release >/dev/null
  cmake --build "$BUILD" -j"$(nproc)" --target cellsight
  CELLSIGHT_BIN=$BUILD/app/cellsight
fi
BIN=$(realpath "$CELLSIGHT_BIN")

# The soak's cell (scripts/sim_cell.sh, shared with the browser test): calibration and a 3-part database, cached in
# WORK/cell.
scripts/sim_cell.sh "$BIN" "$WORK"
CELL=$WORK/cell
CONFIG=$CELL/cellsight.yaml

ARGS=(--cellsight "$BIN" --config "$CONFIG" --calibration "$CELL/calibration.yaml" --models "$CELL/models"
      --sim-parts plate_4h,plate_5h,bracket_l --parts "$PARTS" --restarts "$RESTARTS" --disk-full
      --timeout $((PARTS / 2 + 600)))  # a hung run fails instead of holding CI
[ -n "$JSON" ] && ARGS+=(--json "$JSON")
[ -n "$KEEP" ] && ARGS+=(--keep "$KEEP")
echo "== soak: $PARTS parts, $RESTARTS restarts after SIGTERM mid-pass, faults injected (tests/soak.py)"
/usr/bin/python3 tests/soak.py "${ARGS[@]}"
