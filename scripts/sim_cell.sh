#!/usr/bin/env bash
# The small simulated cell of the runtime tests (the soak, tests/soak.py, and the browser test, tests/browser/):
# the shipped configuration on a 4.4 mm grid with one frame per 4.4 mm of travel (148 frames a pass instead of 296),
# the simulated sensor calibrated, and a database of 3 parts (plate_4h, plate_5h, bracket_l; 8 passes each,
# PLC ids 1-3) taught and trained. What these tests exercise is the runtime, not the recogniser's accuracy. Cached
# in WORK/cell: a changed configuration, catalogue or executable starts it over.
#
# usage: scripts/sim_cell.sh BIN WORK   (BIN: the cellsight executable)
# makes: WORK/cell/cellsight.yaml, WORK/cell/parts.yaml, WORK/cell/calibration.yaml, WORK/cell/models/
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -eq 2 ] || { echo "usage: scripts/sim_cell.sh BIN WORK" >&2; exit 2; }
BIN=$(realpath "$1")
CELL=$2/cell

mkdir -p "$CELL"
CONFIG=$CELL/cellsight.yaml
sed -e 's/^  nx: 296 /  nx: 148 /' -e 's/^  ny: 500 /  ny: 250 /' -e 's/^  nz: 182 /  nz: 91  /' \
    -e 's/^  resolution_m: 0.0022$/  resolution_m: 0.0044/' -e 's/^  folds: 5 /  folds: 3 /' \
    -e 's/^  sa_iterations: 200$/  sa_iterations: 6/' -e 's/^  trigger_every_counts: 22 /  trigger_every_counts: 44 /' \
    config/cellsight.yaml > "$CONFIG.new"
for want in "nx: 148" "ny: 250" "nz: 91" "resolution_m: 0.0044" "folds: 3" "sa_iterations: 6" "trigger_every_counts: 44"; do
  grep -q "^  $want" "$CONFIG.new" || { echo "sim_cell.sh: config/cellsight.yaml changed: cannot set '$want'" >&2; exit 1; }
done
cp config/parts.yaml "$CELL/parts.yaml"
# A changed configuration or executable invalidates the cached calibration and database.
STAMP=$( (cat "$CONFIG.new" "$CELL/parts.yaml"; sha256sum "$BIN") | sha256sum | cut -c1-16)
if [ "$(cat "$CELL/stamp" 2>/dev/null)" != "$STAMP" ]; then
  rm -rf "$CELL/models" "$CELL/calibration.yaml"* "$CELL/calwork"
fi
mv "$CONFIG.new" "$CONFIG"
if [ ! -f "$CELL/calibration.yaml" ]; then
  echo "== sim_cell: calibrating the simulated sensor"
  CELLSIGHT_BIN=$BIN scripts/calibrate.sh --sim --config "$CONFIG" --calibration "$CELL/calibration.yaml" \
    --work "$CELL/calwork" > "$CELL/calibrate.log" 2>&1 || { tail -20 "$CELL/calibrate.log"; exit 1; }
fi
if ! "$BIN" --config "$CONFIG" --models "$CELL/models" parts list 2>/dev/null | grep -q "^bracket_l"; then
  echo "== sim_cell: teaching 3 parts (8 passes each) and training"
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
