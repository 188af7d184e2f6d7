#!/usr/bin/env bash
# Soak and fault injection of the production runtime (README "Soak test"): builds cellsight (Release), sets up a
# small simulated cell (calibration and a 3-part model database, cached in WORK), and runs tests/soak.py: SIGTERM
# mid-pass with restarts, then `cellsight run --sim` for PARTS parts with an acknowledging PLC, a polling client, a
# client abusing the port, camera stalls and hiccups, encoder glitches, photo-eye chatter and a teach into a full
# disk; checked against the simulator's truth. Exit 0 only when every check passed.
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

# The soak's cell: the shipped configuration on a 4.4 mm grid with one frame per 4.4 mm of travel (148 frames a
# pass instead of 296), the small database of the PLC integration test. What is soaked is the runtime, not the
# recogniser's accuracy.
CELL=$WORK/cell
mkdir -p "$CELL"
CONFIG=$CELL/cellsight.yaml
sed -e 's/^  nx: 296 /  nx: 148 /' -e 's/^  ny: 500 /  ny: 250 /' -e 's/^  nz: 182 /  nz: 91  /' \
    -e 's/^  resolution_m: 0.0022$/  resolution_m: 0.0044/' -e 's/^  folds: 5 /  folds: 3 /' \
    -e 's/^  sa_iterations: 200$/  sa_iterations: 6/' -e 's/^  trigger_every_counts: 22 /  trigger_every_counts: 44 /' \
    config/cellsight.yaml > "$CONFIG.new"
for want in "nx: 148" "ny: 250" "nz: 91" "resolution_m: 0.0044" "folds: 3" "sa_iterations: 6" "trigger_every_counts: 44"; do
  grep -q "^  $want" "$CONFIG.new" || { echo "soak.sh: config/cellsight.yaml changed: cannot set '$want'" >&2; exit 1; }
done
cp config/parts.yaml "$CELL/parts.yaml"
# A changed configuration or executable invalidates the cached calibration and database.
STAMP=$( (cat "$CONFIG.new" "$CELL/parts.yaml"; sha256sum "$BIN") | sha256sum | cut -c1-16)
if [ "$(cat "$CELL/stamp" 2>/dev/null)" != "$STAMP" ]; then
  rm -rf "$CELL/models" "$CELL/calibration.yaml"* "$CELL/calwork"
fi
mv "$CONFIG.new" "$CONFIG"
if [ ! -f "$CELL/calibration.yaml" ]; then
  echo "== soak: calibrating the simulated sensor"
  CELLSIGHT_BIN=$BIN scripts/calibrate.sh --sim --config "$CONFIG" --calibration "$CELL/calibration.yaml" \
    --work "$CELL/calwork" > "$CELL/calibrate.log" 2>&1 || { tail -20 "$CELL/calibrate.log"; exit 1; }
fi
if ! "$BIN" --config "$CONFIG" --models "$CELL/models" parts list 2>/dev/null | grep -q "^bracket_l"; then
  echo "== soak: teaching 3 parts (8 passes each) and training"
  rm -rf "$CELL/models"
  id=1
  for part in plate_4h plate_5h bracket_l; do
    "$BIN" --config "$CONFIG" --models "$CELL/models" --log-level warn teach --sim --part "$part" --id "$id" \
      --count 8 --calibration "$CELL/calibration.yaml" > "$CELL/teach.log" 2>&1 || { cat "$CELL/teach.log"; exit 1; }
    id=$((id + 1))
  done
  "$BIN" --config "$CONFIG" --models "$CELL/models" --log-level warn train --calibration "$CELL/calibration.yaml" \
    > "$CELL/train.log" 2>&1 || { tail -20 "$CELL/train.log"; exit 1; }
fi
echo "$STAMP" > "$CELL/stamp"

ARGS=(--cellsight "$BIN" --config "$CONFIG" --calibration "$CELL/calibration.yaml" --models "$CELL/models"
      --sim-parts plate_4h,plate_5h,bracket_l --parts "$PARTS" --restarts "$RESTARTS" --disk-full
      --timeout $((PARTS / 2 + 600)))  # a hung run fails instead of holding CI
[ -n "$JSON" ] && ARGS+=(--json "$JSON")
[ -n "$KEEP" ] && ARGS+=(--keep "$KEEP")
echo "== soak: $PARTS parts, $RESTARTS restarts after SIGTERM mid-pass, faults injected (tests/soak.py)"
/usr/bin/python3 tests/soak.py "${ARGS[@]}"
