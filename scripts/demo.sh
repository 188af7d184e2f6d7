#!/usr/bin/env bash
# The main command (README): installs what is missing, builds cellsight (Release) and runs the whole cell on the
# simulated hardware — no hardware needed:
#   1. calibrates the simulated sensor (camera, laser, conveyor, carrier plane) as a technician would,
#   2. teaches the catalogue (COUNT simulated passes per part) into a model database,
#   3. trains the recogniser (features, simulated annealing + k-fold CV, SVM, template thresholds),
#   4. runs the production loop for PARTS parts with the Modbus server up (127.0.0.1:1502), one log line per part,
#      while a PLC program (tests/modbus_plc_client.py, pymodbus) takes every result by the handshake, and the
#      operator's screen is served at http://127.0.0.1:8080/ (printed below; open it in a browser while it runs).
# A database that is already taught and trained is reused (delete out/demo to start over).
#
# usage: scripts/demo.sh [PARTS] [COUNT]      (defaults: 20 parts, 12 teach passes per part type)
set -euo pipefail
cd "$(dirname "$0")/.."

PARTS=${1:-20}
COUNT=${2:-12}
OUT=out/demo
MODELS=$OUT/models
CAL=$OUT/calibration/calibration.yaml

scripts/setup.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build build -j"$(nproc)" --target cellsight
BIN=./build/app/cellsight
mkdir -p "$OUT"

if [ ! -f "$CAL" ]; then
  echo "== 1. calibrating the simulated sensor"
  scripts/calibrate.sh --sim --work "$OUT/calibration" --calibration "$CAL" | grep -E "PASS|FAIL|result" || true
  [ -f "$CAL" ] || { echo "demo: calibration failed" >&2; exit 1; }
fi

if ! "$BIN" --models "$MODELS" parts list >/dev/null 2>&1 || "$BIN" --models "$MODELS" parts list | grep -q stale; then
  echo "== 2. teaching the catalogue ($COUNT passes per part type)"
  id=1
  for part in $("$BIN" sim --list | awk 'NR > 1 {print $1}'); do
    if ! "$BIN" --models "$MODELS" parts show "$part" >/dev/null 2>&1; then
      "$BIN" --models "$MODELS" teach --part "$part" --id "$id" --sim --count "$COUNT" --calibration "$CAL"
    fi
    id=$((id + 1))
  done
  echo "== 3. training"
  "$BIN" --models "$MODELS" train --calibration "$CAL" --report "$OUT/report"
fi
"$BIN" --models "$MODELS" parts list

echo "== 4. running the cell for $PARTS parts, with a PLC program (tests/modbus_plc_client.py) taking every result"
echo "   over Modbus TCP 127.0.0.1:1502 by the RESULT_VALID / RESULT_ACK handshake (the cell: log lines; the PLC: JSON)"
echo "   operator's screen: http://127.0.0.1:8080/ (hmi section of config/cellsight.yaml; accounts:"
echo "   build/app/cellsight hmi-user NAME --role operator|maintenance; viewing from this machine needs none)"
"$BIN" --models "$MODELS" run --sim --parts "$PARTS" --wait-plc --calibration "$CAL" &
CELL=$!
trap 'kill "$CELL" 2>/dev/null || true' EXIT
for _ in $(seq 100); do  # until the Modbus server listens
  (exec 3<>/dev/tcp/127.0.0.1/1502) 2>/dev/null && break
  kill -0 "$CELL" 2>/dev/null || break
  sleep 0.1
done
PLC=0
/usr/bin/python3 tests/modbus_plc_client.py --host 127.0.0.1 --port 1502 --count "$PARTS" --timeout 600 || PLC=$?
CELL_EXIT=0
wait "$CELL" || CELL_EXIT=$?
trap - EXIT
echo "== done: cell exit $CELL_EXIT, PLC exit $PLC"
[ "$CELL_EXIT" -eq 0 ] && [ "$PLC" -eq 0 ]
